"""stepwisefit: MATLAB semantics (Hald golden case, rules) and equality with a plain
statsmodels OLS refit loop on generated problems, including ill-conditioned ones."""
import warnings

import numpy as np
import pytest

from deltatwin.calibration.blackbox.features import thermal_preset
from deltatwin.calibration.blackbox.stepwise import (
    resolve_thresholds,
    stepwise_refit_loop,
    stepwisefit,
)
from deltatwin.calibration.errors import (
    CalibrationInputError,
    DegenerateColumnWarning,
    DroppedRowsWarning,
)

HALD_X = np.array([[7, 26, 6, 60], [1, 29, 15, 52], [11, 56, 8, 20], [11, 31, 8, 47],
                   [7, 52, 6, 33], [11, 55, 9, 22], [3, 71, 17, 6], [1, 31, 22, 44],
                   [2, 54, 18, 22], [21, 47, 4, 26], [1, 40, 23, 34], [11, 66, 9, 12],
                   [10, 68, 8, 12]], dtype=float)
HALD_Y = np.array([78.5, 74.3, 104.3, 87.6, 95.9, 109.2, 102.7, 72.5, 93.1, 115.9, 83.8,
                   113.3, 109.4])


def test_hald_defaults_reproduce_matlab():
    r = stepwisefit(HALD_X, HALD_Y)
    assert r.steps() == [("add", 3), ("add", 0)]
    assert r.history[0].F == pytest.approx(22.7985, abs=5e-5)
    assert r.history[0].pval == pytest.approx(5.762e-4, rel=1e-3)
    assert r.history[1].F == pytest.approx(108.2239, abs=5e-5)
    assert r.history[1].pval == pytest.approx(1.105e-6, rel=1e-3)
    assert r.inmodel.tolist() == [True, False, False, True]
    assert r.intercept == pytest.approx(103.0974, abs=5e-5)
    assert r.coef[0] == pytest.approx(1.4400, abs=5e-5)
    assert r.coef[3] == pytest.approx(-0.6140, abs=5e-5)
    assert r.rmse == pytest.approx(2.7343, abs=5e-5)
    # MATLAB also reports, for the terms out, the coefficient they would have if added
    assert r.coef[1] == pytest.approx(0.4161, abs=5e-5)
    assert r.coef[2] == pytest.approx(-0.4100, abs=5e-5)
    assert r.penter == 0.05 and r.premove == 0.10
    assert r.stop_reason == "no step qualifies"


def test_hald_penter_006_adds_then_removes_x4():
    r = stepwisefit(HALD_X, HALD_Y, penter=0.06)
    assert r.steps() == [("add", 3), ("add", 0), ("add", 1), ("remove", 3)]
    assert r.history[2].pval == pytest.approx(0.051687, abs=5e-7)
    assert r.history[3].F == pytest.approx(1.8633, abs=5e-5)
    assert r.history[3].pval == pytest.approx(0.2054, abs=5e-5)
    assert r.inmodel.tolist() == [True, True, False, False]
    assert r.intercept == pytest.approx(52.577, abs=5e-4)
    assert r.coef[0] == pytest.approx(1.4683, abs=5e-5)
    assert r.coef[1] == pytest.approx(0.66225, abs=5e-6)
    # history: rmse and model after each step
    assert r.history_in.shape == (4, 4)
    assert r.history_in[-1].tolist() == [True, True, False, False]
    assert r.history[-1].rmse == pytest.approx(r.rmse)


def test_final_coefficients_equal_a_direct_least_squares_fit():
    r = stepwisefit(HALD_X, HALD_Y, penter=0.06)
    A = np.column_stack([np.ones(13), HALD_X[:, r.inmodel]])
    sol = np.linalg.lstsq(A, HALD_Y, rcond=None)[0]
    assert r.intercept == pytest.approx(sol[0], rel=1e-12)
    assert np.allclose(r.coef[r.inmodel], sol[1:], rtol=1e-12)
    assert np.allclose(r.predict(HALD_X), A @ sol, rtol=1e-12)


def test_threshold_defaults_and_checks():
    assert resolve_thresholds() == (0.05, 0.10)
    assert resolve_thresholds(0.2) == (0.2, 0.2)           # premove = max(penter, 0.10)
    assert resolve_thresholds(premove=0.03) == (0.03, 0.03)  # penter = min(premove, 0.05)
    assert resolve_thresholds(premove=0.2) == (0.05, 0.2)
    with pytest.raises(CalibrationInputError, match="penter"):
        resolve_thresholds(0.2, 0.1)
    with pytest.raises(CalibrationInputError, match="penter"):
        stepwisefit(HALD_X, HALD_Y, penter=0.06, premove=0.05)


def test_keep_inmodel_maxiter():
    r = stepwisefit(HALD_X, HALD_Y, keep=[2])
    assert r.inmodel[2] and all(h.column != 2 for h in r.history)
    r = stepwisefit(HALD_X, HALD_Y, inmodel=np.array([True, True, True, True]))
    # starting from the full model, the rules remove the weakest terms
    assert r.history[0].action == "remove"
    ref_in, ref_steps = stepwise_refit_loop(HALD_X, HALD_Y, inmodel=[0, 1, 2, 3])
    assert ref_steps == r.steps() and np.array_equal(ref_in, r.inmodel)
    r = stepwisefit(HALD_X, HALD_Y, penter=0.06, maxiter=2)
    assert r.n_steps == 2 and r.stop_reason == "maxiter"
    with pytest.raises(CalibrationInputError, match="outside"):
        stepwisefit(HALD_X, HALD_Y, keep=[7])


def test_nan_rows_dropped_with_named_warning_and_same_result():
    X = np.vstack([HALD_X, [np.nan, 1, 1, 1]])
    y = np.append(HALD_Y, 100.0)
    with pytest.warns(DroppedRowsWarning, match="1 row"):
        r = stepwisefit(X, y)
    assert r.n_dropped == 1 and r.n_obs == 13
    assert r.steps() == stepwisefit(HALD_X, HALD_Y).steps()
    with pytest.raises(CalibrationInputError, match="infinite"):
        stepwisefit(np.vstack([HALD_X, [np.inf, 1, 1, 1]]), y)
    with pytest.raises(CalibrationInputError, match="rows"):
        stepwisefit(HALD_X, HALD_Y[:-1])


def test_constant_duplicate_and_collinear_columns_are_reported_never_selected():
    rng = np.random.default_rng(3)
    N = 80
    A = rng.normal(size=(N, 3))
    X = np.column_stack([A, np.full(N, 22.0), A[:, 0], A[:, 1] + 2 * A[:, 2]])
    y = 3 * A[:, 0] - 2 * A[:, 1] + A[:, 2] + rng.normal(0, 0.1, N)
    with pytest.warns(DegenerateColumnWarning) as rec:
        r = stepwisefit(X, y)
    msgs = " ".join(str(w.message) for w in rec)
    assert "constant" in msgs and "x5 = x1" in msgs
    assert r.constant.tolist() == [False, False, False, True, False, False]
    assert r.duplicate.tolist() == [-1, -1, -1, -1, 0, -1]
    assert r.inmodel.tolist()[:3] == [True, True, True]
    assert not r.inmodel[3:].any()
    assert r.collinear[5]                 # x2 + 2 x3 is in the span of the model
    assert r.pval[5] == pytest.approx(1.0)
    with pytest.raises(CalibrationInputError, match="constant"):
        stepwisefit(X, y, keep=[3])


def test_rank_deficient_initial_model_removes_nan_p_first():
    rng = np.random.default_rng(4)
    A = rng.normal(size=(60, 3))
    X = np.column_stack([A, A[:, 0] + A[:, 1]])
    y = A[:, 0] + rng.normal(0, 0.1, 60)
    r = stepwisefit(X, y, inmodel=[0, 1, 3])
    first = r.history[0]
    assert first.action == "remove" and np.isnan(first.pval)
    assert not r.aliased.any()


def _cubic_temperature_problem(rng, n=400, k=3):
    """Cubic monomials of q (±0.06 rad) times temperatures near 22 degC: ill-conditioned."""
    from deltatwin.calibration.blackbox.features import FeatureSet, Product, geometric, temperatures
    sensors = [f"s{i}" for i in range(k)]
    geo = geometric()
    temps = temperatures(sensors)
    fs = FeatureSet([geo, temps, Product(geo, temps)])
    q = rng.uniform(-0.06, 0.06, (n, 3))
    t = np.linspace(0, 1, n)
    vals = {"q1": q[:, 0], "q2": q[:, 1], "q3": q[:, 2]}
    for i, s in enumerate(sensors):
        vals[f"T_{s}"] = 22.0 + 0.8 * np.sin(2 * np.pi * (t + 0.3 * i)) + rng.normal(0, 1e-3, n)
    X = fs.matrix(vals)
    T0 = vals["T_s0"] - 22.0
    y = (0.08 * q[:, 0] - 0.04 * q[:, 1] + 0.03 * q[:, 0] ** 2 + 0.2 * q[:, 0] ** 3
         + 4e-7 * T0 + 8.6e-6 * 0.08 * q[:, 0] * T0 + 2e-3 * q[:, 1] * q[:, 2] * T0
         + rng.normal(0, 5e-9, n))
    return X, y


def _problems():
    rng = np.random.default_rng(2024)
    out = []
    # 1. sparse truth among correlated gaussian columns
    N, P = 300, 25
    L = rng.normal(size=(P, P)) * 0.3 + np.eye(P)
    X = rng.normal(size=(N, P)) @ L
    beta = np.zeros(P)
    beta[[1, 4, 7, 12, 20]] = [1.0, -0.5, 0.3, 0.2, -0.15]
    out.append(("correlated", X, X @ beta + rng.normal(0, 1, N), {}))
    # 2. a proxy column enters first, then the true ones, then the proxy leaves
    a, b = rng.normal(size=(2, N))
    X = np.column_stack([rng.normal(size=(N, 3)), a + b + rng.normal(0, 0.3, N), a, b])
    out.append(("removal", X, a + b + rng.normal(0, 0.2, N), {}))
    # 3. ill-conditioned cubic x temperature columns (raw degC)
    X, y = _cubic_temperature_problem(rng)
    out.append(("cubic x temperature", X, y, {}))
    # 4. same with keep, inmodel and other thresholds
    out.append(("cubic x temperature, keep/inmodel", X, y,
                dict(keep=[0], inmodel=[5, 25], penter=0.01, premove=0.02)))
    return out


@pytest.mark.parametrize("name,X,y,kw", _problems(), ids=[p[0] for p in _problems()])
def test_same_selection_order_as_plain_statsmodels_refit_loop(name, X, y, kw):
    r = stepwisefit(X, y, **kw)
    ref_in, ref_steps = stepwise_refit_loop(X, y, **kw)
    assert r.n_steps >= 3
    assert r.steps() == ref_steps
    assert np.array_equal(r.inmodel, ref_in)
    assert r.refit_rel_diff < 1e-8
    if name == "removal":
        assert ("remove", 3) in r.steps()


def test_ill_conditioned_coefficients_match_statsmodels_fit():
    import statsmodels.api as sm
    X, y = _cubic_temperature_problem(np.random.default_rng(8))
    Z = (X - X.mean(0)) / X.std(0)
    s = np.linalg.svd(Z, compute_uv=False)
    assert s[0] / s[-1] > 1e5            # ill-conditioned even after standardising
    A = np.column_stack([np.ones(len(y)), X])
    assert np.linalg.cond(A) > 1e10      # and badly so as given (normal equations: 1e20)
    r = stepwisefit(X, y)
    fit = sm.OLS(y, sm.add_constant(X[:, r.inmodel])).fit()
    assert np.allclose(r.predict(X), fit.fittedvalues, rtol=0, atol=1e-13)
    assert np.allclose(r.pval[r.inmodel], fit.pvalues[1:], rtol=1e-6, atol=1e-300)


def test_paper_preset_width_runs_and_is_deterministic():
    sensors = [f"s{i}" for i in range(9)]
    fs = thermal_preset(sensors)
    rng = np.random.default_rng(5)
    n = 600
    vals = {f"q{i}": rng.uniform(-0.06, 0.06, n) for i in (1, 2, 3)}
    for s in sensors:
        base = 22 + rng.normal(0, 0.5) + np.cumsum(rng.normal(0, 0.01, n))
        vals[f"T_{s}"] = base
        vals[f"dT_{s}"] = np.gradient(base)
        vals[f"d2T_{s}"] = np.gradient(vals[f"dT_{s}"])
    X = fs.matrix(vals)
    assert X.shape == (n, 217)
    y = 0.08 * vals["q1"] + 1e-6 * vals["T_s3"] + rng.normal(0, 5e-9, n)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        r1 = stepwisefit(X, y, names=fs.names)
    r2 = stepwisefit(X, y, names=fs.names)
    assert r1.steps() == r2.steps() and r1.inmodel[0] and r1.inmodel[fs.names.index("T_s3")]
