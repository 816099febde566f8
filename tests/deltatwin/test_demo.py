"""``deltatwin demo``: the hidden-effect story end to end (reduced scale), and its bad input."""
import json
import re
import subprocess
import sys

import pytest


def _demo(tmp_path, *args):
    return subprocess.run([sys.executable, "-m", "deltatwin.cli", "demo", *args],
                          capture_output=True, text=True, cwd=tmp_path)


@pytest.mark.slow
def test_demo_finds_the_hidden_effect_and_writes_report_and_recording(tmp_path):
    r = _demo(tmp_path, "--out", "run", "--json", "--scale", "0.3")
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert out["hidden_effect"] == ["magnetic_force"]
    assert out["diagnosed_effect"] == "magnetic_force"
    ladder = [row["val_err90_nm"] for row in out["ladder"]]
    floor = max(out["noise_floor_nm"].values())
    assert len(ladder) == 2 and ladder[0] >= 3 * ladder[1] and ladder[1] <= 1.5 * floor
    run = tmp_path / "run"
    for name in ("data.parquet", "model0.toml", "model1.toml", "report.md", "report.html",
                 "ladder.png", "residual_time.png", "residual_vs.png", "distribution.png",
                 "workspace_1.png", "workspace_2.png", "workspace_compare.png",
                 "recording.rrd"):
        assert (run / name).stat().st_size > 0, name
    report = (run / "report.md").read_text()
    assert "magnetic_force" in report
    # every figure the report shows was written, and every figure written is shown
    shown = set(re.findall(r"!\[[^]]*\]\(([^)]+\.png)\)", report))
    assert shown == {p.name for p in run.glob("*.png")} and "ladder.png" in shown


def test_demo_bad_input_is_named_and_writes_nothing(tmp_path):
    r = _demo(tmp_path, "--out", "run", "--scenario", "paper-force")
    assert r.returncode == 2 and "no [hidden] table" in r.stderr
    r = _demo(tmp_path, "--out", "run", "--scale", "2")
    assert r.returncode == 2 and "--scale" in r.stderr
    r = _demo(tmp_path, "--out", "run", "--scenario", "quiet/no-such")
    assert r.returncode == 2 and "no such scenario" in r.stderr
    assert not (tmp_path / "run").exists()
