"""The prediction band of a fitted physics model: where its validation error would fall if the
model were right, from its parameters' uncertainty and the calibration residual's noise.

A model whose validation error lies above its band is misspecified (an effect missing, or
conditions it extrapolates to wrongly); one inside it is as good as these data can tell.
``validation_band`` draws the fitted parameters' error from their covariance along the
identified directions (``PhysicsFit.covariance_z_``, the sandwich of calibration/stats.py) and
from the held directions' deviation from the prior (``PhysicsFit.consider_``) and the
readings' noise as a first-order autoregressive series per (session, axis) group, with the
standard deviation and lag-1 correlation of the calibration residual of the same axis; each
draw's prediction change is zeroed on the calibration rows as the fit zeroes the data; the
band is the draws' 2.5 and 97.5 % quantiles of the validation error 90 %.
"""
from __future__ import annotations

import numpy as np

from deltatwin.twin.instruments.optics import AXES

BAND_DRAWS = 200
BAND_LEVEL = 0.95


def _noise_of_axis(fit, k: int) -> tuple[float, float]:
    """(sigma m, lag-1 correlation) of the calibration residual on axis ``k``, its groups'
    means out, readings in time order within each group."""
    meas = fit.measurements_
    t = meas.df["t_s"].to_numpy()
    parts = []
    for g, (_, axis) in enumerate(meas.groups):
        if axis != AXES[k]:
            continue
        rows = np.flatnonzero((meas.group[:, k] == g) & meas.cal)
        e = fit.residual_[rows[np.argsort(t[rows], kind="stable")], k]
        e = e[np.isfinite(e)]
        if e.size > 2:
            parts.append(e - e.mean())
    if not parts:
        return 0.0, 0.0
    ss = sum(float(e @ e) for e in parts)
    rho = sum(float(e[1:] @ e[:-1]) for e in parts) / ss if ss > 0 else 0.0
    sigma = np.sqrt(ss / max(sum(e.size for e in parts) - len(parts), 1))
    return float(sigma), float(np.clip(rho, 0.0, 0.999))


def _ar1(rng: np.random.Generator, n: int, draws: int, sigma: float, rho: float) -> np.ndarray:
    """(n, draws) stationary AR(1) series of standard deviation ``sigma``, lag-1 ``rho``."""
    w = rng.standard_normal((n, draws)) * sigma
    out = np.empty_like(w)
    if n:
        out[0] = w[0]
        c = np.sqrt(1.0 - rho * rho)
        for i in range(1, n):
            out[i] = rho * out[i - 1] + c * w[i]
    return out


def _square_root(cov: np.ndarray) -> np.ndarray:
    """L with L L^T = ``cov`` (symmetric, positive semi-definite up to round-off: the
    sandwich's eigenvalues below zero, round-off, are taken as zero)."""
    w, U = np.linalg.eigh(0.5 * (cov + cov.T))
    return U * np.sqrt(np.clip(w, 0.0, None))


def validation_band(fit, rng: np.random.Generator, draws: int = BAND_DRAWS,
                    level: float = BAND_LEVEL) -> dict:
    """{axis or "all": (low, high) nm}: the band the validation error 90 % of ``fit`` (a
    fitted PhysicsFit) falls in with probability ``level`` if its model is right (module
    docstring); ``rng`` draws parameters and noise. Empty without validation readings."""
    meas = fit.measurements_
    val = meas.val[:, None] & (meas.group >= 0) & np.isfinite(fit.residual_)
    if not val.any():
        return {}
    # the parameters' error: the identified directions' (covariance_z_) and what the held
    # directions' deviation from the prior does (consider_, one typical size each)
    k = fit.covariance_z_.shape[0]
    root = np.hstack([fit.identified_directions_ @ _square_root(fit.covariance_z_)
                      if k else np.zeros((fit.model_.n_free, 0)), fit.consider_])
    JR = (fit.jacobian_ * fit.model_.scales) @ root                     # (N, 3, k + held)
    t = meas.df["t_s"].to_numpy()
    errors = np.full(meas.y.shape + (draws,), np.nan)
    for a in range(3):
        sigma, rho = _noise_of_axis(fit, a)
        change = JR[:, a, :] @ rng.standard_normal((root.shape[1], draws))
        for g in np.unique(meas.group[:, a][meas.group[:, a] >= 0]):
            in_g = meas.group[:, a] == g
            cal = in_g & meas.cal
            zero = change[cal].mean(axis=0) if cal.any() else change[in_g].mean(axis=0)
            rows = np.flatnonzero(in_g & val[:, a])
            rows = rows[np.argsort(t[rows], kind="stable")]
            errors[rows, a] = change[rows] - zero + _ar1(rng, rows.size, draws, sigma, rho)
    q = ((1 - level) / 2, 1 - (1 - level) / 2)
    out = {}
    for name, cols in [*((a, [i]) for i, a in enumerate(AXES)), ("all", [0, 1, 2])]:
        e = np.abs(errors[:, cols][val[:, cols]])
        if e.size:
            p90 = np.quantile(e, 0.9, axis=0) * 1e9
            out[name] = tuple(float(x) for x in np.quantile(p90, q))
    return out

