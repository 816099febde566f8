"""The physics model is the twin's own physics: with the twin's true parameters it reproduces
noise-free readings counted from each session's zero (the dead path's index change included),
and the sensor_contact effect's inversion gives back the parts' temperatures from their
sensors."""
import os
import sys

import numpy as np
import pytest

from deltatwin.calibration.physics.measurements import measurements
from deltatwin.calibration.physics.model import (
    PhysicsModel,
    figures_nm,
    group_offsets,
    residuals,
    richardson_derivative,
)
from deltatwin.twin.campaign import simulate_campaign
from deltatwin.twin.scenario import Scenario

PARTS = ["base", "arm1", "arm2", "arm3", "rod1", "rod2", "rod3", "platform", "frame", "table"]
SCENARIO = """
[scenario]
name = "model-is-twin"
seed = 5

[effects]
on = ["thermal_expansion", "loop_drift", "air_refraction", "room_climate"{contact}]

[effects.room_climate]
ac_off_s = -3600.0
daily_amplitude_C = 2.0
pressure_std_Pa = 0.0          # the data record no barometer

[effects.air_refraction]
beam_room_fraction = 0.0       # the data record no room-air sensor away from the beams

[sensors]
{sensors}

[instruments]
noise_floor_m = 5e-9
T_noise_C = 0.0
T_resolution_C = 0.0

[campaign]
kind = "thermal"
warmup_s = 7200.0
n_positions = 100
sessions = [{{ name = "xy", axes = ["x", "y"], cal = 700, val = 300 }},
            {{ name = "z", axes = ["z"], cal = 700, val = 300 }}]
"""


def _scenario(tmp_path, contact: bool, more: str = "") -> Scenario:
    sensors = "\n".join(f'{p} = "{p}"' for p in PARTS + ["air_x", "air_y", "air_z"])
    path = tmp_path / "model-is-twin.toml"
    path.write_text(SCENARIO.format(contact=(', "sensor_contact"' if contact else "") + more,
                                    sensors=sensors))
    return Scenario.load(path)


def _noise_free(sc):
    twin, plan = sc.build()
    _, clean = simulate_campaign(plan, twin, sc.settings, sc.cosine, sc.dead_path(),
                                 noise_free=True)
    return twin, clean, sc.metadata(twin, None)


def _true_model_residual_nm(sc, twin, clean, meta, model_effects):
    values = {e.name: dict(e.values) for e in sc.effects if e.name in model_effects}
    model = PhysicsModel(model_effects, params=twin.params, values=values)
    meas = measurements(clean, meta, model.params)
    pred = model.predict_path(meas)
    res = residuals(meas, pred, group_offsets(meas, pred, meas.cal))
    return figures_nm(res, np.ones(meas.n, bool))["all"]["err_p90"], meas


def test_true_model_reproduces_noise_free_readings_counted_from_the_zero(tmp_path):
    sc = _scenario(tmp_path, contact=False)
    twin, clean, meta = _noise_free(sc)
    span = np.nanmax(np.abs(clean[["x_nm", "y_nm", "z_nm"]].to_numpy()))
    assert span > 1e4                          # the readings move by tens of micrometres
    err, _ = _true_model_residual_nm(sc, twin, clean, meta,
                                     ["thermal_expansion", "loop_drift", "air_refraction"])
    # without the zero term (the dead path times the index change since the zero) the same
    # model leaves 10.9 nm here
    assert err < 2.0, err


def test_held_supports_are_modelled_at_the_set_point_the_laboratory_states(tmp_path):
    """Peltier-held interferometer supports (the papers' laboratory: 25 degC, +-0.01) sit at
    their set point while the table warms under them: the data's setup states it (simulate
    writes it, as a laboratory knows its own set point), and the model's supports are then
    the twin's to its regulation; the same data without that statement put the supports at
    the table's temperature, kelvins off; the model reproduces the readings either way to
    what the loop's support term moves here (under a nanometre)."""
    sc = _scenario(tmp_path, contact=False, more=', "peltier_supports"')
    twin, clean, meta = _noise_free(sc)
    assert meta["setup"]["known"]["peltier_supports"] == {"setpoint_C": 25.0}
    effects = ["thermal_expansion", "loop_drift", "air_refraction"]
    err, meas = _true_model_residual_nm(sc, twin, clean, meta, effects)
    actual = twin.points(clean["t_s"].to_numpy(), np.zeros((len(clean), 3)),
                         np.zeros((len(clean), 3))).support_C
    n = meas.n
    for a in "xyz":
        assert np.abs(meas.points.support_C[a][:n] - actual[a]).max() < 0.05
    unstated = {**meta, "setup": {**meta["setup"], "known": {}}}
    err_unstated, meas = _true_model_residual_nm(sc, twin, clean, unstated, effects)
    assert meas.support_held_C is None
    assert np.abs(meas.points.support_C["z"][:n] - actual["z"]).min() > 2.0
    assert err < 2.0 and err < err_unstated, (err, err_unstated)


def test_sensor_contact_inversion_recovers_the_parts(tmp_path):
    sc = _scenario(tmp_path, contact=True)
    twin, clean, meta = _noise_free(sc)
    t = clean["t_s"].to_numpy()
    parts = twin.node_temperatures(t)
    effects = ["thermal_expansion", "loop_drift", "air_refraction"]
    model = PhysicsModel(effects + ["sensor_contact"], params=twin.params)
    meas = measurements(clean, meta, model.params)
    sensed = meas.part_temperatures(model.effects)
    raw = meas.sensor_node_T
    # after the causal rate's first window (600 s: before it the rate has no history, and the
    # lag's correction with it: 3.6-4.9 mK on an arm at the first row)
    later = t > 600.0
    for p in ("table", "frame", "base", "arm1"):
        err_raw = np.abs(raw[p][:meas.n] - parts[p])[later].max()
        err_inv = np.abs(sensed[p][:meas.n] - parts[p])[later].max()
        assert err_raw > 0.01, (p, err_raw)    # the sensor misses its part by > 10 mK
        assert err_inv < 0.3 * err_raw, (p, err_raw, err_inv)
    # and the model with the contact reproduces the readings; without it, it does not
    with_contact, _ = _true_model_residual_nm(sc, twin, clean, meta, effects + ["sensor_contact"])
    without, _ = _true_model_residual_nm(sc, twin, clean, meta, effects)
    assert with_contact < 0.5 * without, (with_contact, without)


def test_the_room_is_the_beams_air_less_what_the_held_supports_and_the_table_give_it(tmp_path):
    """The laboratory's air thermometers sit by the beams, whose air the Peltier-held supports
    (25 degC) and the table warm: the data's setup states those shares (room_climate's
    air_support_share, air_table_share; simulate writes the twin's network's), and the room
    taken from that air is the twin's room to mK; the contact's inversion then gives back the
    parts, and the model the readings. Without the shares the beams' air, 0.9 K above the
    room, stands for it, and the parts come out 50 mK off."""
    sc = _scenario(tmp_path, contact=True, more=', "peltier_supports"')
    twin, clean, meta = _noise_free(sc)
    t = clean["t_s"].to_numpy()
    room = np.interp(t, twin.t_grid, twin.env.room_C)
    parts = twin.node_temperatures(t)
    effects = ["thermal_expansion", "loop_drift", "air_refraction", "sensor_contact"]
    stated = meta["setup"]["known"]["room_climate"]
    assert stated == pytest.approx({"air_support_share": 0.3 / 1.35,
                                    "air_table_share": 0.05 / 1.35}, abs=1e-4)
    unstated = {**meta, "setup": {**meta["setup"], "known": {
        k: v for k, v in meta["setup"]["known"].items() if k != "room_climate"}}}
    found = {}
    for name, m in (("stated", meta), ("unstated", unstated)):
        err, meas = _true_model_residual_nm(sc, twin, clean, m, effects)
        sensed = PhysicsModel(effects, params=twin.params).effects
        sensed = meas.part_temperatures(sensed)
        found[name] = (err, np.abs(meas.points.room_C[:meas.n] - room).max(),
                       max(np.abs(sensed[p][:meas.n] - parts[p]).max() for p in PARTS))
    (err, room_off, part_off), (err_u, room_off_u, part_off_u) = found["stated"], found["unstated"]
    assert room_off < 0.02 and room_off_u > 0.5, found
    assert part_off < 0.01 and part_off_u > 0.04, found
    assert err < 1.0 and err_u > 4 * err, found


def test_without_sensor_contact_a_sensor_reads_its_part_exactly(tmp_path):
    sc = _scenario(tmp_path, contact=False)
    twin, clean, _ = _noise_free(sc)
    k = np.floor(clean["t_s"].to_numpy() / sc.settings.scan_period_s)
    parts = twin.node_temperatures(k * sc.settings.scan_period_s)
    for p in PARTS:
        np.testing.assert_array_equal(clean[f"T_{p}_C"].to_numpy(), parts[p])


@pytest.mark.parametrize("bad", [{"glue_W_per_K": 0.0}, {"leak_W_per_K": -0.001}])
def test_sensor_contact_refuses_impossible_contacts(bad):
    from deltatwin.twin.effects import EffectError, make_effect
    with pytest.raises(EffectError, match=next(iter(bad))):
        make_effect("sensor_contact", bad)


def _central_difference(model, meas, theta, j, step):
    """Richardson-extrapolated central differences of the whole prediction in parameter j,
    from ``step`` down (calibration.physics.model.richardson_derivative)."""
    def at(offset):
        th = theta.copy()
        th[j] += offset
        return (model.predict_path(meas, th),)
    return richardson_derivative(at, step)[0]


PATH_ROUND_OFF_M = 3e-16   # five ulps of a 0.3 m optical path: no difference resolves less


@pytest.mark.parametrize("scenario, effects", [
    ("quiet/loop-drift", ["geometric_errors", "thermal_expansion", "sensor_contact",
                           "loop_drift", "gravity_sag", "air_refraction", "beam_misalignment"]),
    ("quiet/magnetic-force", ["geometric_errors", "magnetic_force"])])
def test_jacobian_matches_central_differences_at_the_corrected_geometry(scenario, effects):
    """The Jacobian (implicit-function kinematics under each point's part temperatures, the
    home where the instruments were aligned, central differences elsewhere) agrees with central
    differences of the whole prediction to 1e-7 of each column (in m per fit scale; or to the
    paths' round-off, 3e-16 m, for a column that moves the readings by less than 3 nm), away from
    the starting values. The reference's own error is measured by differencing from two
    starting steps (3 and 0.7 fit scales, neither a step the Jacobian takes)."""
    df, meta = Scenario.load(scenario).simulate(0.02)
    model = PhysicsModel(effects, values={"loop_drift": {"frame_arm_m": [-0.6, 0.0]}}
                         if "loop_drift" in effects else None)
    meas = measurements(df, meta, model.params)
    theta = model.theta() + model.scales * np.random.default_rng(3).standard_normal(model.n_free)
    _, J = model.jacobian(meas, theta)
    for j, label in enumerate(model.labels):
        scale = model.scales[j]
        coarse = _central_difference(model, meas, theta, j, 3.0 * scale) * scale
        fine = _central_difference(model, meas, theta, j, 0.7 * scale) * scale
        size = np.nanmax(np.abs(coarse))
        assert size > 0, label
        reference_error = np.nanmax(np.abs(coarse - fine))
        assert reference_error < max(5e-8 * size, PATH_ROUND_OFF_M), (label, reference_error / size)
        error = np.nanmax(np.abs(J[:, :, j] * scale - coarse))
        assert error < max(1e-7 * size, PATH_ROUND_OFF_M), (label, error / size, size)


def _counting(calls: list):
    """A wrapper that records each offset a Richardson derivative evaluates in ``calls``."""
    def counted(f):
        def evaluate(offset):
            calls.append(offset)
            return (f(offset),)
        return evaluate
    return counted


def test_richardson_keeps_its_first_stencil_only_when_the_differences_agree():
    """Four evaluations for a function linear over the step (or whose differences are round-off
    below ``roundoff``); a curved one is still halved until the estimate settles."""
    calls = []
    counted = _counting(calls)
    x = np.linspace(-1.0, 1.0, 7)
    (d,) = richardson_derivative(counted(lambda h: 3e-9 * (1.0 + x) * h + 0.3), 1.0)
    assert len(calls) == 4 and np.allclose(d, 3e-9 * (1.0 + x), rtol=1e-6, atol=0)
    calls.clear()
    (d,) = richardson_derivative(counted(lambda h: np.sin(2.0 * (h + x))), 1.0)
    assert len(calls) > 4
    np.testing.assert_allclose(d, 2.0 * np.cos(2.0 * x), rtol=0, atol=1e-8)
    # a curvature whose share over the step is below the round-off floor given: four
    calls.clear()
    richardson_derivative(counted(lambda h: 1e-9 * h + 1e-17 * h ** 3 + x), 1.0, roundoff=1e-15)
    assert len(calls) == 4
    calls.clear()
    richardson_derivative(counted(lambda h: 1e-9 * h + 1e-17 * h ** 3 + x), 1.0)
    assert len(calls) > 4


def test_richardson_with_the_value_at_zero_keeps_three_evaluations_only_when_the_third_difference_is_small():
    """Given f(0), a function whose third derivative's share is below the tolerance costs three
    evaluations (f(h), f(-h), f(2h)) and its derivative is exact; a curved one is still
    halved until the estimate settles."""
    calls = []
    counted = _counting(calls)
    x = np.linspace(-1.0, 1.0, 7)
    quadratic = lambda h: 3e-9 * (1.0 + x) * h + 2e-9 * x * h ** 2 + 0.3  # noqa: E731
    (d,) = richardson_derivative(counted(quadratic), 1.0, at_zero=(quadratic(0.0),))
    assert len(calls) == 3 and np.allclose(d, 3e-9 * (1.0 + x), rtol=1e-6, atol=1e-15)
    calls.clear()
    cubic = lambda h: 1e-9 * h + 1e-18 * h ** 3 * (1 + x)  # noqa: E731
    # the third derivative's error removed: exact for a cubic too
    (d,) = richardson_derivative(counted(cubic), 1.0, at_zero=(cubic(0.0),))
    np.testing.assert_allclose(d, 1e-9, rtol=1e-12)
    assert len(calls) == 3
    calls.clear()
    wave = lambda h: np.sin(2.0 * (h + x))  # noqa: E731
    (d,) = richardson_derivative(counted(wave), 1.0, at_zero=(wave(0.0),))
    assert len(calls) > 4
    np.testing.assert_allclose(d, 2.0 * np.cos(2.0 * x), rtol=0, atol=1e-8)


def test_an_optics_step_re_uses_the_earlier_effects_optics_bit_for_bit():
    """A step of an optics parameter applies its effect and those after it on the optics the
    earlier effects made, and keeps the geometric reading of a beam the step left unmoved:
    the paths and indices equal those of the whole optics stage exactly, for a parameter of
    each optics effect (first, middle and last in the model) and both step signs."""
    effects = ["geometric_errors", "loop_drift", "air_refraction", "beam_misalignment"]
    df, meta = Scenario.load("quiet/loop-drift").simulate(0.02)
    model = PhysicsModel(effects, values={"loop_drift": {"frame_arm_m": [-0.6, 0.0]}})
    meas = measurements(df, meta, model.params)
    theta = model.theta() + model.scales * np.random.default_rng(4).standard_normal(model.n_free)
    model.set_theta(theta)
    stage = model._kinematics(meas)
    truth = model._truth(meas, stage)
    optics_at = model._optics_at(meas, stage, truth)
    at_theta = model._optics_paths(meas, stage, truth.pose)
    checked = set()
    for f in model.free:
        if f.effect == "geometric_errors":
            continue
        for j in (f.sl.start, f.sl.stop - 1):
            for sign in (1.0, -1.0):
                th = theta.copy()
                th[j] += sign * model.scales[j]
                model.set_theta(th)
                effect = model.effects[model.names.index(f.effect)]
                stepped = model._stepped_optics_paths(meas, stage, truth, effect, optics_at)
                whole = model._optics_paths(meas, stage, truth.pose)
                for got, want in zip(stepped, whole):
                    np.testing.assert_array_equal(got, want, err_msg=model.labels[j])
                # the step moved something (a path, or only the index of a compensation)
                assert any(np.any(w != a) for w, a in zip(whole, at_theta)), model.labels[j]
                checked.add(f.effect)
    assert checked == {"loop_drift", "air_refraction", "beam_misalignment"}


def test_a_probe_re_uses_the_fitted_models_linearisation_only_where_it_holds():
    """A diagnosis' probe (an effect appended at values where it changes nothing: where the
    motors sit, a load at zero force) re-uses the stage, readings and pose sensitivities of the
    model it extends (``jacobian(..., extends=)``): its columns equal those computed afresh, and
    the linearisation is refused where it does not hold (the base's values moved since its
    Jacobian, a probe that moves the motors, other measurements)."""
    from deltatwin.calibration.diagnosis.model_form import CurrentLoad, MotorError

    effects = ["geometric_errors", "thermal_expansion", "magnetic_force", "loop_drift"]
    df, meta = Scenario.load("quiet/magnetic-force").simulate(0.02)
    base = PhysicsModel(effects)
    meas = measurements(df, meta, base.params)
    assert np.ptp(meas.points.currents_A) > 0                 # the load probe sees currents
    theta = base.theta() + 0.3 * base.scales * np.random.default_rng(7).standard_normal(
        base.n_free)
    base.jacobian(meas, theta)

    def probe(cls, values, extends):
        model = PhysicsModel(effects + [cls], base.params, {**base.values(), cls.name: values})
        new = np.array([lab.startswith(cls.name) for lab in model.labels])
        reused = model._linearisation_of(extends, meas) is not None
        A, J = model.jacobian(meas, model.theta(), columns=new, extends=extends)
        return reused, A, J[:, :, new]

    for cls, values in ((MotorError, {"period_rad": (0.7, 1.1, 1.9)}), (CurrentLoad, {})):
        reused, A, J = probe(cls, values, base)
        assert reused, cls.name
        _, A_fresh, J_fresh = probe(cls, values, None)
        np.testing.assert_array_equal(A, A_fresh)
        size = np.max(np.abs(J_fresh), axis=(0, 1))
        assert np.all(size > 0), cls.name
        # the same numbers; to round-off only where the fresh kinematics take another path
        # (per point where the motors' positions are an array of their own)
        assert np.max(np.abs(J - J_fresh) / size) < 1e-12, cls.name
    # a probe that moves the motors is not at the base's stage
    assert not probe(MotorError, {"backlash_rad": (1e-6, 0.0, 0.0)}, base)[0]
    # nor a load that pushes
    assert not probe(CurrentLoad, {"force_N": ((0.0, 0.0, 1e-3),) + ((0.0,) * 3,) * 2},
                     base)[0]
    # other measurements (the same rows, another object)
    other = PhysicsModel(effects + [MotorError], base.params, base.values())
    assert other._linearisation_of(base, measurements(df, meta, base.params)) is None
    # the base's values moved since its Jacobian
    base.set_theta(theta + 0.1 * base.scales)
    assert not probe(MotorError, {}, base)[0]


def test_the_jacobian_is_the_same_whatever_its_row_chunks_and_the_columns_asked_for(monkeypatch):
    """The pose-moving blocks are formed chunk by chunk of rows (``_add_counted``), and a
    Jacobian of fewer than half its columns is stored column by column: neither changes a bit.
    Chunks of 7 rows (session zeros and run boundaries inside chunks) against one chunk for
    all rows; the columns of one effect asked for alone against the same columns of the whole
    Jacobian."""
    import deltatwin.calibration.physics.model as physics_model

    df, meta = Scenario.load("quiet/magnetic-force").simulate(0.02)
    model = PhysicsModel(["geometric_errors", "thermal_expansion", "magnetic_force",
                          "loop_drift", "beam_misalignment"],
                         values={"loop_drift": {"frame_arm_m": [-0.6, 0.0]}})
    meas = measurements(df, meta, model.params)
    theta = model.theta() + model.scales * np.random.default_rng(5).standard_normal(model.n_free)
    monkeypatch.setattr(physics_model, "ROW_CHUNK", meas.n + 1)
    A_one, J_one = model.jacobian(meas, theta)
    monkeypatch.setattr(physics_model, "ROW_CHUNK", 7)
    A, J = model.jacobian(meas, theta)
    assert meas.n > 50 and np.array_equal(A, A_one) and np.array_equal(J, J_one)
    for effect in ("thermal_expansion", "geometric_errors", "beam_misalignment"):
        few = np.zeros(model.n_free, bool)
        for f in model.free:
            few[f.sl] |= f.effect == effect
        _, J_few = model.jacobian(meas, theta, columns=few)
        # fewer than half the columns (all but the geometry's 63 of 92): column by column
        assert J_few.shape == J.shape
        assert J_few.flags.c_contiguous == (effect == "geometric_errors")
        assert np.array_equal(J_few[:, :, few], J[:, :, few]) and not J_few[:, :, ~few].any()


def test_a_wrong_wrench_derivatives_hook_is_named_not_misread():
    """A researcher's ``wrench_derivatives`` answer is checked before it is used: a parameter
    the effect does not have, a column block of the wrong shape (the same size in another
    layout too), a pose block of the wrong shape or another type are refused, naming the
    effect, the entry and the shapes; a right answer and None pass."""
    from deltatwin.calibration.physics.model import _checked_derivatives
    from deltatwin.twin.effects import LIBRARY, EffectError
    from deltatwin.twin.effects.base import WrenchDerivatives

    effect = LIBRARY["magnetic_force"]()
    shapes = {p.name: p.shape for p in effect.parameters}
    name, shape = next((n, s) for n, s in shapes.items() if s)      # a vector parameter
    n = 5
    right = WrenchDerivatives({name: np.zeros((n, 6) + shape)}, np.zeros((n, 6, 9)))
    assert _checked_derivatives(effect, right, n, shapes) is right
    assert _checked_derivatives(effect, None, n, shapes) is None
    for wrong, message in (
            (WrenchDerivatives({"nothing_m": np.zeros((n, 6))}, None), "'nothing_m' is not a"),
            (WrenchDerivatives({name: np.zeros((6, n) + shape)}, None), f"'{name}' has shape"),
            (WrenchDerivatives({}, np.zeros((n, 6, 3))), "'pose' has shape"),
            ({name: np.zeros((n, 6) + shape)}, "returned dict")):
        with pytest.raises(EffectError, match=f"magnetic_force.wrench_derivatives: {message}"):
            _checked_derivatives(effect, wrong, n, shapes)


@pytest.mark.skipif(not sys.platform.startswith("linux"),
                    reason="the background process is forked on Linux only")
def test_the_optics_columns_made_in_a_background_process_are_the_same_bit_for_bit(monkeypatch):
    """With a second process (models.batched.BACKGROUND, as a command on two cores sets it) a
    Jacobian of half its columns or more makes its optics columns there (when they hold
    ``BESIDE_ROW_COLUMNS`` rows times columns or more), the rest here: the Jacobian, the
    readings and the kept linearisation's pose sensitivities equal those made all in one
    process; a probe's few columns and less optics work start no process."""
    import deltatwin.calibration.physics.model as physics_model
    from deltatwin.models import batched

    df, meta = Scenario.load("quiet/magnetic-force").simulate(0.02)
    model = PhysicsModel(["geometric_errors", "thermal_expansion", "magnetic_force",
                          "loop_drift", "air_refraction", "beam_misalignment"],
                         values={"loop_drift": {"frame_arm_m": [-0.6, 0.0]}})
    meas = measurements(df, meta, model.params)
    theta = model.theta() + model.scales * np.random.default_rng(6).standard_normal(model.n_free)
    monkeypatch.setattr(batched, "BACKGROUND", False)
    A_here, J_here = model.jacobian(meas, theta)
    adjoint_here = model._linearised.sensitivity[1]
    started = []

    def counted(fun, *args, **kwargs):
        started.append(fun.__name__)
        return in_background(fun, *args, **kwargs)
    in_background = batched.in_background
    optics = [j for f in model.free for j in range(f.sl.start, f.sl.stop)
              if f.effect in ("loop_drift", "air_refraction", "beam_misalignment")]
    monkeypatch.setattr(batched, "BACKGROUND", True)
    monkeypatch.setattr(batched, "in_background", counted)
    # this small campaign's optics work is made beside at the threshold, not below it
    monkeypatch.setattr(physics_model, "BESIDE_ROW_COLUMNS", len(optics) * A_here.shape[0])
    parent = os.getpid()
    A, J = model.jacobian(meas, theta)
    assert os.getpid() == parent and started == ["optics_columns"]
    assert np.any(J[:, :, optics] != 0.0)
    assert np.array_equal(A, A_here) and np.array_equal(J, J_here)
    assert np.array_equal(model._linearised.sensitivity[1], adjoint_here)
    few = np.zeros(model.n_free, bool)
    few[optics] = True
    _, J_few = model.jacobian(meas, theta, columns=few)
    assert started == ["optics_columns"]
    assert np.array_equal(J_few[:, :, few], J_here[:, :, few])
    monkeypatch.setattr(physics_model, "BESIDE_ROW_COLUMNS", len(optics) * A_here.shape[0] + 1)
    _, J_all_here = model.jacobian(meas, theta)
    assert started == ["optics_columns"] and np.array_equal(J_all_here, J_here)
