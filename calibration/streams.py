"""Temperature streams as both calibration paths read them: a causal polynomial fit over the past
window of each sensor's samples, its level (a smoothing that follows a linear trend without lag)
and its first and second time derivatives (K/s, K/s^2)."""
from __future__ import annotations

import numpy as np

from deltatwin.calibration.errors import CalibrationInputError

DEFAULT_WINDOW_S = 600.0       # the past window of the causal fit, s


def causal_derivatives(t_s, values, window_s: float = DEFAULT_WINDOW_S, degree: int = 2):
    """First and second time derivatives using only past and present samples (see
    ``causal_fit``). Returns ``(d1, d2, n_used)`` with the shape of ``values``."""
    _, d1, d2, count = causal_fit(t_s, values, window_s, degree)
    return d1, d2, count


def causal_fit(t_s, values, window_s: float = DEFAULT_WINDOW_S, degree: int = 2):
    """Level and first and second time derivatives using only past and present samples.

    ``t_s``: (n,) sample times, non-decreasing (one session).  ``values``: (n,) or (n, c).
    At each sample i, fits a polynomial of ``degree`` (1 or 2) in time by least squares to
    the samples with ``t_i - window_s <= t_j <= t_i`` and returns its derivatives at ``t_i``.
    Uneven spacing is handled; fewer distinct times than ``degree + 1`` lower the degree
    (1 sample: the sample itself, derivatives 0).  Returns ``(level, d1, d2, n_used)`` with
    the shape of ``values``: ``level`` is the polynomial's value at ``t_i``, a causal smoothing
    of the samples that follows a linear trend without lag.
    """
    t = np.asarray(t_s, dtype=float).ravel()
    v = np.asarray(values, dtype=float)
    squeeze = v.ndim == 1
    v = v.reshape(len(t), -1)
    if v.shape[0] != t.size:
        raise CalibrationInputError(f"causal_derivatives: {t.size} times but {v.shape[0]} rows")
    if not np.all(np.isfinite(t)) or not np.all(np.isfinite(v)):
        raise CalibrationInputError("causal_derivatives: times and values must be finite")
    if np.any(np.diff(t) < 0):
        raise CalibrationInputError("causal_derivatives: times must be non-decreasing")
    if not (window_s > 0) or degree not in (1, 2):
        raise CalibrationInputError(f"causal_derivatives: window_s = {window_s} must be > 0 "
                                    f"and degree = {degree} 1 or 2")
    n, c = v.shape
    level = v.copy()
    d1 = np.zeros((n, c))
    d2 = np.zeros((n, c))
    if n == 0:
        return ((level[:, 0], d1[:, 0], d2[:, 0], np.zeros(0, int)) if squeeze
                else (level, d1, d2, np.zeros(0, int)))
    lo = np.searchsorted(t, t - window_s, side="left")
    count = np.arange(n) - lo + 1
    new_time = np.concatenate([[1], (np.diff(t) > 0).astype(int)])
    cum = np.cumsum(new_time)
    distinct = cum - cum[lo] + 1
    # normal equations of every row's window, accumulated over the window's offsets k (sample
    # i - k): moments sum w tau^m (Hankel matrix G) and sum w tau^p (v_{i-k} - v_i) (B, values
    # centred on the current sample to keep them small); (n, p) and (n, p, c) arrays, never
    # one as large as (n, window, c)
    p_max = degree + 1
    moments = np.zeros((2 * p_max - 1, n))
    B = np.zeros((p_max, n, c))
    i = np.arange(n)
    for k in range(int(count.max())):
        valid = i - k >= lo
        j = np.where(valid, i - k, 0)
        tau = np.where(valid, (t[j] - t) / window_s, 0.0)               # in [-1, 0]
        power = valid.astype(float)                                     # w tau^m, m = 0, 1, ...
        Y = v[j] - v
        for m in range(2 * p_max - 1):
            moments[m] += power
            if m < p_max:
                B[m] += power[:, None] * Y
            power = power * tau
    deg = np.minimum(degree, distinct - 1)
    for dg in (1, 2):
        rows = np.flatnonzero(deg == dg)
        if rows.size == 0:
            continue
        G = np.stack([np.stack([moments[a + b, rows] for b in range(dg + 1)], axis=1)
                      for a in range(dg + 1)], axis=1)                 # (r, dg+1, dg+1)
        coef = np.linalg.solve(G, B[:dg + 1, rows].transpose(1, 0, 2))  # (r, dg+1, c)
        level[rows] = v[rows] + coef[:, 0, :]
        d1[rows] = coef[:, 1, :] / window_s
        if dg == 2:
            d2[rows] = 2.0 * coef[:, 2, :] / window_s**2
    if squeeze:
        return level[:, 0], d1[:, 0], d2[:, 0], count
    return level, d1, d2, count


def causal_weights(t_s, window_s: float = DEFAULT_WINDOW_S, degree: int = 2):
    """The linear maps ``causal_fit`` applies to the samples: sparse (n, n) matrices
    ``(level, d1)`` with ``level @ v`` equal to ``causal_fit(t_s, v, ...)``'s level (and ``d1``
    its first derivative, per second) for every ``v`` (n,). Row i holds the weights of the
    samples of its window only, so they are read from one ``causal_fit`` of as many columns as
    the widest window: column c has a 1 on every sample j = c mod width, and no window holds two
    of them."""
    from scipy import sparse

    t = np.asarray(t_s, dtype=float).ravel()
    n = t.size
    if n == 0:
        return sparse.csr_matrix((0, 0)), sparse.csr_matrix((0, 0))
    lo = np.searchsorted(t, t - window_s, side="left")
    count = np.arange(n) - lo + 1
    width = int(count.max())
    colour = np.arange(n) % width
    basis = np.zeros((n, width))
    basis[np.arange(n), colour] = 1.0
    level, d1 = causal_fit(t, basis, window_s, degree)[:2]
    rows = np.repeat(np.arange(n), count)
    cols = rows - (np.arange(rows.size) - np.repeat(np.cumsum(count) - count, count))
    return tuple(sparse.csr_matrix((m[rows, colour[cols]], (rows, cols)), shape=(n, n))
                 for m in (level, d1))
