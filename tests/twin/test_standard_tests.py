"""The standards' test plans: the geometry the standards ask for, recomputed here from the
plan's own targets, the cycles' order, the nominal commands, and the scenario's [campaign]
kinds."""
import numpy as np
import pytest

from deltatwin.models.geometry import build_geometry
from deltatwin.models.kinematics import forward
from deltatwin.models.params import load_params
from deltatwin.twin import standard_tests as st
from deltatwin.twin.instruments.simulated import InstrumentSettings
from deltatwin.twin.scenario import Scenario, ScenarioError

PARAMS = load_params(None)


def readings_of(q):
    g = build_geometry(PARAMS)
    return forward(g, q).p - forward(g, np.zeros((1, 3))).p[0]


def test_iso9283_poses_on_the_cube_diagonal_plane():
    t = st.iso9283_plan(PARAMS, cycles=3)
    poses = t.positions_m["poses"]
    side = t.parameters["cube_side_m"]
    c = poses[0]
    corners = c + 0.5 * side * np.array([[-1, -1, -1], [1, -1, -1], [1, 1, 1], [-1, 1, 1]])
    diagonal = np.linalg.norm(corners[2] - corners[0])
    for k in range(4):   # P2..P5: 10 % of the plane's diagonal from a corner, towards the centre
        assert np.linalg.norm(poses[k + 1] - corners[k]) == pytest.approx(0.1 * diagonal,
                                                                          rel=1e-12)
        assert np.linalg.norm(poses[k + 1] - c) == pytest.approx(0.4 * diagonal, rel=1e-12)
    # the plane holds the x axis and the (0, 1, 1) diagonal: its normal is (0, 1, -1)
    assert np.allclose((poses - c) @ np.array([0.0, 1.0, -1.0]), 0.0, atol=1e-15)
    # the cube's corners are reachable within 90 % of the stroke, a 1 % larger one is not
    ws = st.Workspace(PARAMS)
    signs = np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1])).reshape(3, -1).T
    assert ws.reachable(c + 0.5 * side * signs)
    assert not ws.reachable(c + 0.505 * side * signs)


def test_iso9283_order_and_nominal_commands():
    t = st.iso9283_plan(PARAMS, cycles=3)
    assert t.item[0] == -1 and np.all(t.targets_m[0] == t.positions_m["poses"][0])  # start: P1
    names = [st.POSE_NAMES[i] for i in t.item[1:]]
    assert names == ["P5", "P4", "P3", "P2", "P1"] * 3
    assert list(t.cycle[1:]) == [0] * 5 + [1] * 5 + [2] * 5
    np.testing.assert_allclose(readings_of(t.plan.q), t.targets_m, rtol=0, atol=1e-12)
    assert np.all(np.abs(t.plan.q) <= 0.9 * 0.065 + 1e-15)


def test_iso230_2_linear_cycle():
    t = st.iso230_2_plan(PARAMS, np.random.default_rng(5), axes=("y",), targets=6, approaches=3,
                         overrun=0.1)
    pos = t.positions_m["y"][:, 1]
    travel = t.parameters["travel_m"]["y"]
    assert pos[0] == pytest.approx(-travel / 2) and pos[-1] == pytest.approx(travel / 2)
    gaps = np.diff(pos)
    assert np.all(gaps > 0) and np.ptp(gaps) > 0.01 * travel / 5      # non-uniform intervals
    y = t.targets_m[:, 1]
    run = 2 * 6 + 2
    for j in range(3):
        r = slice(j * run, (j + 1) * run)
        assert t.item[r][0] == -1 and y[r][0] == pytest.approx(pos[0] - 0.1 * travel)
        assert list(t.item[r][1:7]) == list(range(6)) and np.all(t.direction[r][1:7] == 1)
        assert t.item[r][7] == -1 and y[r][7] == pytest.approx(pos[-1] + 0.1 * travel)
        assert list(t.item[r][8:]) == list(range(5, -1, -1)) and np.all(t.direction[r][8:] == -1)
    assert np.all(t.targets_m[:, [0, 2]] == 0.0)       # along y through the centre (home)
    np.testing.assert_allclose(readings_of(t.plan.q), t.targets_m, rtol=0, atol=1e-12)
    assert t.plan.sessions == (("iso230-2 y", ("y",)),)


def test_iso230_3_at_rest_for_the_duration():
    s = InstrumentSettings()
    t = st.iso230_3_plan(PARAMS, s, duration_h=0.25)
    assert len(t.plan) == int(np.ceil(900 / st.point_time_at_rest(s)))
    assert np.all(t.plan.q == t.plan.q[0])
    with pytest.raises(ValueError, match="not a reachable reading"):
        st.iso230_3_plan(PARAMS, s, 1.0, position_m=[0.05, 0.0, 0.0])


def test_scenario_kinds_scale_and_refuse():
    sc = Scenario.load("paper-thermal")
    iso = sc.with_campaign({"kind": "iso230-2", "targets": 11, "approaches": 5})
    assert iso.identity(None)["scenario_sha256"] != sc.identity(None)["scenario_sha256"]
    assert iso.seed == sc.seed and iso.sensors == sc.sensors
    test = iso.standard_test(np.random.default_rng(0), scale=0.2)
    assert test.parameters["targets"] == 3 and test.parameters["approaches"] == 2
    with pytest.raises(ScenarioError, match=r"\[campaign\]: unknown key 'cycle'"):
        sc.with_campaign({"kind": "iso9283", "cycle": 3})
    with pytest.raises(ScenarioError, match="order"):
        sc.with_campaign({"kind": "iso9283", "order": ["P1", "P7"]})
