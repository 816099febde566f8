"""The uncertainty budget: the mixture's 90 % figure, and a budget on a small campaign whose
lines follow their inputs (a reading's 90 % is 1.645 sigma, servo lines scale with the angle)."""
import numpy as np
import pytest
from scipy import stats

from deltatwin.calibration.design.budget import mixture_p90, uncertainty_budget
from deltatwin.calibration.physics.fit import PhysicsFit
from deltatwin.twin.scenario import Scenario


def test_mixture_p90_of_equal_and_mixed_uncertainties():
    assert mixture_p90(np.full(10, 2.0)) == pytest.approx(2.0 * stats.norm.ppf(0.95), rel=1e-5)
    x = mixture_p90(np.array([1.0, 3.0]))
    cover = np.mean([2 * stats.norm.cdf(x / u) - 1 for u in (1.0, 3.0)])
    assert cover == pytest.approx(0.9, abs=1e-6) and 1.645 < x < 3 * 1.645


def test_budget_lines_follow_their_inputs():
    sc = Scenario.load("quiet/gravity-sag")
    df, meta = sc.simulate(0.02)
    fit = PhysicsFit(["gravity_sag"], noise_nm=5.0).fit(df, meta)
    a = uncertainty_budget(fit, df, meta, 5e-9, 0.003, 1e-7, 100.0).set_index("source")
    b = uncertainty_budget(fit, df, meta, 5e-9, 0.003, 2e-7, 100.0).set_index("source")
    assert a.loc["interferometer reading", "all_p90_nm"] == pytest.approx(5 * 1.6449, rel=1e-3)
    servo_a = a.loc[[s for s in a.index if s.startswith("servo")][0], "all_p90_nm"]
    servo_b = b.loc[[s for s in b.index if s.startswith("servo")][0], "all_p90_nm"]
    assert servo_b == pytest.approx(2 * servo_a, rel=1e-3) and servo_a > 1.0
    par = a[a.kind == "parameters"]
    assert len(par) == 1 and 0 < par.all_p90_nm.iloc[0] < a[a.kind == "combined"].all_p90_nm.iloc[0]
    assert a.variance_share.iloc[:-1].sum() == pytest.approx(1.0, abs=1e-9)
