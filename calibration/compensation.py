"""Compensation in the loop: a fitted model turns a Cartesian target and the conditions read at
that moment (temperature scans, coil currents) into motor coordinates, as the papers' controller
did.

A target is an interferometer reading (m, per axis x, y, z) counted from the session's zero,
taken at home (q = 0) with the coils off at the start of the session. Each model kind is a
``Compensator``:

* ``nominal``: the robot's nominal kinematics (and nominal optics and statics), no effect, no
  condition: what the robot does uncompensated;
* ``stepwise``: the first paper's DGM inverted by Newton (blackbox/igm.py);
* ``direct_igm``: the second paper's direct IGM, q = f(X, Y, Z, F [, T]);
* ``physics``: a fitted physics model inverted (physics/inverse.py).

A black-box model predicts readings counted from its calibration session's zero; the zero of a
compensation session is taken in other conditions, so the model's own reading at that zero (home,
coils off, the zero's temperatures) is added to every target ("zero transfer"). The physics model
counts from the session's zero itself.

``ConditionLog`` keeps what the controller has read (the zero's scan, one scan per decision) and
gives it as dataset rows, so that every model derives its temperatures, rates and smoothing from
them exactly as from its calibration data. ``LoopController`` is what ``twin.campaign.
run_campaign`` calls at each point. Units: m, rad, s, N, A, degC in the temperature columns.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from deltatwin.calibration.blackbox.dgm import DGM
from deltatwin.calibration.blackbox.direct_igm import DirectIGM
from deltatwin.calibration.blackbox.igm import IGM
from deltatwin.calibration.blackbox.model_file import load_model
from deltatwin.calibration.blackbox.validation import evaluate
from deltatwin.calibration.errors import CalibrationInputError, ModelFileError
from deltatwin.calibration.metrics import error_figures
from deltatwin.calibration.physics.band import BAND_DRAWS, BAND_LEVEL, square_root
from deltatwin.calibration.physics.inverse import PhysicsInverse
from deltatwin.calibration.physics.measurements import TEMPERATURE_WINDOW_S, measurements
from deltatwin.calibration.physics.model import PhysicsModel, figures_nm, group_offsets, residuals
from deltatwin.calibration.physics.model_file import load_fitted, saved_uncertainty
from deltatwin.models.params import RobotParams, load_params
from deltatwin.twin.instruments.optics import AXES

SESSION = "compensation"
HISTORY_S = 900.0     # scans kept: longer than every model's smoothing / derivative window (600 s)


@dataclass
class Command:
    """One decision: motor coordinates (3,) rad, the solver's status and residual (m)."""
    q: np.ndarray
    status: str
    residual_m: float
    reason: str


class ConditionLog:
    """The session's zero scan and the scans read at each decision, as dataset rows."""

    def __init__(self, sensors, history_s: float = HISTORY_S,
                 zero_window_s: float = TEMPERATURE_WINDOW_S):
        self.sensors = tuple(sensors)
        self.history_s = float(history_s)
        self.zero_window_s = float(zero_window_s)
        self.zero_t_s = None
        self._zero_scan_t_s = None
        self._zero_T = None
        self._scans: dict[float, list] = {}

    def zero(self, t_s: float, T_C, scan_t_s: float | None = None) -> None:
        """A new session zero (the time it refers to, and its scan, read at ``scan_t_s``, by
        default ``t_s``): the history starts again. A zero averaged over home settles refers
        to their mean time, after the scan read when the interferometers were zeroed."""
        self.zero_t_s, self._zero_T, self._scans = float(t_s), list(T_C), {}
        self._zero_scan_t_s = self.zero_t_s if scan_t_s is None else float(scan_t_s)

    def add(self, t_s: float, T_C) -> None:
        """A scan completed at ``t_s`` (a scan read twice is kept once)."""
        self._scans[float(t_s)] = list(T_C)

    def zero_temperatures(self) -> np.ndarray:
        """The temperatures at the zero (degC per sensor): a straight line fitted to the zero's
        scan and those of the ``zero_window_s`` after it, at the zero's time. Every decision
        comes after that window (the controller's fill), so the whole window is known by then;
        one scan alone carries the thermometers' noise into every reading of the session (a
        frame hanging the robot from a 0.6 m aluminium arm reads 14 nm per mK along X)."""
        T0 = np.asarray(self._zero_T, dtype=np.float64)
        t0 = self._zero_scan_t_s
        after = sorted(t for t in self._scans if 0 < t - t0 <= self.zero_window_s)
        if not after or T0.size == 0:
            return T0
        dt = np.array([t0 - self.zero_t_s] + [t - self.zero_t_s for t in after])
        T = np.vstack([T0] + [self._scans[t] for t in after])
        line = np.linalg.lstsq(np.column_stack([np.ones_like(dt), dt]), T, rcond=None)[0]
        return line[0]

    @property
    def n_scans(self) -> int:
        """Scans recorded since the zero."""
        return len(self._scans)

    def frame(self, currents_A=None, force_N: float = 0.0, target_m=None) -> pd.DataFrame:
        """Rows in the dataset format: the zero (home, coils off), then the scans of the last
        ``history_s``; the last row carries the present currents, force and target (m)."""
        if self.zero_t_s is None:
            raise CalibrationInputError("ConditionLog: no session zero recorded yet")
        times = sorted(t for t in self._scans if t > self.zero_t_s)
        if times:
            times = [t for t in times if t >= times[-1] - self.history_s]
        t = np.array([self.zero_t_s] + times)
        T = np.array([self.zero_temperatures()] + [self._scans[x] for x in times],
                     dtype=np.float64)
        n = t.size
        df = pd.DataFrame({"t_s": t, "pos_id": np.arange(n), "split": "val", "session": SESSION,
                           "q1_rad": 0.0, "q2_rad": 0.0, "q3_rad": 0.0})
        target = np.full(3, np.nan) if target_m is None else np.asarray(target_m, float)
        for k, a in enumerate(AXES):
            col = np.full(n, np.nan)
            col[-1] = target[k] * 1e9
            df[f"{a}_nm"] = col
        for j, s in enumerate(self.sensors):
            df[f"T_{s}_C"] = T[:, j]
        I = np.zeros((n, 3))
        if currents_A is not None and n > 1:
            I[-1] = currents_A
        for i in range(3):
            df[f"coil{i + 1}_A"] = I[:, i]
        F = np.zeros(n)
        F[-1] = force_N if n > 1 else 0.0
        df["F_N"] = F
        df["cosine_corrected"] = False
        return df


class Compensator:
    """A model kind that commands the robot. ``zero(frame)`` at each session zero (a frame of
    the zero row only); ``command(target_m, frame)``: the motor coordinates for the last row."""
    kind = "?"
    model_path: str | None = None
    calibration_data: str | None = None      # the dataset a physics model file names
    covariance: np.ndarray | None = None     # a physics model file's parameter covariance (SI)

    def zero(self, frame: pd.DataFrame) -> None:
        """Nothing to transfer by default."""

    def command(self, target_m: np.ndarray, frame: pd.DataFrame) -> Command:
        raise NotImplementedError

    def predicted(self, df: pd.DataFrame, meta: dict | None) -> dict:
        """The model's validation figures per axis on its calibration data (nm), three ways:

        * ``err_p90``, ``err_1645sigma``: what a compensation can reach. A compensation counts
          every target from one zero reading at home, so its error is the model's error at the
          target minus its error at the zero: two draws of the validation error, the second
          one shared by the whole session. Predicted as the figures of e_i - e_j over pairs of
          validation rows of one session (``pairwise_differences``): each session's constant
          cancels, every row stands once for the zero.
        * ``fitted_err_p90``, ``fitted_err_1645sigma``: as the model's fit reports them (a
          constant per session fitted on the calibration rows, which no compensation can).
        * ``zero_err_p90``, ``zero_err_1645sigma``: referenced to the calibration session's own
          zero (one draw of the zero's error per session: paper-thermal has one session per
          axis)."""
        raise NotImplementedError

    def band(self, achieved: pd.DataFrame, rows: np.ndarray, zero_t_s: np.ndarray,
             cal_df: pd.DataFrame, cal_meta: dict | None, rng: np.random.Generator,
             zero_settles: int = 1, draws: int = BAND_DRAWS, level: float = BAND_LEVEL) -> dict:
        """{axis: (low, high) nm}: the band the achieved error 90 % over the compensated
        campaign's ``rows`` (of ``achieved``, its dataset: the conditions each target was
        commanded in; ``zero_t_s`` (N,) s: the time of each row's session zero) falls in with
        probability ``level`` if the model is right; {} for a model whose file holds no
        covariance. Two parts, drawn ``draws`` times with ``rng``:

        * the model's parameters' error, drawn from their covariance, moves each target by the
          model's sensitivity there, in those conditions (the temperatures of hours later: the
          extrapolation in time), counted from the session's zero (``_parameter_change``);
        * the model's own error (noise and misfit) at a target counted from its zero: the
          difference of two of the model's validation errors on its calibration data
          ``cal_df`` as far apart in time, in one session, as the target is from its zero
          (``time_matched_differences``): a model's misfit drifts, so a target minutes after
          its zero differs from it by less than two validation rows hours apart; the zero is
          the mean of ``zero_settles`` home settles, its fast part (the readings' noise)
          averaged."""
        change = self._parameter_change(achieved, rows, rng, draws)
        if change is None:
            return {}
        err, group, val = self._validation_errors(cal_df, cal_meta)
        t_cal = cal_df["t_s"].to_numpy(dtype=float)
        gap = (achieved["t_s"].to_numpy(dtype=float) - np.asarray(zero_t_s, float))[rows]
        out = {}
        for k, a in enumerate(AXES):
            column = f"{a}_nm"
            if (column not in achieved
                    or not np.isfinite(achieved[column].to_numpy(dtype=float)[rows]).any()):
                continue
            own = time_matched_differences(err[val, k], group[val, k], t_cal[val], gap, rng,
                                           draws, zero_settles)
            if own is None:
                continue
            p90 = np.quantile(np.abs(change[:, k] + own), 0.9, axis=0) * 1e9
            q = np.quantile(p90, ((1 - level) / 2, 1 - (1 - level) / 2))
            out[a] = (float(q[0]), float(q[1]))
        return out

    def _parameter_change(self, achieved: pd.DataFrame, rows: np.ndarray,
                          rng: np.random.Generator, draws: int) -> np.ndarray | None:
        """(rows, 3, draws) m: each target's reading moved by a draw of the parameters' error
        (counted from its session's zero); None without a covariance."""
        return None

    def _validation_errors(self, df: pd.DataFrame, meta: dict | None):
        """((N, 3) m, (N, 3) int, (N,) bool): the model's error at each row of its calibration
        data, each reading's (session, axis) group (-1: none) and the validation rows."""
        raise NotImplementedError

    def _zero_referenced(self, df, errors) -> dict:
        """{axis: figures} of ``errors(session rows, zero frame)`` ((rows, 3) m) over the
        validation rows of each session, referenced to the session's zero, and of their
        differences within each session (``pairwise``)."""
        err = np.full((len(df), 3), np.nan)
        session = df["session"].astype(str).to_numpy()
        t = df["t_s"].to_numpy(dtype=np.float64)
        for s in dict.fromkeys(session):
            idx = np.flatnonzero(session == s)
            first = idx[np.argmin(t[idx])]
            self.zero(df.iloc[[first]])
            err[idx] = errors(df.iloc[idx])
        val = (df["split"].astype(str) == "val").to_numpy()
        codes = pd.factorize(session)[0]
        return {a: {"zero": error_figures(err[val, k]),
                    "pairwise": error_figures(pairwise_differences(err[val, k], codes[val]))}
                for k, a in enumerate(AXES)}


PAIR_SHIFTS = 64   # partners per row in ``pairwise_differences``


def pairwise_differences(err: np.ndarray, group: np.ndarray, shifts: int = PAIR_SHIFTS):
    """Differences e_i - e_j (m) of errors ``err`` (n,) between rows of the same ``group``
    (n,) (NaN rows left out): all ordered pairs of a group of up to ``shifts`` + 1 rows, else
    each row against the rows ``k * n_g // (shifts + 1)`` places on (k = 1..``shifts``, cyclic,
    in the rows' order): partners spread evenly over the whole session, deterministic."""
    out = []
    for g in np.unique(group):
        e = err[group == g]
        e = e[np.isfinite(e)]
        n = e.size
        if n < 2:
            continue
        ks = np.arange(1, n) if n <= shifts + 1 else \
            np.unique(np.arange(1, shifts + 1) * n // (shifts + 1))
        out.append((e[:, None] - e[(np.arange(n)[:, None] + ks[None]) % n]).ravel())
    return np.concatenate(out) if out else np.zeros(0)


ZERO_SMOOTHING_ROWS = 5    # the rows a zero's slow error is taken over (its fast part the rest)


def time_matched_differences(err: np.ndarray, group: np.ndarray, t_s: np.ndarray,
                             gap_s: np.ndarray, rng: np.random.Generator, draws: int,
                             zero_settles: int = 1):
    """(len(gap_s), draws) m: for each gap (s) and draw, e_i - z_j of errors ``err`` (n,)
    (NaN: none) of one ``group`` (n,; < 0: none) taken at ``t_s`` (n,): i drawn uniformly,
    j the row of i's group nearest to t_i - gap (t_i + gap where that is before the group's
    first row; where that is past its last row too, the end farther from t_i). z_j is e_j as
    a zero averaged over ``zero_settles`` readings sees it: its slow part (the mean of the
    ZERO_SMOOTHING_ROWS rows about j) as it is, its fast part (the rest: the readings' noise)
    over sqrt(``zero_settles``). None with no group of two rows."""
    ok = np.isfinite(err) & (group >= 0)
    groups = [g for g in np.unique(group[ok]) if np.sum(ok & (group == g)) > 1]
    if not groups:
        return None
    parts = [np.flatnonzero(ok & (group == g)) for g in groups]
    parts = [p[np.argsort(t_s[p], kind="stable")] for p in parts]
    sizes = np.array([p.size for p in parts])
    pick = rng.integers(0, sizes.sum(), (gap_s.size, draws))
    which = np.searchsorted(np.cumsum(sizes), pick, side="right")
    out = np.empty(pick.shape)
    zero = err.copy()
    for rows in parts:
        slow = pd.Series(err[rows]).rolling(ZERO_SMOOTHING_ROWS, center=True,
                                             min_periods=1).mean().to_numpy()
        zero[rows] = slow + (err[rows] - slow) / np.sqrt(zero_settles)
    for g, rows in enumerate(parts):
        mine = which == g
        i = rows[pick[mine] - (sizes[:g].sum())]
        gap = np.broadcast_to(gap_s[:, None], pick.shape)[mine]
        times = t_s[rows]
        when = np.where(t_s[i] - gap >= times[0], t_s[i] - gap, t_s[i] + gap)
        farther = np.where(t_s[i] - times[0] >= times[-1] - t_s[i], times[0], times[-1])
        when = np.where(when > times[-1], farther, when)
        at = np.clip(np.searchsorted(times, when), 1, rows.size - 1)
        nearer = np.where(when - times[at - 1] <= times[at] - when, at - 1, at)
        out[mine] = err[i] - zero[rows[nearer]]
    return out


def _by_session(df: pd.DataFrame, err: np.ndarray):
    """(``err`` (N, 3) m, (N, 3) its (session, axis) group: the session's code, -1 where the
    error is not finite, (N,) the validation rows): a black box's ``_validation_errors``."""
    codes = pd.factorize(df["session"].astype(str))[0]
    group = np.where(np.isfinite(err), codes[:, None], -1)
    return err, group, (df["split"].astype(str) == "val").to_numpy()


def _figures(fitted: dict, zero: dict | None = None, pairwise: dict | None = None) -> dict:
    """The three predictions (see ``Compensator.predicted``) of one axis, nm."""
    main = pairwise if pairwise is not None else fitted
    out = {"err_p90": main.get("err_p90"), "err_1645sigma": main.get("err_1645sigma"),
           "n": main.get("n"), "fitted_err_p90": fitted.get("err_p90"),
           "fitted_err_1645sigma": fitted.get("err_1645sigma")}
    if zero is not None:
        out.update(zero_err_p90=zero.get("err_p90"), zero_err_1645sigma=zero.get("err_1645sigma"))
    return out


class PhysicsCompensator(Compensator):
    """A physics model inverted (target + temperatures + currents -> q)."""
    kind = "physics"

    def __init__(self, model: PhysicsModel, sensors: dict, q0=None, known: dict | None = None,
                 **inverse_kw):
        self.model = model
        self.sensors = dict(sensors)
        # the laboratory's constants the model was fitted with (its file's [known]: the set
        # point of held supports)
        self.known = dict(known or {})
        self.inverse = PhysicsInverse(model, **inverse_kw)

    def measurements(self, frame: pd.DataFrame):
        return measurements(frame, {"sensors": self.sensors, "setup": {"known": self.known}},
                            self.model.params, where="compensation conditions")

    def command(self, target_m, frame, q0=None) -> Command:
        meas = self.measurements(frame)
        r = self.inverse.solve(meas, np.asarray(target_m, float)[None], [meas.n - 1], q0=q0)
        return Command(r.q[0], str(r.status[0]), float(r.residual_m[0]), r.reason(0))

    def forward(self, q: np.ndarray, frame: pd.DataFrame) -> np.ndarray:
        """Readings (n, 3) m the model predicts at motor coordinates q (n, 3) in the conditions
        of the frame's last row."""
        q = np.atleast_2d(q)
        rows = pd.concat([frame] + [frame.iloc[[-1]]] * (q.shape[0] - 1), ignore_index=True)
        rows["pos_id"] = np.arange(len(rows))
        meas = self.measurements(rows)
        idx = np.arange(len(frame) - 1, len(rows))
        return self.inverse.predict(meas, idx, q)

    def predicted(self, df, meta):
        meas, res = self._calibration_errors(df, meta)
        pred = meas.y - res
        fig = figures_nm(residuals(meas, pred, group_offsets(meas, pred, meas.cal)), meas.val)
        zero = figures_nm(res, meas.val)
        return {a: _figures(fig[a], zero[a], error_figures(pairwise_differences(
                    res[meas.val, k], meas.group[meas.val, k])))
                for k, a in enumerate(AXES) if a in fig}

    def _calibration_errors(self, df, meta):
        """(measurements, (N,3) m): the model's error at each row of its calibration data,
        referenced to each session's zero (no constant fitted)."""
        meas = measurements(df, meta, self.model.params, where="calibration data")
        pred = self.model.predict_path(meas)
        return meas, residuals(meas, pred, np.zeros(len(meas.groups)))

    def _parameter_change(self, achieved, rows, rng, draws):
        """The parameters' error drawn from the model file's ``covariance`` (p, p; SI) through
        the model's Jacobian in each target's conditions (its reading is counted from the
        session's zero)."""
        if self.covariance is None:
            return None
        meas = self.measurements(achieved)
        J = np.nan_to_num(self.model.jacobian(meas, self.model.theta())[1][rows])
        return J @ square_root(self.covariance) @ rng.standard_normal((J.shape[2], draws))

    def _validation_errors(self, df, meta):
        meas, res = self._calibration_errors(df, meta)
        return res, meas.group, meas.val


class NominalCompensator(PhysicsCompensator):
    """The nominal robot (no effect: nominal kinematics, statics and optics): uncompensated."""
    kind = "nominal"

    def __init__(self, params: RobotParams | None = None, **inverse_kw):
        super().__init__(PhysicsModel([], params), {}, **inverse_kw)

    def predicted(self, df, meta):
        return None


class StepwiseCompensator(Compensator):
    """The first paper's stepwise DGM, inverted by Newton within the stroke."""
    kind = "stepwise"

    def __init__(self, dgm: DGM, stroke_rad=None):
        self.dgm = dgm
        self.igm = IGM(dgm, stroke_rad=stroke_rad)
        self.order = [dgm.output_names_.index(a) for a in AXES]
        self.zero_reading_m = None

    def _zero_values(self, frame: pd.DataFrame) -> dict:
        """The DGM's variables at the zero: home (q = 0) in the conditions of the frame's
        first row."""
        v = self.dgm.variables(frame.iloc[[0]])
        v.update(q1=np.zeros(1), q2=np.zeros(1), q3=np.zeros(1))
        return v

    def zero(self, frame):
        self.zero_reading_m = self.dgm.predict_values(self._zero_values(frame))[0, self.order]

    def _parameter_change(self, achieved, rows, rng, draws):
        """Each axis's kept coefficients' error, drawn from their covariance (the model file's:
        ``deltatwin calibrate`` keeps it), through the terms at the target less the terms at
        its session's zero (the first row's conditions, home: as ``zero`` takes it)."""
        outputs = [self.dgm.output(a) for a in AXES if a in self.dgm.output_names_]
        if any(o.covariance is None for o in outputs):
            return None
        # one draw of the model's error for every session: the same model commands them all
        drawn = [square_root(o.covariance) @ rng.standard_normal((len(o.terms), draws))
                 for o in outputs]
        at = [o.term_matrix(self.dgm.variables(achieved))[rows] for o in outputs]
        session = achieved["session"].astype(str).to_numpy()
        change = np.zeros((int(rows.sum()), 3, draws))
        for s in dict.fromkeys(session[rows]):
            zero = self._zero_values(achieved.iloc[[np.flatnonzero(session == s)[0]]])
            mine = (session == s)[rows]
            for o, X, xi in zip(outputs, at, drawn):
                change[mine, AXES.index(o.output)] = (X[mine] - o.term_matrix(zero)) @ xi
        return change

    def _validation_errors(self, df, meta):
        return _by_session(df, self.dgm.errors_m(df)[:, self.order])

    def command(self, target_m, frame) -> Command:
        v = self.dgm.variables(frame)
        aux = {k: v[k][-1:] for k in self.igm.aux_variables}
        r = self.igm.solve((np.asarray(target_m, float) + self.zero_reading_m)[None], aux)
        return Command(r.q[0], str(r.status[0]), float(r.residual_m[0]), r.reason(0))

    def predicted(self, df, meta):
        ev = evaluate(self.dgm, df)["outputs"]
        reading = self.dgm.targets(df)[:, self.order]

        def errors(rows):
            return (self.dgm.predict(rows)[:, self.order] - self.zero_reading_m
                    - reading[rows.index.to_numpy()])
        zero = self._zero_referenced(df.reset_index(drop=True), errors)
        return {a: _figures(ev[a]["val"], zero[a]["zero"], zero[a]["pairwise"])
                for a in AXES if a in ev}


class DirectIGMCompensator(Compensator):
    """The second paper's direct IGM, q = f(X, Y, Z, F [, T]): evaluated, not solved; the zero
    transfer solves f(X0, F = 0, T_zero) = 0 for X0 by Newton on the model's Jacobian."""
    kind = "direct_igm"

    def __init__(self, model: DirectIGM, stroke_rad=None, tol_m: float = 1e-12,
                 max_iter: int = 30):
        if model.output_names_ != ["q1", "q2", "q3"]:
            raise ModelFileError(f"a direct IGM commands q1, q2, q3; this one has outputs "
                                 f"{model.output_names_}")
        self.model = model
        lo, hi = load_params(None).stroke_rad if stroke_rad is None else stroke_rad
        self.stroke_rad = (float(lo), float(hi))
        self.tol_m, self.max_iter = tol_m, max_iter
        self.zero_reading_m = None

    def zero(self, frame):
        self.zero_reading_m = self._home_reading(frame)

    def _home_reading(self, frame: pd.DataFrame) -> np.ndarray:
        """(3,) m: where the model puts home (q = 0, no force) in the conditions of the
        frame's first row, by Newton on its Jacobian."""
        v = self.model.variables(frame.iloc[[0]].assign(x_nm=0.0, y_nm=0.0, z_nm=0.0, F_N=0.0))
        X = np.zeros(3)
        for _ in range(self.max_iter):
            v.update(X=X[0:1], Y=X[1:2], Z=X[2:3])
            q = self.model.predict_values(v)[0]
            J = self.model.jacobian(v)[0]                       # dq/dX (3, 3) rad/m
            if not (np.all(np.isfinite(J)) and abs(np.linalg.det(J)) > 0):
                raise CalibrationInputError("direct IGM: its Jacobian dq/dX is singular at "
                                            f"X = {X.tolist()} m: the home reading at the zero "
                                            "cannot be found")
            dX = np.linalg.solve(J, q)
            X = X - dX
            if np.max(np.abs(dX)) <= self.tol_m:
                break
        else:
            raise CalibrationInputError(f"direct IGM: the home reading at the zero did not "
                                        f"converge (last step {np.max(np.abs(dX)):.3g} m)")
        return X

    def command(self, target_m, frame) -> Command:
        X = np.asarray(target_m, float) + self.zero_reading_m
        f = frame.copy()
        for k, a in enumerate(AXES):
            f.loc[f.index[-1], f"{a}_nm"] = X[k] * 1e9
        v = self.model.variables(f)
        q = self.model.predict_values({k: a[-1:] for k, a in v.items()})[0]
        lo, hi = self.stroke_rad
        if not np.all(np.isfinite(q)):
            return Command(np.zeros(3), "not_finite", math.inf, "not finite: the model gave "
                           f"q = {q.tolist()} rad")
        if np.any((q < lo) | (q > hi)):
            return Command(np.clip(q, lo, hi), "out_of_stroke", math.nan,
                           f"out of stroke: the model asks q = {q.tolist()} rad, outside "
                           f"[{lo}, {hi}] rad; commanded the nearest stroke end")
        return Command(q, "converged", 0.0, "evaluated: q = f(X, Y, Z, F)")

    def _parameter_change(self, achieved, rows, rng, draws):
        """The motors' models' coefficients' error, drawn from their covariance (the file's),
        as a position: the robot goes where the true q = f(X) equals the commanded f^(X_t),
        so a target moves by J^-1 df there, and the zero's transfer by J^-1 df at home (J =
        dq/dX, df the drawn error of the motors' q at X); a reading counts the difference."""
        outputs = self.model.outputs_
        if any(o.covariance is None for o in outputs):
            return None
        session = achieved["session"].astype(str).to_numpy()
        target = np.column_stack([achieved[f"target_{a}_nm"].to_numpy(dtype=float) * 1e-9
                                  for a in AXES])
        xi = [square_root(o.covariance) @ rng.standard_normal((len(o.terms), draws))
              for o in outputs]
        change = np.zeros((int(rows.sum()), 3, draws))
        for s in dict.fromkeys(session[rows]):
            first = np.flatnonzero(session == s)[0]
            X0 = self._home_reading(achieved.iloc[[first]])
            home = self.model.variables(achieved.iloc[[first]].assign(F_N=0.0, **{
                f"{a}_nm": X0[k] * 1e9 for k, a in enumerate(AXES)}))
            at = self.model.variables(achieved.assign(**{
                f"{a}_nm": (target[:, k] + X0[k]) * 1e9 for k, a in enumerate(AXES)}))
            mine = (session == s)[rows]
            change[mine] = (self._moved(at, xi)[rows][mine]
                            - self._moved(home, xi)[0][None])
        return change

    def _moved(self, values: dict, xi: list) -> np.ndarray:
        """(n, 3, draws) m: J^-1 df at each point of ``values``, df the motors' q error of
        the drawn coefficient errors ``xi`` (one (k, draws) per motor)."""
        dq = np.stack([o.term_matrix(values) @ x for o, x in zip(self.model.outputs_, xi)],
                      axis=1)                                             # (n, 3, draws)
        return np.linalg.solve(self.model.jacobian(values), dq)

    def _validation_errors(self, df, meta):
        v = self.model.variables(df)
        dq = self.model.predict_values(v) - self.model.targets(df)
        err = np.linalg.solve(self.model.jacobian(v), dq[:, :, None])[:, :, 0]
        reading = np.column_stack([df[f"{a}_nm"].to_numpy(dtype=float) for a in AXES])
        return _by_session(df, np.where(np.isfinite(reading), err, np.nan))

    def predicted(self, df, meta):
        ev = evaluate(self.model, df).get("position") or {}
        q_meas = self.model.targets(df)

        def errors(rows):
            shifted = rows.assign(**{f"{a}_nm": rows[f"{a}_nm"] + self.zero_reading_m[k] * 1e9
                                     for k, a in enumerate(AXES)})
            v = self.model.variables(shifted)
            dq = self.model.predict_values(v) - q_meas[rows.index.to_numpy()]
            return np.linalg.solve(self.model.jacobian(v), dq[:, :, None])[:, :, 0]
        zero = self._zero_referenced(df.reset_index(drop=True), errors)
        return {a: _figures(ev[a]["val"], zero[a]["zero"], zero[a]["pairwise"])
                for a in AXES if a in ev}


def load_compensator(path, trust_effects=False) -> Compensator:
    """The compensator of a model file: a fitted physics model (TOML, ``deltatwin fit -o``)
    or a black-box model (JSON, ``deltatwin calibrate -o``: a DGM or a direct IGM). The user
    effects a physics model names run only with ``trust_effects`` (``load_fitted``)."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such model file")
    if path.suffix.lower() == ".toml":
        model, doc = load_fitted(path, trust_effects)
        comp = PhysicsCompensator(model, doc["model"].get("sensors") or {},
                                  known=doc.get("known", {}))
        comp.covariance = saved_uncertainty(doc, model)[1]
        comp.calibration_data = doc["model"].get("data")
    else:
        m = load_model(path)
        comp = StepwiseCompensator(m) if isinstance(m, DGM) else DirectIGMCompensator(m)
    comp.model_path = str(path)
    return comp


class LoopController:
    """What ``run_campaign`` calls at each point: reads the scan (and the coil currents), lets
    the point's compensator decide, returns the motor coordinates and a record of what it read.

    ``compensators``: {mode: Compensator}; ``modes`` (n,), ``targets_m`` (n, 3) per plan point;
    ``force_per_A``: the force simulator's nominal N/A (the force a direct IGM is given).

    After each zero, before its first decision, the controller lets its temperature loop run
    for ``fill_s`` (a scan every ``scan_period_s``, the robot at home): the models' temperature
    rates and smoothing need that history (with two or three scans a second derivative of mK
    noise over 10 s is ~1e-5 K/s^2, and a DGM's d2T terms then move the target by micrometres)."""

    def __init__(self, compensators: dict, modes, targets_m, sensors, force_per_A: float = 1.0,
                 fill_s: float = 600.0, scan_period_s: float = 10.0):
        self.compensators = compensators
        self.modes = list(modes)
        self.targets = np.asarray(targets_m, dtype=np.float64)
        self.log = ConditionLog(sensors)
        self.force_per_A = float(force_per_A)
        self.fill_s, self.scan_period_s = float(fill_s), float(scan_period_s)
        self.latency_s: dict[str, list] = {m: [] for m in compensators}
        self._nominal_q = {}
        self._transferred = False

    def _zero(self, zero: dict) -> None:
        if self.log.zero_t_s != zero["zero_t_s"]:
            self.log.zero(zero["zero_t_s"], zero["zero_T_C"], zero.get("zero_scan_t_s"))
            self._transferred = False

    def _transfer_zero(self) -> None:
        """Each compensator's zero transfer, once per zero, at its first decision: after the
        fill, when the zero's temperatures are known from the window after it."""
        if not self._transferred:
            frame = self.log.frame()
            for c in self.compensators.values():
                c.zero(frame.iloc[[0]])
            self._transferred = True

    def _scan(self, inst) -> tuple[float, list]:
        scan = inst.thermometers.scan()
        T = [scan.temperatures_C[s] for s in self.log.sensors]
        self.log.add(scan.t_s, T)
        return scan.t_s, T

    def command(self, k, inst, zero):
        self._zero(zero)
        history = []
        if self.log.n_scans == 0:                # a new zero: fill the temperature history
            for _ in range(int(math.ceil(self.fill_s / self.scan_period_s))):
                inst.clock.sleep(self.scan_period_s)
                history.append(self._scan(inst))
        scan_t, T = self._scan(inst)
        self._transfer_zero()
        I = inst.coils.read_currents() if inst.coils is not None else np.zeros(3)
        F = float(np.mean(I)) * self.force_per_A
        frame = self.log.frame(I, F, self.targets[k])
        comp = self.compensators[self.modes[k]]
        t0 = time.perf_counter()
        kw = {}
        if isinstance(comp, PhysicsCompensator) and k in self._nominal_q:
            kw["q0"] = self._nominal_q[k]          # start where the nominal robot went
        cmd = comp.command(self.targets[k], frame, **kw)
        self.latency_s[self.modes[k]].append(time.perf_counter() - t0)
        if self.modes[k] == "nominal":
            for j in range(k + 1, min(k + 3, len(self.modes))):
                self._nominal_q[j] = cmd.q
        record = {"scan_t_s": scan_t, "T_C": T, "currents_A": np.asarray(I, float),
                  "force_N": F, "mode": self.modes[k], "status": cmd.status,
                  "residual_m": cmd.residual_m, "reason": cmd.reason, "history": history}
        return cmd.q, record

    def replayed(self, k, point):
        self._zero(point)
        c = point["control"]
        for t, T in c["history"]:
            self.log.add(t, T)
        self.log.add(c["scan_t_s"], c["T_C"])
        if c["mode"] == "nominal":
            for j in range(k + 1, min(k + 3, len(self.modes))):
                self._nominal_q[j] = np.asarray(point["q_cmd_rad"], float)


def achieved_figures(errors_m: np.ndarray, ok: np.ndarray) -> dict:
    """Per axis error figures (nm) of reading - target over the rows ``ok``."""
    return {a: error_figures(errors_m[ok, k]) for k, a in enumerate(AXES)
            if np.isfinite(errors_m[ok, k]).any()}
