"""Which recorded variable a model's residual depends on, when no library effect explains it.

The variables are the ones a laboratory thinks in (``laboratory_variables``): time, each
temperature and its rate, the motor coordinates, the Cartesian position, the force and the coil
currents, the autocollimators' rotations, the direction of each motor's last move, the session.
Each variable has a few *terms* (``variable_terms``): the first, second and third power of the
standardised variable, each a term of its own; for a coordinate or time also the sine and cosine
at the peak of the residual's periodogram against it (``scipy.signal.lombscargle``: irregular
sampling), and for time the best single step (an event: a mirror knocked, a laser relocked); for
the session a per-session drift in time (its offset is the session's zero, already removed); on
a physics model the force also has the model's own response to a load growing with the coils'
current (model_form.py). A term joins on its own: a step in time is not dragged down by a cubic
that extrapolates wildly into a validation period that follows the calibration in time.

Attribution is joint, by validation: forward selection over the terms fits the residual on the
calibration rows (each session-axis zero re-estimated there, as in the fit; on a physics model
with the model's own identified directions re-adjusted too, model_form.py: a term the fitted
parameters partly absorbed is judged with them free, as the researcher's effect will be) and
keeps adding the term that lowers the *validation* residual power most, while the addition is
significant on the calibration rows (partial F test, the scanned period or step time counted as
a parameter, Bonferroni over the terms tried) and explains at least ``MIN_SHARE`` of the
validation residual power. The autocollimators' rotations are readings of the platform's
response, like the residual itself: a tilt follows whatever disturbs the platform (a force, a
motor's backlash), so a rotation's term is tried only once no term of the variables the
laboratory sets or records as conditions qualifies. Each selected variable is then credited
with what it explains beyond the others: the validation power that returns when its terms
alone are dropped from the joint fit (a condition's beyond the other conditions, a rotation's
beyond every term: a rotation that reads the tilt a force makes takes no credit from the
force). This is what ranks a large, non-polynomial perturbation
(a periodic encoder error) above a small smooth one a cubic fits well, and what keeps time from
being credited with a temperature's work (or the reverse) when the room climbs and both rise
together.

Units: residuals in m inside, reported in nm (``explained_nm``: the rms over the validation
readings of the part the variable alone explains).
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import numpy as np
import pandas as pd
from scipy import optimize, special

from deltatwin.calibration.blackbox.features import causal_derivatives
from deltatwin.calibration.physics.measurements import move_directions
from deltatwin.calibration.stats import ALPHA
from deltatwin.models.geometry import build_geometry
from deltatwin.models.kinematics import KinematicsError, forward
from deltatwin.models.params import load_params
from deltatwin.twin.instruments.optics import AC_CHANNELS, AXES

log = logging.getLogger(__name__)

# an added family is significant at the rule's alpha (before Bonferroni) and explains at least
# this share of the validation power (the missing term's form, term_form.py, selects so too)
MIN_SHARE = 0.02
MAX_TERMS = 8
OVERSAMPLING = 3      # periodogram frequencies per 1 / range
SCANNED = {"sine": 1, "step": 1}   # parameters chosen by a scan (period, step time)


@dataclass(frozen=True)
class Variable:
    """A recorded or derived variable: ``values`` (N,) in SI, ``kind`` decides its family."""
    name: str
    values: np.ndarray
    kind: str        # "time", "coordinate", "smooth", "sign", "session"
    response: bool = False   # a reading of the platform's response (a rotation), not a condition


def _rates(t: np.ndarray, session: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Causal rate (unit/s) of every column of ``v`` (N,c) within each session, rows in any
    order (the columns in one call per session: the windows are found once)."""
    out = np.empty_like(v)
    for s in dict.fromkeys(session):
        rows = np.flatnonzero(session == s)
        rows = rows[np.argsort(t[rows], kind="stable")]
        out[rows] = causal_derivatives(t[rows], v[rows], degree=1)[0]
    return out


def laboratory_variables(df: pd.DataFrame) -> list[Variable]:
    """The variables a residual can depend on, named by their column (rates
    ``dT_<sensor>_dt_K_per_s``; ``x_m``, ``y_m``, ``z_m``: the nominal robot's forward
    kinematics of the motor coordinates; ``dir_q<i>``: sign of motor i's last move)."""
    t = df["t_s"].to_numpy(dtype=np.float64)
    session = df["session"].astype(str).to_numpy() if "session" in df else np.full(len(df), "1")
    out = [Variable("t_s", t, "time")]
    temperatures = [c for c in df.columns if c.startswith("T_") and c.endswith("_C")]
    T = df[temperatures].to_numpy(dtype=np.float64) if temperatures else np.zeros((len(df), 0))
    rates = _rates(t, session, T)
    for k, c in enumerate(temperatures):
        out.append(Variable(c, T[:, k], "smooth"))
        out.append(Variable(f"dT_{c[2:-2]}_dt_K_per_s", rates[:, k], "smooth"))
    if all(f"q{i}_rad" in df for i in (1, 2, 3)):
        q = df[["q1_rad", "q2_rad", "q3_rad"]].to_numpy(dtype=np.float64)
        out += [Variable(f"q{i + 1}_rad", q[:, i], "coordinate") for i in range(3)]
        ok = np.all(np.isfinite(q), axis=1)
        qu, inv = np.unique(q[ok], axis=0, return_inverse=True)
        try:
            p = np.full((len(df), 3), np.nan)
            p[ok] = forward(build_geometry(load_params(None)), qu).p[inv.reshape(-1)]
            out += [Variable(f"{a}_m", p[:, k], "coordinate") for k, a in enumerate(AXES)]
        except KinematicsError as exc:     # not this robot's coordinates: no Cartesian position
            log.warning("attribution without the Cartesian position: %s", exc)
        if ok.all():
            rows, _ = move_directions(t, q, session)
            out += [Variable(f"dir_q{i + 1}", rows[:, i], "sign") for i in range(3)]
    for c in ("F_N", "coil1_A", "coil2_A", "coil3_A"):
        if c in df:
            out.append(Variable(c, df[c].to_numpy(dtype=np.float64), "smooth"))
    for c in (f"{a}_arcsec" for a in AC_CHANNELS):
        if c in df:
            out.append(Variable(c, df[c].to_numpy(dtype=np.float64), "smooth", response=True))
    if len(set(session)) > 1:
        out.append(Variable("session", session, "session"))
    return _distinct([v for v in out if v.kind == "session" or np.nanstd(v.values) > 0])


def _distinct(variables: list[Variable]) -> list[Variable]:
    """The variables without those that carry the same information as an earlier one (an
    affine function of it: the coil currents of a campaign that sets F = k I on all coils are
    the force)."""
    out, seen = [], []
    for v in variables:
        if v.kind != "session":
            x = np.where(np.isfinite(v.values), v.values, 0.0)
            z = (x - x.mean()) / x.std()
            if any(abs(float(z @ w)) / z.size > 1 - 1e-9 for w in seen):
                continue
            seen.append(z)
        out.append(v)
    return out


class Residual:
    """A residual (N,3) prepared for regression: per axis the rows with a reading, the
    calibration / validation masks, and each (session, axis) zero removed with its
    calibration-row mean (the same zeros a fit re-estimates)."""

    def __init__(self, res: np.ndarray, cal: np.ndarray, val: np.ndarray, session: np.ndarray,
                 time_s: np.ndarray):
        self.res, self.cal, self.val, self.session, self.time = res, cal, val, session, time_s
        self.scans: dict = {}     # variable -> scanned period / step moment (shared by users)
        self.axes = []
        for k in range(res.shape[1]):
            rows = np.isfinite(res[:, k])
            if (rows & cal).sum() < 20 or (rows & val).sum() < 5:
                continue
            groups = session[rows]
            means = {g: float(np.mean(res[rows & cal & (session == g), k]))
                     if np.any(rows & cal & (session == g)) else 0.0 for g in set(groups)}
            r = res[rows, k] - np.array([means[g] for g in groups])
            self.axes.append((k, rows, r))

    @classmethod
    def of(cls, df: pd.DataFrame, res: np.ndarray, cal: np.ndarray, val: np.ndarray) -> Residual:
        """The residual ``res`` (N,3) m of the rows of ``df`` (its sessions and times)."""
        session = (df["session"].astype(str).to_numpy() if "session" in df
                   else np.full(len(df), "1"))
        return cls(res, np.asarray(cal, bool), np.asarray(val, bool), session,
                   df["t_s"].to_numpy(dtype=np.float64))

    def only(self, k: int) -> Residual:
        """The same residual restricted to axis ``k``."""
        out = object.__new__(Residual)
        out.__dict__.update(self.__dict__)
        out.axes = [a for a in self.axes if a[0] == k]
        return out

    def demeaned(self, X: np.ndarray, rows: np.ndarray) -> np.ndarray:
        """Columns X (N,p) on ``rows`` minus their calibration mean within each session."""
        Xr = X[rows]
        s, c = self.session[rows], self.cal[rows]
        for g in set(s):
            m = s == g
            # the sessions' rows are disjoint: this one's are still as in X
            Xr[m] -= Xr[m & c].mean(axis=0) if np.any(m & c) else 0.0
        return Xr

    def fit(self, X: np.ndarray):
        """Least squares of every axis on columns X (N,p) over the calibration rows: per axis
        (axis, rows, coefficients, fitted (rows,), residual (rows,)); and totals
        {rss_cal, n_cal, val_power, rank}."""
        per_axis, rss, n_cal, val_power, rank = [], 0.0, 0, 0.0, 0
        for k, rows, r in self.axes:
            Xd = self.demeaned(X, rows) if X.shape[1] else np.zeros((rows.sum(), 0))
            c = self.cal[rows]
            if Xd.shape[1]:
                scale = np.std(Xd[c], axis=0)
                scale[scale == 0] = 1.0
                coef, _, rk, _ = np.linalg.lstsq(Xd[c] / scale, r[c], rcond=None)
                coef = coef / scale
            else:
                coef, rk = np.zeros(0), 0
            fitted = Xd @ coef
            e = r - fitted
            rss += float(e[c] @ e[c])
            n_cal += int(c.sum())
            val_power += float(np.sum(e[self.val[rows]] ** 2))
            rank += int(rk)
            per_axis.append((k, rows, coef, fitted, e))
        return per_axis, {"rss_cal": rss, "n_cal": n_cal, "val_power": val_power, "rank": rank}

    def rss_each(self, X: np.ndarray) -> np.ndarray:
        """The calibration sum of squares (every axis) after each column of X (N,c) fitted
        alone, as ``fit`` fits one column (its least squares in closed form: a column of
        zeros fits nothing), for a scan over c columns in one pass: (c,)."""
        out = np.zeros(X.shape[1])
        for _, rows, r in self.axes:
            c = self.cal[rows]
            Xc, rc = self.demeaned(X, rows)[c], r[c]
            xx = np.einsum("ij,ij->j", Xc, Xc)
            coef = (Xc.T @ rc) / np.where(xx > 0, xx, 1.0)
            e = rc[:, None] - Xc * coef
            out += np.einsum("ij,ij->j", e, e)
        return out

    def val_power(self) -> float:
        return sum(float(np.sum(r[self.val[rows]] ** 2)) for _, rows, r in self.axes)

    def n_val(self) -> int:
        return sum(int(self.val[rows].sum()) for _, rows, _ in self.axes)


def _standard(v: np.ndarray, cal: np.ndarray) -> np.ndarray:
    m = np.isfinite(v) & cal
    s = np.std(v[m])
    return (v - np.mean(v[m])) / (s if s > 0 else 1.0)


SPREAD = 14   # grid points each side of a sample in _fourier_sums: sums to ~1e-12 of sum |w|


def _fourier_sums(x: np.ndarray, w: np.ndarray, omega0: float, d_omega: float,
                  count: int) -> np.ndarray:
    """sum_j w[j] exp(i (omega0 + k d_omega) x[j]) for k < ``count`` and every column of ``w``
    (n, s): (count, s) complex, by a non-uniform FFT (Gaussian gridding, Greengard & Lee 2004,
    SIAM Review 46: each sample spread onto 2 SPREAD + 1 points of a uniform grid of the phase
    d_omega x modulo 2 pi, one FFT, the Gaussian divided out) to ~1e-12 of sum |w|: O(n SPREAD +
    count log count) instead of the O(n count) of a phasor per sample and frequency."""
    from scipy import fft, sparse

    n_grid = fft.next_fast_len(4 * count)       # k < count <= n_grid / 4: twice oversampled
    tau = 4 * np.pi * SPREAD / (3 * n_grid ** 2)     # the Gaussian's width (phase^2)
    h = 2 * np.pi / n_grid
    theta = np.mod(d_omega * x, 2 * np.pi)
    nearest = np.rint(theta / h).astype(np.int64)
    points = nearest[:, None] + np.arange(-SPREAD, SPREAD + 1)             # (n, 2 SPREAD + 1)
    kernel = np.exp(-(points * h - theta[:, None]) ** 2 / (4 * tau))
    spread = sparse.csr_matrix(
        (kernel.ravel(), (np.mod(points, n_grid).ravel(), np.repeat(np.arange(x.size),
                                                                     points.shape[1]))),
        shape=(n_grid, x.size))
    grid = spread @ (w * np.exp(1j * omega0 * x)[:, None])
    k = np.arange(count)
    return (fft.ifft(grid, axis=0)[:count]
            * (np.sqrt(np.pi / tau) * np.exp(k * k * tau))[:, None])


def periodogram(x: np.ndarray, y: np.ndarray, omega0: float, d_omega: float, count: int,
                mask: np.ndarray | None = None) -> np.ndarray:
    """Lomb-Scargle power of the centred series ``y`` sampled at ``x`` at the angular
    frequencies ``omega0 + k d_omega``, k < ``count`` (the classical normalisation of
    ``scipy.signal.lombscargle``, which this reproduces to ~1e-12). The sums over the samples
    at every frequency are one non-uniform FFT (``_fourier_sums``; one frequency: directly):
    a full-scale campaign's 20,000 distinct times at 15,000 frequencies in 0.1 s instead of
    3.6 s. ``y`` (n,) or (n, s): s series on the same abscissae, series j sampled where
    ``mask[:, j]`` (default everywhere; its other entries are ignored)."""
    series = y[:, None] if y.ndim == 1 else y
    inside = (np.ones(series.shape) if mask is None else np.asarray(mask, np.float64))
    series = np.where(inside > 0, series, 0.0)
    counts = inside.sum(axis=0)                             # samples of each series
    if count == 1:
        phasor = np.exp(1j * omega0 * x)
        sums_y, sums_2 = (phasor @ series)[None], (phasor * phasor @ inside)[None]
    else:
        sums_y = _fourier_sums(x, series, omega0, d_omega, count)
        sums_2 = _fourier_sums(x, inside, 2 * omega0, 2 * d_omega, count)  # exp(2 i omega x)
    cy, sy, c2, s2 = sums_y.real, sums_y.imag, sums_2.real, sums_2.imag
    two_tau = np.arctan2(s2, c2)                            # 2 omega tau
    ct, st = np.cos(0.5 * two_tau), np.sin(0.5 * two_tau)
    # sum cos^2(omega (x - tau)) = (n + |sum exp(2 i omega x)|) / 2, sin^2: (n - ...) / 2
    r2 = np.hypot(c2, s2)
    out = ((ct * cy + st * sy) ** 2 / (counts + r2)
           + (ct * sy - st * cy) ** 2 / np.maximum(counts - r2, 1e-12 * counts))
    return out[:, 0] if y.ndim == 1 else out


def _series(v: np.ndarray, target: Residual, fixed: np.ndarray | None) -> list:
    """Per axis of ``target``, its residual (calibration rows, after ``fixed`` columns) against
    ``v``: (distinct values x, mean residual at each, centred); only axes with at least 20
    distinct values and a varying residual."""
    X = np.zeros((v.size, 0)) if fixed is None else fixed
    per_axis, _ = target.fit(X)
    series = []
    for _, rows, _, _, e in per_axis:
        c = target.cal[rows]
        x, inv = np.unique(v[rows][c], return_inverse=True)
        inv = inv.reshape(-1)
        y = np.bincount(inv, e[c]) / np.bincount(inv)
        if x.size >= 20 and np.std(y) > 0:
            series.append((x, y - y.mean()))
    return series


def peak_period(v: np.ndarray, target: Residual, fixed: np.ndarray | None = None,
                nyquist_factor: float = 2.5) -> float | None:
    """The period (unit of ``v``) at which the residual (summed over axes, calibration rows,
    after ``fixed`` columns) varies most, from a Lomb-Scargle periodogram (irregular sampling;
    readings at the same value of ``v`` averaged first) over periods from the range of ``v``
    down to 1 / ``nyquist_factor`` of its mean spacing of distinct values (random positions
    resolve periods below their mean spacing, a campaign's near-regular times do not); None if
    ``v`` has too few distinct values."""
    return peak_periods(v, [(target, fixed)], nyquist_factor)[0]


def peak_periods(v: np.ndarray, jobs: list, nyquist_factor: float = 2.5) -> list:
    """``peak_period`` of each (target, fixed) of ``jobs`` (residuals of the same rows: a
    fitted model's and the same one step further), their periodograms made in one pass where
    their frequency grids agree: every axis' series on the union of their abscissae."""
    todo = {}
    for j, (target, fixed) in enumerate(jobs):
        series = _series(v, target, fixed)
        if not series:
            continue
        span = max(np.ptp(x) for x, _ in series)
        n_distinct = max(x.size for x, _ in series)
        d_omega = 2 * np.pi / (OVERSAMPLING * span)
        omega0 = 2 * np.pi / span
        count = int((2 * np.pi * nyquist_factor * n_distinct / span - omega0) / d_omega)
        if count >= 1:
            todo.setdefault((omega0, d_omega, count), []).append((j, series))
    periods = [None] * len(jobs)
    for (omega0, d_omega, count), group in todo.items():
        xu = np.unique(np.concatenate([x for _, series in group for x, _ in series]))
        n_series = sum(len(series) for _, series in group)
        Y, inside = np.zeros((xu.size, n_series)), np.zeros((xu.size, n_series), bool)
        owner, var = [], []
        for j, series in group:
            for x, y in series:
                at = np.searchsorted(xu, x)
                Y[at, len(owner)], inside[at, len(owner)] = y, True
                owner.append(j)
                var.append(np.var(y))
        # the union's own origin keeps omega * x small (float64 phases)
        xs = xu - xu[0]
        every = periodogram(xs, Y, omega0, d_omega, count, mask=inside)
        for j, _ in group:
            cols = [i for i, o in enumerate(owner) if o == j]
            power = np.zeros(count)
            for i in cols:
                power += every[:, i] / var[i]
            best = int(np.argmax(power))
            if power[best] <= 0:
                continue
            # the peak between the grid's frequencies (a period off by a fraction of a bin
            # leaves a beat in the residual over the range)
            weights = np.array([1.0 / var[i] for i in cols])
            total = lambda w, x=xs, y=Y[:, cols], m=inside[:, cols], dw=d_omega, wt=weights: \
                -float(periodogram(x, y, w, dw, 1, mask=m)[0] @ wt)
            w0 = omega0 + best * d_omega
            peak = optimize.minimize_scalar(total, bounds=(w0 - d_omega, w0 + d_omega),
                                            method="bounded",
                                            options={"xatol": 1e-6 * d_omega})
            periods[j] = float(2 * np.pi / (peak.x if peak.fun <= -power[best] else w0))
    return periods


def tail_sums(X: np.ndarray) -> np.ndarray:
    """The sums of the rows of ``X`` (n, ...) from row k to the last, for k = 1..n-1: a step
    after the first k rows, scanned by cumulative sums."""
    return np.cumsum(X[::-1], axis=0)[::-1][1:]


def best_step(t: np.ndarray, target: Residual, fixed: np.ndarray | None = None) -> float | None:
    """The time (s) of the single step that best fits the residual (summed over axes,
    calibration rows, after ``fixed``): for a centred residual e and an indicator h of
    t > tau the reduction is (e . h_c)^2 / (h_c . h_c), scanned over every calibration time by
    cumulative sums."""
    X = np.zeros((t.size, 0)) if fixed is None else fixed
    per_axis, _ = target.fit(X)
    gain_t, gain = [], []
    for _, rows, _, _, e in per_axis:
        c = target.cal[rows]
        tc, ec = t[rows][c], e[c] - e[c].mean()
        o = np.argsort(tc, kind="stable")
        tc, ec = tc[o], ec[o]
        n = tc.size
        k = np.arange(1, n)                          # rows after the step: n - k
        tail = tail_sums(ec)                         # sum of e over rows k..n-1
        hh = (n - k) * k / n                         # |h_c|^2
        gain_t.append(0.5 * (tc[:-1] + tc[1:]))
        gain.append(tail ** 2 / hh)
    if not gain_t:
        return None
    taus = np.unique(np.concatenate(gain_t))
    total = np.zeros(taus.size)
    for tt, g in zip(gain_t, gain):
        # each axis' gain at the candidate times (a step between two of its samples)
        idx = np.clip(np.searchsorted(tt, taus), 0, tt.size - 1)
        total += g[idx]
    return float(taus[np.argmax(total)]) if total.size else None


@dataclass(frozen=True)
class Term:
    """One function of a variable tried by the attribution: ``columns`` (N,p) SI, fitted on
    every reading axis with coefficients of its own, or (N,3,p) already per reading axis (a
    load's response); ``scanned``: its parameters chosen by a scan (period, step time); ``info``:
    how it was built ({"period": ...} or {"step_s": ...})."""
    variable: str
    kind: str
    columns: np.ndarray
    scanned: int = 0
    info: dict = field(default_factory=dict)


def variable_terms(var: Variable, target: Residual) -> list[Term]:
    """The terms of one variable (module docstring), periods and step moments scanned on
    ``target``."""
    v = var.values
    if var.kind == "session":
        t = target.time
        cols = np.column_stack([np.where(v == s, t - t[v == s].mean(), 0.0)
                                for s in dict.fromkeys(v)])
        return [Term(var.name, "drift", cols / 3600.0)]
    if var.kind == "sign":
        return [Term(var.name, "sign", v[:, None].astype(np.float64))]
    x = _standard(v, target.cal)
    terms = [Term(var.name, f"power {k}", (x ** k)[:, None]) for k in (1, 2, 3)]
    info = scans(var, target)
    if "period" in info:
        phase = 2 * np.pi * v / info["period"]
        terms.append(Term(var.name, "sine", np.column_stack([np.sin(phase), np.cos(phase)]),
                          SCANNED["sine"], {"period": info["period"]}))
    if "step_s" in info:
        terms.append(Term(var.name, "step", (v > info["step_s"]).astype(np.float64)[:, None],
                          SCANNED["step"], {"step_s": info["step_s"]}))
    return terms


class AxisFrame:
    """Terms fitted to a residual (``Residual``) on each of its axes by least squares on the
    calibration rows, each (session, axis) zero re-estimated there: the attribution's frame when
    there is no physics model to re-adjust (a stepwise DGM's residual)."""

    def __init__(self, target: Residual):
        self.target = target
        self.n_axes = len(target.axes)

    def blocks(self, terms: list[Term]) -> list[np.ndarray]:
        """Each term's columns, rows with a non-finite value zeroed."""
        for t in terms:
            if t.columns.ndim != 2:
                raise ValueError(f"term {t.variable} {t.kind}: per-axis columns need a "
                                 "physics model's frame (model_form.JointFrame)")
        return [np.where(np.all(np.isfinite(t.columns), axis=1)[:, None], t.columns, 0.0)
                for t in terms]

    def n_val(self) -> dict:
        return {k: int(self.target.val[rows].sum()) for k, rows, _ in self.target.axes}

    def estimates(self, lead: list, trials: list) -> list:
        """Estimates of ``fit`` of the ``lead`` blocks with each of ``trials`` in turn, None
        for each: every trial is fitted (model_form.JointFrame's are estimated)."""
        return [None] * len(trials)

    def fit(self, blocks: list) -> dict:
        """{rss_cal, rank, dof (calibration residual's degrees of freedom), val_power,
        val_by_axis {axis: power}} of the blocks fitted together."""
        X = np.column_stack(blocks) if blocks else np.zeros((self.target.res.shape[0], 0))
        per_axis, total = self.target.fit(X)
        return {"rss_cal": total["rss_cal"], "rank": total["rank"],
                "dof": total["n_cal"] - total["rank"] - self.n_axes,
                "val_power": total["val_power"],
                "val_by_axis": {k: float(np.sum(e[self.target.val[rows]] ** 2))
                                for k, rows, _, _, e in per_axis}}


def _poly(var: Variable, target: Residual) -> np.ndarray:
    x = _standard(var.values, target.cal)
    return np.column_stack([x, x ** 2, x ** 3])


def scans(var: Variable, target: Residual) -> dict:
    """The scanned parameters of a coordinate's or time's family on ``target`` (once per
    variable, kept on the target): the periodogram's peak period after the cubic polynomial
    and, for time, the best step moment."""
    if var.name not in target.scans:
        scan_together([var], [target])
    return target.scans[var.name]


def scan_together(variables: list[Variable], targets: list[Residual], step=None) -> None:
    """``scans`` of every variable on every target (residuals of the same rows, e.g. a model's
    and the same one linear step further), kept on each target: the periodograms of all the
    targets' axes made in one pass per variable (the costly part of a diagnosis). ``step``:
    the scan of a step's moment in time, ``step(t, target)`` -> s or None (default
    ``best_step``, on the residual alone; a physics model's frame re-adjusts the model's
    directions: model_form.JointFrame.scan)."""
    step = best_step if step is None else step
    for var in variables:
        todo = [t for t in targets if var.name not in t.scans]
        if not todo:
            continue
        infos = [{} for _ in todo]
        if var.kind in ("coordinate", "time"):
            periods = peak_periods(var.values, [(t, _poly(var, t)) for t in todo],
                                   0.5 if var.kind == "time" else 2.5)
            for info, period in zip(infos, periods):
                if period:
                    info["period"] = period
        if var.kind == "time":
            for info, t in zip(infos, todo):
                tau = step(var.values, t)
                if tau is not None:
                    info["step_s"] = tau
        for info, t in zip(infos, todo):
            t.scans[var.name] = info


def _joins(term: Term, after: dict, current: dict, n_axes: int, limit: float,
           min_gain: float, rss_tol: float = 0.0, val_tol: float = 0.0):
    """(validation gain, p value) of ``term`` joining a fit (``current`` -> ``after``), None
    where it does not qualify: significant on the calibration rows (partial F test, its scanned
    parameters counted on every axis) and lowering the validation power by ``min_gain``. With
    tolerances: whether it can qualify when ``after``'s sum of squares and validation power
    are within them (the most favourable of those)."""
    gain = current["val_power"] - after["val_power"] + val_tol
    # the most favourable sum of squares is no less than zero: a fit within its tolerance of
    # exact is the strongest trial there is, not one whose F test is undefined
    rss = max(after["rss_cal"] - rss_tol, 0.0)
    k = after["rank"] - current["rank"] + term.scanned * n_axes
    if k <= 0 or after["dof"] <= 0 or rss >= current["rss_cal"]:
        return None
    F = math.inf if rss == 0 else ((current["rss_cal"] - rss) / k) / (rss / after["dof"])
    p = float(special.fdtrc(k, after["dof"], F))
    return (gain, p) if p < limit and gain >= min_gain else None


def _best_addition(frame, terms: list, blocks: list, chosen: list, trials: list,
                   current: dict, limit: float, min_gain: float):
    """The term of ``trials`` (indices) that, added to the ``chosen``, lowers the validation
    power most among those that qualify (``_joins``; the first of equal gains): (index, gain,
    p, the fit with it), or None. The frame's estimates (``estimates``: with error bounds)
    rule out the trials that cannot qualify, and the others are fitted in the order of the
    most they can gain until none can gain more than the best fitted: the same choice as
    fitting every trial, fitting a few."""
    lead = [blocks[j] for j in chosen]
    bounds = []
    for i, est in zip(trials, frame.estimates(lead, [blocks[i] for i in trials])):
        if est is None:
            bounds.append((math.inf, i))
            continue
        can = _joins(terms[i], {"rss_cal": est["rss"], "val_power": est["val_power"],
                                "rank": est["rank"], "dof": est["dof"]},
                     current, frame.n_axes, limit, min_gain, est["rss_tol"], est["val_tol"])
        if can is not None:
            bounds.append((can[0], i))
    best = None
    for bound, i in sorted(bounds, key=lambda b: (-b[0], b[1])):
        if best is not None and bound < best[1]:
            break
        after = frame.fit(lead + [blocks[i]])
        joins = _joins(terms[i], after, current, frame.n_axes, limit, min_gain)
        if joins is not None and (best is None or joins[0] > best[1]
                                  or (joins[0] == best[1] and i < best[0])):
            best = (i, *joins, after)
    return best


def attribute(df: pd.DataFrame, target: Residual, alpha: float = ALPHA,
              min_share: float = MIN_SHARE, variables: list[Variable] | None = None,
              frame=None, extra_terms: tuple = ()) -> dict:
    """Rank the laboratory variables by the validation residual power each explains beyond the
    others (module docstring). ``target``: the residual of the rows of ``df``
    (``Residual.of``); ``variables``: ``laboratory_variables(df)`` when already made;
    ``frame``: where the terms are fitted (default ``AxisFrame(target)``; on a physics model
    model_form.JointFrame, the model's directions re-adjusted); ``extra_terms``: terms beyond
    the variables' own (a load's response through the model, model_form.load_terms).

    Returns {"variables": [{variable, explained_nm, explained_fraction, by_axis_nm, p_value,
    terms, columns}, ...] strongest first, "val_rms_nm", "explained_fraction" (all selected
    together), "tried"}."""
    variables = laboratory_variables(df) if variables is None else variables
    frame = AxisFrame(target) if frame is None else frame
    start = frame.fit([])
    p0 = start["val_power"]
    n_val = frame.n_val()
    n_all = max(sum(n_val.values()), 1)
    out = {"val_rms_nm": float(np.sqrt(p0 / n_all) * 1e9), "variables": [],
           "explained_fraction": 0.0, "tried": [v.name for v in variables]}
    if not frame.n_axes or p0 <= 0:
        return out
    terms = [t for var in variables for t in variable_terms(var, target)] + list(extra_terms)
    blocks = frame.blocks(terms)
    responses = {v.name for v in variables if v.response}
    chosen: list[int] = []
    p_values = {}
    current = start
    limit = alpha / max(len(terms), 1)
    conditions_only = bool(responses)
    while len(chosen) < MAX_TERMS:
        best = _best_addition(frame, terms, blocks, chosen, [
            i for i, term in enumerate(terms)
            if i not in chosen and not (conditions_only and term.variable in responses)],
            current, limit, min_share * p0)
        if best is None:
            if conditions_only:        # no condition explains more: the rotations may
                conditions_only = False
                continue
            break
        chosen.append(best[0])
        p_values[best[0]] = best[2]
        current = best[3]
    if not chosen:
        return out
    full = frame.fit([blocks[j] for j in chosen])
    # a condition is credited beyond the other conditions, a response beyond every term: a
    # rotation that reads the tilt a force makes takes no credit from the force
    conditions = [j for j in chosen if terms[j].variable not in responses]
    of_conditions = (full if len(conditions) == len(chosen)
                     else frame.fit([blocks[j] for j in conditions]))
    ranked = []
    for name in dict.fromkeys(terms[j].variable for j in chosen):
        peers = chosen if name in responses else conditions
        reference = full if name in responses else of_conditions
        own = [j for j in peers if terms[j].variable == name]
        without = frame.fit([blocks[j] for j in peers if j not in own])
        unique = max(without["val_power"] - reference["val_power"], 0.0)
        by_axis = {AXES[k]: float(np.sqrt(max(without["val_by_axis"][k]
                                              - reference["val_by_axis"][k], 0.0)
                                          / max(n_val[k], 1)) * 1e9) for k in n_val}
        ranked.append({"variable": name, "explained_nm": float(np.sqrt(unique / n_all) * 1e9),
                       "explained_fraction": unique / p0, "by_axis_nm": by_axis,
                       "p_value": min(p_values[j] for j in own),
                       "terms": [terms[j].kind for j in own],
                       "columns": {k: float(v) for j in own for k, v in terms[j].info.items()}})
    # a variable is named for what it explains beyond the others, by the same share that let
    # its terms join: below it, the credit left is the residual's noise (at the noise floor, a
    # fraction of a nanometre that a rounding can bring or take away)
    ranked = [r for r in ranked if r["explained_fraction"] >= min_share]
    ranked.sort(key=lambda r: -r["explained_nm"])
    out["variables"] = ranked
    out["explained_fraction"] = 1.0 - full["val_power"] / p0
    return out
