"""The controller's inverse geometric model: position + temperatures -> motor coordinates, by
vectorised Newton-Raphson on a fitted DGM."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from deltatwin.calibration.blackbox.dgm import DGM
from deltatwin.calibration.blackbox.estimator import AXIS_COLUMNS, _solve3
from deltatwin.calibration.errors import CalibrationInputError


@dataclass
class IGMResult:
    q: np.ndarray            # (n, 3) rad; last iterate where not converged
    converged: np.ndarray    # (n,) bool: |DGM(q) - target| <= tol_m on every axis
    iterations: np.ndarray   # (n,) Newton iterations used
    residual_m: np.ndarray   # (n,) max |DGM(q) - target| over the axes, m

    @property
    def n_failed(self) -> int:
        return int((~self.converged).sum())


class IGM:
    """Inverse geometric model by Newton-Raphson on a fitted DGM with x, y and z outputs.

    ``solve(position_m, aux)`` finds q with ``DGM(q, aux) = position`` for a batch, in a
    vectorised loop over the points not yet converged.  A point is converged when every
    axis' residual is <= ``tol_m`` (default 1e-12 m = 0.001 nm); points whose Jacobian is
    singular or whose iterates leave the finite range, or that are still above ``tol_m``
    after ``max_iter`` iterations, are reported (``converged`` False), never silently kept.
    """

    def __init__(self, dgm: DGM, tol_m: float = 1e-12, max_iter: int = 30):
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
        self.dgm = dgm
        self.tol_m = float(tol_m)
        self.max_iter = int(max_iter)
        order = [dgm.output_names_.index(a) for a in AXIS_COLUMNS]
        self._order = np.array(order)

    @property
    def aux_variables(self) -> tuple[str, ...]:
        """Non-geometric variables the IGM needs (temperatures, rates), SI."""
        return self.dgm._eval.aux_vars

    def solve(self, position_m, aux: dict | None = None, q0=None,
              chunk: int = 32768) -> IGMResult:
        """``position_m``: (n, 3) target readings x, y, z in m; ``aux``: dict of the aux
        variables (arrays (n,) or scalars, SI: K relative to the reference, K/s, K/s^2);
        ``q0``: start (default 0 = the campaign's zero).  Points are solved in chunks."""
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
        conv = np.zeros(n, bool)
        iters = np.zeros(n, int)
        resid = np.full(n, np.inf)
        for s0 in range(0, n, chunk):
            sl = slice(s0, min(n, s0 + chunk))
            self._solve_chunk(x[sl], {k: v[sl] for k, v in aux.items()}, q[sl], conv[sl],
                              iters[sl], resid[sl])
        return IGMResult(q=q, converged=conv, iterations=iters, residual_m=resid)

    def _solve_chunk(self, x, aux, q_out, conv, iters, resid):
        ev = self.dgm._eval
        m = x.shape[0]
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
            dq, det = _solve3(J, r)
            step_ok = np.isfinite(det) & (det != 0.0) & np.all(np.isfinite(dq), axis=0)
            keep = ~ok & np.isfinite(rmax) & step_ok
            if not keep.all():
                idx, C, X, q, dq = idx[keep], C[:, :, keep], X[:, keep], q[:, keep], dq[:, keep]
            q = q - dq
            iters[idx] += 1

    def solve_frame(self, df: pd.DataFrame, position_m) -> IGMResult:
        """Solve with the temperatures (and causal derivatives) of the rows of ``df``."""
        return self.solve(position_m, self.dgm.variables(df))


# ----- direct IGM ------------------------------------------------------------------------

