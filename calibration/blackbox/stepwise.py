"""Stepwise regression with the semantics of MATLAB's ``stepwisefit`` (Statistics Toolbox).

The seeds' calibration kept the terms chosen by MATLAB's ``stepwisefit``.  This module
reproduces its rules exactly (see docs/calibration.md):

* one change per iteration, adding before removing;
* among the terms out of the model (and not kept) the one with the smallest p-value enters
  if ``p < penter``; its p-value is the added-variable t test with ``dfe - 1`` degrees of
  freedom (the partial F = t**2);
* otherwise a term in the model (and not kept) with a NaN p-value leaves first; else the one
  with the largest p-value (t test, ``dfe`` degrees of freedom) leaves if ``p > premove``;
* ties go to the lowest column index; the loop stops when no step qualifies or at ``maxiter``;
* ``penter`` defaults to 0.05 and ``premove`` to ``max(penter, 0.10)``; given only ``premove``,
  ``penter = min(premove, 0.05)``; ``penter <= premove`` is required;
* the fit is a pivoted QR with rank tolerance ``max(N, P + 1) * eps``; a candidate whose
  residual on the model is below ``tol * sum(x**2)`` is "perfectly fitted" and gets p = 1.

How it is fast without changing a single decision: the columns are standardised, and the
augmented matrix ``[Z y]`` (N x (P+1)) is reduced once by a Householder QR to its triangular
factor ``R`` ((P+1) x (P+1)).  Because ``[Z y] = Q R`` with orthonormal ``Q``, every residual
norm and inner product of every sub-model is the same computed on the rows of ``R`` as on
the N rows of the data, so each step runs MATLAB's own ``stepcalc`` (pivoted QR of the
model columns, all candidates' added-variable statistics at once) on P+1 rows instead of N.
The condition number is not squared (no cross-product matrix).  At the end the selected
model is refitted on the full standardised data with a stable least-squares solve
(``scipy.linalg.lstsq``) and the coefficients are reported from that refit, together with
its relative difference to the reduced computation (``refit_rel_diff``).
"""
from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg
import scipy.linalg.lapack
import scipy.special

from deltatwin.calibration.errors import (
    CalibrationInputError,
    DegenerateColumnWarning,
    DroppedRowsWarning,
)

__all__ = ["stepwisefit", "StepwiseResult", "StepRecord", "stepwise_refit_loop",
           "resolve_thresholds"]


class _DefaultFloat(float):
    """The default ``penter``: a float that remembers it was not given by the caller."""


PENTER_DEFAULT = _DefaultFloat(0.05)


@dataclass(frozen=True)
class StepRecord:
    """One step of the stepwise loop (what MATLAB prints and keeps in ``history``)."""
    step: int          # 1-based
    action: str        # "add" or "remove"
    column: int        # 0-based column index
    name: str
    F: float           # partial F (= t**2) of that column before the step; NaN if its p was NaN
    pval: float        # its p-value before the step (the one compared with penter / premove)
    rmse: float        # root mean square error of the model after the step (units of y)
    df0: int           # number of model terms after the step (rank, intercept excluded)
    n_in: int          # number of columns in the model after the step


@dataclass
class StepwiseResult:
    """Result of :func:`stepwisefit`; arrays are indexed by column of X (0-based)."""
    inmodel: np.ndarray        # bool (P,): final model
    coef: np.ndarray           # (P,) in-model: final QR refit; out: value it would have if added
    intercept: float
    se: np.ndarray             # (P,) standard errors (out: of the added-variable coefficient)
    tstat: np.ndarray          # (P,)
    pval: np.ndarray           # (P,) in: t test with dfe dof; out: added-variable test, dfe-1 dof
    rmse: float
    dfe: int                   # residual degrees of freedom of the final model
    df0: int                   # regression degrees of freedom (rank of the model, no intercept)
    n_obs: int                 # rows used (after removing rows with NaN)
    history: list[StepRecord]  # one record per step
    history_in: np.ndarray     # bool (n_steps, P): model after each step
    names: list[str]
    constant: np.ndarray       # bool (P,): constant columns (never eligible)
    duplicate: np.ndarray      # (P,) int: index of the earlier identical column, -1 if none
                               #   (after standardisation; duplicates are never eligible)
    aliased: np.ndarray        # bool (P,): in-model columns dropped by the rank test at the end
    collinear: np.ndarray      # bool (P,): out-of-model, non-constant columns that the final
                               #   model fits exactly (in its span: they can never enter)
    penter: float
    premove: float
    stop_reason: str           # "no step qualifies" or "maxiter"
    n_dropped: int = 0         # rows removed because X or y held NaN
    refit_rel_diff: float = 0.0  # |RSS(final QR refit) - RSS(reduced computation)| / RSS
    x_mean: np.ndarray = field(default=None, repr=False)   # column means used to standardise
    x_std: np.ndarray = field(default=None, repr=False)    # column std (ddof=1); 1 if constant
    y_mean: float = 0.0
    y_std: float = 1.0

    @property
    def selected(self) -> np.ndarray:
        """Indices of the columns in the final model, ascending."""
        return np.flatnonzero(self.inmodel)

    @property
    def n_steps(self) -> int:
        return len(self.history)

    def steps(self) -> list[tuple[str, int]]:
        """``[(action, column), ...]`` in order: the selection path."""
        return [(h.action, h.column) for h in self.history]

    def predict(self, X) -> np.ndarray:
        X = np.asarray(X, dtype=float)
        return self.intercept + X[:, self.inmodel] @ self.coef[self.inmodel]

    def summary(self) -> str:
        lines = []
        for h in self.history:
            word = "added" if h.action == "add" else "removed"
            lines.append(f"Step {h.step}, {word} column {h.column + 1} ({h.name}), "
                         f"F={h.F:.6g}, p={h.pval:.6g}")
        lines.append(f"Final model: {self.inmodel.sum()} terms, intercept {self.intercept:.6g}, "
                     f"RMSE {self.rmse:.6g}, stop: {self.stop_reason}")
        return "\n".join(lines)


def resolve_thresholds(penter=PENTER_DEFAULT, premove=None) -> tuple[float, float]:
    """MATLAB's defaults and check for the entry / removal p-value thresholds."""
    given_penter = not isinstance(penter, _DefaultFloat)
    if premove is None:
        penter = float(penter)
        premove = max(penter, 0.10)
    elif not given_penter:
        premove = float(premove)
        penter = min(premove, 0.05)
    penter, premove = float(penter), float(premove)
    for name, v in (("penter", penter), ("premove", premove)):
        if not (0.0 < v <= 1.0) or math.isnan(v):
            raise CalibrationInputError(f"stepwisefit: {name} = {v} must be in (0, 1]")
    if penter > premove:
        raise CalibrationInputError(f"stepwisefit: penter = {penter} must be <= premove = "
                                    f"{premove} (otherwise a term could enter and leave forever)")
    return penter, premove


def _mask(arg, P: int, what: str) -> np.ndarray:
    """A boolean mask of length P from None, a boolean mask or column indices."""
    if arg is None:
        return np.zeros(P, bool)
    a = np.asarray(arg)
    if a.dtype == bool:
        if a.shape != (P,):
            raise CalibrationInputError(f"stepwisefit: {what} mask has shape {a.shape}; "
                                        f"expected ({P},) for {P} columns")
        return a.copy()
    a = a.ravel()
    if a.size and not np.issubdtype(a.dtype, np.integer):
        raise CalibrationInputError(f"stepwisefit: {what} must be a boolean mask or integer "
                                    f"column indices, got dtype {a.dtype}")
    bad = a[(a < 0) | (a >= P)]
    if bad.size:
        raise CalibrationInputError(f"stepwisefit: {what} holds column index(es) "
                                    f"{bad.tolist()} outside 0..{P - 1}")
    m = np.zeros(P, bool)
    m[a.astype(int)] = True
    return m


def _prepare(X, y, names, what="stepwisefit"):
    """Validate inputs, drop NaN rows (named warning). Returns X, y, names, n_dropped."""
    if names is None and hasattr(X, "columns"):
        names = [str(c) for c in X.columns]
    X = np.array(X, dtype=float, copy=True)
    y = np.array(y, dtype=float, copy=True).ravel()
    if X.ndim == 1:
        X = X[:, None]
    if X.ndim != 2:
        raise CalibrationInputError(f"{what}: X must be 2-D (rows x columns), got shape {X.shape}")
    N, P = X.shape
    if y.shape[0] != N:
        raise CalibrationInputError(f"{what}: X has {N} rows but y has {y.shape[0]}")
    if P == 0:
        raise CalibrationInputError(f"{what}: X has no columns")
    if names is None:
        names = [f"x{j + 1}" for j in range(P)]
    names = [str(n) for n in names]
    if len(names) != P:
        raise CalibrationInputError(f"{what}: {len(names)} names for {P} columns")
    if np.isinf(X).any() or np.isinf(y).any():
        rows = np.flatnonzero(np.isinf(X).any(axis=1) | np.isinf(y))
        raise CalibrationInputError(f"{what}: infinite value(s) in row(s) {rows[:10].tolist()}")
    bad = np.isnan(X).any(axis=1) | np.isnan(y)
    n_dropped = int(bad.sum())
    if n_dropped:
        cols = [names[j] for j in np.flatnonzero(np.isnan(X[bad]).any(axis=0))]
        warnings.warn(f"{what}: {n_dropped} row(s) with NaN dropped (NaN in "
                      f"{cols[:10] + (['y'] if np.isnan(y).any() else [])})",
                      DroppedRowsWarning, stacklevel=3)
        X, y = X[~bad], y[~bad]
    if X.shape[0] < 2:
        raise CalibrationInputError(f"{what}: {X.shape[0]} usable row(s); at least 2 needed")
    return X, y, names, n_dropped


def _constant_columns(X: np.ndarray, tol: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Column means, centred norms, and the mask of columns the intercept fits exactly.

    MATLAB's "perfectly fitted" test on the intercept-only model: sum(resid**2) <= tol * sum(x**2).
    """
    mean = X.mean(axis=0)
    cnorm2 = np.einsum("ij,ij->j", X - mean, X - mean)
    rnorm2 = np.einsum("ij,ij->j", X, X)
    const = (cnorm2 <= tol * rnorm2) | (rnorm2 == 0.0)
    return mean, cnorm2, const


def _duplicates(Z: np.ndarray, const: np.ndarray) -> np.ndarray:
    """For each column, the index of the first earlier column identical to it, else -1."""
    P = Z.shape[1]
    dup = np.full(P, -1)
    Zt = np.ascontiguousarray(Z.T)
    first: dict[int, list[int]] = {}
    for j in range(P):
        if const[j]:
            continue
        h = hash(Zt[j].tobytes())
        for i in first.get(h, ()):
            if np.array_equal(Zt[i], Zt[j]):
                dup[j] = i
                break
        else:
            first.setdefault(h, []).append(j)
    return dup


def _tpval(t: np.ndarray, df: int) -> np.ndarray:
    """Two-sided p-value of a t statistic (NaN for NaN t or df <= 0)."""
    if df <= 0:
        return np.full(t.shape, np.nan)
    with np.errstate(invalid="ignore"):
        # Student's t survival function (what scipy.stats.t.sf computes, without importing
        # scipy.stats)
        return 2.0 * scipy.special.stdtr(df, -np.abs(t))


def _safediv(num, den):
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.true_divide(num, den)


def _stepcalc(Rc, ry, inm, N, tol, xsq, sstotal):
    """MATLAB's ``stepcalc`` on the reduced problem (rows of R instead of data rows).

    Rc: (m, P) reduced standardised columns; ry: (m,) reduced standardised response.
    Returns b, se, t, p (all (P,), standardised units), rmse, dfe, df0, aliased mask,
    SSresid, and the mask of out-of-model columns perfectly fitted by the model.
    """
    P = Rc.shape[1]
    idx_in = np.flatnonzero(inm)
    idx_out = np.flatnonzero(~inm)
    b = np.zeros(P)
    se = np.zeros(P)
    aliased = np.zeros(P, bool)
    perfect = np.zeros(P, bool)
    if idx_in.size:
        A = Rc[:, idx_in]
        Q, R, perm = scipy.linalg.qr(A, mode="economic", pivoting=True, check_finite=False)
        rd = np.abs(np.diag(R))
        rank = int(np.sum(rd > tol * rd[0])) if rd.size and rd[0] > 0 else 0
        Q, R, perm = Q[:, :rank], R[:rank, :rank], perm[:rank]
        aliased[idx_in] = True
        aliased[idx_in[perm]] = False
        qty = Q.T @ ry
        bin_ = np.zeros(idx_in.size)
        if rank:
            bin_[perm] = scipy.linalg.solve_triangular(R, qty, check_finite=False)
        r = ry - Q @ qty
    else:
        rank = 0
        Q = np.zeros((Rc.shape[0], 0))
        R = np.zeros((0, 0))
        perm = np.zeros(0, int)
        bin_ = np.zeros(0)
        r = ry.copy()
    dfe = N - 1 - rank
    df0 = rank
    ssresid = float(r @ r)
    if dfe == 0 or ssresid < tol * sstotal:
        ssresid = 0.0
        r = np.zeros_like(r)
    rmse = math.sqrt(ssresid / dfe) if dfe > 0 else math.nan
    if idx_in.size:
        b[idx_in] = bin_
        if rank:
            Rinv, info = scipy.linalg.lapack.dtrtri(R, lower=0)
            if info != 0:                       # cannot happen after the rank test
                Rinv = np.linalg.pinv(R)
            sein = np.zeros(idx_in.size)
            sein[perm] = rmse * np.sqrt(np.einsum("ij,ij->i", Rinv, Rinv))
            se[idx_in] = sein
    t = np.full(P, np.nan)
    p = np.full(P, np.nan)
    if idx_in.size:
        t[idx_in] = _safediv(b[idx_in], se[idx_in])
        p[idx_in] = _tpval(t[idx_in], dfe)
    if idx_out.size:
        Xo = Rc[:, idx_out]
        xr = Xo - Q @ (Q.T @ Xo) if rank else Xo.copy()
        xx = np.einsum("ij,ij->j", xr, xr)
        pf = xx <= tol * xsq[idx_out]
        perfect[idx_out] = pf
        if pf.any():
            xr[:, pf] = 0.0
            xx[pf] = 1.0
        b2 = (r @ xr) / xx
        r2 = r[:, None] - xr * b2
        df2 = max(0, dfe - 1)
        s2 = _safediv(np.sqrt(_safediv(np.einsum("ij,ij->j", r2, r2), df2)), np.sqrt(xx))
        b[idx_out] = b2
        se[idx_out] = s2
        t[idx_out] = _safediv(b2, s2)
        p[idx_out] = _tpval(t[idx_out], df2)
    return b, se, t, p, rmse, dfe, df0, aliased, ssresid, perfect


# p-values this close (relative) are one tie: columns whose partial F tests are equal in exact
# arithmetic (x6 = x2 + 2 x3 with x2 in the model) differ by rounding only, and which rounding
# wins changes with the BLAS and numpy builds; MATLAB gives exact ties to the lowest index
TIE_REL = 1e-9


def _next_step(inm, keep, eligible, p, penter, premove):
    """MATLAB's ``stepnext``: (column, action) or (-1, '')."""
    out = np.flatnonzero(~inm & ~keep & eligible)
    if out.size:
        po = p[out]
        po = np.where(np.isnan(po), np.inf, po)
        k = int(np.argmax(po <= po.min() * (1 + TIE_REL)))   # lowest index among the tied
        if po[k] < penter:
            return int(out[k]), "add"
    tin = np.flatnonzero(inm & ~keep)
    if tin.size:
        pin = p[tin]
        nan = np.flatnonzero(np.isnan(pin))
        if nan.size:
            return int(tin[nan[0]]), "remove"
        k = int(np.argmax(pin >= pin.max() * (1 - TIE_REL)))  # lowest index among the tied
        if pin[k] > premove:
            return int(tin[k]), "remove"
    return -1, ""


def stepwisefit(X, y, penter=PENTER_DEFAULT, premove=None, keep=None, inmodel=None,
                maxiter=None, names=None) -> StepwiseResult:
    """Stepwise linear regression with MATLAB ``stepwisefit`` semantics.

    Parameters
    ----------
    X : (N, P) array or DataFrame of candidate columns (an intercept is always included;
        do not add a column of ones).
    y : (N,) response.
    penter, premove : entry / removal p-value thresholds (defaults 0.05 and max(penter, 0.10);
        given only premove, penter = min(premove, 0.05)).
    keep : columns forced into the model and never removed (bool mask or indices).
    inmodel : columns in the initial model (bool mask or indices).
    maxiter : maximum number of steps (None: no limit).
    names : column names for the history (default: DataFrame columns or x1..xP).

    Rows with NaN in X or y are dropped (``DroppedRowsWarning``), as MATLAB does.
    Constant columns and exact duplicates of an earlier column (after standardisation) are
    reported in ``constant`` / ``duplicate`` (``DegenerateColumnWarning``) and never enter
    (with compressed data an exact tie could otherwise be broken by rounding); columns in
    the span of the final model are reported in ``collinear``.
    """
    penter, premove = resolve_thresholds(penter, premove)
    X, y, names, n_dropped = _prepare(X, y, names)
    N, P = X.shape
    if maxiter is None:
        maxiter = math.inf
    elif not (maxiter >= 0):
        raise CalibrationInputError(f"stepwisefit: maxiter = {maxiter} must be >= 0")
    keep_m = _mask(keep, P, "keep")
    in_m = _mask(inmodel, P, "inmodel") | keep_m
    eps = np.finfo(float).eps
    tol = max(N, P + 1) * eps

    mean, cnorm2, const = _constant_columns(X, tol)
    bad = np.flatnonzero(const & in_m)
    if bad.size:
        raise CalibrationInputError(
            f"stepwisefit: column(s) {[names[j] for j in bad]} are constant and cannot be "
            "kept or put in the initial model (the intercept already represents them)")
    if const.any():
        warnings.warn(f"stepwisefit: {int(const.sum())} constant column(s) never eligible: "
                      f"{[names[j] for j in np.flatnonzero(const)][:10]}",
                      DegenerateColumnWarning, stacklevel=2)
    std = np.where(const, 1.0, np.sqrt(cnorm2 / max(N - 1, 1)))
    Z = (X - mean) / std
    Z[:, const] = 0.0
    dup = _duplicates(Z, const)
    if (dup >= 0).any():
        pairs = [f"{names[j]} = {names[dup[j]]}" for j in np.flatnonzero(dup >= 0)]
        warnings.warn(f"stepwisefit: {len(pairs)} column(s) duplicate an earlier column and "
                      f"are never eligible: {pairs[:10]}", DegenerateColumnWarning,
                      stacklevel=2)
    xsq = np.einsum("ij,ij->j", X, X) / std**2       # MATLAB's sum(x.^2) in standardised units
    y_mean = float(y.mean())
    yc = y - y_mean
    y_std = float(np.sqrt(yc @ yc / max(N - 1, 1)))
    if y_std == 0.0:
        y_std = 1.0
    ys = yc / y_std
    sstotal = float(ys @ ys)

    # One Householder QR of [Z y]: the reduced problem has P+1 rows whatever N is.
    Rfull = np.linalg.qr(np.column_stack([Z, ys]), mode="r")
    Rc, ry = np.ascontiguousarray(Rfull[:, :P]), np.ascontiguousarray(Rfull[:, P])
    eligible = ~const & ((dup < 0) | in_m)

    stats = _stepcalc(Rc, ry, in_m, N, tol, xsq, sstotal)
    history: list[StepRecord] = []
    hist_in: list[np.ndarray] = []
    stop = "no step qualifies"
    while True:
        if len(history) >= maxiter:
            stop = "maxiter"
            break
        j, action = _next_step(in_m, keep_m, eligible, stats[3], penter, premove)
        if j < 0:
            break
        F = float(stats[2][j] ** 2)
        pj = float(stats[3][j])
        in_m[j] = not in_m[j]
        stats = _stepcalc(Rc, ry, in_m, N, tol, xsq, sstotal)
        history.append(StepRecord(len(history) + 1, action, j, names[j], F, pj,
                                  float(stats[4] * y_std), int(stats[6]), int(in_m.sum())))
        hist_in.append(in_m.copy())

    b, se, t, p, rmse, dfe, df0, aliased, ssresid, perfect = stats
    # Final refit of the selected model on the full standardised data, stable least squares.
    sel = np.flatnonzero(in_m & ~aliased)
    beta = b.copy()
    refit_rel_diff = 0.0
    if sel.size:
        sol, _, _, _ = scipy.linalg.lstsq(Z[:, sel], ys, check_finite=False)
        res = ys - Z[:, sel] @ sol
        rss = float(res @ res)
        beta[sel] = sol
        refit_rel_diff = abs(rss - ssresid) / ssresid if ssresid > 0 else abs(rss)
    beta[in_m & aliased] = 0.0
    coef = beta * y_std / std
    coef[const] = 0.0
    se_raw = se * y_std / std
    intercept = float(y_mean - coef[in_m] @ mean[in_m])
    return StepwiseResult(
        inmodel=in_m, coef=coef, intercept=intercept, se=se_raw, tstat=t, pval=p,
        rmse=float(rmse * y_std), dfe=int(dfe), df0=int(df0), n_obs=N, history=history,
        history_in=np.array(hist_in, dtype=bool).reshape(len(hist_in), P), names=names,
        constant=const, duplicate=dup, aliased=in_m & aliased, collinear=perfect & ~const,
        penter=penter, premove=premove,
        stop_reason=stop, n_dropped=n_dropped, refit_rel_diff=float(refit_rel_diff),
        x_mean=mean, x_std=std, y_mean=y_mean, y_std=y_std)


def stepwise_refit_loop(X, y, penter=PENTER_DEFAULT, premove=None, keep=None, inmodel=None,
                        maxiter=None, names=None):
    """The plain reference: the same rules, every p-value from a fresh statsmodels OLS fit.

    For each step it fits the current model once (p-values of the terms in) and the current
    model plus each candidate (the candidate's p-value).  Slow by design; used to check
    :func:`stepwisefit` and as the benchmark baseline.  Returns ``(inmodel, steps)`` with
    ``steps = [(action, column), ...]``.  Constant and duplicate columns are skipped, as in
    stepwisefit.
    """
    import statsmodels.api as sm

    penter, premove = resolve_thresholds(penter, premove)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DroppedRowsWarning)
        X, y, names, _ = _prepare(X, y, names, what="stepwise_refit_loop")
    N, P = X.shape
    maxiter = math.inf if maxiter is None else maxiter
    keep_m = _mask(keep, P, "keep")
    in_m = _mask(inmodel, P, "inmodel") | keep_m
    _, cnorm2, const = _constant_columns(X, max(N, P + 1) * np.finfo(float).eps)
    Xm = X - X.mean(axis=0)
    std = np.where(const, 1.0, np.sqrt(cnorm2 / max(N - 1, 1)))
    Zs = Xm / std
    Zs[:, const] = 0.0
    skip = const | (_duplicates(Zs, const) >= 0)
    ones = np.ones((N, 1))

    def fit(cols):
        return sm.OLS(y, np.hstack([ones, X[:, cols]])).fit()

    steps = []
    while len(steps) < maxiter:
        cols_in = list(np.flatnonzero(in_m))
        best_p, best_j = math.inf, -1
        for j in np.flatnonzero(~in_m & ~keep_m & ~skip):
            pj = float(fit(cols_in + [int(j)]).pvalues[-1])
            if pj < best_p:             # strict: the lowest index wins ties
                best_p, best_j = pj, int(j)
        if best_j >= 0 and best_p < penter:
            in_m[best_j] = True
            steps.append(("add", best_j))
            continue
        cur_p = np.asarray(fit(cols_in).pvalues[1:], dtype=float) if cols_in else np.zeros(0)
        cand = [(c, pv) for c, pv in zip(cols_in, cur_p) if not keep_m[c]]
        nan = [c for c, pv in cand if math.isnan(pv)]
        if nan:
            j = nan[0]
        else:
            j, worst = -1, -math.inf
            for c, pv in cand:
                if pv > worst:
                    j, worst = c, pv
            if not (j >= 0 and worst > premove):
                break
        in_m[j] = False
        steps.append(("remove", int(j)))
    return in_m, steps
