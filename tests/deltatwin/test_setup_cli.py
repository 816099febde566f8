"""The laboratory's setup on the command line: `simulate` writes and prints it, `fit` uses its
constants and baseline without --set (--set overrides and says so), `deltatwin setup` and
`campaign --setup` state it from a setup file (a bad one: one line, exit 2, nothing written),
`compensate` says where the model's constants are not the data's setup."""
import json
import tomllib
from pathlib import Path

import pytest

from deltatwin.cli import main
from deltatwin.twin.dataset import read_dataset, write_dataset
from deltatwin.twin.lab_setup import load_setup

EXAMPLE = Path(__file__).resolve().parents[2] / "docs" / "lab-setup.toml"
ARM = [-0.6, 0.0]
# what simulate states of the papers' laboratory besides: its supports' set point and the
# shares of the beams' air the supports and the table warm (the room's estimate)
HELD = {"peltier_supports": {"setpoint_C": 25.0},
        "room_climate": {"air_support_share": 0.2222, "air_table_share": 0.037}}
FROM_SETUP = {f"{e}.{p}": "the data's setup" for e, values in HELD.items() for p in values}
OVERRIDE = "--set loop_drift.frame_arm_m overrides the data's setup value [-0.6, 0.0]"


@pytest.fixture(scope="module")
def drift_data(tmp_path_factory):
    """hidden/loop-drift at its reduced scale (its [hidden.known]: the 0.6 m frame arm) and
    what simulate printed."""
    import contextlib
    import io

    path = tmp_path_factory.mktemp("setup") / "drift.parquet"
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        assert main(["simulate", "hidden/loop-drift", "--reduced", "--no-floor", "-q",
                     "-o", str(path)]) == 0
    return path, out.getvalue()


def fit_json(capsys, *argv) -> tuple[dict, str]:
    assert main(["fit", *map(str, argv), "--json", "-q"]) == 0
    captured = capsys.readouterr()
    return json.loads(captured.out), captured.err


def test_simulate_writes_the_scenario_s_setup_and_says_so(drift_data):
    path, printed = drift_data
    _, meta = read_dataset(path)
    assert meta["setup"] == {"source": "scenario hidden/loop-drift",
                             "known": {"loop_drift": {"frame_arm_m": ARM}, **HELD},
                             "baseline": ["geometric_errors", "thermal_expansion",
                                          "sensor_contact"]}
    line = next(x for x in printed.splitlines() if x.strip().startswith("setup:"))
    assert "loop_drift.frame_arm_m = [-0.6, 0.0]" in line
    assert "baseline geometric_errors,thermal_expansion,sensor_contact" in line
    assert "(from scenario hidden/loop-drift)" in line


def test_fit_takes_the_frame_arm_from_the_data_and_the_model_file_records_it(drift_data,
                                                                           tmp_path, capsys):
    path, _ = drift_data
    model = tmp_path / "m.toml"
    s, err = fit_json(capsys, path, "--effects", "loop_drift", "-o", model)
    assert s["values"]["loop_drift"]["frame_arm_m"] == ARM
    assert s["constants_from"] == {"loop_drift.frame_arm_m": "the data's setup", **FROM_SETUP}
    assert "overrides" not in err
    doc = tomllib.loads(model.read_text())
    assert doc["effects"]["loop_drift"]["frame_arm_m"] == ARM
    assert doc["known"] == {"loop_drift": {"frame_arm_m": ARM}, **HELD}
    # the same fit without the setup in the data hangs the robot from the library's portal
    df, meta = read_dataset(path)
    write_dataset(df, {k: v for k, v in meta.items() if k != "setup"}, tmp_path / "bare.parquet")
    s, _ = fit_json(capsys, tmp_path / "bare.parquet", "--effects", "loop_drift")
    assert s["values"]["loop_drift"]["frame_arm_m"] == [0.0, 0.0]


def test_set_overrides_the_data_s_setup_and_says_so_in_one_line(drift_data, tmp_path, capsys):
    path, _ = drift_data
    s, err = fit_json(capsys, path, "--effects", "loop_drift",
                      "--set", "loop_drift.frame_arm_m=-0.5,0", "-o", tmp_path / "m.toml")
    assert err.strip().splitlines() == [OVERRIDE]
    assert s["values"]["loop_drift"]["frame_arm_m"] == [-0.5, 0.0]
    assert s["constants_from"] == {"loop_drift.frame_arm_m": "--set", **FROM_SETUP}
    # the same value as the setup's overrides nothing
    _, err = fit_json(capsys, path, "--effects", "loop_drift",
                      "--set", "loop_drift.frame_arm_m=-0.6,0")
    assert "overrides" not in err


def test_fit_without_effects_fits_the_data_s_baseline(drift_data, capsys):
    path, _ = drift_data
    s, _ = fit_json(capsys, path)
    assert s["effects"] == ["geometric_errors", "thermal_expansion", "sensor_contact"]
    # loop drift is not in the baseline: its arm is kept for the candidates a diagnosis adds
    assert s["constants"] == {"loop_drift": {"frame_arm_m": ARM}, **HELD}


def test_fit_without_effects_on_data_without_a_baseline_is_one_line(tmp_path, capsys):
    path = tmp_path / "plain.parquet"
    assert main(["simulate", "paper-force", "--scale", "0.05", "--no-floor", "-q",
                 "-o", str(path)]) == 0
    capsys.readouterr()
    assert main(["fit", str(path), "-q", "-o", str(tmp_path / "m.toml")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "declares no baseline" in err[0] and "--effects" in err[0], err
    assert not (tmp_path / "m.toml").exists()


def test_a_laboratory_s_setup_file_is_put_into_its_own_csv(drift_data, tmp_path, capsys):
    """A laboratory's CSV without metadata gets the example file's setup; fit then uses it."""
    path, _ = drift_data
    df, meta = read_dataset(path)
    df.to_csv(tmp_path / "lab.csv", index=False)           # a lab's CSV: no sidecar
    out = tmp_path / "lab-with-setup.parquet"
    assert main(["setup", str(tmp_path / "lab.csv"), str(EXAMPLE), "-o", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "loop_drift.frame_arm_m = [-0.6, 0.0]" in printed and str(EXAMPLE) in printed
    _, meta = read_dataset(out)
    assert meta["setup"]["known"] == load_setup(EXAMPLE)["known"]
    assert meta["setup"]["known"]["loop_drift"] == {"frame_arm_m": ARM}
    assert meta["setup"]["baseline"][-1] == "loop_drift"
    assert meta["instruments"]["T_noise_C"] == 0.003
    assert meta["sensors"]["frame"] == "frame"
    s, _ = fit_json(capsys, out, "--effects", "loop_drift")
    assert s["values"]["loop_drift"]["frame_arm_m"] == ARM


@pytest.mark.parametrize("text, words", [
    ("[known.loop_drift]\nframe_arm_mm = [-600, 0]\n", "did you mean 'frame_arm_m'"),
    ("[instruments]\ninterferometer_noise_m = 5\n", "interferometer_noise_m = 5"),
    ("[sensors]\nfoo = 'base'\n", "no column T_foo_C"),
])
def test_a_bad_setup_file_is_one_line_exit_2_and_nothing_written(drift_data, tmp_path, capsys,
                                                                 text, words):
    path, _ = drift_data
    bad = tmp_path / "lab.toml"
    bad.write_text(text)
    assert main(["setup", str(path), str(bad), "-o", str(tmp_path / "out.parquet")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(bad) in err[0] and words in err[0], err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["lab.toml"]


@pytest.mark.slow
def test_campaign_writes_the_setup_file_s_setup_and_refuses_a_bad_one_before_measuring(
        tmp_path, capsys):
    out = tmp_path / "c.parquet"
    argv = ["campaign", "hidden/loop-drift", "--instruments", "sim", "--scale", "0.003", "-q"]
    bad = tmp_path / "bad.toml"
    bad.write_text("[known.loop_drift]\nframe_arm_m = -0.6\n")
    assert main([*argv, "--setup", str(bad), "-o", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "bad.toml: known.loop_drift.frame_arm_m" in err[0], err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.toml"]     # no journal either
    assert main([*argv, "--setup", str(EXAMPLE), "-o", str(out)]) == 0
    _, meta = read_dataset(out)
    assert meta["setup"]["source"] == str(EXAMPLE)
    assert meta["setup"]["baseline"][-1] == "loop_drift"
    # the instruments' specifications kept beside how they were reached
    assert meta["instruments"]["kind"] == "sim" and meta["instruments"]["T_noise_C"] == 0.003


def test_compensate_says_where_the_model_s_constants_are_not_the_data_s_setup(drift_data,
                                                                             tmp_path, capsys):
    path, _ = drift_data
    model = tmp_path / "portal.toml"
    fit_json(capsys, path, "--effects", "loop_drift", "--set", "loop_drift.frame_arm_m=0,0",
             "-o", model)
    assert main(["compensate", "hidden/loop-drift", "--model", str(model), "--targets", "2",
                 "--reduced", "-q", "--json", "-o", str(tmp_path / "comp.parquet")]) == 0
    err = capsys.readouterr().err
    assert (f"{model}: the model's loop_drift.frame_arm_m = [0.0, 0.0] overrides the data's "
            "setup value [-0.6, 0.0]") in err, err
    _, meta = read_dataset(tmp_path / "comp.parquet")
    assert meta["setup"]["known"] == {"loop_drift": {"frame_arm_m": ARM}, **HELD}
    assert meta["instruments"]["kind"] == "sim" and "T_noise_C" in meta["instruments"]


def test_the_command_diagnose_prints_runs_as_pasted_with_the_setup_s_arm(drift_data, tmp_path,
                                                                        capsys, monkeypatch):
    """Followed literally, diagnose's "add it with" command fits loop drift hanging from the
    data's frame arm, with no --set."""
    import shlex

    path, _ = drift_data
    monkeypatch.chdir(tmp_path)
    assert main(["fit", str(path), "-q", "-o", "base.toml"]) == 0
    assert main(["diagnose", str(path), "--model", "base.toml", "-q"]) == 0
    out = capsys.readouterr().out.splitlines()
    command = out[out.index(next(x for x in out if x.endswith("add it with:"))) + 1].strip()
    assert "loop_drift" in command and "--set" not in command, command
    argv = shlex.split(command)
    assert argv[0] == "deltatwin" and main([*argv[1:], "-q"]) == 0
    doc = tomllib.loads((tmp_path / "fitted.toml").read_text())
    assert doc["effects"]["loop_drift"]["frame_arm_m"] == ARM
