"""The IGM respects the robot: a root outside the actuators' stroke or a
target out of reach is reported as such with a reason, never as converged; in-stroke roots are
preferred over out-of-stroke ones."""
import numpy as np
import pytest

from deltatwin.calibration.blackbox.dgm import DGM
from deltatwin.calibration.blackbox.estimator import OutputModel
from deltatwin.calibration.blackbox.features import FeatureSet, Term, geometric
from deltatwin.calibration.blackbox.igm import IGM, STATUSES
from deltatwin.calibration.errors import CalibrationInputError

STROKE = 0.065      # the nominal robot's stroke, +-rad (models/delta_agietron/params.toml)


@pytest.fixture(scope="module")
def setup(thermal_data, thermal_dgm):
    df, _ = thermal_data
    igm = IGM(thermal_dgm)
    rng = np.random.default_rng(21)
    n = 1500
    vals = thermal_dgm.variables(df)
    rows = rng.integers(0, len(df), n)
    aux = {v: vals[v][rows] for v in igm.aux_variables}
    order = [thermal_dgm.output_names_.index(a) for a in "xyz"]

    def dgm(q):
        return thermal_dgm.predict_values({**aux, "q1": q[:, 0], "q2": q[:, 1],
                                           "q3": q[:, 2]})[:, order]
    return igm, aux, dgm, rng, n


def _check_answers(igm, res, target, dgm):
    """Every converged answer is in the stroke and reaches the target to 0.001 nm (checked
    by the DGM's own prediction); every other answer has a status and a reason."""
    assert igm.stroke_rad == (-STROKE, STROKE)
    assert set(res.status) <= set(STATUSES)
    c = res.converged
    assert np.array_equal(c, res.status == "converged")
    assert np.all(np.abs(res.q[c]) <= STROKE + 1e-12)
    assert np.abs(dgm(res.q)[c] - target[c]).max(initial=0) <= 1e-12
    for i in np.flatnonzero(~c)[:20]:
        assert res.reason(i).startswith(("out of stroke", "out of reach", "not finite"))
    out = res.status == "out_of_stroke"
    # an out-of-stroke root is a root: it reaches the target, outside the stroke
    assert np.all(np.abs(res.q[out]).max(axis=1) > STROKE)
    assert np.abs(dgm(res.q)[out] - target[out]).max(initial=0) <= 1e-12


def test_targets_of_angles_up_to_6x_the_stroke_are_not_converged(setup):
    igm, aux, dgm, rng, n = setup
    q_far = rng.uniform(-6 * STROKE, 6 * STROKE, (n, 3))
    target = dgm(q_far)
    res = igm.solve(target, aux)
    _check_answers(igm, res, target, dgm)
    outside = np.abs(q_far).max(axis=1) > STROKE
    # before: every one came back "converged" at its out-of-stroke angles. Now none does
    # unless the model has another root inside the stroke (then that root is returned)
    assert outside.sum() > 0.99 * n
    assert res.converged[outside].mean() < 0.01
    assert np.all(igm.in_stroke(res.q[res.converged]))


@pytest.mark.parametrize("distance_m, max_converged, min_converged", [
    (1e-3, 0.98, 0.5), (1e-2, 0.4, 0.0), (1e-1, 0.0, 0.0)])
def test_targets_off_reachable_ones(setup, distance_m, max_converged, min_converged):
    """Targets 1 mm, 1 cm and 10 cm (random direction) from reachable ones: before, 19 %, 93 %
    and 62 % came back "converged" at out-of-stroke or meaningless distant roots."""
    igm, aux, dgm, rng, n = setup
    q_in = rng.uniform(-STROKE, STROKE, (n, 3))
    u = rng.standard_normal((n, 3))
    target = dgm(q_in) + distance_m * u / np.linalg.norm(u, axis=1)[:, None]
    res = igm.solve(target, aux)
    _check_answers(igm, res, target, dgm)
    assert min_converged <= res.converged.mean() <= max_converged
    assert not np.any(res.status == "not_finite")


def test_in_stroke_root_is_preferred_to_the_first_start():
    """x = q1^2 - 0.1 q1 has the roots 0.05 +- sqrt(0.0025 + x): for x = 1.11e-3 one is
    outside the stroke (0.1101 rad), where Newton from q0 = 0.2 ends, the other inside
    (-0.0101 rad): the in-stroke one is returned."""
    fs = FeatureSet([geometric()])
    mk = lambda name, terms, c: OutputModel(name, "m", f"{name}_nm", 1e-9, terms, np.array(c),
                                            0.0, np.zeros(len(c)), np.ones(len(c)), 0.0, 1.0)
    dgm = DGM.from_outputs(fs, [mk("x", [Term((("q1", 2),)), Term((("q1", 1),))], [1.0, -0.1]),
                                mk("y", [Term((("q2", 1),))], [0.1]),
                                mk("z", [Term((("q3", 1),))], [0.1])])
    igm = IGM(dgm)
    target = np.array([[1.11e-3, 1e-3, -2e-3]])
    root = np.sqrt(0.0025 + 1.11e-3)
    alone = IGM(dgm, stroke_rad=(-1.0, 1.0)).solve(target, q0=[0.2, 0.0, 0.0])
    assert alone.converged[0] and alone.q[0, 0] == pytest.approx(0.05 + root, abs=1e-9)
    res = igm.solve(target, q0=[0.2, 0.0, 0.0])
    assert res.converged[0] and res.q[0, 0] == pytest.approx(0.05 - root, abs=1e-9)
    assert res.residual_m[0] <= 1e-12
    # x = 0.02: roots 0.2 and -0.1, both outside the stroke
    res = igm.solve(np.array([[0.02, 1e-3, -2e-3]]), q0=[0.2, 0.0, 0.0])
    assert res.status[0] == "out_of_stroke" and not res.converged[0]
    assert res.q[0, 0] == pytest.approx(0.2, abs=1e-9) and "out of stroke" in res.reason(0)


def test_nan_target_and_bad_stroke(setup, thermal_dgm):
    igm, aux, dgm, _, n = setup
    target = dgm(np.zeros((n, 3)))
    target[1, 2] = np.nan
    res = igm.solve(target, aux)
    assert list(res.status[:3]) == ["converged", "not_finite", "converged"]
    assert "not finite" in res.reason(1)
    with pytest.raises(CalibrationInputError, match="stroke_rad"):
        IGM(thermal_dgm, stroke_rad=(0.1, -0.1))
