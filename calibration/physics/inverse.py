"""The physics model inverted: target reading + measured conditions (temperatures, coil currents)
-> motor coordinates, vectorised over points, within the actuators' stroke.

The model (calibration/physics/model.py) predicts what the interferometers count from their
session's zero at given motor coordinates and conditions. ``PhysicsInverse.solve`` finds, for
every row of a ``Measurements`` it is asked about, the motor coordinates q at which that
prediction equals the target, by Newton-Raphson with the Jacobian d reading / d q taken by
central differences of the model itself (the three columns for all rows at once: rows are
independent). Every iterate is held inside the stroke (projected Newton): the model's kinematics
refuse motor coordinates outside it, and the robot cannot go there. A row is converged when
every axis' residual is <= ``tol_m`` (default 1e-12 m = 0.001 nm), re-evaluated at the final q;
otherwise it is reported, with a reason, as out of reach (the closest in-stroke q is returned).
Units: m, rad.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from deltatwin.calibration.errors import FitError
from deltatwin.calibration.physics.measurements import Measurements
from deltatwin.calibration.physics.model import PhysicsModel

CONVERGED = "converged"
OUT_OF_REACH = "out_of_reach"
NOT_FINITE = "not_finite"
_STROKE_SLACK_RAD = 1e-12


@dataclass
class InverseResult:
    q: np.ndarray            # (n, 3) rad, the rows asked about
    status: np.ndarray       # (n,) converged / out_of_reach / not_finite
    residual_m: np.ndarray   # (n,) max over the axes of |prediction(q) - target|, m
    iterations: np.ndarray   # (n,) Newton iterations used
    stroke_rad: tuple[float, float]

    @property
    def converged(self) -> np.ndarray:
        return self.status == CONVERGED

    def reason(self, i: int) -> str:
        lo, hi = self.stroke_rad
        s, q, r = self.status[i], self.q[i].tolist(), self.residual_m[i]
        if s == CONVERGED:
            return f"converged: |prediction - target| = {r * 1e9:.2e} nm at q = {q} rad"
        if s == OUT_OF_REACH:
            return (f"out of reach: no motor coordinates inside the stroke [{lo}, {hi}] rad give "
                    f"the target; the closest found, q = {q} rad, is {r * 1e9:.4g} nm off")
        return "not finite: the target or the conditions are NaN or infinite"


def with_motor_coordinates(meas: Measurements, rows: np.ndarray, q: np.ndarray) -> Measurements:
    """A copy of ``meas`` whose ``rows`` have motor coordinates ``q`` (len(rows), 3) rad (the
    statics are recomputed there on the next evaluation)."""
    Q = meas.points.q.copy()
    Q[rows] = q
    return dataclasses.replace(meas, points=dataclasses.replace(meas.points, q=Q),
                               _statics=None)


class PhysicsInverse:
    """Invert a fitted ``PhysicsModel``: see the module docstring.

    ``tol_m``: convergence on the readings (m); ``max_iter``: Newton iterations;
    ``step_rad``: central-difference step of the Jacobian (1e-6 rad moves the platform by
    ~0.1 um: the model's curvature gives a relative error ~1e-6 of J, its rounding ~1e-9 m /
    1e-7 m, both far below what Newton needs to converge); ``stroke_rad``: the actuators'
    stroke (default: the model's robot)."""

    def __init__(self, model: PhysicsModel, tol_m: float = 1e-12, max_iter: int = 20,
                 step_rad: float = 1e-6, stroke_rad=None):
        if not isinstance(model, PhysicsModel):
            raise FitError(f"PhysicsInverse needs a PhysicsModel, got {type(model).__name__}")
        if not (tol_m > 0 and max_iter >= 1 and step_rad > 0):
            raise FitError(f"PhysicsInverse: tol_m = {tol_m}, max_iter = {max_iter}, step_rad = "
                           f"{step_rad}: must be > 0, >= 1, > 0")
        stroke = model.params.stroke_rad if stroke_rad is None else stroke_rad
        lo, hi = (float(v) for v in np.asarray(stroke, dtype=float).reshape(2))
        if not lo < hi:
            raise FitError(f"PhysicsInverse: stroke_rad = {stroke!r} must be [low, high] rad")
        self.model, self.tol_m, self.max_iter, self.step_rad = model, tol_m, max_iter, step_rad
        self.stroke_rad = (lo, hi)
        self.n_evaluations = 0

    def predict(self, meas: Measurements, rows: np.ndarray, q: np.ndarray) -> np.ndarray:
        """The model's reading (len(rows), 3) m at motor coordinates q of ``rows``."""
        self.n_evaluations += 1
        return self.model.predict_path(with_motor_coordinates(meas, rows, q))[rows]

    def solve(self, meas: Measurements, target_m, rows=None, q0=None) -> InverseResult:
        """Motor coordinates for ``rows`` (default all rows of ``meas``; their conditions are
        the rows' times, temperatures and coil currents, their session zero the session's
        first row) at which the model reads ``target_m`` (len(rows), 3) m. ``q0``: start
        (default 0, the home pose)."""
        rows = np.arange(meas.n) if rows is None else np.asarray(rows, dtype=np.int64).reshape(-1)
        target = np.atleast_2d(np.asarray(target_m, dtype=np.float64))
        if target.shape != (rows.size, 3):
            raise FitError(f"PhysicsInverse.solve: {rows.size} row(s) but targets of shape "
                           f"{target.shape}; expected ({rows.size}, 3) m")
        lo, hi = self.stroke_rad
        n = rows.size
        q = np.zeros((n, 3)) if q0 is None else np.array(np.broadcast_to(q0, (n, 3)), float)
        q = np.clip(q, lo, hi)
        status = np.full(n, OUT_OF_REACH, dtype=object)
        resid = np.full(n, np.inf)
        iters = np.zeros(n, int)
        finite = np.all(np.isfinite(target), axis=1) & np.all(np.isfinite(q), axis=1)
        status[~finite] = NOT_FINITE
        active = np.flatnonzero(finite)
        h = self.step_rad
        for it in range(self.max_iter + 1):
            if active.size == 0:
                break
            r = self.predict(meas, rows[active], q[active]) - target[active]
            rmax = np.max(np.abs(r), axis=1)
            resid[active] = np.where(np.isfinite(rmax), rmax, np.inf)
            done = rmax <= self.tol_m
            status[active[done]] = CONVERGED
            bad = ~np.isfinite(rmax)
            status[active[bad]] = NOT_FINITE
            active, r = active[~done & ~bad], r[~done & ~bad]
            if it == self.max_iter or active.size == 0:
                break
            J = self._jacobian(meas, rows[active], q[active], h)
            with np.errstate(invalid="ignore", divide="ignore"):
                ok = np.abs(np.linalg.det(J)) > 0
            dq = np.zeros_like(r)
            dq[ok] = np.linalg.solve(J[ok], r[ok][..., None])[..., 0]
            stuck = ~ok | ~np.all(np.isfinite(dq), axis=1)
            active = active[~stuck]
            q[active] = np.clip(q[active] - dq[~stuck], lo, hi)
            iters[active] += 1
        return InverseResult(q=q, status=status.astype(str), residual_m=resid, iterations=iters,
                             stroke_rad=self.stroke_rad)

    def _jacobian(self, meas, rows, q, h):
        """d reading / d q (len(rows), 3, 3) by central differences inside the stroke (one-sided
        where q sits within h of a stroke end)."""
        lo, hi = self.stroke_rad
        J = np.zeros((rows.size, 3, 3))
        for j in range(3):
            up, dn = q.copy(), q.copy()
            up[:, j] = np.minimum(q[:, j] + h, hi)
            dn[:, j] = np.maximum(q[:, j] - h, lo)
            J[:, :, j] = ((self.predict(meas, rows, up) - self.predict(meas, rows, dn))
                          / (up[:, j] - dn[:, j])[:, None])
        return J
