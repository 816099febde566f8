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

(``delta0``: the candidate's change at its starting values, X = [Jm, candidate columns]), and
the diagnosis calls the effect significant when F exceeds all three of its thresholds expressed
on F: the F test's critical value at ``alpha``; the BIC's fall, F > (n^(k/n) - 1) df2 / k; the
explained fraction e* of the validation residual's power, F > 1 + n e* / ((1 - e*) rho k),
with ``rho`` the effect's signal per validation reading over its signal per calibration
reading (both after the baseline's fit). The power is the non-central F's tail beyond the
largest: an instant estimate from one simulated campaign, checked against the Monte Carlo rate
of a sweep.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pandas as pd
from scipy import stats

from deltatwin.calibration.diagnosis.diagnose import ALPHA, MIN_EXPLAINED
from deltatwin.calibration.physics.fit import PhysicsFit
from deltatwin.calibration.physics.model import PhysicsModel, _projected, group_offsets, residuals
from deltatwin.calibration.design.sweep import Case, case_scenario


def linearised_power(fit: PhysicsFit, effect: str, true_values: dict, sigma_m: float,
                     alpha: float = ALPHA, min_explained: float = MIN_EXPLAINED) -> dict:
    """Predicted probability that the diagnosis of ``fit`` (a baseline fitted to a campaign
    without ``effect``) finds ``effect`` significant when the data hold it at ``true_values``
    ({parameter: value}, SI; None: the effect off, the false-alarm rate); ``sigma_m`` is the readings' noise (m). Returns the power, the
    non-centrality, the degrees of freedom and the thresholds (module docstring)."""
    meas = fit.measurements_
    cal, val = meas.cal, meas.val
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
    Jc = _projected(meas, cal, J[:, :, new] * cand.scales[new])
    k_m = fit.identifiability_["n_identified_directions"]
    Jm = (_projected(meas, cal, fit.jacobian_ * fit.model_.scales) @ fit.identified_directions_
          if k_m else np.zeros((Jc.shape[0], 0)))
    Qm = np.linalg.qr(Jm)[0] if k_m else np.zeros((Jc.shape[0], 0))
    beyond = Jc - Qm @ (Qm.T @ Jc)
    k = 0
    if beyond.shape[1]:
        _, s, Vt = np.linalg.svd(beyond, full_matrices=False)
        keep = s > sigma_threshold(fit)
        k = int(keep.sum())
    X = np.hstack([Jm, Jc @ Vt[keep].T]) if k else Jm
    Qx = np.linalg.qr(X)[0] if X.shape[1] else X
    d = _projected(meas, cal, delta)
    d1 = d - _projected(meas, cal, delta0)
    rss0 = float(np.sum((d - Qm @ (Qm.T @ d)) ** 2))
    rss1 = float(np.sum((d1 - Qx @ (Qx.T @ d1)) ** 2))
    n = d.size
    lam = max(rss0 - rss1, 0.0) / sigma_m ** 2
    df1, df2 = max(k, 1), max(n - k_m - k - len(meas.groups), 1)
    # the effect's signal left after the baseline's fit, per validation and calibration reading
    coef = np.linalg.lstsq(Jm, d, rcond=None)[0] if k_m else np.zeros(0)
    absorbed = (fit.jacobian_ * fit.model_.scales @ fit.identified_directions_ @ coef
                if k_m else 0.0)
    # the signal alone with its session zeros removed: residuals() subtracts a prediction from
    # the readings, so the "prediction" y - left leaves left minus its zeros
    as_pred = meas.y - (delta - absorbed)
    after_baseline = residuals(meas, as_pred, group_offsets(meas, as_pred, cal))
    rows_val = val[:, None] & np.isfinite(after_baseline)
    per_val = float(np.mean(after_baseline[rows_val] ** 2)) if rows_val.any() else 0.0
    rho = per_val / (rss0 / n) if rss0 > 0 else 0.0
    thresholds = {"f_test": float(stats.f.isf(alpha, df1, df2)),
                  "bic": (n ** (df1 / n) - 1.0) * df2 / df1,
                  "explained": (1.0 + n * min_explained / ((1.0 - min_explained) * rho * df1)
                                if rho > 0 else math.inf)}
    f_star = max(thresholds.values())
    # scipy's non-central F is wrong at lambda = 0 (negative tails): the central F there
    tail = stats.ncf.sf(f_star, df1, df2, lam) if lam > 0 else stats.f.sf(f_star, df1, df2)
    power = float(tail) if math.isfinite(f_star) else 0.0
    return {"power": power, "noncentrality": lam, "df1": df1, "df2": df2, "k_new": k,
            "f_critical": f_star, "binding": max(thresholds, key=thresholds.get),
            "signal_rms_nm": math.sqrt(rss0 / n) * 1e9, "sigma_nm": sigma_m * 1e9}


def sigma_threshold(fit: PhysicsFit) -> float:
    """The singular value (m) above which the diagnosis counts a direction (its rule)."""
    return fit.noise_nm * 1e-9 / fit.identifiable_ratio


def predicted_power_curve(case: Case, magnitudes) -> pd.DataFrame:
    """The linearised power of ``case``'s design at each magnitude: one campaign simulated with
    the effect off (the case's seed), the baseline fitted, the effect's true values per
    magnitude the scenario's value times the magnitude, as the sweep makes it (0: off). ``sigma`` is the fit's residual
    standard deviation (what the readings' noise is on that campaign)."""
    off = dataclasses.replace(case, magnitude=0.0)
    sc = case_scenario(off)
    df, meta = sc.simulate(case.scale)
    fit = PhysicsFit(list(case.baseline), noise_nm=sc.settings.noise_floor_m * 1e9).fit(df, meta)
    sigma = fit.identifiability_["residual_sigma_nm"] * 1e-9
    full = next(e for e in case_scenario(dataclasses.replace(case, magnitude=1.0)).effects
                if e.name == case.effect).values
    rows = []
    for m in magnitudes:
        values = {**full, case.parameter: np.asarray(full[case.parameter], float) * m} \
            if m else None
        rows.append({"magnitude": float(m),
                     **linearised_power(fit, case.effect, values, sigma)})
    return pd.DataFrame(rows)


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
    t = mc.merge(predicted[["magnitude", "power", "noncentrality"]], on="magnitude")
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
    ax.plot(t.magnitude, t.predicted, "-o", label="linearised (non-central F)")
    ax.errorbar(t.magnitude, t.mc_significant, yerr=2 * t.mc_se, fmt="s", capsize=3,
                label="Monte Carlo: significant (+-2 s.e.)")
    ax.plot(t.magnitude, t.mc_named, "x", label="Monte Carlo: named as the missing effect")
    ax.set_xlabel("effect magnitude (factor on the scenario's parameter)")
    ax.set_ylabel("detection power")
    ax.set_ylim(-0.05, 1.05)
    ax.grid(alpha=0.3)
    ax.legend(loc="lower right", fontsize=8)
    ax.set_title(title, fontsize=9)
    return fig
