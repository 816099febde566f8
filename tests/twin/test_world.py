"""The twin's thermal grid at floating-point boundaries."""
import numpy as np
import pytest

from deltatwin.twin.instruments.simulated import SimulatedLab
from deltatwin.twin.scenario import Scenario

# the start offsets of the in-process trial (9 of which failed before the fix), plus four
START_OFFSETS_S = [0.1, 0.25, 0.7, 1.3, 3.7, 14.64, 33.3, 250.75, 1000.0, 0.0, 1.0, 7.3, 4321.9]


@pytest.fixture(scope="module")
def built():
    return Scenario.load("paper-thermal").build(0.0003)


def test_clock_a_few_ulp_above_a_whole_second(built):
    """t a few ulp above a grid point: t + warmup rounds onto the grid point; the twin must still
    integrate past t and interpolate there, between the neighbouring grid temperatures."""
    twin, _ = built
    on_boundary = 0
    for whole in [1.0, 2.0, 37.0, 1000.0, 3000.0]:
        for ulps in (1, 2, 5):
            t = whole
            for _ in range(ulps):
                t = np.nextafter(t, np.inf)
            on_boundary += t + 7200.0 == whole + 7200.0     # the boundary case itself
            twin.advance(t, twin.schedule)
            T = twin.node_temperatures(np.array([t]))
            lo = twin.node_temperatures(np.array([whole]))
            for node in T:
                assert np.isfinite(T[node][0]) and T[node][0] == pytest.approx(lo[node][0],
                                                                              abs=1e-9)
    assert on_boundary >= 10


@pytest.mark.slow
@pytest.mark.parametrize("offset_s", START_OFFSETS_S)
def test_campaign_from_any_start_offset(offset_s):
    """A campaign whose clock starts at ``offset_s`` (fractional sums of sleeps land a few ulp
    off whole seconds) runs to the end through the simulated instruments."""
    from deltatwin.twin.campaign import run_campaign
    sc = Scenario.load("paper-force")        # at 0.02 the offset 250.75 s failed before the fix
    twin, plan = sc.build(0.02)
    lab = SimulatedLab(twin, sc.settings)
    lab.t = offset_s
    df = run_campaign(plan, lab.instrument_set(), sc.settings, sc.cosine, sc.dead_path(),
                      progress=False)
    assert len(df) == len(plan) and np.isfinite(df["x_nm"].dropna()).all()
    assert df["t_s"].min() > offset_s


def test_interpolation_between_grid_points_is_linear(built):
    twin, _ = built
    twin.advance(50.0, twin.schedule)
    a, b, mid = (twin.node_temperatures(np.array([t])) for t in (40.0, 41.0, 40.25))
    for node in a:
        assert mid[node][0] == pytest.approx(0.75 * a[node][0] + 0.25 * b[node][0], abs=1e-12)
