"""The statistical rule (calibration/stats.py): each test's false-claim rate on null data where
the truth is known, its immunity to offsets, its power on a real change, and its formulas
against independent computations (scipy.stats, a plain loop)."""
import math

import numpy as np
import pytest
from scipy import stats as sps

from deltatwin.calibration import stats
from tests.calibration.series import ar1


def _layout(n: int, sessions: int = 1):
    """(group (N,3), val (N,), session (N,), t_s (N,)): n validation rows read on three axes,
    cut into ``sessions`` consecutive sessions (a group per (session, axis))."""
    session = np.arange(n) * sessions // n
    group = session[:, None] * 3 + np.arange(3)[None, :]
    return group, np.ones(n, bool), session, np.arange(n, dtype=float)


@pytest.mark.parametrize("rho", [0.0, 0.9, 0.97])
def test_the_validation_test_holds_its_level_on_correlated_residuals(rho):
    """Under the null (a change unrelated to the residual, both AR(1), slow where rho is near
    1) the block test's p-value is below a level no more often than the level allows: the
    spurious regression of two slow series is what the blocks guard against (rho = 0.97: a
    series correlated over about 60 rows, a fifth of the rows)."""
    rng = np.random.default_rng(15)
    n = 300
    group, val, session, t = _layout(n)
    p = []
    for _ in range(600):
        before = np.column_stack([ar1(rng, n, rho) for _ in range(3)]) * 1e-8
        change = np.column_stack([ar1(rng, n, rho) for _ in range(3)]) * 1e-8
        p.append(stats.validation_p(before, before - change, group, val, session, t))
    p = np.array(p)
    # 600 draws: a rate of 0.05 lies within 0.03-0.07 with 99 % probability
    assert np.mean(p < 0.05) <= 0.08
    assert np.mean(p < 0.01) <= 0.025
    assert np.mean(p < 0.001) <= 0.005


def test_offsets_are_never_evidence():
    """Constant offsets per (session, axis), 1-50 nm, drawn 1000 times: as the change they are
    no evidence (p = 1), and added to the residual they leave a real change's p-value as it
    was (to round-off)."""
    rng = np.random.default_rng(41)
    n = 240
    group, val, session, t = _layout(n, sessions=2)
    tt = np.linspace(0, 1, n)
    shape = np.column_stack([np.sin(5 * tt), tt ** 2, np.cos(3 * tt)]) * 1e-8
    for _ in range(1000):
        before = rng.standard_normal((n, 3)) * 1e-8
        offsets = rng.uniform(1e-9, 50e-9, 6) * rng.choice([-1, 1], 6)
        shift = offsets[group]
        assert stats.validation_p(before, before - shift, group, val, session, t) == 1.0
        real = before + shape
        p = stats.validation_p(real, real - shape, group, val, session, t)
        p_shifted = stats.validation_p(real + shift, real + shift - shape, group, val, session, t)
        assert p_shifted == pytest.approx(p, rel=1e-9, abs=1e-300)


def test_the_validation_test_finds_a_change_that_explains_the_residual():
    """A change that is the residual's structure, leaving white noise, is shown (tiny p); the
    same change with the opposite sign, or none, is not."""
    rng = np.random.default_rng(16)
    n = 300
    group, val, session, t = _layout(n)
    tt = np.linspace(0, 1, n)
    change = np.column_stack([np.sin(9 * tt), tt ** 2, np.cos(7 * tt)]) * 2e-8
    before = change + rng.standard_normal((n, 3)) * 5e-9
    assert stats.validation_p(before, before - change, group, val, session, t) < 1e-6
    assert stats.validation_p(before, before + change, group, val, session, t) > 0.99
    assert stats.validation_p(before, before, group, val, session, t) == 1.0


def test_the_validation_test_against_a_cluster_robust_regression_written_here():
    """The p-value equals a plain-loop computation of the cluster-robust slope t test: each
    group's means removed, the slope through the origin, the blocks' score sums, G / (G - 1)
    small-sample factor, Student's t with G - 1 degrees of freedom (scipy.stats); eight time
    blocks, each holding the three axes' readings of its span."""
    rng = np.random.default_rng(5)
    n = 97                                  # blocks of unequal length
    group, val, session, t = _layout(n)
    before = rng.standard_normal((n, 3))
    change = 0.3 * before + rng.standard_normal((n, 3))
    got = stats.validation_p(before, before - change, group, val, session, t)
    xs, ys, clusters = [], [], []
    for g in range(3):
        b = before[:, g] - before[:, g].mean()
        c = change[:, g] - change[:, g].mean()
        for i in range(n):
            xs.append(c[i])
            ys.append(b[i])
            clusters.append((i * 8) // n)    # a block holds every axis of its time span
    xs, ys = np.array(xs), np.array(ys)
    slope = sum(x * y for x, y in zip(xs, ys)) / sum(x * x for x in xs)
    sums = {}
    for x, y, c in zip(xs, ys, clusters):
        sums[c] = sums.get(c, 0.0) + x * (y - slope * x)
    G = len(sums)
    var = G / (G - 1) * sum(v * v for v in sums.values()) / sum(x * x for x in xs) ** 2
    assert G == 8
    assert got == pytest.approx(sps.t.sf(slope / math.sqrt(var), G - 1), rel=1e-10)


@pytest.mark.parametrize("rho", [0.0, 0.95])
def test_the_calibration_f_test_holds_its_level_on_correlated_rows(rho):
    """Under the null (a slow candidate change unrelated to a slow residual, both AR(1) with
    rho = 0.95) the F test on independent rows is below 0.01 in over a third of the draws;
    with the serial-correlation factor it comes near its level. On independent rows the factor
    stays near 1 (nothing lost), and a change that varies row to row is barely penalised on a
    slow residual."""
    rng = np.random.default_rng(31)
    n = 400
    naive, corrected, factors, pose_factors = [], [], [], []
    for _ in range(300):
        e, x = ar1(rng, n, rho), ar1(rng, n, rho)
        e, x = e - e.mean(), x - x.mean()
        e1 = e - x * (x @ e) / (x @ x)
        factors.append(stats.serial_inflation([n], e - e1, e1))
        naive.append(stats.f_test_p(e @ e, e1 @ e1, 1, n - 2))
        corrected.append(stats.f_test_p(e @ e, e1 @ e1, 1, n - 2, factors[-1]))
        white = rng.standard_normal(n)
        left = e - white * (white @ e) / (white @ white)
        pose_factors.append(stats.serial_inflation([n], e - left, left))
    naive, corrected = np.array(naive), np.array(corrected)
    assert np.mean(corrected < 0.01) <= 0.07
    assert np.median(pose_factors) < 1.5
    if rho:
        assert np.mean(naive < 0.01) > 0.3 and np.median(factors) > 5
    else:
        assert np.median(factors) < 1.2


def test_the_serial_factor_skips_groups_without_readings():
    """A (session, axis) group with no readings adds nothing to the factor, and one of a
    single reading no lag: the factor is that of the other groups."""
    rng = np.random.default_rng(37)
    n = 200
    e, x = ar1(rng, n, 0.95), ar1(rng, n, 0.95)
    e1 = e - x * (x @ e) / (x @ x)
    alone = stats.serial_inflation([n], e - e1, e1)
    padded = stats.serial_inflation([n, 1, 0], np.r_[e - e1, 0.0], np.r_[e1, 0.0])
    assert alone > 5 and padded == pytest.approx(alone, rel=1e-9)


def test_the_formulas_against_scipy():
    """The F test's p-value against scipy.stats.f, the rule's critical F against its inverse,
    the BIC's zero against the BIC itself, Fisher's combination against scipy.stats."""
    assert stats.f_test_p(120.0, 100.0, 3, 400) == pytest.approx(
        sps.f.sf((20.0 / 3) / (100.0 / 400), 3, 400), rel=1e-12)
    assert stats.f_test_p(100.0, 120.0, 3, 400) == 1.0
    rule = stats.DecisionRule(alpha=1e-3)
    assert rule.f_critical(4, 300) == pytest.approx(sps.f.isf(1e-3, 4, 300), rel=1e-10)
    n, k, df2 = 1000, 3, 980
    F = stats.f_at_zero_bic(n, k, df2)
    rss0 = 1.0
    rss1 = rss0 / (1 + F * k / df2)               # the F statistic's definition inverted
    assert stats.bic_change(n, rss0, rss1, k) == pytest.approx(0.0, abs=1e-9)
    assert stats.fisher_p(0.01, 0.2) == pytest.approx(
        sps.combine_pvalues([0.01, 0.2], method="fisher")[1], rel=1e-12)


def test_a_bad_rule_is_refused():
    with pytest.raises(ValueError, match="alpha = 0"):
        stats.DecisionRule(alpha=0)
    with pytest.raises(ValueError, match="validation_blocks = 1"):
        stats.DecisionRule(validation_blocks=1)
    with pytest.raises(ValueError, match="min_explained = 1.5: a share"):
        stats.DecisionRule(min_explained=1.5)
    with pytest.raises(ValueError, match="at_floor = 0.9: a factor"):
        stats.DecisionRule(at_floor=0.9)


@pytest.mark.parametrize("p, dbic, p_comb, explained, gap, at_floor, routes", [
    (1e-5, -10.0, 1e-6, 0.20, 0.0, False, ("calibration",)),        # detected and relevant
    (1e-5, -10.0, 1e-6, 0.05, 0.0, False, ()),                      # detected, explains 5 %
    (1e-5, -10.0, 1e-6, 0.05, 0.6, False, ("calibration", "validation")),
    (1e-5, +3.0, 1e-6, 0.50, 0.0, False, ()),                       # the BIC rises
    (1e-5, -10.0, 1e-6, 0.50, 0.0, True, ()),                       # the model at its floor
    (0.2, +3.0, 1e-4, 0.02, 0.55, False, ("validation",)),          # the validation rows show it
    (0.2, +3.0, 2e-3, 0.02, 0.90, False, ()),                       # ... not below alpha
    (1e-3, -10.0, 1e-6, 0.50, 0.0, False, ()),                      # p equal to alpha: no
])
def test_the_rules_routes(p, dbic, p_comb, explained, gap, at_floor, routes):
    """Each route of the rule on hand-picked figures at its defaults (alpha 1e-3, min_explained
    0.1, gap_closed 0.5): written out case by case, not from the rule's code."""
    rule = stats.DecisionRule()
    assert rule.routes(p, dbic, p_comb, explained, gap, at_floor) == routes


def test_the_rule_decides_at_floor_by_its_factor():
    rule = stats.DecisionRule()
    assert rule.is_at_floor(54.9, 50.0) and not rule.is_at_floor(55.1, 50.0)
    assert rule.is_at_floor(80.0, None) is None
    assert stats.DecisionRule(at_floor=2.0).is_at_floor(99.0, 50.0)


def test_every_parameter_of_the_rule_is_a_module_default_and_documented():
    """The rule's parameters are all the decision thresholds the diagnosis has: each is a field
    of DecisionRule whose default is the module constant of the same name, and each has its row
    in docs/statistics.md's table; the diagnosis modules define no threshold of their own
    (printed: the count the rule rests on)."""
    import ast
    import dataclasses
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    doc = (root / "docs" / "statistics.md").read_text()
    fields = dataclasses.fields(stats.DecisionRule)
    for f in fields:
        assert getattr(stats, f.name.upper()) == f.default, f.name
        assert f"| `{f.name}` | {f.default:g} |" in doc, f.name
    print(f"the rule's parameters: {len(fields)}: "
          + ", ".join(f"{f.name} = {f.default:g}" for f in fields))
    rule_names = {f.name.upper() for f in fields} | {"ALPHA"}
    for module in ("diagnose.py", "floor.py", "compare.py", "attribution.py", "term_form.py",
                   "model_form.py"):
        tree = ast.parse((root / "calibration" / "diagnosis" / module).read_text())
        own = {t.id for node in tree.body if isinstance(node, ast.Assign)
               for t in node.targets if isinstance(t, ast.Name)}
        assert not own & rule_names, (module, own & rule_names)


def test_overlapping_batch_means_against_statsmodels_newey_west():
    """The long-run covariance by overlapping batches of L rows equals statsmodels' Bartlett-
    kernel (Newey-West) estimate with L - 1 lags to within 1 % on 20,000 rows of AR(1)
    scores, and the plain sum of outer products at L = 1."""
    from scipy.signal import lfilter
    from statsmodels.stats.sandwich_covariance import S_hac_simple

    rng = np.random.default_rng(0)
    for rho in (0.0, 0.9):
        x = lfilter([1.0], [1.0, -rho], rng.standard_normal((20000, 3)), axis=0)
        x -= x.mean(axis=0)
        assert np.allclose(stats.overlapping_batch_means(x, 1), x.T @ x, rtol=1e-12)
        for L in (20, 100):
            nw, obm = S_hac_simple(x, nlags=L - 1), stats.overlapping_batch_means(x, L)
            assert np.allclose(np.diag(obm), np.diag(nw), rtol=0.01), (rho, L)


def test_the_sandwich_is_unbiased_where_a_few_rows_carry_the_fit():
    """Independent rows of unequal leverage (20 coefficients on 200 rows, the largest row's
    leverage near 0.9): the fit takes a row's own share out of its residual, and a sandwich of
    the raw residual (HC0) is then biased low (measured: 0.70 of the truth); with the rows'
    scores over sqrt(1 - h) (HC2) its mean variance is the truth's sigma^2 (X^T X)^-1 to within
    the batches' own O(b / n) (measured: 0.976)."""
    rng = np.random.default_rng(1)
    X = rng.standard_normal((200, 20)) * np.exp(rng.standard_normal((200, 1)))
    truth = np.diag(np.linalg.inv(X.T @ X))
    total = np.zeros(20)
    for _ in range(1000):
        e = rng.standard_normal(200)
        r = e - X @ np.linalg.lstsq(X, e, rcond=None)[0]
        total += np.diag(stats.sandwich_covariance(X, r, np.arange(200), np.arange(200.0)))
    assert 0.94 < np.mean(total / 1000 / truth) < 1.06
