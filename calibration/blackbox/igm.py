"""The controller's inverse geometric model: position + temperatures -> motor coordinates, by
vectorised Newton-Raphson on a fitted DGM, within the actuators' strokes."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from deltatwin.calibration.blackbox.dgm import DGM
from deltatwin.calibration.blackbox.estimator import AXIS_COLUMNS, solve3
from deltatwin.calibration.errors import CalibrationInputError
from deltatwin.models.params import load_params

# what an IGM answer is, per point
CONVERGED = "converged"          # |DGM(q) - target| <= tol on every axis, q inside the stroke
OUT_OF_STROKE = "out_of_stroke"  # the model reaches the target only with q outside the stroke
OUT_OF_REACH = "out_of_reach"    # no q inside the stroke reaches the target (from any start)
NOT_FINITE = "not_finite"        # a target or an aux variable is NaN / infinite
STATUSES = (CONVERGED, OUT_OF_STROKE, OUT_OF_REACH, NOT_FINITE)

# starts of the second pass: a 3 x 3 x 3 grid at these fractions of the half-stroke about its
# centre (Newton from the first start may end on a root outside the stroke, or stall)
_START_FRACTIONS = (-0.6, 0.0, 0.6)
_STROKE_SLACK_RAD = 1e-12        # the robot's own stroke check allows the same (kinematics.py)


@dataclass
class IGMResult:
    q: np.ndarray            # (n, 3) rad: the solution; else the out-of-stroke root or the
                             # in-stroke point closest to the target that was found
    converged: np.ndarray    # (n,) bool: status == "converged"
    iterations: np.ndarray   # (n,) Newton iterations of the first pass
    residual_m: np.ndarray   # (n,) max |DGM(q) - target| over the axes, m (inf: not finite)
    status: np.ndarray       # (n,) one of STATUSES
    stroke_rad: tuple[float, float] = (np.nan, np.nan)

    @property
    def n_failed(self) -> int:
        return int((~self.converged).sum())

    def reason(self, i: int) -> str:
        """Why point ``i`` has its status, in words (units in the text)."""
        lo, hi = self.stroke_rad
        q, s, r = self.q[i], self.status[i], self.residual_m[i]
        if s == CONVERGED:
            return f"converged: |DGM(q) - target| = {r * 1e9:.2e} nm at q = {q.tolist()} rad"
        if s == OUT_OF_STROKE:
            return (f"out of stroke: the model reaches the target at q = {q.tolist()} rad, "
                    f"outside the stroke [{lo}, {hi}] rad, and from no start inside it")
        if s == OUT_OF_REACH:
            return (f"out of reach: no motor coordinates inside the stroke [{lo}, {hi}] rad "
                    f"reach the target; the closest found, q = {q.tolist()} rad, is "
                    f"{r * 1e9:.4g} nm off")
        return "not finite: the target or a temperature variable is NaN or infinite"


class IGM:
    """Inverse geometric model by Newton-Raphson on a fitted DGM with x, y and z outputs.

    ``solve(position_m, aux)`` finds q with ``DGM(q, aux) = position`` for a batch, in a
    vectorised loop over the points not yet converged.  A point is converged when every
    axis' residual is <= ``tol_m`` (default 1e-12 m = 0.001 nm) **and** q lies inside the
    actuators' stroke ``stroke_rad`` (default: the nominal robot's).  Newton runs first from
    ``q0``; a point whose root lies outside the stroke, or that did not converge, is solved
    again from 27 starts inside the stroke with every iterate held in the stroke, and the
    in-stroke root nearest ``q0`` wins.  A point with no in-stroke root is reported
    ``out_of_stroke`` (the model's root lies outside: that q is returned) or ``out_of_reach``
    (no root found: the closest in-stroke point is returned), never as converged.
    """

    def __init__(self, dgm: DGM, tol_m: float = 1e-12, max_iter: int = 30, stroke_rad=None):
        if not isinstance(dgm, DGM):
            raise CalibrationInputError(f"IGM needs a DGM, got {type(dgm).__name__}")
        dgm._check_fitted()
        missing = [a for a in AXIS_COLUMNS if a not in dgm.output_names_]
        if missing:
            raise CalibrationInputError(f"IGM needs DGM outputs x, y and z; axis(es) {missing} "
                                        "were not fitted")
        if not (tol_m > 0) or not (max_iter >= 1):
            raise CalibrationInputError(f"IGM: tol_m = {tol_m} must be > 0 and max_iter = "
                                        f"{max_iter} >= 1")
        stroke = load_params(None).stroke_rad if stroke_rad is None else stroke_rad
        lo, hi = (float(v) for v in np.asarray(stroke, dtype=float).reshape(2))
        if not (np.isfinite(lo) and np.isfinite(hi) and lo < hi):
            raise CalibrationInputError(f"IGM: stroke_rad = {stroke!r} must be [low, high] rad "
                                        "with low < high")
        self.dgm = dgm
        self.tol_m = float(tol_m)
        self.max_iter = int(max_iter)
        self.stroke_rad = (lo, hi)
        order = [dgm.output_names_.index(a) for a in AXIS_COLUMNS]
        self._order = np.array(order)

    def __repr__(self) -> str:
        return (f"IGM({self.dgm!r}, tol_m={self.tol_m:g}, max_iter={self.max_iter}, "
                f"stroke_rad=({self.stroke_rad[0]:g}, {self.stroke_rad[1]:g}))")

    @property
    def aux_variables(self) -> tuple[str, ...]:
        """Non-geometric variables the IGM needs (temperatures, rates), SI."""
        return self.dgm._eval.aux_vars

    def in_stroke(self, q: np.ndarray) -> np.ndarray:
        """(n,) whether motor coordinates q (n, 3) rad lie inside the stroke."""
        lo, hi = self.stroke_rad
        return np.all((q >= lo - _STROKE_SLACK_RAD) & (q <= hi + _STROKE_SLACK_RAD), axis=1)

    def starts(self) -> np.ndarray:
        """The second pass's starting points (27, 3) rad, inside the stroke."""
        lo, hi = self.stroke_rad
        g = 0.5 * (lo + hi) + 0.5 * (hi - lo) * np.asarray(_START_FRACTIONS)
        return np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1).reshape(-1, 3)

    def solve(self, position_m, aux: dict | None = None, q0=None,
              chunk: int = 32768) -> IGMResult:
        """``position_m``: (n, 3) target readings x, y, z in m; ``aux``: dict of the aux
        variables (arrays (n,) or scalars, SI: K relative to the reference, K/s, K/s^2);
        ``q0``: first start (default 0 = the campaign's zero).  Points are solved in chunks."""
        x = np.atleast_2d(np.asarray(position_m, dtype=float))
        if x.ndim != 2 or x.shape[1] != 3:
            raise CalibrationInputError(f"IGM.solve: positions must be (n, 3), got {x.shape}")
        n = x.shape[0]
        aux = dict(aux or {})
        for k, v in aux.items():
            v = np.asarray(v, dtype=float).reshape(-1)
            aux[k] = np.full(n, v.item()) if v.size == 1 and n != 1 else v
            if aux[k].size != n:
                raise CalibrationInputError(f"IGM.solve: variable {k!r} has {v.size} values "
                                            f"for {n} points")
        q = np.zeros((n, 3)) if q0 is None else np.array(np.broadcast_to(q0, (n, 3)), float)
        start = q.copy()
        conv = np.zeros(n, bool)
        iters = np.zeros(n, int)
        resid = np.full(n, np.inf)
        self._solve(x, aux, q, conv, iters, resid, chunk, bounded=False)
        status = np.full(n, NOT_FINITE, dtype=object)
        status[conv] = OUT_OF_STROKE
        ok = conv & self.in_stroke(q)
        status[ok] = CONVERGED
        retry = np.flatnonzero(~ok & np.isfinite(resid))
        if retry.size:
            self._second_pass(x, aux, q, resid, status, start, retry, chunk)
        return IGMResult(q=q, converged=status == CONVERGED, iterations=iters, residual_m=resid,
                         status=status.astype(str), stroke_rad=self.stroke_rad)

    def _second_pass(self, x, aux, q, resid, status, start, retry, chunk):
        """Newton from every start of ``starts()`` with the iterates held in the stroke, for
        the points ``retry``; keeps the in-stroke root nearest the first start."""
        S = self.starts()
        k = S.shape[0]
        rep = np.repeat(retry, k)
        qs = np.tile(S, (retry.size, 1))
        cs = np.zeros(rep.size, bool)
        rs = np.full(rep.size, np.inf)
        self._solve(x[rep], {v: a[rep] for v, a in aux.items()}, qs, cs, np.zeros(rep.size, int),
                    rs, chunk, bounded=True)
        cs &= self.in_stroke(qs)
        dist = np.where(cs, np.linalg.norm(qs - start[rep], axis=1), np.inf).reshape(-1, k)
        best = np.argmin(dist, axis=1)
        found = np.isfinite(dist[np.arange(retry.size), best])
        pick = np.arange(retry.size) * k + best
        won = retry[found]
        q[won], resid[won], status[won] = qs[pick[found]], rs[pick[found]], CONVERGED
        # no in-stroke root: keep an out-of-stroke root of the first pass; else report the
        # in-stroke point closest to the target
        lost = ~found & (status[retry] != OUT_OF_STROKE)
        near = np.argmin(np.where(np.isfinite(rs), rs, np.inf).reshape(-1, k), axis=1)
        pick = np.arange(retry.size) * k + near
        idx = retry[lost]
        q[idx], resid[idx], status[idx] = qs[pick[lost]], rs[pick[lost]], OUT_OF_REACH

    def _solve(self, x, aux, q, conv, iters, resid, chunk, bounded):
        n = x.shape[0]
        for s0 in range(0, n, chunk):
            sl = slice(s0, min(n, s0 + chunk))
            self._solve_chunk(x[sl], {k: v[sl] for k, v in aux.items()}, q[sl], conv[sl],
                              iters[sl], resid[sl], bounded)

    def _solve_chunk(self, x, aux, q_out, conv, iters, resid, bounded):
        ev = self.dgm._eval
        m = x.shape[0]
        lo, hi = self.stroke_rad
        C = ev.coefficients(aux, m)[self._order]                    # (3, n_geo, m)
        X = np.ascontiguousarray(x.T)                               # (3, m)
        q = np.ascontiguousarray(q_out.T)                           # (3, m)
        idx = np.flatnonzero(np.all(np.isfinite(X), axis=0) & np.all(np.isfinite(C), axis=(0, 1)))
        if idx.size < m:
            C, X, q = C[:, :, idx], X[:, idx], q[:, idx]
        for it in range(self.max_iter + 1):
            if idx.size == 0:
                break
            f, J = ev.value_and_jacobian(C, q)
            r = f - X
            rmax = np.max(np.abs(r), axis=0)
            resid[idx] = rmax
            q_out[idx] = q.T
            ok = rmax <= self.tol_m
            conv[idx[ok]] = True
            if it == self.max_iter:
                break
            dq, det = solve3(J, r)
            step_ok = np.isfinite(det) & (det != 0.0) & np.all(np.isfinite(dq), axis=0)
            keep = ~ok & np.isfinite(rmax) & step_ok
            if not keep.all():
                idx, C, X, q, dq = idx[keep], C[:, :, keep], X[:, keep], q[:, keep], dq[:, keep]
            q = q - dq
            if bounded:                  # projected Newton: the robot cannot go further
                q = np.clip(q, lo, hi)
            iters[idx] += 1

    def solve_frame(self, df: pd.DataFrame, position_m) -> IGMResult:
        """Solve with the temperatures (and causal derivatives) of the rows of ``df``."""
        return self.solve(position_m, self.dgm.variables(df))
