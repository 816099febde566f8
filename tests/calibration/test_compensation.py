"""Compensation in the loop: the physics model inverted, and each model kind's
command with the zero transfer, checked against the models' own forward predictions."""
from dataclasses import replace

import numpy as np
import pytest

from deltatwin.calibration.blackbox.dgm import DGM
from deltatwin.calibration.blackbox.direct_igm import DirectIGM
from deltatwin.calibration.compensation import (
    ConditionLog,
    DirectIGMCompensator,
    NominalCompensator,
    StepwiseCompensator,
    pairwise_differences,
    time_matched_differences,
)
from deltatwin.calibration.physics.inverse import PhysicsInverse, with_motor_coordinates
from deltatwin.calibration.physics.measurements import measurements
from deltatwin.calibration.physics.model import PhysicsModel
from deltatwin.twin.scenario import Scenario

STROKE = 0.065


@pytest.fixture(scope="module")
def thermal_measurements():
    sc = Scenario.load("paper-thermal")
    df, meta = sc.simulate(sc.reduced_scale)
    model = PhysicsModel(["geometric_errors", "thermal_expansion", "gravity_sag", "loop_drift",
                          "air_refraction"])
    return model, measurements(df, meta, model.params)


def test_physics_inverse_round_trip_within_0_001_nm(thermal_measurements):
    model, meas = thermal_measurements
    rows = np.arange(0, meas.n, 7)                   # rows of both sessions, many conditions
    q_true = meas.points.q[rows]
    target = model.predict_path(meas)[rows]
    inv = PhysicsInverse(model)
    res = inv.solve(meas, target, rows)
    assert res.converged.all()
    assert res.residual_m.max() <= 1e-12
    assert np.abs(res.q - q_true).max() < 1e-9
    # an independent evaluation of the model at the returned q, all rows at once
    back = model.predict_path(with_motor_coordinates(meas, rows, res.q))[rows]
    assert np.abs(back - target).max() <= 1e-12


def test_physics_inverse_flags_what_it_cannot_reach(thermal_measurements):
    model, meas = thermal_measurements
    rows = np.array([3, 10, 20])
    target = model.predict_path(meas)[rows]
    target[0] += [0.01, 0.0, 0.0]                      # 1 cm beyond a reachable target
    # the corner of the stroke, a little further still
    corner = with_motor_coordinates(meas, rows[1:2], np.full((1, 3), STROKE))
    target[1] = model.predict_path(corner)[rows[1]] + 2e-6 * np.sign(
        model.predict_path(corner)[rows[1]] - model.predict_path(meas)[rows[1]])
    target[2, 1] = np.nan
    res = PhysicsInverse(model).solve(meas, target, rows)
    assert list(res.status) == ["out_of_reach", "out_of_reach", "not_finite"]
    assert np.all(np.abs(res.q[:2]) <= STROKE)          # never outside the stroke
    assert res.residual_m[0] > 1e-3 and res.residual_m[1] > 1e-7
    assert "out of reach" in res.reason(0) and "not finite" in res.reason(2)


def _log(sensors, rng, n=40):
    log = ConditionLog(sensors)
    T0 = 20.5 + rng.normal(0, 0.2, len(sensors))
    log.zero(1000.0, T0)
    for k in range(n):                               # a scan every 10 s, warming at 0.5 K/h
        log.add(1000.0 + 10.0 * (k + 1), T0 + 0.5 * (k + 1) * 10 / 3600 + 0.3)
    return log


def test_stepwise_command_with_the_zero_transfer(thermal_dgm):
    rng = np.random.default_rng(4)
    log = _log(tuple(thermal_dgm.sensors_), rng)      # the DGM's structure sensors
    comp = StepwiseCompensator(thermal_dgm)
    comp.zero(log.frame().iloc[[0]])
    target = np.array([1.2e-3, -0.8e-3, 0.5e-3])
    frame = log.frame(target_m=target)
    cmd = comp.command(target, frame)
    assert cmd.status == "converged" and np.all(np.abs(cmd.q) <= STROKE)
    # the DGM at q in the present conditions, minus the DGM at home in the zero's conditions
    v = thermal_dgm.variables(frame)
    order = [thermal_dgm.output_names_.index(a) for a in "xyz"]
    at = lambda q, i: thermal_dgm.predict_values(
        {**{k: a[[i]] for k, a in v.items()}, "q1": q[:1], "q2": q[1:2], "q3": q[2:]})[0, order]
    v0 = thermal_dgm.variables(frame.iloc[[0]])
    home = thermal_dgm.predict_values({**v0, "q1": np.zeros(1), "q2": np.zeros(1),
                                       "q3": np.zeros(1)})[0, order]
    assert np.abs(at(cmd.q, -1) - home - target).max() <= 1e-12
    # the conditions moved the model's home reading: the transfer is not zero
    assert np.abs(at(np.zeros(3), -1) - home).max() > 1e-8


def test_direct_igm_command_with_the_zero_transfer(force_igm):
    log = _log((), np.random.default_rng(5))
    comp = DirectIGMCompensator(force_igm)
    comp.zero(log.frame().iloc[[0]])
    X0 = comp.zero_reading_m
    at = lambda X, F: force_igm.predict_values({"X": X[:1], "Y": X[1:2], "Z": X[2:],
                                                "F": np.array([F])})[0]
    assert np.abs(at(X0, 0.0)).max() < 1e-10          # home, coils off: q = 0
    target = np.array([0.4e-3, 0.3e-3, -0.2e-3])
    cmd = comp.command(target, log.frame(np.full(3, 1.3), 1.3, target))
    assert cmd.status == "converged"
    np.testing.assert_allclose(cmd.q, at(target + X0, 1.3), rtol=0, atol=1e-15)
    far = comp.command(np.array([0.2, 0.0, 0.0]), log.frame(np.zeros(3), 0.0))
    assert far.status == "out_of_stroke" and np.all(np.abs(far.q) <= STROKE)


def test_condition_log_keeps_the_zero_and_the_recent_history():
    log = ConditionLog(("a",), history_s=100.0)
    with pytest.raises(ValueError, match="zero"):
        log.frame()
    log.zero(0.0, [20.0])
    for t in (10.0, 10.0, 50.0, 200.0, 250.0):
        log.add(t, [20.0 + t / 1000])
    f = log.frame(np.full(3, 0.5), 0.5, np.array([1e-3, 0.0, 0.0]))
    assert f["t_s"].tolist() == [0.0, 200.0, 250.0]    # zero + the last 100 s
    assert f["coil1_A"].tolist() == [0.0, 0.0, 0.5] and f["F_N"].iloc[-1] == 0.5
    assert f["x_nm"].iloc[-1] == pytest.approx(1e6) and np.isnan(f["x_nm"].iloc[0])
    # the zero's temperature: the straight line through the zero's scan and the window after
    assert f["T_a_C"].iloc[0] == pytest.approx(20.0, abs=1e-12)


def test_the_zero_temperature_is_fitted_over_the_window_after_it():
    """One scan carries the thermometer's noise into every reading of a session; the line
    through the 600 s after the zero (all known at the first decision) carries a quarter."""
    rng = np.random.default_rng(5)
    errors = {"raw": [], "fitted": []}
    for _ in range(200):
        log = ConditionLog(("a", "b"))
        log.zero(100.0, 20.0 + 1e-3 * rng.standard_normal(2))
        assert log.zero_temperatures() == pytest.approx(log._zero_T)   # nothing after it yet
        for t in np.arange(110.0, 100.0 + 900.0, 10.0):     # drifting 1 mK/min, 1 mK noise
            log.add(t, 20.0 + (t - 100.0) / 60e3 + 1e-3 * rng.standard_normal(2))
        errors["raw"] += list(np.asarray(log._zero_T) - 20.0)
        errors["fitted"] += list(log.zero_temperatures() - 20.0)
        assert log.frame()["T_b_C"].iloc[0] == log.zero_temperatures()[1]
    raw, fitted = np.std(errors["raw"]), np.std(errors["fitted"])
    assert fitted < 0.35 * raw, (raw, fitted)          # 2 / sqrt(61) = 0.26 for a line's end


def test_an_averaged_zero_takes_the_temperatures_of_its_mean_time():
    """A zero averaged over home settles refers to their mean time, after its scan (read when
    the interferometers were zeroed): the line through the scans is taken at that time, and
    the scan enters it at its own time (on a ramp of 1 mK/min: exact)."""
    ramp = lambda t: 20.0 + t / 60e3
    log = ConditionLog(("a",))
    log.zero(135.0, [ramp(100.0)], scan_t_s=100.0)
    for t in np.arange(110.0, 700.0, 10.0):
        log.add(t, [ramp(t)])
    assert log.zero_temperatures()[0] == pytest.approx(ramp(135.0), abs=1e-12)
    assert log.frame()["t_s"].iloc[0] == 135.0


def test_nominal_forward_and_inverse_agree():
    nominal = NominalCompensator()
    log = ConditionLog(())
    log.zero(0.0, [])
    q = np.random.default_rng(6).uniform(-0.05, 0.05, (4, 3))
    x = nominal.forward(q, log.frame())
    assert np.all(np.abs(x) > 1e-5)                    # readings of tens of micrometres and more
    for k in range(4):
        cmd = nominal.command(x[k], log.frame(target_m=x[k]))
        assert cmd.status == "converged" and np.abs(cmd.q - q[k]).max() < 1e-9


def test_pairwise_differences_cancel_each_sessions_constant():
    """The prediction of a compensation: error at a target minus error at the zero, within one
    session; a constant per session cancels, independent errors give sqrt(2) sigma."""
    rng = np.random.default_rng(3)
    e = np.concatenate([rng.normal(0.0, 1.0, 3000) + 50.0, rng.normal(0.0, 1.0, 2000) - 80.0])
    group = np.repeat([0, 1], [3000, 2000])
    d = pairwise_differences(e, group)
    assert abs(d.mean()) < 0.05                       # no +50 / -80 constant survives
    assert abs(d.std() - np.sqrt(2.0)) < 0.03
    small = pairwise_differences(np.array([1.0, 2.0, 4.0, np.nan]), np.zeros(4, int))
    assert sorted(small.tolist()) == [-3.0, -2.0, -1.0, 1.0, 2.0, 3.0]   # every ordered pair
    assert pairwise_differences(np.array([1.0]), np.zeros(1, int)).size == 0


def test_a_dgm_s_band_is_its_coefficients_uncertainty_at_the_target_less_at_the_zero(
        thermal_data, thermal_dgm):
    """With calibration data the DGM fits to a constant per session (its own error none), the
    band of one target is that of |d|, d ~ N(0, s^2): s the spread of the reading's change from
    the zero under the coefficients' error. Checked against DGMs whose coefficients are drawn
    from the file's covariance, evaluated by the model's own evaluator."""
    df, meta = thermal_data
    order = [thermal_dgm.output_names_.index(a) for a in "xyz"]
    cal = df.copy()
    exact = thermal_dgm.predict(df)[:, order]
    for k, a in enumerate("xyz"):
        cal[f"{a}_nm"] = exact[:, k] * 1e9 + 7.0
    log = _log(tuple(thermal_dgm.sensors_), np.random.default_rng(6), n=80)
    frame = log.frame(target_m=np.array([1e-3, -1e-3, 5e-4]))
    frame.loc[frame.index[-1], ["q1_rad", "q2_rad", "q3_rad"]] = [0.03, -0.02, 0.045]
    rows = np.zeros(len(frame), bool)
    rows[-1] = True
    comp = StepwiseCompensator(thermal_dgm)
    band = comp.band(frame, rows, np.full(len(frame), frame["t_s"].iloc[0]), cal, meta,
                     np.random.default_rng(7), draws=4000)
    # the independent spread: the evaluator at the target less at home in the zero's conditions
    rng = np.random.default_rng(8)
    v, v0 = thermal_dgm.variables(frame), thermal_dgm.variables(frame.iloc[[0]])
    at_target = {k: a[-1:] for k, a in v.items()}
    home = {**v0, "q1": np.zeros(1), "q2": np.zeros(1), "q3": np.zeros(1)}
    changes = []
    for _ in range(400):
        outputs = [replace(o, coef=rng.multivariate_normal(o.coef, o.covariance))
                   for o in thermal_dgm.outputs_]
        drawn = DGM.from_outputs(thermal_dgm.features_, outputs, thermal_dgm.sensors_)
        changes.append((drawn.predict_values(at_target) - drawn.predict_values(home))[0])
    s = np.std(changes, axis=0)[order] * 1e9
    for k, a in enumerate("xyz"):
        low, high = band[a]
        assert s[k] > 1.0, (a, s)                 # a spread to see, not round-off
        assert high == pytest.approx(2.241 * s[k], rel=0.12), (a, band[a], s[k])
        assert low == pytest.approx(0.0313 * s[k], rel=0.5), (a, band[a], s[k])


def test_time_matched_differences_are_the_drift_over_the_gap_within_a_session():
    """Errors drifting at 2 nm/s in one session and -1 nm/s in another, on a 10 s grid, with
    each session's own constant: the difference of two rows as far apart as the gap is the
    drift over the gap, never mixing the sessions, whether the partner comes before or after
    (near a session's start); for a gap longer than the session the partner is the session's
    end farther away."""
    t = np.concatenate([np.arange(0.0, 600.0, 10.0), np.arange(5000.0, 5300.0, 10.0)])
    group = np.repeat([0, 1], [60, 30])
    err = np.where(group == 0, 2e-9 * t + 5e-6, -1e-9 * (t - 5000.0) - 3e-6)
    gaps = np.array([50.0, 120.0, 1000.0])
    d = time_matched_differences(err, group, t, gaps, np.random.default_rng(1), 500)
    for k, gap in enumerate(gaps[:2]):
        drift = np.abs(d[k])
        assert np.all(np.isclose(drift, 2e-9 * gap, rtol=1e-9, atol=0)
                      | np.isclose(drift, 1e-9 * gap, rtol=1e-9, atol=0))
        assert np.isclose(drift, 1e-9 * gap, rtol=1e-9, atol=0).any()
    # longer than either session: the partner is the end farther away, half a session at least
    assert np.all(np.abs(d[2]) >= 1e-9 * 150 - 1e-18)
    assert time_matched_differences(err[:1], group[:1], t[:1], gaps,
                                    np.random.default_rng(1), 5) is None


def test_a_zero_averaged_over_settles_has_its_noise_averaged():
    """White errors of 1 nm: a target less a single-reading zero differs by sqrt(2) nm; less a
    zero of 100 settles by about 1 nm (what is left of the zero's noise: the 5-row mean the
    slow part is taken over, a fifth of the variance)."""
    rng = np.random.default_rng(3)
    t = np.arange(0.0, 20000.0, 10.0)
    err = 1e-9 * rng.standard_normal(t.size)
    group = np.zeros(t.size, int)
    for settles, expected in ((1, 2.0), (100, 1.0 + 0.2 + 0.8 / 100)):
        d = time_matched_differences(err, group, t, np.full(50, 600.0),
                                     np.random.default_rng(4), 400, settles)
        assert np.var(d) / 1e-18 == pytest.approx(expected, rel=0.06), settles


def test_a_direct_igm_s_band_is_where_its_coefficients_error_sends_the_robot(force_data,
                                                                             force_igm):
    """With calibration data the direct IGM fits exactly, the band of one target is that of
    |d|, d the reading's error when models drawn from the file's covariance command the robot
    (their own zero transfer and command) and the fitted model is the robot (Newton on it
    finds where the commanded q takes it, read from its own home)."""
    df, meta = force_data
    cal = df.copy()
    exact = force_igm.predict(df)
    for k, motor in enumerate(("q1", "q2", "q3")):
        cal[f"{motor}_rad"] = exact[:, k]
    target, force = np.array([0.4e-3, 0.3e-3, -0.2e-3]), 1.3
    frame = _log((), np.random.default_rng(5), n=5).frame(np.full(3, force), force, target)
    frame = frame.assign(**{f"target_{a}_nm": target[k] * 1e9 for k, a in enumerate("xyz")})
    rows = np.zeros(len(frame), bool)
    rows[-1] = True
    band = DirectIGMCompensator(force_igm).band(
        frame, rows, np.full(len(frame), frame["t_s"].iloc[0]), cal, meta,
        np.random.default_rng(7), draws=4000)
    robot = DirectIGMCompensator(force_igm)
    robot.zero(frame.iloc[[0]])
    home = robot.zero_reading_m
    rng = np.random.default_rng(8)
    errors = []
    for _ in range(300):
        drawn = DirectIGMCompensator(DirectIGM.from_outputs(
            force_igm.features_, [replace(o, coef=rng.multivariate_normal(o.coef, o.covariance))
                                  for o in force_igm.outputs_], force_igm.sensors_))
        drawn.zero(frame.iloc[[0]])
        q = drawn.command(target, frame).q
        x = target + home
        for _ in range(8):
            at = {"X": x[:1], "Y": x[1:2], "Z": x[2:], "F": np.array([force])}
            x = x - np.linalg.solve(force_igm.jacobian(at)[0], force_igm.predict_values(at)[0] - q)
        errors.append(x - home - target)
    s = np.std(errors, axis=0) * 1e9
    for k, a in enumerate("xyz"):
        low, high = band[a]
        assert s[k] > 1.0, (a, s)
        assert high == pytest.approx(2.241 * s[k], rel=0.12), (a, band[a], s[k])
