"""The prediction band of a fitted physics model: where its validation error would fall if the
model were right, from its parameters' uncertainty and the calibration residual's noise.

A model whose validation error lies above its band is misspecified (an effect missing, or
conditions it extrapolates to wrongly); one inside it is as good as these data can tell.
``prediction_band`` draws the fitted parameters' error from their covariance (``PhysicsFit
.covariance_``: along the identified directions the residual's sandwich and the slow sources
propagated, along the held ones the prior's width through the consider covariance), and the
readings' noise as the calibration residual of the same axis shows it, resampled in blocks (a
moving-block bootstrap: its own distribution, whose tails a Gaussian of the same standard
deviation overstates at the 90 % point, and its serial correlation); each draw's prediction
change is zeroed on the calibration rows as the fit zeroes the data; the band is the draws' 2.5
and 97.5 % quantiles of the validation error 90 %. ``validation_band`` is that of a fit on its
own data; ``deltatwin compare`` draws that of a saved model on any dataset.
"""
from __future__ import annotations

import numpy as np

from deltatwin.twin.instruments.optics import AXES

BAND_DRAWS = 200
BAND_LEVEL = 0.95


def _residual_of_axis(meas, residual: np.ndarray, k: int) -> np.ndarray:
    """The calibration residual (m, ``residual`` (N,3) on ``meas``) on axis ``k``, each
    group's mean out, readings in time order within each group, the groups one after the
    other."""
    t = meas.df["t_s"].to_numpy()
    parts = []
    for g, (_, axis) in enumerate(meas.groups):
        if axis != AXES[k]:
            continue
        rows = np.flatnonzero((meas.group[:, k] == g) & meas.cal)
        e = residual[rows[np.argsort(t[rows], kind="stable")], k]
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


def square_root(cov: np.ndarray) -> np.ndarray:
    """L with L L^T = ``cov`` (symmetric, positive semi-definite up to round-off), taken on the
    correlation matrix (parameters of unlike units differ in variance by 20 orders of
    magnitude: on ``cov`` itself the small ones would be round-off of the large), its
    eigenvalues below zero (round-off) taken as zero."""
    sigma = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    unit = np.where(sigma > 0, sigma, 1.0)
    corr = cov / np.outer(unit, unit)
    w, U = np.linalg.eigh(0.5 * (corr + corr.T))
    return unit[:, None] * U * np.sqrt(np.clip(w, 0.0, None))


def validation_band(fit, rng: np.random.Generator, draws: int = BAND_DRAWS,
                    level: float = BAND_LEVEL) -> dict:
    """{axis or "all": (low, high) nm}: the band the validation error 90 % of ``fit`` (a
    fitted PhysicsFit) falls in with probability ``level`` if its model is right
    (``prediction_band`` on its own data); ``rng`` draws parameters and noise."""
    return prediction_band(fit.measurements_, fit.jacobian_, fit.covariance_, fit.residual_,
                           rng, draws, level)


def prediction_band(meas, jacobian: np.ndarray, covariance: np.ndarray, residual: np.ndarray,
                    rng: np.random.Generator, draws: int = BAND_DRAWS,
                    level: float = BAND_LEVEL) -> dict:
    """{axis or "all": (low, high) nm}: the band of the validation error 90 % on the data
    ``meas`` of a model of Jacobian ``jacobian`` there ((N, 3, p), m per parameter unit) whose
    parameters have the ``covariance`` (p, p; SI) and whose ``residual`` there ((N, 3) m,
    after each session's zero) shows the readings' noise on the calibration rows (module
    docstring); ``rng`` draws parameters and noise. Empty without validation readings."""
    val = meas.val[:, None] & (meas.group >= 0) & np.isfinite(residual)
    if not val.any():
        return {}
    JR = np.nan_to_num(jacobian) @ square_root(covariance)             # (N, 3, p)
    t = meas.df["t_s"].to_numpy()
    errors = np.full(meas.y.shape + (draws,), np.nan)
    for a in range(3):
        noise = _residual_of_axis(meas, residual, a)
        change = JR[:, a, :] @ rng.standard_normal((JR.shape[2], draws))
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
