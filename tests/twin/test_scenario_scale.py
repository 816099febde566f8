"""``Scenario.load(name, scale=S)`` sets the campaign's scale: simulate, run, build and plan use
it when they are given none, an explicit scale wins, and a bad scale is refused at load."""
import math

import pytest

from deltatwin.twin.scenario import Scenario, ScenarioError


def test_the_scale_given_to_load_is_the_campaigns():
    full = Scenario.load("paper-force")
    small = Scenario.load("paper-force", scale=0.05)
    df, meta = small.simulate()
    reference, ref_meta = full.simulate(0.05)
    assert meta["scale"] == ref_meta["scale"] == 0.05
    assert len(df) == len(reference) < len(full.plan(None)) / 10
    assert df.equals(reference)
    assert small.identity(None)["scale"] == 0.05 and full.identity(None)["scale"] == 1.0
    # an explicit scale wins over the scenario's own
    assert len(small.plan(None, 1.0)) == len(full.plan(None))
    # a scenario derived from it keeps its scale
    assert small.with_perfect(["air"]).scale == 0.05
    assert small.with_campaign(small.campaign).scale == 0.05


@pytest.mark.parametrize("scale", [0, -0.5, 1.5, math.nan, math.inf, "0.3", True])
def test_a_bad_scale_is_refused_at_load(scale):
    with pytest.raises(ScenarioError, match="scale"):
        Scenario.load("paper-force", scale=scale)


def test_an_unknown_keyword_is_refused():
    with pytest.raises(TypeError, match="scales"):
        Scenario.load("paper-force", scales=0.1)
