"""The exported model file evaluated by the plain-Python reference evaluator (what a controller
implements) equals the fitted model: outputs, the DGM's inverse with its stroke statuses, and
the direct IGM."""
import numpy as np
import pytest

from deltatwin.calibration.blackbox import reference_evaluator as ref
from deltatwin.calibration.blackbox.igm import IGM

STROKE = (-0.065, 0.065)


@pytest.fixture(scope="module")
def exported(tmp_path_factory, thermal_dgm, force_igm):
    d = tmp_path_factory.mktemp("export")
    return ref.load(thermal_dgm.save(d / "dgm.json")), ref.load(force_igm.save(d / "igm.json"))


def _points(dgm, df, n, rng, q_scale=1.0):
    vals = dgm.variables(df)
    rows = rng.integers(0, len(df), n)
    aux = {v: vals[v][rows] for v in IGM(dgm).aux_variables}
    q = rng.uniform(q_scale * STROKE[0], q_scale * STROKE[1], (n, 3))
    return aux, q


def test_reference_evaluator_equals_the_fitted_dgm(exported, thermal_dgm, thermal_data):
    model, _ = exported
    rng = np.random.default_rng(31)
    aux, q = _points(thermal_dgm, thermal_data[0], 300, rng)
    fitted = thermal_dgm.predict_values({**aux, "q1": q[:, 0], "q2": q[:, 1], "q3": q[:, 2]})
    for i in range(300):
        out = ref.evaluate(model, {**{k: float(v[i]) for k, v in aux.items()},
                                   "q1": q[i, 0], "q2": q[i, 1], "q3": q[i, 2]})
        for j, name in enumerate(thermal_dgm.output_names_):
            assert out[name] == pytest.approx(fitted[i, j], rel=0, abs=1e-15)   # m


def test_reference_inverse_equals_the_igm(exported, thermal_dgm, thermal_data):
    model, _ = exported
    rng = np.random.default_rng(32)
    aux, q = _points(thermal_dgm, thermal_data[0], 40, rng, q_scale=3.0)   # some out of stroke
    order = [thermal_dgm.output_names_.index(a) for a in "xyz"]
    target = thermal_dgm.predict_values({**aux, "q1": q[:, 0], "q2": q[:, 1],
                                         "q3": q[:, 2]})[:, order]
    res = IGM(thermal_dgm, stroke_rad=STROKE).solve(target, aux)
    assert 0 < res.converged.sum() < 40                  # both kinds of answer are compared
    for i in range(40):
        qr, status = ref.inverse(model, target[i].tolist(),
                                 {k: float(v[i]) for k, v in aux.items()}, STROKE)
        assert status == res.status[i]
        if status == "converged":
            assert np.abs(np.array(qr) - res.q[i]).max() < 1e-12


def test_reference_evaluator_equals_the_direct_igm(exported, force_igm, force_data):
    _, model = exported
    df = force_data[0]
    vals = force_igm.variables(df)
    fitted = force_igm.predict_values(vals)
    for i in np.random.default_rng(33).integers(0, len(df), 100):
        out = ref.evaluate(model, {k: float(v[i]) for k, v in vals.items()})
        for j, name in enumerate(force_igm.output_names_):
            assert out[name] == pytest.approx(fitted[i, j], rel=0, abs=1e-15)    # rad


def test_reference_evaluator_refuses_other_files(tmp_path):
    p = tmp_path / "x.json"
    p.write_text('{"format": "something else"}')
    with pytest.raises(ValueError, match="not a deltatwin-calibration-model"):
        ref.load(p)
