"""The physics model inverted: target reading + measured conditions (temperatures, coil currents)
-> motor coordinates, vectorised over points, within the actuators' stroke.

The model (calibration/physics/model.py) predicts what the interferometers count from their
session's zero at given motor coordinates and conditions. ``PhysicsInverse.solve`` finds, for
every row of a ``Measurements`` it is asked about, the motor coordinates q at which that
prediction equals the target, by Newton-Raphson with the Jacobian d reading / d q taken by
central differences of the model itself: the value and the six displaced evaluations of every row
in one evaluation of the model (rows are independent), on those rows only (their conditions were
derived from the whole table before). Every iterate is held inside the stroke (projected
Newton): the model's kinematics refuse motor coordinates outside it, and the robot cannot go
there. A row is converged when
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
_NOT_PER_ROW = ("params", "home_p", "pose")     # Points fields shared by every row


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


def _take(value, idx, n_all):
    """``value`` (an array with a leading axis of every row and zero, a dict or tuple of them)
    at the rows ``idx``; anything else unchanged."""
    if isinstance(value, np.ndarray) and value.ndim and value.shape[0] == n_all:
        return value[idx]
    if isinstance(value, dict):
        return {k: _take(v, idx, n_all) for k, v in value.items()}
    if isinstance(value, tuple):
        return tuple(_take(v, idx, n_all) for v in value)
    return value


def rows_only(meas: Measurements, rows: np.ndarray) -> tuple[Measurements, np.ndarray]:
    """(the Measurements reduced to ``rows`` and the session zeros, the rows' new indices):
    the conditions were derived (smoothed, rates) from every row already, so evaluating the
    model needs only these; an inverse's cost then does not grow with the history."""
    rows = np.asarray(rows, dtype=np.int64)
    n, n_all = meas.n, meas.points.t_s.shape[0]
    keep = np.concatenate([rows, np.arange(n, n_all)])
    pts = dataclasses.replace(meas.points, pose=None, **{
        f.name: _take(getattr(meas.points, f.name), keep, n_all)
        for f in dataclasses.fields(meas.points) if f.name not in _NOT_PER_ROW})
    m = rows.size
    per_row = {f.name: getattr(meas, f.name)[rows] for f in dataclasses.fields(meas)
               if isinstance(getattr(meas, f.name), np.ndarray)
               and getattr(meas, f.name).shape[:1] == (n,)}     # readings, cosine terms, splits
    per_row.update(df=meas.df.iloc[rows], points=pts, zero_row=meas.zero_row[rows] - n + m,
                   sensor_node_T=_take(meas.sensor_node_T, keep, n_all), _statics=None)
    return dataclasses.replace(meas, **per_row), np.arange(m)


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
        sub, idx = rows_only(meas, rows)
        return self.model.predict_path(with_motor_coordinates(sub, idx, q))

    def _value_and_jacobian(self, meas, rows, q):
        """The readings (m, 3) at q and d reading / d q (m, 3, 3) by central differences
        inside the stroke (one-sided within h of a stroke end), in one evaluation of the model
        on the rows repeated seven times (q, q +- h e_j)."""
        lo, hi = self.stroke_rad
        h, m = self.step_rad, rows.size
        Q = [q]
        for j in range(3):
            up, dn = q.copy(), q.copy()
            up[:, j] = np.minimum(q[:, j] + h, hi)
            dn[:, j] = np.maximum(q[:, j] - h, lo)
            Q += [up, dn]
        A = self.predict(meas, np.tile(rows, 7), np.concatenate(Q)).reshape(7, m, 3)
        step = [Q[1 + 2 * j][:, j] - Q[2 + 2 * j][:, j] for j in range(3)]
        J = np.stack([(A[1 + 2 * j] - A[2 + 2 * j]) / step[j][:, None] for j in range(3)],
                     axis=-1)
        return A[0], J

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
        for it in range(self.max_iter + 1):
            if active.size == 0:
                break
            last = it == self.max_iter
            if last:
                f, J = self.predict(meas, rows[active], q[active]), None
            else:
                f, J = self._value_and_jacobian(meas, rows[active], q[active])
            r = f - target[active]
            rmax = np.max(np.abs(r), axis=1)
            resid[active] = np.where(np.isfinite(rmax), rmax, np.inf)
            done = rmax <= self.tol_m
            status[active[done]] = CONVERGED
            bad = ~np.isfinite(rmax)
            status[active[bad]] = NOT_FINITE
            go = ~done & ~bad
            active, r = active[go], r[go]
            if last or active.size == 0:
                break
            J = J[go]
            with np.errstate(invalid="ignore", divide="ignore"):
                ok = np.abs(np.linalg.det(J)) > 0
            dq = np.full_like(r, np.nan)
            dq[ok] = np.linalg.solve(J[ok], r[ok][..., None])[..., 0]
            stuck = ~np.all(np.isfinite(dq), axis=1)
            active, dq = active[~stuck], dq[~stuck]
            q[active] = np.clip(q[active] - dq, lo, hi)
            iters[active] += 1
        return InverseResult(q=q, status=status.astype(str), residual_m=resid, iterations=iters,
                             stroke_rad=self.stroke_rad)
