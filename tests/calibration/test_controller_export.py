"""The physics model exported for a controller (issue 19 item 4): the standalone reference
evaluator's forward and inverse against the fitted model it was exported from."""
import ast
from pathlib import Path

import numpy as np
import pytest

from deltatwin.calibration.errors import FitError
from deltatwin.calibration.physics import controller_evaluator as ce
from deltatwin.calibration.physics.export import (
    evaluator_conditions,
    write_controller_model,
)
from deltatwin.calibration.physics.inverse import with_motor_coordinates
from deltatwin.calibration.physics.measurements import measurements
from deltatwin.calibration.physics.model import PhysicsModel, model_effects
from deltatwin.twin.scenario import Scenario

MATCH_M = 1e-11       # the issue: the exported model equals the fitted one to < 0.01 nm


@pytest.fixture(scope="module")
def force_case():
    """paper-force at its reduced scale (coil currents, every model effect) and a model of all
    eight model effects at values away from their defaults and starts (drawn from a seeded
    generator within their fit scales), as a fit would leave them."""
    sc = Scenario.load("paper-force")
    df, meta = sc.simulate(sc.reduced_scale)
    rng = np.random.default_rng(19)
    base = PhysicsModel(model_effects())
    theta = base.theta() + rng.normal(0.0, 0.5, base.n_free) * base.scales
    base.set_theta(theta)
    model = PhysicsModel(model_effects(), None, base.values())
    meas = measurements(df, meta, model.params)
    meas.cos_scale[:] = 1.0            # a controller's readings are not cosine corrected
    meas.cos_offset[:] = 0.0
    return model, meas, meta


def _session_rows(meas):
    """Every other row, grouped by session zero."""
    rows = np.arange(0, meas.n, 2)
    return [rows[meas.zero_row[rows] == z] for z in np.unique(meas.zero_row[rows])]


def test_exported_model_forward_and_inverse_match_the_fitted_model(force_case, tmp_path):
    model, meas, meta = force_case
    path = write_controller_model(model, tmp_path / "controller.json", meta["sensors"])
    exported = ce.load(path)
    assert exported["statics"]["check"]["preload_max_error_m"] <= 1e-13
    pred = model.predict_path(meas)
    assert np.ptp(meas.points.currents_A) > 0.1             # the coils were driven
    worst_forward, worst_inverse, n = 0.0, 0.0, 0
    for rows in _session_rows(meas):
        cond, zero = evaluator_conditions(model, meas, rows)
        session = ce.Session(exported, zero)
        got = session.forward(meas.points.q[rows], cond)
        worst_forward = max(worst_forward, np.abs(got - pred[rows]).max())
        # the inverse from home: the exported model's q gives the fitted model's readings
        res = session.inverse(pred[rows], cond)
        assert (res["status"] == "converged").all()
        assert res["residual_m"].max() <= 1e-12
        assert np.abs(res["q"] - meas.points.q[rows]).max() < 1e-9
        back = model.predict_path(with_motor_coordinates(meas, rows, res["q"]))[rows]
        worst_inverse = max(worst_inverse, np.abs(back - pred[rows]).max())
        n += rows.size
    assert n > 50
    assert worst_forward < MATCH_M, worst_forward
    assert worst_inverse < MATCH_M, worst_inverse


def test_inverse_warm_start_and_stroke(force_case, tmp_path):
    model, meas, meta = force_case
    exported = ce.load(write_controller_model(model, tmp_path / "c.json", meta["sensors"]))
    rows = _session_rows(meas)[0][:10]
    cond, zero = evaluator_conditions(model, meas, rows)
    session = ce.Session(exported, zero)
    target = session.forward(meas.points.q[rows], cond)
    cold = session.inverse(target, cond)
    warm = session.inverse(target + 1e-9, cond, q0=cold["q"], pose0=cold["pose"])
    assert (warm["status"] == "converged").all() and warm["iterations"] < cold["iterations"]
    # a target only reachable beyond the stroke's end: found there and flagged
    lo, hi = exported["geometry"]["stroke_rad"]
    beyond = np.array([[hi + 0.005, 0.0, 0.0]])
    res = session.inverse(session.forward(beyond, {}), {})
    assert res["status"][0] == "out_of_stroke", res
    assert np.abs(res["q"] - beyond).max() < 1e-9


def test_evaluator_is_standalone_and_refuses_other_formats(tmp_path):
    """numpy and the standard library only: a controller's author reads and ports it alone."""
    tree = ast.parse(Path(ce.__file__).read_text())
    imported = {a.name.split(".")[0] for n in ast.walk(tree) if isinstance(n, ast.Import)
                for a in n.names}
    imported |= {n.module.split(".")[0] for n in ast.walk(tree)
                 if isinstance(n, ast.ImportFrom) and n.module}
    assert imported <= {"numpy", "json", "sys", "__future__"}, imported
    bad = tmp_path / "bad.json"
    bad.write_text('{"format": "deltatwin-physics-model", "format_version": 1}')
    with pytest.raises(ce.ControllerModelError, match="format"):
        ce.load(bad)
    bad.write_text('{"format": "deltatwin-physics-controller", "form')     # cut short
    with pytest.raises(ce.ControllerModelError, match="not a JSON file"):
        ce.load(bad)
    for missing in (tmp_path / "absent.json", tmp_path):           # no file; a folder
        with pytest.raises(ce.ControllerModelError, match="cannot be read"):
            ce.load(missing)


def test_the_standalone_evaluator_refuses_a_bad_file_with_exit_2(tmp_path, capsys):
    """The evaluator's own command line: a broken file is an error message and exit 2."""
    bad = tmp_path / "bad.json"
    bad.write_text("[1, 2")
    assert ce.main([str(bad)]) == 2
    assert "bad.json" in capsys.readouterr().err
    assert ce.main([str(tmp_path / "absent.json")]) == 2


def test_export_refuses_an_effect_it_cannot_evaluate(tmp_path, monkeypatch):
    from deltatwin.calibration.physics import export
    monkeypatch.setattr(export, "EXPORTED", export.EXPORTED - {"gravity_sag"})
    with pytest.raises(FitError, match="gravity_sag"):
        export.controller_model(PhysicsModel(["gravity_sag"]))
