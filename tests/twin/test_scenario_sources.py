"""Scenario.with_perfect: the laboratory's error sources made perfect on the same seed, so that
two runs differ by those sources' errors alone (the floor's budget and the design budget's
Monte Carlo both measure a source this way)."""
import numpy as np
import pytest

from deltatwin.twin.scenario import ERROR_SOURCES, Scenario, ScenarioError

SCALE = 0.01


@pytest.fixture(scope="module")
def thermal():
    sc = Scenario.load("paper-thermal")
    return sc, sc.simulate(SCALE)[0]


def test_sources_present_in_the_papers_scenarios():
    assert Scenario.load("paper-thermal").sources() == ["interferometers", "thermometers", "air"]
    assert Scenario.load("paper-force").sources() == list(ERROR_SOURCES)


def test_a_perfect_source_changes_its_own_columns_only(thermal):
    """Perfect thermometers: the same timeline and readings, every temperature column on the
    1 mK-free true value; perfect interferometers: the same temperatures, other readings."""
    sc, df = thermal
    temps = [c for c in df if c.startswith("T_") and c.endswith("_C")]
    readings = [c for c in ("x_nm", "y_nm", "z_nm") if c in df]
    quiet_T = sc.with_perfect(["thermometers"]).simulate(SCALE)[0]
    np.testing.assert_array_equal(quiet_T["t_s"], df["t_s"])
    np.testing.assert_array_equal(quiet_T[readings], df[readings])
    diff = np.abs(quiet_T[temps].to_numpy() - df[temps].to_numpy())
    assert 1.0 < np.nanmax(diff) * 1e3 < 30     # mK: the 3 mK noise and 1 mK steps, a few sigma
    quiet_i = sc.with_perfect(["interferometers"]).simulate(SCALE)[0]
    np.testing.assert_array_equal(quiet_i[temps], df[temps])
    assert not np.allclose(quiet_i[readings].to_numpy(), df[readings].to_numpy())
    assert sc.with_perfect([]).simulate(SCALE)[0].equals(df)


def test_an_unknown_source_is_refused_by_name(thermal):
    with pytest.raises(ScenarioError, match="barometers"):
        thermal[0].with_perfect(["barometers"])
