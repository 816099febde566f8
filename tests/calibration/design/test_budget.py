"""The uncertainty budget: the mixture's 90 % figure, a budget on a small campaign whose lines
follow their inputs (a reading's 90 % is 1.645 sigma, servo lines scale with the angle), one
robot across campaigns for the Monte Carlo check, and that check on a well-specified fit."""
import numpy as np
import pytest
from scipy import stats

from deltatwin.calibration.design.budget import (
    budget_monte_carlo,
    fixed_robot,
    mixture_p90,
    refit_map,
    uncertainty_budget,
    wander_u,
)
from deltatwin.calibration.physics.fit import PhysicsFit
from deltatwin.calibration.stats import exponential_kernel_sums
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
    air = {"pressure_Pa": (100.0, 86400.0)}
    a = uncertainty_budget(fit, df, meta, 5e-9, 0.003, 1e-7, air,
                           np.random.default_rng(1)).set_index("source")
    b = uncertainty_budget(fit, df, meta, 5e-9, 0.003, 2e-7, air,
                           np.random.default_rng(1)).set_index("source")
    assert a.loc["interferometer reading", "all_p90_nm"] == pytest.approx(5 * 1.6449, rel=1e-3)
    servo_a = a.loc[[s for s in a.index if s.startswith("servo")][0], "all_p90_nm"]
    servo_b = b.loc[[s for s in b.index if s.startswith("servo")][0], "all_p90_nm"]
    assert servo_b == pytest.approx(2 * servo_a, rel=1e-3) and servo_a > 1.0
    par = a[a.kind == "parameters"]
    # one effect: its line and the correlated line of all parameters are the same figure
    assert len(par) == 2 and par.all_p90_nm.iloc[0] == pytest.approx(par.all_p90_nm.iloc[1])
    assert 0 < par.all_p90_nm.iloc[0] < a[a.kind == "combined"].all_p90_nm.iloc[0]
    lines = a.drop(index=["all parameters (correlated)"]).iloc[:-1]
    assert lines.variance_share.sum() == pytest.approx(1.0, abs=1e-9)


def test_fixed_robot_keeps_the_robot_and_redraws_the_noise():
    a = fixed_robot(Scenario.load("quiet/magnetic-force", seed=1), 99)
    b = fixed_robot(Scenario.load("quiet/magnetic-force", seed=2), 99)
    (twin_a, _), (twin_b, _) = a.build(0.05), b.build(0.05)
    assert np.array_equal(twin_a.params.d_rod_length_m, twin_b.params.d_rod_length_m)
    assert np.any(twin_a.params.d_rod_length_m != 0)
    own = Scenario.load("quiet/magnetic-force", seed=2).build(0.05)[0]
    assert not np.array_equal(own.params.d_rod_length_m, twin_b.params.d_rod_length_m)
    da, db = a.simulate(0.05)[0], b.simulate(0.05)[0]
    assert not np.allclose(da.x_nm, db.x_nm)       # the readings' noise differs


@pytest.mark.slow
def test_monte_carlo_check_of_a_well_specified_budget():
    """The force grids fitted with the effects the data hold: the parameters' sampling spread
    and the reading noise the budget predicts are what three campaigns of one robot show (the
    reading line pools hundreds of readings: a tight check of its 1.645 sigma / 2; the
    parameters' spread, three draws, a loose one)."""
    t = budget_monte_carlo("quiet/magnetic-force", ["geometric_errors", "magnetic_force"], 3,
                           0.05, 5, n_boot=200).set_index("source")
    reading = t.loc["interferometer reading"]
    assert reading.budget_p90_nm == pytest.approx(5.0 / 2 * stats.norm.ppf(0.95), rel=1e-3)
    assert reading.agrees and abs(reading.ratio - 1) < 0.1
    params = t.loc["all parameters (correlated)"]
    assert params.kind == "parameters" and params.mc_p90_nm > 0
    # three campaigns: the chi-square interval of a spread on 2 degrees of freedom
    assert params.mc_high_nm / params.mc_low_nm == pytest.approx(
        np.sqrt(stats.chi2.ppf(0.975, 2) / stats.chi2.ppf(0.025, 2)), rel=1e-9)
    assert params.agrees and params.budget_p90_nm <= params.with_prior_p90_nm
    assert t.mc_low_nm.le(t.mc_p90_nm).all() and t.mc_p90_nm.le(t.mc_high_nm).all()


def test_exponential_kernel_sums_against_the_dense_sum():
    rng = np.random.default_rng(3)
    t = np.round(rng.uniform(0, 5e4, 300), -2)            # ties included
    w = rng.standard_normal(300)
    for time_s in (3600.0, 86400.0, 0.0):
        K = (np.exp(-np.abs(t[:, None] - t[None, :]) / time_s) if time_s
             else (t[:, None] == t[None, :]).astype(float))
        assert np.allclose(exponential_kernel_sums(t, w, time_s), K @ w, rtol=1e-10, atol=1e-10)


def test_wander_line_is_the_exact_variance_up_to_the_session_zeros():
    """The air line's standard uncertainty per reading is the variance of the Ornstein-
    Uhlenbeck wander's increment since the session's zero, taken up to the zero the fit refits
    (the mean over the session's calibration rows): checked against the dense quadratic form,
    and the wander's scale: slow against the session, it is far below a white wander's."""
    sc = Scenario.load("paper-force")
    df, meta = sc.simulate(0.05)
    fit = PhysicsFit(["geometric_errors"], noise_nm=7.0).fit(df, meta)
    meas = fit.measurements_
    rng = np.random.default_rng(4)
    a, b = (rng.uniform(1e-10, 3e-10, meas.y.shape) for _ in range(2))
    std, time_s = 80.0, 86400.0
    u = wander_u(meas, a, b, std, time_s)
    t = meas.points.t_s
    for g, (_, axis) in enumerate(meas.groups):
        k = "xyz".index(axis)
        rows = np.flatnonzero(meas.group[:, k] == g)
        cal = meas.cal[rows]
        times = np.append(t[rows], t[meas.zero_row[rows[0]]])
        K = std ** 2 * np.exp(-np.abs(times[:, None] - times[None, :]) / time_s)
        W = np.zeros((rows.size, rows.size + 1))          # r = W p: reading minus cal mean
        W[np.arange(rows.size), np.arange(rows.size)] = a[rows, k]
        W[:, -1] = b[rows, k]
        W[:, :-1] -= (cal * a[rows, k])[None, :] / cal.sum()
        W[:, -1] -= b[rows, k][cal].mean()
        assert np.allclose(u[rows, k], np.sqrt(np.einsum("ij,jk,ik->i", W, K, W)), rtol=1e-8)
    # with the fit's first-order refit taken out too: the dense r = (Z - G W^T) L p
    G, W = refit_map(fit)
    read = meas.group >= 0
    ent = np.argwhere(read)                                 # (row, axis) of every reading
    n = meas.y.shape[0]
    L = np.zeros((len(ent), t.size))
    L[np.arange(len(ent)), ent[:, 0]] = a[read]
    L[np.arange(len(ent)), meas.zero_row[ent[:, 0]]] += b[read]
    K = std ** 2 * np.exp(-np.abs(t[:, None] - t[None, :]) / time_s)
    Z = np.zeros((len(ent), len(ent)))
    for i, (row, k) in enumerate(ent):
        same = (meas.group[ent[:, 0], ent[:, 1]] == meas.group[row, k])
        Z[i, i] = 1.0
        Z[i, same & meas.cal[ent[:, 0]]] -= 1.0 / (same & meas.cal[ent[:, 0]]).sum()
    M = Z - G[read] @ W[read].T
    dense = np.sqrt(np.einsum("ij,jk,ik->i", M @ L, K, M @ L))
    refitted = wander_u(meas, a, b, std, time_s, (G, W))
    assert n == len(meas.df) and np.allclose(refitted[read], dense, rtol=1e-6)
    assert np.nanmean(refitted[read]) < np.nanmean(u[read])
    # a dead path's lever: the zero's level counts against the reading's
    slow, white = (wander_u(meas, a, -a, std, tau) for tau in (time_s, 0.0))
    read = meas.group >= 0
    assert np.nanmean(slow[read]) < 0.3 * np.nanmean(white[read])
