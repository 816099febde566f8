"""The form of a missing term fitted jointly with a physics model: the candidate functions of
term_form.py plus the response to a load outside the library, selected on the residual the
model's own identified directions leave (so a term whose part the model's parameters absorb is
judged by what remains of it, and its coefficients are those of a joint fit).

A load's effect on the readings is not a function of the force alone: the same force deflects
the platform more where the structure is softer, and tilts it too, so no polynomial of the
force (or the force times the position) reproduces it. The load candidates are the model's own
response: the derivative of the readings with respect to a force f (N) along world x, y or z
applied as ``f * (I / 1 A)^k`` (I the coils' mean current, k = 1, 2, 3) at the fitted
parameters, through the model's statics (the path of a library effect's wrench): one term per
power and direction, its response on all three reading axes with one coefficient, the force
(the compliance divides it between the axes). A researcher's effect written from one is a
``wrench`` hook (deltatwin effect new --from).

``joint_form`` is term_form's forward selection on the stacked readings. Each block it tries is
a candidate on one reading axis; or on every axis at once with coefficients of its own per axis,
for an error in where a motor sits (the direction of its last move, a sine of its angle: the
kinematics show it on every axis); or a load's response with its shared coefficient. The
model's identified directions are always in the fit (Frisch-Waugh: the columns and the
residual are taken orthogonal to them); a block joins while it is significant on the
calibration rows (partial F test, a scanned period or moment counted as a parameter,
Bonferroni over the blocks) and lowers the validation residual power (zeros re-estimated on the
calibration rows, the model's directions re-adjusted) by at least ``MIN_SHARE`` of it; at most
``MAX_TERMS`` per axis. Then a backward pass: a block that no longer passes that test given the
blocks that joined after it leaves (a step in time that followed a backlash's pattern of moves
until the direction's offset joined). A polynomial of the force on one reading axis gives its
place to the load of the same power of the current, and a motor's sign or periodic term fitted
axis by axis to where that motor sits (``MotorError``: its offset along its last move, its
periodic error, rad), unless it fits significantly better: the physical forms, through the
compliance or the kinematics, on every axis with one coefficient. The rotations' candidates
are tried only once no other qualifies (readings of the platform's response, attribution.py:
an effect written from a rotation reading removes nothing of the load or backlash that tilts
it).
"""
from __future__ import annotations

import functools
import math
import weakref
from typing import NamedTuple

import numpy as np

from deltatwin.calibration.diagnosis.attribution import (
    MIN_SHARE,
    Residual,
    Term,
    best_step,
    laboratory_variables,
    scan_together,
    scans,
    tail_sums,
)
from deltatwin.calibration.diagnosis.term_form import MAX_TERMS, Candidate, candidate_library
from deltatwin.calibration.physics.model import (
    PhysicsModel,
    as_slice,
    group_offsets,
    residuals,
)
from deltatwin.calibration.stats import ALPHA, f_test_p
from deltatwin.twin.effects import Effect, Parameter
from deltatwin.twin.instruments.optics import AXES

POWERS = (1, 2, 3)
# columns projected in one pass of the model's directions (_Joint.columns): enough to
# amortise the pass, few enough to keep the arrays small (n readings x this)
COLUMNS_AT_ONCE = 64
# _Joint.estimates: a block's estimate is sure when the smallest eigenvalue of its Gram matrix
# (columns at unit norm, the lead's part out) is at least this (condition <= ~2,500: digits
# lost to the Gram matrix ~1e-16 / this), the lead's when its singular values span less than
# 1 / SURE_LEAD (its rank not in doubt)
SURE_EIGENVALUE = 1e-6
SURE_LEAD = 1e-3


class CurrentLoad(Effect):
    """A force on the platform, world frame, per power of the coils' mean current (the
    diagnosis' probe for a load outside the library; never simulated)."""
    name = "diagnosis_current_load"
    summary = "force f[k] * (I / 1 A)^(k+1) on the platform, world x, y, z"
    parameters = (Parameter("force_N", "N", ((0.0,) * 3,) * len(POWERS),
                            "per power of the mean current 1, 2, 3: the force along x, y, z",
                            fit_scale=0.01),)

    # (the coils' currents, the powers of their mean) last computed: the probe's Jacobian asks
    # for the wrench ~50 times on the same rows (its columns' stencils, the pose's)
    _powers = (None, None)

    def wrench(self, points):
        currents, powers = self._powers
        if currents is not points.currents_A:
            current = np.mean(points.currents_A, axis=1)
            currents, powers = points.currents_A, [current[:, None] ** p for p in POWERS]
            self._powers = (currents, powers)
        w = np.zeros((powers[0].shape[0], 6))
        for k, power in enumerate(powers):
            w[:, :3] += power * self.force_N[k]
        return w


def load_candidates(fit) -> list[Candidate]:
    """The load candidates of a fitted physics model (calibration.physics.fit.PhysicsFit): per
    power and force direction, the readings' response on all three axes (N,3,1) m per N, one
    term with one coefficient (the force): the compliance sets how it divides between the
    axes, so none is fitted on one axis alone. None when the coil currents do not vary (no load
    to probe)."""
    meas = fit.measurements_
    if not np.ptp(np.mean(meas.points.currents_A[:meas.n], axis=1)) > 0:
        return []
    model = PhysicsModel(fit.effects + [CurrentLoad], fit.model_.params,
                         {**fit.model_.values(), CurrentLoad.name: {}})
    new = np.zeros(model.n_free, bool)
    for f in model.free:
        new[f.sl] = f.effect == CurrentLoad.name
    # at zero force the probe changes nothing: the fitted model's stage is re-used
    _, J = model.jacobian(meas, model.theta(), columns=new, extends=fit.model_)
    response = J[:, :, new]                                   # (N,3,9) m per N
    return [Candidate("load", "F_N", response[:, :, 3 * i + j, None], power=power,
                      extra={"direction": direction})
            for i, power in enumerate(POWERS) for j, direction in enumerate(AXES)
            if np.any(response[:, :, 3 * i + j])]


class MotorError(Effect):
    """Where each motor sits, off its encoder's reading, rad (the diagnosis' probe for a
    backlash or an encoder's periodic error outside the library; never simulated): motor m
    sits ``backlash_rad[m]`` further along its last move and ``sin_rad[m] sin(2 pi qm /
    period_rad[m]) + cos_rad[m] cos(...)`` off."""
    name = "diagnosis_motor_error"
    summary = "motor m sits off its encoder's reading: along its last move, periodic in qm"
    parameters = (Parameter("backlash_rad", "rad", (0.0,) * 3, "per motor: offset along the "
                            "last move's direction", fit_scale=1e-6),
                  Parameter("sin_rad", "rad", (0.0,) * 3, "per motor: sine amplitude",
                            fit_scale=1e-6),
                  Parameter("cos_rad", "rad", (0.0,) * 3, "per motor: cosine amplitude",
                            fit_scale=1e-6),
                  Parameter("period_rad", "rad", (1.0,) * 3, "per motor: period in qm"))

    # (the encoders' readings, the periods, sin and cos of the phase) last computed: the
    # probe's Jacobian asks for the angles ~30 times at one period (its columns' stencils)
    _phase = (None, None, None, None)

    def motor_angles(self, points):
        q, period, sin, cos = self._phase
        if q is not points.q or not np.array_equal(period, self.period_rad):
            phase = 2 * np.pi * points.q / self.period_rad
            q, period, sin, cos = points.q, np.array(self.period_rad), np.sin(phase), np.cos(phase)
            self._phase = (q, period, sin, cos)
        return self.backlash_rad * points.move_direction + self.sin_rad * sin + self.cos_rad * cos


def motor_candidates(fit, variables: list, target) -> list[Candidate]:
    """The motor candidates of a fitted physics model: per motor, the readings' response on all
    three axes (N,3,c) m per rad to it sitting off its encoder's reading along its last move
    (c = 1: a backlash) and periodically in its angle at the period the residual's
    periodogram peaks at (c = 2, sine and cosine: an encoder's periodic error): one term whose
    coefficients (rad) the kinematics divide between the axes, as a load's force the
    compliance. Only for the motors whose last-move sign or periodic scan the rows have."""
    meas = fit.measurements_
    by_name = {v.name: v for v in variables}
    periods = [scans(by_name[f"q{m + 1}_rad"], target).get("period")
               if f"q{m + 1}_rad" in by_name else None for m in range(3)]
    signs = [f"dir_q{m + 1}" in by_name for m in range(3)]
    if not any(signs) and all(p is None for p in periods):
        return []
    model = PhysicsModel(fit.effects + [MotorError], fit.model_.params,
                         {**fit.model_.values(), MotorError.name: {
                             "period_rad": tuple(p or 1.0 for p in periods)}})
    new = np.zeros(model.n_free, bool)
    for f in model.free:
        new[f.sl] = f.effect == MotorError.name
    # the motors where their encoders say: the fitted model's stage is re-used
    _, J = model.jacobian(meas, model.theta(), columns=new, extends=fit.model_)
    response = J[:, :, new]                   # (N,3,9) m per rad: backlash, sin, cos x motor
    out = []
    for m in range(3):
        if signs[m] and np.any(response[:, :, m]):
            out.append(Candidate("motor_sign", f"dir_q{m + 1}", response[:, :, [m]],
                                 extra={"motor": m + 1}))
        if periods[m] is not None and np.any(response[:, :, [3 + m, 6 + m]]):
            out.append(Candidate("motor_sine", f"q{m + 1}_rad", response[:, :, [3 + m, 6 + m]],
                                 scanned=1, period=periods[m], extra={"motor": m + 1}))
    return out


def _orthonormal(X: np.ndarray) -> np.ndarray:
    """An orthonormal basis of the columns of X (rank by singular values, relative 1e-10)."""
    if not X.shape[1]:
        return X
    if X.shape[1] == 1:
        # one column (most of the forward selection's blocks): itself at unit norm, the SVD's
        # vector up to its sign, at a tenth of its cost; a zero (or underflowing) one the SVD's
        norm = float(np.sqrt(X[:, 0] @ X[:, 0]))
        if norm > 0 and np.isfinite(norm):
            return X / norm
    return ModelSpan(X).orthonormal()


class ModelSpan:
    """The model's identified directions on the calibration readings, Jm (n, k), factorised once
    per diagnosis (one SVD, U s Vt): its orthonormal bases, least squares and pseudo-inverse,
    each with the rank rule of the numpy routine it stands for (before, a QR, two SVDs and a
    least squares of the same Jm)."""

    def __init__(self, Jm: np.ndarray):
        self.n = Jm.shape[0]
        self.U, self.s, self.Vt = np.linalg.svd(Jm, full_matrices=False)
        self.top = self.s.max(initial=0.0)

    def orthonormal(self) -> np.ndarray:
        """As ``_orthonormal(Jm)``: the singular vectors above 1e-10 of the largest."""
        return self.U[:, self.s > max(self.top, 1e-300) * 1e-10]

    def lstsq(self, r: np.ndarray) -> np.ndarray:
        """As ``np.linalg.lstsq(Jm, r, rcond=None)[0]``: singular values above eps max(n, k)
        of the largest count."""
        keep = self.s > np.finfo(float).eps * max(self.n, self.s.size) * self.top
        return self.Vt[keep].T @ ((self.U[:, keep].T @ r) / self.s[keep])

    def pinv(self) -> np.ndarray:
        """As ``np.linalg.pinv(Jm)`` (k, n): singular values above 1e-15 of the largest."""
        keep = self.s > 1e-15 * self.top
        return (self.Vt[keep].T / self.s[keep]) @ self.U[:, keep].T


class Placed(NamedTuple):
    """Columns of one term or candidate on the reading axes, without the zeros an (N,3,width)
    array of them would hold: ``blocks`` [(reading axis, its first column, X (N,w))], at most
    one per axis. ``_Joint.columns`` takes it as it takes such an array."""
    width: int
    blocks: tuple

    def dense(self, shape: tuple) -> np.ndarray:
        """The (N,3,width) array (``shape``: (N,3)), zeros off the blocks."""
        C = np.zeros(shape + (self.width,))
        for k, start, X in self.blocks:
            C[:, k, start:start + X.shape[1]] = X
        return C


def _width(C) -> int:
    return C.width if isinstance(C, Placed) else C.shape[2]


class _Joint:
    """Least squares on the residual a fitted physics model leaves, with the model's identified
    directions always re-adjusted (Frisch-Waugh: columns and residual taken orthogonal to them
    on the calibration readings, session means out), and the validation residual that results
    (zeros re-estimated on the calibration rows), both linear in the added columns."""

    # least_squares' kept factorisation of the leading blocks: (those blocks, Q, R, Q^T r,
    # r - Q Q^T r, their column norms); none yet
    _lead: tuple = (None,)

    def __init__(self, fit, Jm: np.ndarray, JS: np.ndarray, r0: np.ndarray,
                 span: ModelSpan | None = None):
        meas = self.meas = fit.measurements_
        span = ModelSpan(Jm) if span is None else span
        self.Qm = span.orthonormal()
        self.r = r0 - self.Qm @ (self.Qm.T @ r0)
        self.pinv = span.pinv() if Jm.shape[1] else np.zeros((0, r0.size))
        # the model one linear step further: the reference every column is judged against
        change = JS @ (self.pinv @ r0) if Jm.shape[1] else 0.0
        pred = fit.prediction_ + change
        self.before = residuals(meas, pred, group_offsets(meas, pred, meas.cal))
        # each group's readings (one reading axis), found once for the hundreds of columns
        # projected here: (axis, its calibration rows, their place among the calibration
        # readings (projected's order), its validation rows, their place among those)
        self.groups, n_cal, n_val = [], 0, 0
        for g in range(len(meas.groups)):
            in_group = meas.group == g
            k = int(np.flatnonzero(in_group.any(axis=0))[0]) if in_group.any() else 0
            cal_g = np.flatnonzero(in_group[:, k] & meas.cal)
            val_g = np.flatnonzero(in_group[:, k] & meas.val & np.isfinite(self.before[:, k]))
            self.groups.append((k, cal_g, slice(n_cal, n_cal + cal_g.size), val_g,
                                slice(n_val, n_val + val_g.size)))
            n_cal, n_val = n_cal + cal_g.size, n_val + val_g.size
        self.n_cal, self.n_val = n_cal, n_val
        self.axis_of = np.concatenate([np.full(val_g.size, k, np.intp)
                                       for k, _, _, val_g, _ in self.groups])
        self.b = self._val(self.before)
        # the model's directions on the validation readings, and the parts of their pseudo-
        # inverse and orthonormal basis on each axis' calibration readings: a column on one
        # axis is projected with those alone
        self.JS_val = self._val(JS)
        on_axis = {k: np.concatenate([np.arange(n_cal)[sl] for a, _, sl, _, _ in self.groups
                                      if a == k] or [np.zeros(0, np.intp)]) for k in range(3)}
        self.pinv_on_axis = {k: self.pinv[:, i] for k, i in on_axis.items()}
        self.Qm_on_axis = {k: self.Qm[i] for k, i in on_axis.items()}
        self.n_groups = len(meas.groups)

    def _val(self, X: np.ndarray) -> np.ndarray:
        """Values X (N,3,...) on the validation readings, each group's calibration mean out."""
        out = np.zeros((self.n_val,) + X.shape[2:])
        for k, cal_g, _, val_g, sl in self.groups:
            out[sl] = X[val_g, k] - (X[cal_g, k].mean(axis=0) if cal_g.size else 0.0)
        return out

    def axis_columns(self, X: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Columns X (N,c) on reading axis ``k`` alone (zero on the others): as ``columns``."""
        P = np.zeros((self.n_cal, X.shape[1]))
        D = np.zeros((self.n_val, X.shape[1]))
        for axis, cal_g, sl_cal, val_g, sl_val in self.groups:
            if axis != k:
                continue
            mean = X[cal_g].mean(axis=0) if cal_g.size else 0.0
            P[sl_cal] = X[cal_g] - mean
            D[sl_val] = X[val_g] - mean
        Pk = np.concatenate([P[sl] for a, _, sl, _, _ in self.groups if a == k]
                            or [np.zeros((0, X.shape[1]))])
        if self.pinv.shape[0]:
            D -= self.JS_val @ (self.pinv_on_axis[k] @ Pk)
        if self.Qm.shape[1]:
            P -= self.Qm @ (self.Qm_on_axis[k].T @ Pk)
        return P, D

    def columns(self, Cs: list) -> list[tuple[np.ndarray, np.ndarray]]:
        """Each array of columns C (N,3,c) of ``Cs`` (or its ``Placed`` blocks): (on the
        calibration readings orthogonal to the model's directions, the change of the
        validation residual per unit coefficient). Linear in C, so each reading axis' nonzero
        columns of all of them are projected together (``axis_columns``, in batches of
        COLUMNS_AT_ONCE: one pass of the model's directions over the readings per batch
        instead of one per array) and summed back."""
        out = [(np.zeros((self.n_cal, _width(C))), np.zeros((self.n_val, _width(C))))
               for C in Cs]
        for k in range(3):
            # (array, its columns: a slice where they are a range, how many, their values)
            parts = []
            for i, C in enumerate(Cs):
                if isinstance(C, Placed):
                    for axis, first, X in C.blocks:
                        cols = np.flatnonzero(np.any(X != 0, axis=0)) if axis == k else []
                        if len(cols):
                            parts.append((i, as_slice(cols + first), cols.size,
                                          X if cols.size == X.shape[1] else X[:, cols]))
                    continue
                cols = np.flatnonzero(np.any(C[:, k] != 0, axis=0))
                if cols.size:
                    sl = as_slice(cols)
                    parts.append((i, sl, cols.size, C[:, k, sl]))
            for start in range(0, len(parts), COLUMNS_AT_ONCE):
                batch = parts[start:start + COLUMNS_AT_ONCE]
                P, D = self.axis_columns(np.hstack([X for *_, X in batch]), k)
                at = 0
                for i, cols, width, _ in batch:   # a range's block added in place (a slice)
                    out[i][0][:, cols] += P[:, at:at + width]
                    out[i][1][:, cols] += D[:, at:at + width]
                    at += width
        return out

    def least_squares(self, Ps: list) -> tuple[np.ndarray, int]:
        """(coefficients, rank) of the residual's least squares on the blocks of columns
        ``Ps`` [(n,c)]: as np.linalg.lstsq on the columns scaled to unit norm (the minimum-norm
        solution; singular values below eps max(n, p) of the largest do not count), from an
        orthogonal factorisation. The forward selections refit the blocks chosen so far with
        each candidate block in turn: the factorisation of all blocks but the last is kept
        while they lead the calls, so a trial costs its own block's projection, not a
        factorisation of them all."""
        lead, last = Ps[:-1], Ps[-1]
        kept = self._lead[0]
        if (kept is None or len(lead) != len(kept)
                or any(a is not b for a, b in zip(lead, kept))):
            self._lead = (list(lead), *self._factorised(lead))
        _, Q, R, Qr, r_rest, norm_lead = self._lead
        norm = _column_norms(last)
        X = last / norm
        W = Q.T @ X
        Y = X - Q @ W
        again = Q.T @ Y                      # twice is enough (Gram-Schmidt's lost digits)
        Y -= Q @ again
        W += again
        # the last block's triangle, and the residual's coordinates on its orthonormal basis
        # (the residual less its part on the others' basis: the same to rounding), from one
        # triangular factorisation without forming that basis
        c = Y.shape[1]
        R_aug = np.linalg.qr(np.column_stack([Y, r_rest]), mode="r")
        R = np.block([[R, W], [np.zeros((c, R.shape[1])), R_aug[:c, :c]]])
        U, sv, Vt = np.linalg.svd(R)
        rank = int(np.sum(sv > np.finfo(float).eps * max(self.r.size, R.shape[1]) * sv[0]))
        t = np.concatenate([Qr, R_aug[:c, c]])
        coef = Vt[:rank].T @ ((U[:, :rank].T @ t) / sv[:rank])
        return coef / np.concatenate([norm_lead, norm]), rank

    def _factorised(self, Ps: list) -> tuple:
        """(Q, R, Q^T r, r - Q Q^T r, column norms) of the blocks ``Ps`` side by side, columns
        at unit norm (r: the residual)."""
        if not Ps:
            return (np.zeros((self.r.size, 0)), np.zeros((0, 0)), np.zeros(0), self.r,
                    np.zeros(0))
        X = np.hstack(Ps)
        norm = _column_norms(X)
        Q, R = np.linalg.qr(X / norm)
        Qr = Q.T @ self.r
        return Q, R, Qr, self.r - Q @ Qr, norm

    def fit(self, Ps: list, Ds: list) -> tuple[np.ndarray, np.ndarray, float, int]:
        """(coefficients of the columns on the residual, per-axis validation power after, the
        calibration residual's sum of squares after, the columns' rank)."""
        if not Ps:
            return np.zeros(0), self.axis_power(self.b), float(self.r @ self.r), 0
        coef, rank = self.least_squares(Ps)
        e = self.r - _times(Ps, coef)
        return coef, self.axis_power(self.b - _times(Ds, coef)), float(e @ e), rank

    def axis_power(self, e: np.ndarray) -> np.ndarray:
        return np.bincount(self.axis_of, e ** 2, minlength=3)

    def estimates(self, lead: list, trials: list) -> list:
        """For each block (P, D) of ``trials`` fitted with the blocks ``lead``: estimates of
        ``fit``'s calibration sum of squares, total validation power and rank, with bounds on
        their error ({rss, rss_tol, val_power, val_tol, rank}), or None where the estimate
        is not sure (the block nearly in the span of the others, or the lead blocks nearly
        dependent: a rank to decide). From the products of each block with the lead's
        orthonormal basis and the residual (one pass over its columns) and its Gram matrix
        (made once per block): a forward selection screens its hundred blocks per step this
        way and fits exactly only those that can win (attribution.attribute), instead of an
        orthogonal factorisation per block. Exact in exact arithmetic; in floating point the
        Gram matrix loses digits by the square of the block's condition, so a block is
        estimated only when that condition (columns at unit norm, the lead's part out) is
        below 1 / sqrt(SURE_EIGENVALUE), and the bounds hold with a margin of ~100."""
        r, n_lead = self.r, sum(P.shape[1] for P, _ in lead)
        if lead:
            X = np.hstack([P for P, _ in lead])
            norm = _column_norms(X)
            Q, R = np.linalg.qr(X / norm)
            sv = np.linalg.svd(R, compute_uv=False)
            if sv[-1] < SURE_LEAD * sv[0]:
                return [None] * len(trials)
            # the lead's validation columns per unit of its basis' coefficients: D R^-1
            H = np.linalg.solve(R.T, (np.hstack([D for _, D in lead]) / norm).T).T
            Qr = Q.T @ r
            v = self.b - H @ Qr                     # the validation residual of the lead alone
            rss_lead = float(r @ r - Qr @ Qr)
        else:
            Q, H, Qr, v, rss_lead = np.zeros((r.size, 0)), None, np.zeros(0), self.b, float(r @ r)
        A = np.column_stack([Q, r])
        vv = float(v @ v)
        out = []
        for P, D in trials:
            beyond = self._beyond(P, A)
            if beyond is None or np.linalg.eigvalsh(beyond[1])[0] < SURE_EIGENVALUE:
                out.append(None)
                continue
            W, S, Pr, norm = beyond
            L = np.linalg.cholesky(S)
            t = np.linalg.solve(L, Pr - W.T @ Qr)    # r on Y's orthonormal basis
            coef = np.linalg.solve(L.T, t)
            z = D @ (coef / norm) - (H @ (W @ coef) if n_lead else 0.0)
            e = v - z
            val = float(e @ e)
            out.append({"rss": rss_lead - float(t @ t), "rss_tol": 1e-6 * rss_lead,
                        "val_power": val, "val_tol": 1e-5 * (vv + float(z @ z)),
                        "rank": n_lead + P.shape[1]})
        return out

    def gains(self, basis: np.ndarray, Ps: list) -> list:
        """For each block P of ``Ps``: an estimate of what it adds to the orthonormal ``basis``
        (n,m) in the residual's sum of squares, |Pn^T r|^2 (Pn: an orthonormal basis of P less
        its part in ``basis``), and a bound on its error (gain, bound), or None where that is
        not sure (the block nearly in the span of the basis, or of rank in doubt by
        ``_orthonormal``'s rule): as ``estimates``, for model_form._forward."""
        Br = basis.T @ self.r
        A = np.column_stack([basis, self.r])
        out = []
        for P in Ps:
            beyond = self._beyond(P, A)
            if beyond is None:
                out.append(None)
                continue
            W, S, Pr, norm = beyond
            eig = np.linalg.eigvalsh(S)
            # full rank for sure (singular values of P less its basis part well above 1e-10
            # of the largest, unscaled), the estimate sure to SURE_EIGENVALUE (scaled)
            unscaled = np.linalg.eigvalsh(S * np.outer(norm, norm))
            if eig[0] < SURE_EIGENVALUE or unscaled[0] < 1e-12 * unscaled[-1]:
                out.append(None)
                continue
            L = np.linalg.cholesky(S)
            t = np.linalg.solve(L, Pr - W.T @ Br)
            out.append((float(t @ t), 1e-6 * float(self.r @ self.r)))
        return out

    def _beyond(self, P: np.ndarray, A: np.ndarray):
        """A block P (columns at unit norm) against ``A`` = [an orthonormal basis Q, the
        residual r]: (W = Q^T P, S = Y^T Y with Y = P - Q W the block less its part in the
        basis, P^T r, the columns' norms), or None for a block without columns (nothing to
        estimate: it is fitted exactly)."""
        if not P.shape[1]:
            return None
        gram, norm = self._gram(P)
        K = (A.T @ P) / norm                         # (basis + 1, c)
        W = K[:-1]
        return W, gram - W.T @ W, K[-1], norm

    def _gram(self, P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(P^T P with P's columns at unit norm, their norms) of a block, made once (kept by
        the block's id with a weak reference to it: an id reused by a new block is not taken,
        and the block is not kept alive)."""
        grams = self.__dict__.setdefault("_grams", {})
        kept = grams.get(id(P))
        if kept is None or kept[0]() is not P:
            norm = _column_norms(P)
            kept = grams[id(P)] = (weakref.ref(P), (P.T @ P) / np.outer(norm, norm), norm)
        return kept[1:]

    def best_step(self, t: np.ndarray) -> float | None:
        """The time (s) of the single step in ``t`` (N,) that, on one reading axis, lowers the
        calibration residual most with the model's directions re-adjusted, summed over the
        axes: for the step's indicator h on an axis' calibration readings (each group's mean
        out) the gain is (r . h)^2 / |h - Qm Qm^T h|^2 (r, Qm: the residual and the model's
        span, both orthogonal to the group means, so neither mean needs taking), scanned over
        every calibration time by cumulative sums. A step the model's drifts can follow leaves
        a small residual jump (a 230 nm Z step on a force campaign, seed 12345 g09: 18 nm in
        the residual) whose moment the residual alone misplaces; its gain lies in how little
        of it the model can take. Steps the model spans to within 1e-6 are not counted."""
        times, gains = [], []
        for k in sorted({g[0] for g in self.groups}):
            idx = np.concatenate([np.arange(self.n_cal)[sl] for a, _, sl, _, _ in self.groups
                                  if a == k])
            rows = np.concatenate([cal_g for a, cal_g, _, _, _ in self.groups if a == k])
            # a group without calibration readings (possible: _serial_inflation) has no mean
            sizes = [cal_g.size for a, cal_g, _, _, _ in self.groups if a == k and cal_g.size]
            group = np.repeat(np.arange(len(sizes)), sizes)
            order = np.argsort(t[rows], kind="stable")
            tk, rk, Qk, gk = t[rows][order], self.r[idx][order], self.Qm[idx][order], \
                group[order]
            if tk.size < 2:
                continue
            after_by_group = tail_sums(np.eye(len(sizes))[gk])          # (n-1, groups)
            n_g = np.asarray(sizes, float)
            hh = np.sum(after_by_group * (1.0 - after_by_group / n_g), axis=1)
            pp = hh - np.sum(tail_sums(Qk) ** 2, axis=1)
            gain = np.where(pp > 1e-6 * hh, tail_sums(rk) ** 2 / np.maximum(pp, 1e-300), 0.0)
            times.append(tk)
            gains.append(gain)
        every = np.unique(np.concatenate(times)) if times else np.zeros(0)
        if every.size < 2:
            return None
        every = 0.5 * (every[:-1] + every[1:])       # between two calibration times
        total = np.zeros(every.size)
        for tk, gain in zip(times, gains):
            # gain[j]: the step after the axis' first j + 1 readings
            j = np.searchsorted(tk, every, side="right") - 1
            inside = (j >= 0) & (j < gain.size)
            total[inside] += gain[j[inside]]
        if not np.any(total > 0):
            return None                  # no step counted: the residual's own scan stands
        return float(every[np.argmax(total)])


def _column_norms(X: np.ndarray) -> np.ndarray:
    """The Euclidean norms of the columns of X (n,c), 1 for a zero column (a scale to divide
    by): one pass over the rows (np.linalg.norm along axis 0 strides down each column, ~6x
    slower on these tall, narrow blocks)."""
    norm = np.sqrt(np.einsum("ij,ij->j", X, X))
    norm[norm == 0] = 1.0
    return norm


def _times(blocks: list, coef: np.ndarray) -> np.ndarray:
    """The blocks of columns side by side times ``coef``, without joining them."""
    out, at = 0.0, 0
    for X in blocks:
        out = out + X @ coef[at:at + X.shape[1]]
        at += X.shape[1]
    return out


class JointFrame:
    """attribution.py's frame on a fitted physics model: a term's columns on every reading axis
    with coefficients of its own (or per axis already: a load's response), fitted with the
    model's identified directions re-adjusted (``_Joint``), so a variable is credited with what
    the model's parameters cannot take of it (the geometry soaks up the part of a backlash that
    follows the motor coordinate, the temperatures a drift in time). ``target``: the residual
    of the model one linear step further (``Residual``), whose scans the terms use."""

    def __init__(self, fit, Jm: np.ndarray, JS: np.ndarray, r0: np.ndarray,
                 span: ModelSpan | None = None):
        self.joint = _Joint(fit, Jm, JS, r0, span)
        meas = fit.measurements_
        self.target = Residual.of(meas.df, self.joint.before, meas.cal, meas.val)
        self.axes = [k for k, _, _ in self.target.axes]
        self.n_axes = len(self.axes)
        self.shape = meas.y.shape

    def blocks(self, terms: list[Term]) -> list[tuple[np.ndarray, np.ndarray]]:
        """Each term's columns on the fit's readings (``_Joint.columns``): a term of (N,p)
        columns on every axis of the target with coefficients of its own (axis-major), an
        (N,3,p) one as it is; COLUMNS_AT_ONCE terms' columns projected together."""
        out = []
        for start in range(0, len(terms), COLUMNS_AT_ONCE):
            out += self.joint.columns([self._placed(t)
                                       for t in terms[start:start + COLUMNS_AT_ONCE]])
        return out

    def _placed(self, term: Term):
        X = term.columns
        if X.ndim != 2:
            return np.nan_to_num(X)
        X = np.where(np.all(np.isfinite(X), axis=1)[:, None], X, 0.0)
        return Placed(X.shape[1] * self.n_axes,
                      tuple((k, i * X.shape[1], X) for i, k in enumerate(self.axes)))

    def n_val(self) -> dict:
        return {k: int(np.sum(self.joint.axis_of == k)) for k in self.axes}

    def scan(self, variables: list) -> None:
        """The scans of ``variables`` on ``target`` (attribution.scan_together), a step's
        moment in time scanned with the model's directions re-adjusted (``_Joint.best_step``),
        as the terms are fitted here; where no step counts there (the model spans every one),
        the residual's own scan."""
        scan_together(variables, [self.target], step=self._step)

    def _step(self, t: np.ndarray, target) -> float | None:
        """The moment (s) of a step in time ``t`` for ``scan_together``."""
        tau = self.joint.best_step(t)
        return best_step(t, target) if tau is None else tau

    def estimates(self, lead: list, trials: list) -> list:
        """As attribution.AxisFrame.estimates: ``_Joint.estimates``, with ``fit``'s degrees of
        freedom."""
        joint = self.joint
        out = joint.estimates(lead, trials)
        for est in out:
            if est is not None:
                est["dof"] = joint.r.size - joint.Qm.shape[1] - est["rank"] - joint.n_groups
        return out

    def fit(self, blocks: list) -> dict:
        """As attribution.AxisFrame.fit."""
        joint = self.joint
        _, val, rss, rank = joint.fit([P for P, _ in blocks], [D for _, D in blocks])
        return {"rss_cal": rss, "rank": rank,
                "dof": joint.r.size - joint.Qm.shape[1] - rank - joint.n_groups,
                "val_power": float(val.sum()), "val_by_axis": {k: float(val[k]) for k in self.axes}}


def load_terms(candidates: list[Candidate]) -> list[Term]:
    """attribution.py's terms of the force from ``load_candidates``: one per power and
    direction of the load, its response on every reading axis with one coefficient (the
    force), as the form fits it."""
    return [Term(c.variable, f"load I^{c.power} along {c.extra['direction']}", c.columns)
            for c in candidates if c.kind == "load"]


def _on_every_axis(cand: Candidate) -> bool:
    """Whether a candidate is tried on every reading axis at once (coefficients of its own per
    axis): an error in where a motor sits (the direction of its last move: a backlash; a sine
    of its angle: an encoder's periodic error) moves the platform, so the kinematics show it on
    every axis; fitted on one axis at a time, another function can take its place on a weaker
    axis (a motor's coordinate that follows its moves on a grid) and the effect written from
    the form misses it there."""
    return cand.kind == "sign" or (cand.kind == "sine" and cand.variable.startswith("q")
                                   and cand.variable.endswith("_rad"))


def _forward(joint: _Joint, blocks: list, alpha: float, min_share: float,
             limit_of, deferred: frozenset = frozenset(),
             physical: dict | None = None, variable_of: list | None = None) -> list[int]:
    """Forward selection over ``blocks`` [(P, D, scanned)]: the block that lowers the
    calibration residual most joins while it is significant (partial F test, the scanned
    parameters counted, Bonferroni over the blocks) and lowers the validation power by
    ``min_share`` of it. Where it does not lower the validation power so, the blocks of the
    same variable (``variable_of``: each block's) that the calibration rows cannot tell from
    it are tried in its place, strongest first (the same dependence in another form); another
    variable's blocks are not. ``limit_of(chosen, i)``: False when block i may not join any
    more; the ``deferred`` blocks (a rotation's: a reading of the platform's response, as in
    attribution.py) are tried only once no other block qualifies.

    ``physical`` {i: [j, ...]}: the blocks of the physical form block i stands in for (a
    polynomial of the force on one reading axis: the loads of the same power of the current,
    through the model's statics; a motor's last-move sign or periodic term fitted axis by axis:
    where that motor sits, through the kinematics). The strongest of them joins in i's place
    unless i lowers the calibration residual by significantly more (``_better``): where both
    fit within the noise, the physical form carries the pattern the readings share into the
    effect written from the form, the axis' function does not."""
    r, n = joint.r, joint.r.size
    p0 = float(joint.axis_power(joint.b).sum())
    limit = alpha / max(len(blocks), 1)
    physical = physical or {}
    chosen, basis = [], np.zeros((n, 0))
    rss, val_power = float(r @ r), p0
    while True:
        # the trials (i, gain, Pn, kk, df2) of the blocks that can join: the strongest among
        # them found from the gains' estimates with their bounds (_Joint.gains), then the
        # others that decide its tries (its variable's, their physical forms') made too
        eligible = [i for i in range(len(blocks))
                    if i not in chosen and i not in deferred and limit_of(chosen, i)]
        made = {}                  # block -> its trial, or None where it cannot join
        make = functools.partial(_made, made, joint, blocks, basis, rss)
        best = None
        bounds = [(math.inf if est is None else est[0] + est[1], i)
                  for i, est in zip(eligible, joint.gains(basis, [blocks[i][0]
                                                                  for i in eligible]))]
        for bound, i in sorted(bounds, key=lambda b: (-b[0], b[1])):
            if best is not None and bound < best[1]:
                break
            t = make(i)
            if t is not None and (best is None or t[1] > best[1]
                                  or (t[1] == best[1] and i < best[0])):
                best = t
        if best is not None:
            same = [i for i in eligible
                    if variable_of is not None and variable_of[i] == variable_of[best[0]]]
            for i in [best[0]] + same:
                make(i)
                for j in physical.get(i, ()):
                    if j in eligible:
                        make(j)
        tries = _tries(made, best, physical, variable_of, rss, limit)
        best = None
        for i, gain, Pn, kk, df2 in tries:
            trial = chosen + [i]
            vp = float(joint.fit([blocks[j][0] for j in trial],
                                 [blocks[j][1] for j in trial])[1].sum())
            if (f_test_p(rss, rss - gain, kk, df2) < limit
                    and val_power - vp >= min_share * p0):
                best = (i, gain, Pn, kk, df2)
                break
        if best is None:
            if deferred:           # no condition qualifies: the rotations may
                deferred = frozenset()
                continue
            break
        chosen, basis, rss, val_power = trial, np.hstack([basis, Pn]), rss - gain, vp
    return _backward(joint, blocks, chosen, limit, min_share * p0)


def _tries(made: dict, best, physical: dict, variable_of: list | None, rss: float,
           limit: float) -> list:
    """The trials ``_forward`` tries in order, from those ``made`` (block -> trial or None)
    and the strongest, ``best``: it, then those of its variable the calibration rows cannot
    tell from it, strongest first; each preceded by its physical alternative where it is not
    significantly better than that; each block once, in its first place."""
    if best is None:
        return []
    # the trials made, in the order of the blocks (the sort below keeps it among ties)
    trials = {i: made[i] for i in sorted(made) if made[i] is not None}
    alike = [t for t in sorted(trials.values(), key=lambda t: -t[1])
             if t is best or (variable_of is not None
                              and variable_of[t[0]] == variable_of[best[0]]
                              and not _better(best, t, rss, limit))]
    tries = []
    for t in alike:
        alternatives = [trials[j] for j in physical.get(t[0], ()) if j in trials]
        if alternatives:
            alt = max(alternatives, key=lambda a: a[1])
            if not _better(t, alt, rss, limit):
                tries.append(alt)
        tries.append(t)
    return list({t[0]: t for t in tries}.values())


def _made(made: dict, joint: _Joint, blocks: list, basis: np.ndarray, rss: float, i: int):
    """_forward's trial of block i (P, D, scanned) beside the chosen blocks' orthonormal
    ``basis``, made once (kept in ``made``): (i, gain in the calibration sum of squares
    ``rss``, the block's new orthonormal columns Pn, its parameters, the residual's degrees of
    freedom after it), or None where it adds no column or leaves no degree of freedom or no
    residual."""
    if i not in made:
        P, _, scanned = blocks[i]
        Pn = _orthonormal(P - basis @ (basis.T @ P))
        df2 = (joint.r.size - joint.Qm.shape[1] - basis.shape[1] - Pn.shape[1]
               - joint.n_groups)
        gain = float(np.sum((Pn.T @ joint.r) ** 2))
        made[i] = ((i, gain, Pn, Pn.shape[1] + scanned, df2)
                   if Pn.shape[1] and df2 > 0 and gain < rss else None)
    return made[i]


def _better(a: tuple, b: tuple, rss: float, limit: float) -> bool:
    """Whether the trial ``a`` (i, gain, Pn, parameters, df2) lowers the calibration residual
    (sum of squares ``rss`` before either) significantly more than ``b``: the difference of the
    gains per parameter ``a`` has beyond ``b`` (at least one), in units of the residual
    variance after ``a``, beyond the Bonferroni ``limit``."""
    _, gain, _, kk, df2 = a
    extra = max(kk - b[3], 1)
    return bool(f_test_p(rss - b[1], rss - gain, extra, df2) < limit)


def _backward(joint: _Joint, blocks: list, chosen: list[int], limit: float,
              min_power: float) -> list[int]:
    """``chosen`` without the blocks that no longer pass the joining test given all the others
    (significant at ``limit``, lowering the validation power by ``min_power``): a block that
    joined early can be explained by those that joined after it (a step in time that followed
    a backlash's pattern of moves until the direction's offset joined); the one that explains
    least on validation leaves first, then the rest are tested again."""
    fit = lambda idx: joint.fit([blocks[j][0] for j in idx], [blocks[j][1] for j in idx])
    n = joint.r.size
    while len(chosen) > 1:
        _, val, rss, rank = fit(chosen)
        df2 = n - joint.Qm.shape[1] - rank - joint.n_groups
        failing = []
        for i in chosen:
            _, val_o, rss_o, rank_o = fit([j for j in chosen if j != i])
            kk = rank - rank_o + blocks[i][2]
            gain = float(val_o.sum() - val.sum())
            significant = kk > 0 and f_test_p(rss_o, rss, kk, df2) < limit
            if not significant or gain < min_power:
                failing.append((gain, i))
        if not failing:
            break
        chosen = [j for j in chosen if j != min(failing)[1]]
    return chosen


def _blocks(candidates: list, axes: list, joint) -> list:
    """The blocks the selection tries: (candidate, {reading axis: its coefficients' slice}, C
    (N,3,p), P, D), those whose projected columns are not nil; a function fitted on one axis,
    on every axis with coefficients of its own (a motor's error) or on every axis with shared
    ones (a load's response); their columns projected together (_Joint.columns) on the read
    ``axes``."""
    tried, pairs = [], []
    for cand in candidates:
        c = cand.columns.shape[-1]
        if cand.columns.ndim == 3:
            C = np.nan_to_num(cand.columns)
            C[:, [k for k in range(3) if k not in axes]] = 0.0     # axes read too rarely
            layouts = [({k: slice(0, c) for k in axes}, C)]
        else:
            layouts, X = [], np.nan_to_num(cand.columns)
            for group in ([axes] if _on_every_axis(cand) else [[k] for k in axes]):
                layouts.append(({k: slice(i * c, (i + 1) * c) for i, k in enumerate(group)},
                                Placed(c * len(group),
                                       tuple((k, i * c, X) for i, k in enumerate(group)))))
        tried += [(cand, layout, C) for layout, C in layouts]
    for start in range(0, len(tried), COLUMNS_AT_ONCE):
        batch = tried[start:start + COLUMNS_AT_ONCE]
        for (cand, layout, C), (P, D) in zip(batch, joint.columns([C for _, _, C in batch])):
            if np.linalg.norm(P) > 0:
                pairs.append((cand, layout, C, P, D))
    return pairs


def _stands_for(c) -> tuple | None:
    """The physical form a reading function stands in for: a force's polynomial on one axis,
    the loads of its power; a motor's last-move sign or periodic term fitted axis by axis,
    where that motor sits (_forward)."""
    if c.variable == "F_N" and c.kind in ("poly", "product"):
        return ("load", c.power)
    return {"sign": ("motor_sign", c.variable), "sine": ("motor_sine", c.variable)}.get(c.kind)


def _physical_forms(pairs: list) -> dict:
    """{block index: the indices of the physical blocks it stands in for} (``_stands_for``)."""
    physical_of = {}
    for j, (c, *_) in enumerate(pairs):
        if c.kind in ("load", "motor_sign", "motor_sine"):
            key = (c.kind, c.power if c.kind == "load" else c.variable)
            physical_of.setdefault(key, []).append(j)
    return {i: physical_of[_stands_for(c)] for i, (c, *_) in enumerate(pairs)
            if _stands_for(c) in physical_of}


def _form_rows(pairs: list, chosen: list, per_term: list, shares: dict, axes: list, joint,
               p0_axes: np.ndarray, p_full: np.ndarray, min_share: float) -> list:
    """The form's rows per axis (``joint_form``) from the chosen blocks, their coefficients
    ``per_term`` and each (term, axis)'s ``shares``: a term on several axes is listed on those
    where it explains at least a joining term's share, and on its strongest; an axis whose
    terms together explain less than that share is left out."""
    listed = {(j, k) for (j, k), share in shares.items()
              if share >= min_share or share == max(v for (m, _), v in shares.items() if m == j)}
    form = []
    for k in axes:
        terms = []
        for j, c in zip(chosen, per_term):
            if (j, k) in listed:
                term = pairs[j][0].describe(c[pairs[j][1][k]])
                term["explained_fraction"] = shares[j, k]
                terms.append(term)
        if not terms or p0_axes[k] <= 0 or 1.0 - p_full[k] / p0_axes[k] < min_share:
            continue
        terms.sort(key=lambda t: -t["explained_fraction"])
        n_val = max(int(np.sum(joint.axis_of == k)), 1)
        form.append({"axis": AXES[k], "terms": terms,
                     "explained_fraction": 1.0 - p_full[k] / p0_axes[k],
                     "val_rms_nm": float(np.sqrt(p0_axes[k] / n_val) * 1e9),
                     "val_rms_after_nm": float(np.sqrt(p_full[k] / n_val) * 1e9)})
    return form


def joint_form(fit, Jm: np.ndarray, JS: np.ndarray, r0: np.ndarray, alpha: float = ALPHA,
               min_share: float = MIN_SHARE, max_terms: int = MAX_TERMS,
               variables: list | None = None, frame: JointFrame | None = None,
               loads: list | None = None):
    """The missing term's form on a fitted physics model (module docstring). ``Jm`` (n, k_m):
    the model's identified directions on the calibration readings (session means out), ``JS``
    (N,3,k_m) the same directions on every row, ``r0`` (n,) the model's calibration residual
    (session means out). ``variables``: ``laboratory_variables`` of the fit's rows when already
    made; ``frame``: the ``JointFrame`` of the same (made here if None); ``loads``: its
    ``load_candidates`` when already made.

    Returns (form, G, explained): the form as term_form.sparse_form's ([{axis, terms,
    explained_fraction, val_rms_nm, val_rms_after_nm}], relative to the residual the model's
    directions leave), the selected columns G (N,3,p) and the fraction of the validation
    residual power they explain together."""
    meas = fit.measurements_
    frame = JointFrame(fit, Jm, JS, r0) if frame is None else frame
    joint, target = frame.joint, frame.target
    p0_axes = joint.axis_power(joint.b)
    p0 = float(p0_axes.sum())
    empty = [], np.zeros(meas.y.shape + (0,)), 0.0
    if p0 <= 0 or not target.axes:
        return empty
    variables = laboratory_variables(meas.df) if variables is None else variables
    frame.scan(variables)
    candidates = (candidate_library(variables, target)
                  + (load_candidates(fit) if loads is None else loads)
                  + motor_candidates(fit, variables, target))
    axes = [k for k, _, _ in target.axes]
    pairs = _blocks(candidates, axes, joint)
    on = lambda j, k: k in pairs[j][1]
    per_axis = lambda chosen, i: all(sum(on(j, k) for j in chosen) < max_terms
                                     for k in pairs[i][1])
    responses = {v.name for v in variables if v.response}
    chosen = _forward(joint, [(P, D, c.scanned) for c, _, _, P, D in pairs], alpha, min_share,
                      per_axis, frozenset(i for i, pair in enumerate(pairs)
                                          if pair[0].variable in responses),
                      _physical_forms(pairs),
                      [c.variable for c, *_ in pairs])
    if not chosen:
        return empty
    fit_of = lambda idx: joint.fit([pairs[j][3] for j in idx], [pairs[j][4] for j in idx])
    coefs, p_full, _, _ = fit_of(chosen)
    per_term = np.split(coefs, np.cumsum([_width(pairs[j][2]) for j in chosen])[:-1])
    shares = {}         # (term, axis): the share of the axis' power the term alone explains
    for j in chosen:
        without = fit_of([m for m in chosen if m != j])[1]
        for k in pairs[j][1]:
            shares[j, k] = (max(without[k] - p_full[k], 0.0) / p0_axes[k]
                            if p0_axes[k] > 0 else 0.0)
    form = _form_rows(pairs, chosen, per_term, shares, axes, joint, p0_axes, p_full, min_share)
    G = np.concatenate([C.dense(meas.y.shape) if isinstance(C, Placed) else C
                        for C in (pairs[j][2] for j in chosen)], axis=2)
    return form, G, 1.0 - float(p_full.sum()) / p0
