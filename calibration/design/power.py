"""Detection power: will a campaign's diagnosis see an effect of a given magnitude?

The linearised prediction follows the diagnosis's own test (calibration/diagnosis/diagnose.py).
On a campaign simulated without the effect, the baseline model is fitted; then, for the effect
at magnitude m, its signature on the readings ``delta`` (the prediction with the effect at its
true values minus without, session zeros projected out over the calibration readings) is
compared with what the diagnosis fits: the baseline's identified directions ``Jm`` and the
candidate's new directions (its Jacobian columns at its starting values, projected off ``Jm``,
kept when above the identifiability threshold; ``k`` of them). The calibration residual sums of
squares before and after the candidate are then non-central: the nested F statistic follows
F'(k, n - k_m - k - zeros, lambda) with

    lambda = (|P_m_perp delta|^2 - |P_X_perp (delta - delta0)|^2) / sigma^2,

(``delta0``: the candidate's change at its starting values, X = [Jm, candidate columns]). The
diagnosis's F test (p < alpha) and the BIC's fall (F > (n^(k/n) - 1) df2 / k) are thresholds on
that statistic: ``power_f_bic`` is the non-central F's tail beyond the larger. Its third rule,
that the effect explain at least ``min_explained`` of the validation residual's power, is not a
function of F alone (the validation readings have their own noise), so ``power`` evaluates all
three rules on the same linearised campaign with Gaussian noise drawn on every reading (a few
thousand draws of linear algebra, no simulation and no fit): an instant estimate from one
simulated campaign, checked against the Monte Carlo rate of a sweep (which simulates, fits and
diagnoses each case in full).
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pandas as pd
from scipy import stats

from deltatwin.calibration.design.budget import zero_centred
from deltatwin.calibration.design.sweep import case_scenario
from deltatwin.calibration.physics.fit import PhysicsFit
from deltatwin.calibration.physics.model import PhysicsModel, projected
from deltatwin.calibration.stats import (
    ALPHA,
    MIN_EXPLAINED,
    DecisionRule,
    bic_change,
    f_at_zero_bic,
)


def linearised_power(fit: PhysicsFit, effect: str, true_values: dict | None, sigma_m: float,
                     rng: np.random.Generator, n_draws: int = 2000, alpha: float = ALPHA,
                     min_explained: float = MIN_EXPLAINED) -> dict:
    """Predicted probability that the diagnosis of ``fit`` (a baseline fitted to a campaign
    without ``effect``) finds ``effect`` significant when the data hold it at ``true_values``
    ({parameter: value}, SI; None: the effect off, the false-alarm rate); ``sigma_m`` is the
    readings' noise (m); ``rng`` draws the noise of the linearised campaign (module
    docstring). Returns ``power`` (the full rule), ``power_f_bic`` (the non-central F's tail
    beyond the F test's and the BIC's thresholds), the non-centrality and degrees of freedom."""
    meas = fit.measurements_
    cal = meas.cal
    values = fit.model_.values()
    if true_values is None:                      # the effect off: no signature
        delta = np.zeros_like(fit.prediction_)
    else:
        truth = PhysicsModel(fit.effects + [effect], fit.model_.params,
                             {**values, effect: true_values})
        delta = truth.predict_path(meas) - fit.prediction_                    # (N,3) m
    cand = PhysicsModel(fit.effects + [effect], fit.model_.params, values)
    new = np.zeros(cand.n_free, bool)
    for f in cand.free:
        new[f.sl] = f.effect == effect
    A0, J = cand.jacobian(meas, cand.theta(), columns=new)
    delta0 = A0 - fit.prediction_
    Jc_full = J[:, :, new] * cand.scales[new]
    Jc = projected(meas, cal, Jc_full)
    k_m = fit.identifiability_["n_identified_directions"]
    full_m = (fit.jacobian_ * fit.model_.scales @ fit.identified_directions_ if k_m
              else np.zeros(delta.shape + (0,)))
    Jm = projected(meas, cal, full_m)
    Qm = np.linalg.qr(Jm)[0]
    beyond = Jc - Qm @ (Qm.T @ Jc)
    k = 0
    if beyond.shape[1]:
        _, s, Vt = np.linalg.svd(beyond, full_matrices=False)
        keep = s > sigma_threshold(fit)
        k = int(keep.sum())
    full_x = np.concatenate([full_m, Jc_full @ Vt[keep].T], axis=2) if k else full_m
    X = projected(meas, cal, full_x)
    Qx = np.linalg.qr(X)[0]
    d = projected(meas, cal, delta)
    d1 = d - projected(meas, cal, delta0)
    rss0 = float(np.sum((d - Qm @ (Qm.T @ d)) ** 2))
    rss1 = float(np.sum((d1 - Qx @ (Qx.T @ d1)) ** 2))
    n = d.size
    lam = max(rss0 - rss1, 0.0) / sigma_m ** 2
    df1, df2 = max(k, 1), meas.residual_dof(n, k_m + k)
    f_alpha = DecisionRule(alpha).f_critical(df1, df2)
    f_bic = f_at_zero_bic(n, df1, df2)
    f_star = max(f_alpha, f_bic)
    # scipy's non-central F is wrong at lambda = 0 (negative tails): the central F there
    tail = stats.ncf.sf(f_star, df1, df2, lam) if lam > 0 else stats.f.sf(f_star, df1, df2)
    # the full rule, the explained fraction of the validation residual included, on the same
    # linear model with Gaussian noise drawn on every reading
    draws = _linear_draws(meas, delta, delta0, Jm, X, full_m, full_x, sigma_m, n_draws, rng)
    passed = ((draws["F"] > f_alpha) & (draws["dBIC"] < 0)
              & (draws["explained"] >= min_explained))
    return {"power": float(passed.mean()), "power_f_bic": float(tail), "noncentrality": lam,
            "df1": df1, "df2": df2, "k_new": k, "f_critical": f_star,
            "median_explained": float(np.median(draws["explained"])),
            "signal_rms_nm": math.sqrt(rss0 / n) * 1e9, "sigma_nm": sigma_m * 1e9}


def _linear_draws(meas, delta, delta0, Jm, X, full_m, full_x, sigma_m, n_draws, rng) -> dict:
    """The diagnosis's statistics on the linearised campaign: readings = signal ``delta`` +
    noise, the baseline fitted on its identified columns (``Jm`` projected, (n, k_m); ``full_m``
    on every row, (N,3,k_m)), the candidate's ``X`` / ``full_x`` likewise: F, dBIC and the
    explained fraction of the validation residual's power, one per draw (``n_draws``)."""
    cal = meas.cal
    y = delta[:, :, None] + sigma_m * rng.standard_normal(delta.shape + (n_draws,))
    coef_m = np.linalg.lstsq(Jm, projected(meas, cal, y), rcond=None)[0]
    u = y - np.einsum("naj,jd->nad", full_m, coef_m)           # the baseline's residual
    before = zero_centred(meas, u)
    r0 = projected(meas, cal, u)
    r = projected(meas, cal, u - delta0[:, :, None])
    coef = np.linalg.lstsq(X, r, rcond=None)[0]
    after = zero_centred(meas, u - delta0[:, :, None] - np.einsum("naj,jd->nad", full_x, coef))
    rss0 = np.sum(r0 ** 2, axis=0)
    rss1 = np.sum((r - X @ coef) ** 2, axis=0)
    n, k_m, k = r.shape[0], Jm.shape[1], X.shape[1] - Jm.shape[1]
    df1, df2 = max(k, 1), meas.residual_dof(n, k_m + k)
    F = np.where(rss0 > rss1, (rss0 - rss1) / df1 / (rss1 / df2), 0.0)
    dbic = bic_change(n, rss0, rss1, k)
    val = meas.val[:, None] & (meas.group >= 0)
    explained = 1.0 - np.sum(after[val] ** 2, axis=0) / np.sum(before[val] ** 2, axis=0)
    return {"F": F, "dBIC": dbic, "explained": explained}



def sigma_threshold(fit: PhysicsFit) -> float:
    """The singular value (m) above which the diagnosis counts a direction (its rule)."""
    return fit.noise_nm * 1e-9 / fit.identifiable_ratio


def predicted_power_curve(cases, magnitudes, rng: np.random.Generator,
                          n_draws: int = 2000) -> pd.DataFrame:
    """The linearised power of a design at each magnitude, averaged over the simulated
    campaigns of ``cases`` (Case objects of the design, e.g. a few replicates: a campaign plan
    draws its positions from the seed, and the design's power is the mean over its draws). Per
    campaign: simulated with the effect off, the baseline fitted, the effect's true values the
    scenario's times the magnitude as the sweep makes them (0: off), the noise the fit's residual
    standard deviation on that campaign; ``rng`` draws the linearised noise. Columns: magnitude,
    power (mean), power_sd (its spread over the campaigns), power_f_bic, noncentrality (means),
    campaigns."""
    per = []
    for case in cases:
        sc = case_scenario(dataclasses.replace(case, magnitude=0.0))
        df, meta = sc.simulate(case.scale)
        fit = PhysicsFit(list(case.baseline),
                         noise_nm=sc.settings.noise_floor_m * 1e9).fit(df, meta)
        sigma = fit.identifiability_["residual_sigma_nm"] * 1e-9
        full = next(e for e in case_scenario(dataclasses.replace(case, magnitude=1.0)).effects
                    if e.name == case.effect).values
        for m in magnitudes:
            values = {**full, case.parameter: np.asarray(full[case.parameter], float) * m} \
                if m else None
            per.append({"magnitude": float(m),
                        **linearised_power(fit, case.effect, values, sigma, rng, n_draws)})
    g = pd.DataFrame(per).groupby("magnitude")
    out = g[["power", "power_f_bic", "noncentrality", "median_explained", "sigma_nm"]].mean()
    out["power_sd"] = g["power"].std(ddof=0)
    out["campaigns"] = g.size()
    return out.reset_index()


def monte_carlo_power(records: pd.DataFrame) -> pd.DataFrame:
    """Per (scenario, effect, design, magnitude): the sweep's rate of ``significant`` (the
    effect passes the diagnosis's test) and of ``named`` (it is the missing effect named),
    with the binomial standard error of the first."""
    ok = records[records.status == "ok"]
    g = ok.groupby(["scenario", "effect", "design", "magnitude"], observed=True)
    out = g.agg(cases=("case_id", "size"), mc_significant=("significant", "mean"),
                mc_named=("named", "mean")).reset_index()
    out["mc_se"] = np.sqrt(out.mc_significant * (1 - out.mc_significant) / out.cases)
    return out


def power_table(predicted: pd.DataFrame, mc: pd.DataFrame) -> pd.DataFrame:
    """Predicted beside Monte Carlo power, per magnitude, with their difference."""
    t = mc.merge(predicted[["magnitude", "power", "power_sd", "power_f_bic", "noncentrality"]],
                 on="magnitude")
    t = t.rename(columns={"power": "predicted"})
    t["difference"] = t.mc_significant - t.predicted
    return t


def power_figure(table: pd.DataFrame, title: str = ""):
    """Power against magnitude: the prediction, the Monte Carlo rates with +-2 standard errors
    (matplotlib Figure API)."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(6.4, 4.2), layout="constrained")
    ax = fig.add_subplot()
    t = table.sort_values("magnitude")
    ax.plot(t.magnitude, t.predicted, "-o", label="linearised prediction")
    ax.errorbar(t.magnitude, t.mc_significant, yerr=2 * t.mc_se, fmt="s", capsize=3,
                label="Monte Carlo: significant (+-2 s.e.)")
    ax.plot(t.magnitude, t.mc_named, "x", label="Monte Carlo: named as the missing effect")
    ax.set_xlabel("effect magnitude (factor on the scenario's parameter)")
    ax.set_ylabel("detection power")
    ax.set_ylim(-0.05, 1.05)
    ax.grid(alpha=0.3)
    ax.legend(loc="upper left", fontsize=8)
    ax.set_title(title, fontsize=9)
    return fig
