"""The prediction band of a fitted physics model: where its validation error would fall if the
model were right, from its parameters' uncertainty and the calibration residual's noise.

A model whose validation error lies above its band is misspecified (an effect missing, or
conditions it extrapolates to wrongly); one inside it is as good as these data can tell.
``validation_band`` draws the fitted parameters' error from their covariance along the
identified directions (``PhysicsFit.covariance_z_``: the residual's sandwich and the slow
sources propagated) and from the held directions' deviation from the prior
(``PhysicsFit.consider_``), and the readings' noise as the calibration residual of the same
axis shows it, resampled in blocks (a moving-block bootstrap: its own distribution, whose
tails a Gaussian of the same standard deviation overstates at the 90 % point, and its serial
correlation); each draw's prediction change is zeroed on the calibration rows as the fit
zeroes the data; the band is the draws' 2.5 and 97.5 % quantiles of the validation error
90 %.
"""
from __future__ import annotations

import numpy as np

from deltatwin.twin.instruments.optics import AXES

BAND_DRAWS = 200
BAND_LEVEL = 0.95


def _residual_of_axis(fit, k: int) -> np.ndarray:
    """The calibration residual (m) on axis ``k``, each group's mean out, readings in time
    order within each group, the groups one after the other."""
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
    return np.concatenate(parts) if parts else np.zeros(0)


def block_length(e: np.ndarray) -> int:
    """Rows per block of a moving-block bootstrap of the series ``e``: twice its integrated
    correlation time (1 + rho) / (1 - rho) for its lag-1 correlation rho (an AR(1)'s), at
    least 1, at most a quarter of the series."""
    ss = float(e @ e)
    rho = float(np.clip(e[1:] @ e[:-1] / ss, 0.0, 0.99)) if ss > 0 and e.size > 1 else 0.0
    return int(np.clip(np.ceil(2 * (1 + rho) / (1 - rho)), 1, max(e.size // 4, 1)))


def block_bootstrap(rng: np.random.Generator, e: np.ndarray, n: int, draws: int) -> np.ndarray:
    """(n, draws) series resampled from ``e`` in moving blocks of ``block_length`` rows, each
    block starting at a random row and wrapping round (Künsch 1989; the circular variant of
    Politis and Romano 1992): the residual's own distribution, tails and serial correlation,
    with no shape assumed."""
    if e.size == 0 or n == 0:
        return np.zeros((n, draws))
    size = block_length(e)
    blocks = -(-n // size)
    starts = rng.integers(0, e.size, (blocks, draws))
    index = (starts[:, None, :] + np.arange(size)[None, :, None]) % e.size
    return e[index.reshape(blocks * size, draws)[:n]]


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
    # directions' deviation from the prior does (consider_, the prior's width each)
    k = fit.covariance_z_.shape[0]
    root = np.hstack([fit.identified_directions_ @ _square_root(fit.covariance_z_)
                      if k else np.zeros((fit.model_.n_free, 0)), fit.consider_])
    JR = (fit.jacobian_ * fit.model_.scales) @ root                     # (N, 3, k + held)
    t = meas.df["t_s"].to_numpy()
    errors = np.full(meas.y.shape + (draws,), np.nan)
    for a in range(3):
        noise = _residual_of_axis(fit, a)
        change = JR[:, a, :] @ rng.standard_normal((root.shape[1], draws))
        for g in np.unique(meas.group[:, a][meas.group[:, a] >= 0]):
            in_g = meas.group[:, a] == g
            cal = in_g & meas.cal
            zero = change[cal].mean(axis=0) if cal.any() else change[in_g].mean(axis=0)
            rows = np.flatnonzero(in_g & val[:, a])
            rows = rows[np.argsort(t[rows], kind="stable")]
            errors[rows, a] = change[rows] - zero + block_bootstrap(rng, noise, rows.size, draws)
    q = ((1 - level) / 2, 1 - (1 - level) / 2)
    out = {}
    for name, cols in [*((a, [i]) for i, a in enumerate(AXES)), ("all", [0, 1, 2])]:
        e = np.abs(errors[:, cols][val[:, cols]])
        if e.size:
            p90 = np.quantile(e, 0.9, axis=0) * 1e9
            out[name] = tuple(float(x) for x in np.quantile(p90, q))
    return out

