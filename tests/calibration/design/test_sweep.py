"""Sweeps: the same records on the local process pool and on a dask.distributed cluster, a
resume after a kill that recomputes nothing finished, and specifications refused with file and
key."""
import dataclasses
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import pytest

from deltatwin.calibration.design.sweep import (
    SweepError,
    SweepSpec,
    deterministic_columns,
    read_records,
    run_sweep,
)
from deltatwin.cli import main
from tests.user_effect_files import marker_effect_file

TINY = """
[sweep]
name = "tiny"
seed = 7
replicates = 2

[[study]]
scenario = "quiet/gravity-sag"
effect = "gravity_sag"
parameter = "load_factor"
magnitudes = [0.0, 0.5]

[designs.small]
scale = 0.02
"""


def _spec(tmp_path, text=TINY) -> Path:
    p = tmp_path / "spec.toml"
    p.write_text(text)
    return p


def _case_files(out: Path) -> dict:
    return {p.name: p.stat().st_mtime_ns for p in out.glob("*/*/case-*.parquet")}


@pytest.mark.slow
def test_killed_sweep_resumes_and_matches_a_dask_cluster(tmp_path):
    spec = _spec(tmp_path)
    out = tmp_path / "pool"
    cmd = [sys.executable, "-m", "deltatwin", "sweep", str(spec), "-o", str(out), "--workers",
           "1", "--json", "-q"]
    proc = subprocess.Popen(cmd, start_new_session=True, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE)
    deadline = time.monotonic() + 120
    while not _case_files(out) and time.monotonic() < deadline and proc.poll() is None:
        time.sleep(0.02)
    os.killpg(proc.pid, signal.SIGKILL)          # the command and its pool's worker
    proc.wait()
    before = _case_files(out)
    assert 0 < len(before) < 4, "the kill should land between the first and the last case"
    for p in out.glob("*/*/case-*.parquet"):     # written whole or not at all
        assert pq.read_table(p).num_rows == 1
    r = subprocess.run(cmd[:-2] + ["--resume", "--json"], capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0, r.stderr
    summary = json.loads(r.stdout)
    assert summary["skipped"] == len(before) and summary["ran"] == 4 - len(before)
    assert summary["cpu_s_per_case"] > 0 and summary["load_average_start"] >= 0
    after = _case_files(out)
    assert len(after) == 4
    assert all(after[name] == mtime for name, mtime in before.items())   # not rewritten
    pool = read_records(out)

    from distributed import LocalCluster

    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                      dashboard_address=None) as cluster:
        run_sweep(SweepSpec.load(spec), tmp_path / "dask", scheduler=cluster.scheduler_address)
    dask = read_records(tmp_path / "dask")
    cols = deterministic_columns(pool)
    pd.testing.assert_frame_equal(pool[cols], dask[cols], check_exact=True)
    # the sweep saw what it was built for: the switched-off effect is not named, the on one is
    # significant (a load factor of 0.5 sags the platform by tens of nm at 5 nm noise)
    assert not pool.loc[pool.magnitude == 0, "named"].any()
    assert pool.loc[pool.magnitude > 0, "significant"].all()
    assert (pool.status == "ok").all() and np.all(pool.seed.nunique() == 2)


def test_results_folder_with_records_needs_resume(tmp_path, capsys):
    out = tmp_path / "r" / "effect=gravity_sag" / "design=small"
    out.mkdir(parents=True)
    (out / "case-0123456789abcdef.parquet").write_bytes(b"")
    assert main(["sweep", str(_spec(tmp_path)), "-o", str(tmp_path / "r")]) == 2
    assert "--resume" in capsys.readouterr().err


@pytest.mark.parametrize("change, message", [
    (("magnitudes = [0.0, 0.5]", "magnitudes = [-1.0]"), "magnitudes"),
    (("parameter = \"load_factor\"", "parameter = \"load\""), "not a parameter of gravity_sag"),
    (("replicates = 2", "replicates = 0"), "[sweep] replicates"),
    (("scale = 0.02", "scale = 2"), "[designs.small] scale"),
    (("seed = 7", "seed = 7\nseeds = 3"), "unknown key(s) ['seeds']"),
    (("quiet/gravity-sag", "quiet/no-such"), "not a shipped scenario"),
])
def test_bad_specification_names_file_and_key(tmp_path, change, message):
    with pytest.raises(SweepError, match=None) as exc:
        SweepSpec.load(_spec(tmp_path, TINY.replace(*change)))
    assert message in str(exc.value) and "spec.toml" in str(exc.value)


def test_case_seeds_come_from_the_spec_not_the_order(tmp_path):
    a = SweepSpec.load(_spec(tmp_path))
    b = SweepSpec.load(_spec(tmp_path, TINY.replace("[0.0, 0.5]", "[0.5, 0.25, 0.0]")))
    seeds_a = {(c.magnitude, c.replicate): (c.seed, c.case_id) for c in a.cases}
    seeds_b = {(c.magnitude, c.replicate): (c.seed, c.case_id) for c in b.cases}
    for key, value in seeds_a.items():
        assert seeds_b[key] == value
    assert len({c.seed for c in a.cases}) == 2          # one per replicate, shared by magnitudes


def test_a_case_runs_on_its_threads_and_restores_the_callers(tmp_path, monkeypatch):
    """Inside a case the chunk pool and BLAS use ``threads`` (so workers side by side do not
    oversubscribe the cores); the caller's setting comes back; the record carries its CPU and
    wall seconds, which the comparisons of records leave out."""
    from threadpoolctl import threadpool_info, threadpool_limits

    from deltatwin.calibration.design import sweep
    from deltatwin.models import batched

    seen = {}

    def probe(case):
        seen["chunk"] = batched.THREADS
        seen["blas"] = {i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"}
        sum(np.ones(200_000))                   # some CPU time to account for
        return {"case_id": case.case_id}

    monkeypatch.setattr(sweep, "_simulate_fit_diagnose", probe)
    monkeypatch.setattr(batched, "THREADS", 3)
    case = SweepSpec.load(_spec(tmp_path)).cases[0]
    with threadpool_limits(limits=2):            # the caller's own BLAS threads
        rec = sweep.run_case(case)
        after = {i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"}
    assert seen == {"chunk": 1, "blas": {1}} and batched.THREADS == 3 and after == {2}
    assert rec["cpu_s"] > 0 and rec["wall_s"] > 0
    assert deterministic_columns(pd.DataFrame([rec])) == ["case_id"]


def _lab_spec(tmp_path, tag, baseline=None) -> tuple[Path, Path]:
    """A scenario naming a user effect (relative to its own folder, not the working directory),
    and a one-case sweep of it; the effect's code writes ran.txt when imported."""
    lab = tmp_path / "lab"
    lab.mkdir()
    (lab / "fx.py").write_text(marker_effect_file(f"sweep_{tag}"))   # effect names are per process
    text = (Path(__file__).parents[3] / "scenarios" / "quiet" / "gravity-sag.toml").read_text()
    (lab / "scenario.toml").write_text(text.replace('on = ["gravity_sag"]',
                                                    'on = ["gravity_sag", "./fx.py:Ripple"]'))
    spec = TINY.replace("quiet/gravity-sag", "lab/scenario.toml").replace(
        "replicates = 2", "replicates = 1").replace("[0.0, 0.5]", "[0.5]")
    if baseline:
        spec = spec.replace("magnitudes = [0.5]", f"magnitudes = [0.5]\nbaseline = {baseline}")
    return _spec(tmp_path, spec), (lab / "fx.py").resolve()


def test_a_sweep_runs_a_files_user_effect_only_with_consent(tmp_path, capsys, monkeypatch):
    spec, code = _lab_spec(tmp_path, "consent")
    monkeypatch.chdir(tmp_path / "lab")             # the effect's path is the scenario's, not cwd's
    out = tmp_path / "out"
    assert main(["sweep", str(spec), "-o", str(out), "-q"]) == 2
    err = capsys.readouterr().err
    lines = [x for x in err.splitlines() if ": error: " in x]
    assert len(lines) == 1 and "Traceback" not in err, err
    assert "spec.toml" in lines[0] and str(code) in lines[0] and "--trust-effects" in lines[0]
    assert not (tmp_path / "lab" / "ran.txt").exists() and not list(out.glob("*/*/*.parquet"))
    # consent to another file is no consent to this one
    (tmp_path / "lab" / "other.py").write_text("")
    assert main(["sweep", str(spec), "-o", str(out), "-q", "--trust-effects", "other.py"]) == 2
    assert not (tmp_path / "lab" / "ran.txt").exists()
    # consent to this file (as the user names it, from the working directory): the case runs it
    assert main(["sweep", str(spec), "-o", str(out), "-q", "--trust-effects", "fx.py",
                 "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["ran"] == 1
    assert (tmp_path / "lab" / "ran.txt").exists()
    rec = read_records(out)
    assert len(rec) == 1 and rec.status[0] == "ok"


def test_a_sweep_baseline_naming_a_user_effect_needs_consent(tmp_path):
    """The specification is a file too: a user effect its baseline names (relative to its
    folder) needs consent; the cases name it by its absolute path."""
    spec, scenario_code = _lab_spec(tmp_path, "lab", '["geometric_errors", "./base.py:Base"]')
    (tmp_path / "base.py").write_text(marker_effect_file("sweep_base").replace(
        "Ripple", "Base").replace("ran.txt", "base-ran.txt"))
    code = (tmp_path / "base.py").resolve()
    with pytest.raises(SweepError, match="would run the Python code") as exc:
        SweepSpec.load(spec, trust_effects=[str(scenario_code)])
    assert str(code) in str(exc.value) and "spec.toml" in str(exc.value) \
        and "baseline" in str(exc.value)
    assert not (tmp_path / "base-ran.txt").exists()
    case = SweepSpec.load(spec, trust_effects=[str(scenario_code), str(code)]).cases[0]
    assert case.baseline == ("geometric_errors", f"{code}:Base") and case.trust_effects
    # the consent is how a case runs, not what it is
    assert case.case_id == dataclasses.replace(case, trust_effects=False).case_id
