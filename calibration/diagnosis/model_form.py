"""The form of a missing term fitted jointly with a physics model: the candidate functions of
term_form.py plus the response to a load outside the library, selected on the residual the
model's own identified directions leave (so a term whose part the model's parameters absorb is
judged by what remains of it, and its coefficients are those of a joint fit).

A load's effect on the readings is not a function of the force alone: the same force deflects
the platform more where the structure is softer, and tilts it too, so no polynomial of the
force (or the force times the position) reproduces it. The load candidates are the model's own
response: the derivative of the readings with respect to a force f (N) along world x, y or z
applied as ``f * (I / 1 A)^k`` (I the coils' mean current, k = 1, 2, 3) at the fitted
parameters, through the model's statics (the path of a library effect's wrench). A researcher's
effect written from one is a ``wrench`` hook (deltatwin effect new --from).

``joint_form`` is term_form's forward selection on the stacked readings: each (candidate,
reading axis) pair is a column; the model's identified directions are always in the fit
(Frisch-Waugh: the columns and the residual are taken orthogonal to them); a pair joins while it
is significant on the calibration rows (partial F test, a scanned period or moment counted as
a parameter, Bonferroni over the pairs) and lowers the validation residual power (zeros
re-estimated on the calibration rows, the model's directions re-adjusted) by at least
``MIN_SHARE`` of it; at most ``MAX_TERMS`` per axis.
"""
from __future__ import annotations

import numpy as np
from scipy import special

from deltatwin.calibration.diagnosis.attribution import Residual, laboratory_variables
from deltatwin.calibration.diagnosis.term_form import (
    ALPHA,
    MAX_TERMS,
    MIN_SHARE,
    Candidate,
    candidate_library,
)
from deltatwin.calibration.physics.model import (
    PhysicsModel,
    _projected,
    group_offsets,
    residuals,
)
from deltatwin.twin.effects import Effect, Parameter
from deltatwin.twin.instruments.optics import AXES

POWERS = (1, 2, 3)


class CurrentLoad(Effect):
    """A force on the platform, world frame, per power of the coils' mean current (the
    diagnosis' probe for a load outside the library; never simulated)."""
    name = "diagnosis_current_load"
    summary = "force f[k] * (I / 1 A)^(k+1) on the platform, world x, y, z"
    parameters = (Parameter("force_N", "N", ((0.0,) * 3,) * len(POWERS),
                            "per power of the mean current 1, 2, 3: the force along x, y, z",
                            fit_scale=0.01),)

    def wrench(self, points):
        current = np.mean(points.currents_A, axis=1)
        w = np.zeros((current.shape[0], 6))
        for k, power in enumerate(POWERS):
            w[:, :3] += current[:, None] ** power * self.force_N[k]
        return w


def load_candidates(fit) -> list[Candidate]:
    """The load candidates of a fitted physics model (calibration.physics.fit.PhysicsFit): per
    power, force direction and reading axis, the reading's response (N,) m per N, tried on that
    axis only. None when the coil currents do not vary (no load to probe)."""
    meas = fit.measurements_
    if not np.ptp(np.mean(meas.points.currents_A[:meas.n], axis=1)) > 0:
        return []
    model = PhysicsModel(fit.effects + [CurrentLoad], fit.model_.params,
                         {**fit.model_.values(), CurrentLoad.name: {}})
    new = np.zeros(model.n_free, bool)
    for f in model.free:
        new[f.sl] = f.effect == CurrentLoad.name
    _, J = model.jacobian(meas, model.theta(), columns=new)
    response = J[:, :, new]                                   # (N,3,9) m per N
    return [Candidate("load", "F_N", response[:, k, 3 * i + j][:, None], power=power, axis=k,
                      extra={"direction": direction})
            for i, power in enumerate(POWERS) for j, direction in enumerate(AXES)
            for k in range(3) if np.any(response[:, k, 3 * i + j])]


def _orthonormal(X: np.ndarray) -> np.ndarray:
    """An orthonormal basis of the columns of X (rank by singular values, relative 1e-10)."""
    if not X.shape[1]:
        return X
    u, s, _ = np.linalg.svd(X, full_matrices=False)
    return u[:, s > max(s.max(initial=0.0), 1e-300) * 1e-10]


def joint_form(fit, Jm: np.ndarray, JS: np.ndarray, r0: np.ndarray, alpha: float = ALPHA,
               min_share: float = MIN_SHARE, max_terms: int = MAX_TERMS):
    """The missing term's form on a fitted physics model (module docstring). ``Jm`` (n, k_m):
    the model's identified directions on the calibration readings (session means out), ``JS``
    (N,3,k_m) the same directions on every row, ``r0`` (n,) the model's calibration residual
    (session means out).

    Returns (form, G, explained): the form as term_form.sparse_form's ([{axis, terms,
    explained_fraction, val_rms_nm, val_rms_after_nm}], relative to the residual the model's
    directions leave), the selected columns G (N,3,p) and the fraction of the validation
    residual power they explain together."""
    meas = fit.measurements_
    cal, val = meas.cal, meas.val
    Qm = _orthonormal(Jm)

    def after(columns: list, coefs: np.ndarray) -> np.ndarray:
        """Residual (N,3) with the columns at coefficients ``coefs`` and the model's
        directions re-adjusted to what they leave."""
        change = np.zeros(meas.y.shape)
        for C, c in zip(columns, np.split(coefs, np.cumsum([C.shape[2] for C in columns])[:-1])
                        if columns else []):
            change += C @ c
        if Jm.shape[1]:
            rest = r0 - _projected(meas, cal, change)
            change = change + JS @ np.linalg.lstsq(Jm, rest, rcond=None)[0]
        pred = fit.prediction_ + change
        return residuals(meas, pred, group_offsets(meas, pred, cal))

    before = after([], np.zeros(0))
    rows = val[:, None] & np.isfinite(before)
    power = lambda res: np.array([float(np.sum(res[rows[:, k], k] ** 2)) for k in range(3)])
    p0_axes = power(before)
    p0 = float(p0_axes.sum())
    target = Residual.of(meas.df, before, cal, val)
    n_groups = len(meas.groups)
    if p0 <= 0 or not target.axes:
        return [], np.zeros(meas.y.shape + (0,)), 0.0
    candidates = candidate_library(laboratory_variables(meas.df), target) + load_candidates(fit)
    axes = [k for k, _, _ in target.axes]
    pairs = []                        # (candidate, axis, C (N,3,c), P (n,c) orthogonal to Qm)
    for cand in candidates:
        for k in ([cand.axis] if cand.axis is not None else axes):
            if k not in axes:
                continue
            C = np.zeros(meas.y.shape + (cand.columns.shape[1],))
            C[:, k] = np.nan_to_num(cand.columns)
            P = _projected(meas, cal, C)
            if Qm.shape[1]:
                P = P - Qm @ (Qm.T @ P)
            if np.linalg.norm(P) > 0:
                pairs.append((cand, k, C, P))
    r = r0 - Qm @ (Qm.T @ r0) if Qm.shape[1] else r0.copy()
    n = r.size
    limit = alpha / max(len(pairs), 1)
    chosen: list[int] = []
    basis = np.zeros((n, 0))
    rss = float(r @ r)
    current = before
    val_power = p0
    while True:
        counts = np.bincount([pairs[i][1] for i in chosen], minlength=3)
        best = None
        for i, (_, k, _, P) in enumerate(pairs):
            if i in chosen or counts[k] >= max_terms:
                continue
            Pn = _orthonormal(P - basis @ (basis.T @ P))
            gain = float(np.sum((Pn.T @ r) ** 2))
            if best is None or gain > best[1]:
                best = (i, gain, Pn)
        if best is None:
            break
        i, gain, Pn = best
        kk = Pn.shape[1] + pairs[i][0].scanned
        rss1 = rss - gain
        df2 = n - Qm.shape[1] - basis.shape[1] - Pn.shape[1] - n_groups
        if not Pn.shape[1] or df2 <= 0 or rss1 <= 0:
            break
        F = (gain / kk) / (rss1 / df2)
        trial = chosen + [i]
        coefs = _coefficients(pairs, trial, r)
        res = after([pairs[j][2] for j in trial], coefs)
        vp = float(power(res).sum())
        if special.fdtrc(kk, df2, F) >= limit or val_power - vp < min_share * p0:
            break
        chosen, basis, rss, current, val_power = (
            trial, np.hstack([basis, Pn]), rss1, res, vp)
    if not chosen:
        return [], np.zeros(meas.y.shape + (0,)), 0.0
    coefs = _coefficients(pairs, chosen, r)
    per_term = np.split(coefs, np.cumsum([pairs[j][2].shape[2] for j in chosen])[:-1])
    p_full = power(current)
    form = []
    for k in sorted({pairs[j][1] for j in chosen}):
        terms = []
        for j, c in zip(chosen, per_term):
            if pairs[j][1] != k:
                continue
            others = [m for m in chosen if m != j]
            without = after([pairs[m][2] for m in others], _coefficients(pairs, others, r))
            term = pairs[j][0].describe(c)
            term["explained_fraction"] = max(power(without)[k] - p_full[k], 0.0) / p0_axes[k]
            terms.append(term)
        terms.sort(key=lambda t: -t["explained_fraction"])
        n_val = max(int(rows[:, k].sum()), 1)
        form.append({"axis": AXES[k], "terms": terms,
                     "explained_fraction": 1.0 - p_full[k] / p0_axes[k],
                     "val_rms_nm": float(np.sqrt(p0_axes[k] / n_val) * 1e9),
                     "val_rms_after_nm": float(np.sqrt(p_full[k] / n_val) * 1e9)})
    G = np.concatenate([pairs[j][2] for j in chosen], axis=2)
    return form, G, 1.0 - float(p_full.sum()) / p0


def _coefficients(pairs: list, idx: list[int], r: np.ndarray) -> np.ndarray:
    """Least-squares coefficients of the pairs ``idx`` (their columns orthogonal to the model's
    directions) on the residual ``r`` the model leaves: by Frisch-Waugh those of the joint fit
    with the model's directions. Columns scaled to unit norm for the solve."""
    if not idx:
        return np.zeros(0)
    X = np.hstack([pairs[j][3] for j in idx])
    norm = np.linalg.norm(X, axis=0)
    norm[norm == 0] = 1.0
    return np.linalg.lstsq(X / norm, r, rcond=None)[0] / norm
