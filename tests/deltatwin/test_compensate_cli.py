"""``deltatwin compensate`` end to end: commanded through the twin's own physics (the
true model), the robot reaches its targets to the readings' noise, far better than the nominal
kinematics, though the run's temperatures leave the calibration range; a run stopped midway and
resumed from its journal gives the same data."""
import contextlib
import io
import json

import numpy as np
import pandas as pd
import pytest

from deltatwin.calibration.physics import controller_evaluator
from deltatwin.calibration.physics.controller_c import coefficient_block
from deltatwin.cli import main
from deltatwin.files import toml_text
from deltatwin.twin.dataset import write_dataset
from deltatwin.twin.scenario import Scenario
from tests.calibration.test_physics_model import PARTS, SCENARIO

MODEL_EFFECTS = ["thermal_expansion", "loop_drift", "air_refraction"]
TARGETS = 10


@pytest.fixture(scope="module")
def lab(tmp_path_factory):
    d = tmp_path_factory.mktemp("compensate")
    sensors = "\n".join(f'{p} = "{p}"' for p in PARTS + ["air_x", "air_y", "air_z"])
    text = SCENARIO.format(contact="", sensors=sensors).replace(
        "cal = 700, val = 300", "cal = 150, val = 100")
    (d / "lab.toml").write_text(text)
    sc = Scenario.load(d / "lab.toml")
    df, meta = sc.simulate()
    write_dataset(df, meta, d / "cal.parquet")
    # the twin's own parameter values, in the fitted-model file format (deltatwin fit -o)
    doc = {"model": {"effects": MODEL_EFFECTS, "sensors": dict(sc.sensors)},
           "effects": {e.name: dict(e.values) for e in sc.effects if e.name in MODEL_EFFECTS}}
    (d / "true.toml").write_text(toml_text(doc))
    return d


def _run(d, *extra):
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        code = main(["compensate", str(d / "lab.toml"), "--model", str(d / "true.toml"),
                     "--data", str(d / "cal.parquet"), "--targets", str(TARGETS), "--seed", "3",
                     "-o", str(d / "comp.parquet"), "--json", "--quiet", *extra])
    assert code == 0, out.getvalue()
    return json.loads(out.getvalue().strip().splitlines()[-1])


@pytest.fixture(scope="module")
def compensated(lab):
    """The first run's report: comp.parquet, its journal, the recording and the controller's
    files in ``lab`` (a test selected alone still finds them)."""
    return _run(lab, "--view", str(lab / "comp.rrd"), "--controller",
                str(lab / "controller.json"))


def test_true_model_compensates_to_the_noise(lab, compensated):
    rep = compensated
    assert (lab / "comp.rrd").stat().st_size > 0 and rep["view"].endswith("comp.rrd")
    exported = controller_evaluator.load(lab / "controller.json")     # the controller's file
    assert exported["source"]["effects"] == MODEL_EFFECTS
    assert [s["kind"] for s in exported["optics"]["steps"]] == ["loop_drift", "air_refraction"]
    # beside it, the same model as the C evaluator's block
    assert (lab / "controller.bin").read_bytes() == coefficient_block(exported).tobytes()
    assert rep["model"]["kind"] == "physics" and rep["n_not_converged"] == 0
    df = pd.read_parquet(lab / "comp.parquet")
    assert len(df) == 2 * TARGETS and list(df["command"][:2]) == ["nominal", "model"]
    for a in "xyz":
        r = rep["axes"][a]
        # 5 nm reading noise: |error| p90 of a normal is 1.645 sigma = 8 nm
        assert r["achieved_err90_nm"] < 15.0, (a, r)
        assert r["uncompensated_err90_nm"] > 3 * r["achieved_err90_nm"], (a, r)
        assert r["predicted_err90_nm"] < 15.0, (a, r)
        err = df.loc[df["command"] == "model", f"error_{a}_nm"].to_numpy()
        assert np.percentile(np.abs(err), 90) == pytest.approx(r["achieved_err90_nm"])
    # later than the calibration: the room has moved on, outside the calibrated range
    assert rep["outside_calibration_range"]
    # each decision's conditions are journaled with its point
    journal = (lab / "comp.parquet.journal").read_text().splitlines()
    point = json.loads(journal[2])["point"]
    assert point["control"]["mode"] == "model" and len(point["q_cmd_rad"]) == 3


def test_resume_continues_from_the_journal(lab, compensated):
    """A run stopped after 7 points (and a torn line) resumes: the journaled points are kept as
    they were; the interferometers are zeroed again at home (the zero did not survive), and
    the controller takes that zero's conditions, so the resumed points are compensated as
    well."""
    first = pd.read_parquet(lab / "comp.parquet")
    journal = lab / "comp.parquet.journal"
    lines = journal.read_text().splitlines(keepends=True)
    journal.write_text("".join(lines[:1 + 7]) + lines[8][:40])    # 7 points + a torn line
    (lab / "comp.parquet").unlink()
    rep = _run(lab, "--resume")
    assert rep["resumed_with"] == 7
    again = pd.read_parquet(lab / "comp.parquet")
    pd.testing.assert_frame_equal(first.iloc[:7], again.iloc[:7])
    assert not np.allclose(first["t_s"][7:], again["t_s"][7:])     # a new zero, later
    points = [json.loads(x)["point"] for x in journal.read_text().splitlines()[1:]]
    assert [p["rezero"] for p in points[6:9]] == [False, True, False]
    model = again["command"] == "model"
    for a in "xyz":
        assert np.percentile(np.abs(again.loc[model, f"error_{a}_nm"][7:]), 90) < 15.0, a


def test_bad_input_is_named(lab, capsys):
    code = main(["compensate", str(lab / "lab.toml"), "--model", str(lab / "nope.toml")])
    assert code == 2 and "nope.toml" in capsys.readouterr().err
    code = main(["compensate", str(lab / "lab.toml"), "--model", str(lab / "true.toml"),
                 "--targets", "0"])
    assert code == 2 and "--targets" in capsys.readouterr().err
    code = main(["compensate", str(lab / "lab.toml"), "--model", str(lab / "true.toml"),
                 "--zero-settles", "0"])
    assert code == 2 and "--zero-settles" in capsys.readouterr().err


def test_a_controller_file_that_cannot_be_written_is_refused_before_the_run(lab, capsys):
    """--controller naming a folder: exit 2 naming it, before any point is run (no compensated
    data written)."""
    out = lab / "never.parquet"
    code = main(["compensate", str(lab / "lab.toml"), "--model", str(lab / "true.toml"),
                 "--data", str(lab / "cal.parquet"), "--targets", "2", "-o", str(out),
                 "--controller", str(lab)])
    assert code == 2 and "is a folder" in capsys.readouterr().err
    assert not out.exists()


def test_a_fitted_model_s_band_holds_what_it_achieves_and_a_model_lacking_an_effect_s_does_not(
        lab):
    """A fitted model file carries its covariance: compensate reports the achieved error's 95 %
    band (its parameters' uncertainty in the conditions each target was commanded in, and its
    own validation errors' differences). The twin's effects fitted to the calibration data
    reach their targets within it on every axis; without the loop's drift the model misses
    the targets by more than its band on the axis the drift moves most."""
    for effects, name in ((MODEL_EFFECTS, "fitted"), (["thermal_expansion", "air_refraction"],
                                                      "no-drift")):
        assert main(["fit", str(lab / "cal.parquet"), "--effects", ",".join(effects), "-q",
                     "-o", str(lab / f"{name}.toml")]) == 0
    reports = {}
    for name in ("fitted", "no-drift"):
        out = io.StringIO()
        with contextlib.redirect_stdout(out):
            assert main(["compensate", str(lab / "lab.toml"), "--model", str(lab / f"{name}.toml"),
                         "--data", str(lab / "cal.parquet"), "--targets", str(TARGETS),
                         "--seed", "3", "-o", str(lab / f"{name}.parquet"), "--json",
                         "--quiet"]) == 0
        reports[name] = json.loads(out.getvalue().strip().splitlines()[-1])["axes"]
    for a, r in reports["fitted"].items():
        low, high = r["predicted_band_err90_nm"]
        assert low <= r["achieved_err90_nm"] <= high and r["within_band"], (a, r)
    missed = [a for a, r in reports["no-drift"].items()
              if r["achieved_err90_nm"] > r["predicted_band_err90_nm"][1]]
    assert missed and all(not reports["no-drift"][a]["within_band"] for a in missed), reports
