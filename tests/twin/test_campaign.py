"""Campaigns, scenarios, simulated instruments and effects (reduced scale)."""
import subprocess
import sys

import numpy as np
import pytest

from deltatwin.twin.dataset import read_dataset
from deltatwin.twin.effects import make_effect
from deltatwin.twin.instruments.optics import Optics
from deltatwin.twin.scenario import Scenario, ScenarioError
from deltatwin.twin.world import Schedule


@pytest.mark.parametrize("name", ["paper-thermal", "paper-force"])
def test_fast_path_equals_campaign_through_the_interface(name):
    """The vectorised simulation and the point-by-point campaign over the simulated instruments
    give the same dataset (same timeline, same noise draws), to the instruments' resolution."""
    sc = Scenario.load(name)
    fast, _ = sc.simulate(0.005 if name == "paper-thermal" else 0.05)
    slow, _ = sc.run(0.005 if name == "paper-thermal" else 0.05, progress=False)
    assert list(fast.columns) == list(slow.columns) and len(fast) == len(slow) > 20
    for c in fast.columns:
        if fast[c].dtype.kind == "f":
            tol = 1e-6 if c.endswith("_s") else 1e-9
            np.testing.assert_allclose(fast[c], slow[c], rtol=0, atol=tol, err_msg=c)
        else:
            assert (fast[c] == slow[c]).all(), c


def test_same_seed_same_data_other_seed_other_data():
    a, _ = Scenario.load("paper-force").simulate(0.02)
    b, _ = Scenario.load("paper-force").simulate(0.02)
    c, _ = Scenario.load("paper-force", seed=99).simulate(0.02)
    assert a.equals(b)
    assert not np.allclose(a["x_nm"], c["x_nm"])


def test_force_campaign_layout_and_force_response():
    df, meta = Scenario.load("paper-force").simulate(1.0)
    assert (df["split"] == "cal").sum() == 6 ** 3 * 5 and (df["split"] == "val").sum() == 5 ** 3 * 5
    assert len([c for c in df.columns if c.startswith("T_")]) == 13
    sigma_nm = Scenario.load("paper-force").settings.noise_floor_m * 1e9
    assert meta["truth"]["reading_noise_std_nm"] == pytest.approx(sigma_nm)
    # the noise floor counts what no model can predict: the readings' noise (4 readings averaged
    # per point: ~1.645 sigma / 2 plus the window-mean white noise) and where the motors'
    # controllers settled (servo_settling, tens of nm at the platform)
    floor = meta["truth"]["noise_floor_nm"]
    assert set(floor) == {"x", "y", "z"}
    still = Scenario.load("paper-force")
    still.effects = [e for e in still.effects if e.name != "servo_settling"]
    floor_still = still.simulate(1.0)[1]["truth"]["noise_floor_nm"]
    assert all(0.6 * sigma_nm < v < 1.6 * sigma_nm for v in floor_still.values()), floor_still
    assert all(floor[a] > 3 * floor_still[a] for a in floor), (floor, floor_still)
    # repulsive, stronger low: 2 N vs 0 N at each position, Y displacement grows as the platform
    # goes down (all q up = arms down)
    g = df.pivot_table(index="pos_id", columns="F_N", values="y_nm")
    dy = (g[2.0] - g[0.0]).to_numpy()
    qsum = df.groupby("pos_id")[["q1_rad", "q2_rad", "q3_rad"]].first().sum(axis=1).to_numpy()
    assert np.corrcoef(qsum, dy)[0, 1] > 0.5
    assert np.median(np.abs(dy)) > 50.0          # hundreds of nm at 2 N, not noise


def test_thermal_scenario_sessions_and_sensors():
    df, meta = Scenario.load("paper-thermal").simulate(0.01)
    assert set(df["session"]) == {"xy", "z"}
    assert df.loc[df["session"] == "xy", "z_nm"].isna().all()
    assert df.loc[df["session"] == "z", ["x_nm", "y_nm"]].isna().all().all()
    assert len([c for c in df.columns if c.startswith("T_")]) == 11
    assert (df[["x_std_nm", "y_std_nm", "z_std_nm"]].max() < 10.0).all()   # acceptance rule
    ids = df.groupby("pos_id")["split"].nunique()
    assert (ids == 1).all()


def test_room_climate_over_three_days():
    """The campaign starts with the room at the AC consign (20 degC); once the AC is switched
    off the room drifts between about 21 and 25 degC with a daily swing."""
    sc = Scenario.load("paper-thermal")
    ac_off_s = next(e for e in sc.effects if e.name == "room_climate").ac_off_s
    twin, _ = sc.build(None)
    t, room = twin.t_grid, twin.env.room_C
    assert np.allclose(room[(t >= 0) & (t < ac_off_s)], 20.0, atol=0.05)
    free = room[(t > ac_off_s + 6 * 3600) & (t < 3 * 86400)]
    assert 20.5 < free.min() < 22.5 and 23.5 < free.max() < 25.5


def test_thermal_network_pieces_equal_whole():
    """Integrating the network in pieces (as a campaign advances) equals one integration."""
    sc = Scenario.load("paper-force")
    t1, _ = sc.build(0.01)
    t2, _ = sc.build(0.01)
    sched = Schedule()
    sched.set_currents(100.0, [2.0, 2.0, 2.0])
    t1.advance(3000.0, sched)
    for t in np.linspace(10, 3000, 37):
        t2.advance(t, sched)
    a, b = t1.node_temperatures(np.array([2999.0])), t2.node_temperatures(np.array([2999.0]))
    assert a["coil1"][0] > 25.0
    for k in a:
        assert a[k][0] == pytest.approx(b[k][0], abs=1e-9)


@pytest.mark.parametrize("text, words", [
    ('[scenario]\nnmae = "x"\n[campaign]\nkind = "force"\n', ["nmae", "did you mean 'name'"]),
    ('[effects]\non = ["magnetic_forse"]\n[campaign]\nkind = "force"\n',
     ["magnetic_forse", "magnetic_force"]),
    ('[effects]\non = ["room_climate"]\n[effects.room_climate]\npressure_std_Pa = "80 Pa"\n'
     '[campaign]\nkind = "force"\n', ["pressure_std_Pa", "expected a number"]),
    ('[instruments]\nnoise_floor_m = -5e-9\n[campaign]\nkind = "force"\n', ["noise_floor_m", ">= 0"]),
    ('[campaign]\nkind = "force"\nforces_N = [0.0, 3.0]\n', ["forces_N", "2 A"]),
    ('[sensors]\nbase = "bsae"\n[campaign]\nkind = "force"\n', ["bsae", "did you mean 'base'"]),
])
def test_bad_scenarios_name_file_key_reason(tmp_path, text, words):
    f = tmp_path / "bad.toml"
    f.write_text(text)
    with pytest.raises(ScenarioError) as err:
        Scenario.load(f)
    msg = str(err.value)
    assert str(f) in msg
    for w in words:
        assert w in msg


def test_cli_simulate_writes_atomically(tmp_path):
    out = tmp_path / "d.parquet"
    r = subprocess.run([sys.executable, "-m", "deltatwin.cli", "simulate", "paper-force", "-o",
                        str(out), "--scale", "0.02", "--quiet", "--json"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    df, meta = read_dataset(out)
    assert meta["seed"] == 2 and meta["source"] == "twin" and len(df) > 0
    bad = tmp_path / "bad.toml"
    bad.write_text('[campaign]\nkind = "thermal"\n'
                   'sessions = [{name = "xy", axes = ["w"], cal = 5, val = 5}]\n')
    out2 = tmp_path / "e.parquet"
    r = subprocess.run([sys.executable, "-m", "deltatwin.cli", "simulate", str(bad), "-o", str(out2),
                        "--quiet"], capture_output=True, text=True)
    assert r.returncode == 2 and "axes" in r.stderr
    assert list(tmp_path.glob("e.parquet*")) == [] and list(tmp_path.glob(".e.parquet*")) == []


def test_effect_parameters_validated():
    with pytest.raises(ValueError, match="coil_offset_m"):
        make_effect("magnetic_force", {"coil_offset_m": [0.0, 0.0]})


def test_frame_arm_moves_the_robot_by_table_minus_frame_expansion_over_the_arm():
    """A robot hanging from a frame arm: the loop (heads, fold mirror) moves relative to the
    base by -(table CTE dT_table - frame CTE dT_frame) * arm, on top of the portal's drift."""
    n = 3
    dT = np.array([0.0, 1.0, 2.0])
    node_T = {"table": 20.0 + dT, "frame": 20.0 + 0.5 * dT}
    pts = type("P", (), {"node_T": node_T, "support_C": {a: np.full(n, 25.0) for a in "xyz"}})()
    moved = {}
    for arm in ((0.0, 0.0), (-0.6, 0.0)):
        optics = Optics.nominal(np.zeros(3), n)
        make_effect("loop_drift", {"frame_arm_m": arm}).optics(pts, optics)
        moved[arm] = optics.head["x"]
    shift = moved[(-0.6, 0.0)] - moved[(0.0, 0.0)]
    expected_x = -(11.7e-6 * dT - 11.7e-6 * 0.5 * dT) * -0.6
    np.testing.assert_allclose(shift[:, 0], expected_x, rtol=1e-9, atol=1e-15)   # 1 fm
    np.testing.assert_array_equal(shift[:, 1:], 0.0)


def test_servo_settling_moves_the_motors_at_each_settling_but_not_the_encoders():
    """paper-force's controllers settle at a random angle after every move and load change:
    the platform moves between two settlings at the same target; the encoders read the target."""
    from deltatwin.twin.instruments.simulated import SimulatedLab

    sc = Scenario.load("paper-force")
    std = next(e for e in sc.effects if e.name == "servo_settling").angle_std_rad
    twin, _ = sc.build(0.01)
    lab = SimulatedLab(twin, sc.settings)
    inst = lab.instrument_set()
    q = np.array([0.01, -0.02, 0.015])
    inst.robot.move_to(q)
    positions, angles = [], []
    for I in (0.0, 0.0, 1.0, 0.0) * 50:
        inst.coils.set_currents(np.full(3, I))
        inst.clock.sleep(sc.settings.wait_s)
        twin.advance(lab.t, lab.schedule)
        pts = twin.points([lab.t], q[None], lab.currents[None])
        angles.append(pts.q[0] - q)
        positions.append(twin.truth(twin.points([lab.t], q[None], np.zeros((1, 3)))).pose.p[0])
        np.testing.assert_array_equal(inst.robot.read_encoders(), q)
    angles = np.array(angles)
    assert np.all(np.abs(np.diff(angles, axis=0)) > 0)          # a new angle at each settling
    assert 0.8 * std < angles.std() < 1.2 * std, (angles.std(), std)
    spread = np.array(positions).std(axis=0)
    assert np.all(spread > 5e-9), spread                          # tens of nm at the platform
    still = twin.points([lab.t], q[None], np.zeros((1, 3)), settled=False)
    np.testing.assert_array_equal(still.q[0], q)


def test_session_start_puts_coils_to_zero_and_checks_it():
    """A coil supply left at 1 A by an earlier session: the campaign switches it off and reads it
    back before the zero, so the data equal a clean start's (before: every reading offset by
    tens of nm while the rows said 0 A); a supply that does not go to 0 A stops the campaign."""
    from deltatwin.twin.campaign import run_campaign
    from deltatwin.twin.instruments.interface import InstrumentError
    from deltatwin.twin.instruments.simulated import SimCoils, SimulatedLab

    sc = Scenario.load("paper-force")

    def campaign(prepare=None, coils_cls=None):
        twin, plan = sc.build(0.02)
        lab = SimulatedLab(twin, sc.settings)
        inst = lab.instrument_set()
        if coils_cls is not None:
            inst.coils = coils_cls(lab)
        if prepare is not None:
            prepare(inst)
        return run_campaign(plan, inst, sc.settings, sc.cosine, sc.dead_path(), progress=False)

    clean = campaign()
    left_on = campaign(lambda inst: inst.coils.set_currents(np.ones(3)))
    assert (left_on["F_N"] == clean["F_N"]).all()
    # other servo-settling draws (the extra current changes are settling events) scatter the
    # points by tens of nm; an offset would move the median
    for a in ("x_nm", "y_nm", "z_nm"):
        d = (left_on[a] - clean[a]).dropna()
        assert len(d) > 20 and abs(np.median(d)) < 15.0, (a, np.median(d))

    class StuckCoils(SimCoils):          # ignores the order to switch off
        def set_currents(self, currents_A, timeout_s=30.0):
            if np.any(np.asarray(currents_A) != 0):
                super().set_currents(currents_A, timeout_s)

    with pytest.raises(InstrumentError, match=r"coils: set to 0 A at the session start but reads "
                                              r"back \[1\.0, 1\.0, 1\.0\] A"):
        campaign(lambda inst: inst.coils.set_currents(np.ones(3)), StuckCoils)


def _zero_errors(settles: int, sessions: int) -> np.ndarray:
    """(sessions, 3) m: where each session's zero (``settles`` home settles averaged) sits
    along x, y, z from the home the motors were sent to, each session a later one of
    paper-force's robot (its own servo settles and reading windows)."""
    from deltatwin.twin.campaign import known_state, zero_offset
    from deltatwin.twin.instruments.optics import AXES
    from deltatwin.twin.instruments.simulated import SimulatedLab
    from deltatwin.twin.world import Twin

    sc = Scenario.load("paper-force")
    effects = [e for e in sc.effects if e.name in ("geometric_errors", "servo_settling")]
    out = []
    for s in range(sessions):
        twin = Twin(sc.params, effects, sc.sensors, sc.seed, 3600.0, 0.0, session=(s, 0))
        lab = SimulatedLab(twin, sc.settings)
        inst = lab.instrument_set()
        known_state(inst)
        inst.interferometers.zero()
        offset, _ = zero_offset(inst, sc.settings, AXES, 1, settles, lab.t)
        twin.advance(lab.t, lab.schedule)
        still = twin.truth(twin.points([lab.t], np.zeros((1, 3)), np.zeros((1, 3)),
                                       settled=False))
        out.append([(lab.zero_path[a] - still.optical_path_m[a][0]) / still.n_comp[a][0]
                    + offset[k] for k, a in enumerate(AXES)])
    return np.array(out)


def test_zero_averaged_over_home_settles_scatters_by_one_over_sqrt_n():
    """With servo settling the zero holds one settle's error for a whole session (~20 nm per
    axis on paper-force); the mean of 9 home settles holds a third of it (1/sqrt(9); with one
    7 nm reading per settle, 2.8x expected), over 40 sessions, each with its own settles."""
    one, nine = _zero_errors(1, 40), _zero_errors(9, 40)
    assert np.all(one.std(axis=0) > 10e-9), one.std(axis=0)     # the settle, not noise
    ratio = np.sqrt(np.mean(one ** 2) / np.mean(nine ** 2))      # 120 draws each
    assert 2.2 < ratio < 3.7, ratio


def test_a_later_session_draws_its_own_events_on_the_same_robot():
    """A compensated session's world (``session``) has the robot and laboratory of its seed,
    but its own servo settles and interferometer and autocollimator windows: counted from the
    world's start with the robot's seed they were the calibration campaign's (and every
    session's: each session's zero sat on the same settle)."""
    from deltatwin.twin.world import EVENT_STREAMS, random_streams

    base, a, a2, b = (random_streams(2), random_streams(2, (5, 1)), random_streams(2, (5, 1)),
                      random_streams(2, (8, 1)))
    for name, g in base.items():
        draws = [s[name].standard_normal(4) for s in (a, a2, b)]
        np.testing.assert_array_equal(draws[0], draws[1])            # deterministic
        if name in EVENT_STREAMS:
            assert not np.allclose(g.standard_normal(4), draws[0]) and \
                not np.allclose(draws[0], draws[2]), name
        else:
            np.testing.assert_array_equal(g.standard_normal(4), draws[2])   # the same robot
