"""The physics model exported for a controller: the standalone reference
evaluator's forward and inverse against the fitted model it was exported from, and the
portable C evaluator (compiled here with the system compiler) against both."""
import ast
import shutil
from pathlib import Path

import numpy as np
import pytest

from deltatwin.calibration.errors import FitError
from deltatwin.calibration.physics import controller_c
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
C_MATCH_M = 1e-12     # the C evaluator equals the numpy one (readings, m; q, rad)
THERMAL_EFFECTS = ["geometric_errors", "thermal_expansion", "gravity_sag", "loop_drift",
                   "air_refraction", "beam_misalignment", "sensor_contact"]


def _case(df, meta, effects, seed):
    """A model of ``effects`` at values away from their defaults and starts (drawn from a
    seeded generator within their fit scales), as a fit would leave them, and the data's
    measurements as a controller reads them."""
    rng = np.random.default_rng(seed)
    base = PhysicsModel(effects)
    theta = base.theta() + rng.normal(0.0, 0.5, base.n_free) * base.scales
    base.set_theta(theta)
    model = PhysicsModel(effects, None, base.values())
    meas = measurements(df, meta, model.params)
    meas.cos_scale[:] = 1.0            # a controller's readings are not cosine corrected
    meas.cos_offset[:] = 0.0
    return model, meas, meta


@pytest.fixture(scope="module")
def force_case():
    """paper-force at its reduced scale (coil currents) and all eight model effects."""
    sc = Scenario.load("paper-force")
    return _case(*sc.simulate(sc.reduced_scale), model_effects(), 19)


@pytest.fixture(scope="module")
def thermal_case(thermal_data):
    """paper-thermal at 3 % (the DGM tests' campaign) and the thermal model's effects (no
    coils: the weight alone loads the platform)."""
    return _case(*thermal_data, THERMAL_EFFECTS, 20)


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


@pytest.fixture(scope="module")
def c_library(tmp_path_factory):
    if shutil.which("cc") is None and shutil.which("gcc") is None:
        pytest.skip("no C compiler (cc or gcc) on PATH: the C evaluator is not built")
    return controller_c.compile_library(tmp_path_factory.mktemp("c_evaluator"))


@pytest.mark.parametrize("case", ["thermal_case", "force_case"])
def test_c_evaluator_equals_the_numpy_evaluator_and_the_fitted_model(case, c_library, request,
                                                                     tmp_path):
    """Forward and inverse (from home, one point at a time) of the compiled C evaluator on
    the block the exporter wrote beside the JSON, against the numpy evaluator of that JSON and
    the fitted model; the block is the JSON's contents (regenerated from it, equal bytes)."""
    model, meas, meta = request.getfixturevalue(case)
    path = write_controller_model(model, tmp_path / "controller.json", meta["sensors"])
    block = controller_c.block_path(path)
    exported = ce.load(path)
    assert controller_c.coefficient_block(exported).tobytes() == block.read_bytes()
    pred = model.predict_path(meas)
    worst = {"forward": 0.0, "forward_fitted": 0.0, "q": 0.0, "inverse_fitted": 0.0}
    n = 0
    for rows in _session_rows(meas):
        rows = rows[:: max(1, rows.size // 25)]
        cond, zero = evaluator_conditions(model, meas, rows)
        session = ce.Session(exported, zero)
        c_session = controller_c.CSession(c_library, block, {k: v for k, v in zero.items()})
        ref_forward = session.forward(meas.points.q[rows], cond)
        q_c = np.empty((rows.size, 3))
        for i in range(rows.size):
            c_cond = c_session.conditions({k: v[i] for k, v in cond.items()})
            got = c_session.forward(meas.points.q[rows[i]], c_cond)
            worst["forward"] = max(worst["forward"], np.abs(got - ref_forward[i]).max())
            worst["forward_fitted"] = max(worst["forward_fitted"],
                                          np.abs(got - pred[rows[i]]).max())
            # one point at a time as a controller does (a batch iterates until all converge)
            ref = session.inverse(pred[rows[i]], {k: v[i:i + 1] for k, v in cond.items()})
            res = c_session.inverse(pred[rows[i]], c_cond)
            assert res["status"] == ref["status"][0] == "converged", res
            assert res["residual_m"] <= 1e-12 and res["iterations"] == ref["iterations"]
            q_c[i] = res["q"]
            worst["q"] = max(worst["q"], np.abs(q_c[i] - ref["q"][0]).max())
        back = model.predict_path(with_motor_coordinates(meas, rows, q_c))[rows]
        worst["inverse_fitted"] = max(worst["inverse_fitted"], np.abs(back - pred[rows]).max())
        n += rows.size
    assert n >= 25
    assert worst["forward"] < C_MATCH_M and worst["q"] < C_MATCH_M, worst
    assert worst["forward_fitted"] < MATCH_M and worst["inverse_fitted"] < MATCH_M, worst
    print(f"C - numpy evaluator, {n} rows: forward {worst['forward']:.2g} m, inverse q "
          f"{worst['q']:.2g} rad; C - fitted model: forward {worst['forward_fitted']:.2g} m, "
          f"the fitted model at the C inverse's q {worst['inverse_fitted']:.2g} m")


def test_c_evaluator_warm_start_stroke_and_refusals(force_case, c_library, tmp_path):
    """A warm-started point takes the numpy evaluator's steps to its q; a target beyond the
    stroke is found there and flagged; a target that is not a number is not_finite; a block
    of another layout is refused."""
    model, meas, meta = force_case
    path = write_controller_model(model, tmp_path / "c.json", meta["sensors"])
    exported = ce.load(path)
    rows = _session_rows(meas)[0][:5]
    cond, zero = evaluator_conditions(model, meas, rows)
    session = ce.Session(exported, zero)
    c_session = controller_c.CSession(c_library, controller_c.block_path(path), zero)
    for i in range(rows.size):
        one = {k: v[i:i + 1] for k, v in cond.items()}
        c_cond = c_session.conditions({k: v[i] for k, v in cond.items()})
        target = session.forward(meas.points.q[rows[i]], one)[0]
        cold = session.inverse(target, one)
        pose = c_session.new_pose()
        c_cold = c_session.inverse(target, c_cond, pose=pose)
        warm = session.inverse(target + 1e-6, one, q0=cold["q"], pose0=cold["pose"])
        c_warm = c_session.inverse(target + 1e-6, c_cond, q0=c_cold["q"], pose=pose)
        assert (c_cold["iterations"], c_warm["iterations"]) == (cold["iterations"],
                                                                warm["iterations"])
        assert c_warm["iterations"] < c_cold["iterations"]
        assert c_warm["status"] == "converged"
        assert np.abs(c_warm["q"] - warm["q"][0]).max() < C_MATCH_M
    lo, hi = exported["geometry"]["stroke_rad"]
    beyond = np.array([hi + 0.005, 0.0, 0.0])
    ref = c_session.conditions({})
    target = c_session.forward(beyond, ref)
    res = c_session.inverse(target, ref)
    numpy_res = ce.Session(exported, zero).inverse(target, {})
    assert res["status"] == numpy_res["status"][0] == "out_of_stroke", res
    assert np.abs(res["q"] - beyond).max() < 1e-9
    assert c_session.inverse([np.nan, 0.0, 0.0], ref)["status"] == "not_finite"
    bad = tmp_path / "bad.bin"
    controller_c.coefficient_block(exported)[:-1].tofile(bad)        # one double short
    with pytest.raises(controller_c.ControllerCError, match="cannot be read"):
        controller_c.CSession(c_library, bad, zero)
    with pytest.raises(ValueError, match="must not end in .bin"):
        write_controller_model(model, tmp_path / "c.bin", meta["sensors"])
