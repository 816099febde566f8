"""Physics models fitted to measurements: the twin's own effects, evaluated on the conditions the
data recorded, with their free parameters found by nonlinear least squares.

A physics model is a list of effects from the library (twin/effects/). Its prediction of an
interferometer reading runs the twin's stages (twin/world.py: robot -> part temperatures ->
exact kinematics -> load through the compliance -> optics) on conditions taken from the data:
motor coordinates, coil currents and the temperature sensors (each sensor stands for the part it
is glued on, ``metadata['sensors']``; a part without a sensor takes the mean of its sensed
siblings — arm1..3, rod1..3, ... — or the reference temperature). Readings are relative to each
session's zero, as the interferometer counts it: (n s - n0 s0) / n_comp, where n0 s0 is the optical
path at the zero (the robot at home, coils off, the conditions of the session's first row). The
zero's path is a constant, but divided by the compensation index it is not: that is the dead-path
error of an index change, hundreds of nm per kelvin on a 0.1 m dead path, so the model evaluates
the zero too. What remains is an unknown offset per (session, axis): it is projected out of the
fit (variable projection) and estimated on the calibration rows. Cosine-corrected data are
compared with the model's reading divided by the same correction factor from the measured angles.

The fit (``PhysicsFit``, scikit-learn style: ``fit`` then attributes ending in ``_``) works in
parameter units scaled by each parameter's ``fit_scale`` (its typical size): the Jacobian is
computed by forward differences, re-using the kinematics for parameters that only change the
load or the optics; its singular value decomposition says which parameter combinations the data
determine to better than ``identifiable_ratio`` of their typical size, given the readings'
noise. Only those are fitted (Gauss-Newton in the reduced coordinates, scipy.linalg); the
others stay at their starting values and are named in the identifiability report, never fitted
to noise. Units: SI inside (m, rad, K), nm in reports.
"""
from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd
import scipy.linalg
from scipy.spatial.transform import Rotation

from models.geometry import build_geometry
from models.params import RobotParams, load_params
from deltatwin.files import toml_value
from twin.campaign import COSINE_ANGLES
from twin.dataset import temperature_columns
from twin.effects import LIBRARY, EffectError, make_effect
from twin.instruments.optics import AXES, return_factor
from twin.kinematics import Pose, forward
from twin.statics import Statics
from twin.thermal import PART_NODES
from twin.world import Points, kinematic_pose, observe

from .features import causal_fit
from .errors import CalibrationInputError, MissingColumnsError, TooFewPointsError
from .validation import error_figures

SIBLINGS = {"arm": ("arm1", "arm2", "arm3"), "rod": ("rod1", "rod2", "rod3"),
            "motor": ("motor1", "motor2", "motor3"), "coil": ("coil1", "coil2", "coil3"),
            "air": ("air_x", "air_y", "air_z")}
REQUIRED = ("t_s", "split", "session", "q1_rad", "q2_rad", "q3_rad")
TEMPERATURE_WINDOW_S = 600.0   # causal smoothing of the temperature streams
NM = 1e9   # the solver works on residuals in nm, where its tolerances are meaningful


class FitError(CalibrationInputError):
    """A physics fit that cannot be done as asked (effects, data) or did not converge."""


# ---------------------------------------------------------------------------------------------
# the data as a model sees it

@dataclass
class Measurements:
    """A dataset prepared for physics models (arrays with a leading axis N = rows)."""
    df: pd.DataFrame
    sensors: dict                 # sensor name -> part
    y: np.ndarray                 # (N,3) readings (m), NaN where the axis was not measured
    cos_factor: np.ndarray        # (N,3) 1 / cosine-correction factor (1 if not corrected)
    group: np.ndarray             # (N,3) index of the (session, axis) zero, -1 where no reading
    groups: list                  # (session, axis) per group index
    cal: np.ndarray               # (N,) bool
    val: np.ndarray               # (N,) bool
    points: Points                # conditions of the N rows then of the session zeros (N + S
                                  # rows; params/home filled in per evaluation)
    zero_row: np.ndarray          # (N,) index in ``points`` of each row's session zero
    T_ref_C: float
    sensor_node_T: dict           # part temperatures taken at their sensors' readings
    _statics: tuple | None = field(default=None, repr=False)

    @property
    def n(self) -> int:
        return self.y.shape[0]

    def part_temperatures(self, effects) -> dict:
        """Part temperatures (N + S rows) under the model's ``effects``: those that say how a
        sensor reads its part (``sensed_parts``) correct the readings, else each part is at its
        sensors' reading."""
        sensed = {}
        for e in effects:
            sensed.update(e.sensed_parts(self.points) or {})
        if not sensed:
            return self.sensor_node_T
        readings = {k: v[1] for k, v in self.points.sensor_readings.items()}
        return node_temperatures({**readings, **sensed}, self.sensors, self.T_ref_C,
                                 self.points.t_s.shape[0])

    def statics(self, params: RobotParams):
        """Preload deflection (N,6) and compliance (N,6,6) at each row's position, computed
        once with the starting robot (a µm change of geometry changes them by ~1e-4)."""
        if self._statics is None:
            geom = build_geometry(params)
            st = Statics(params, geom)
            qu, inv = np.unique(self.points.q, axis=0, return_inverse=True)
            inv = inv.reshape(-1)
            self._statics = (st.solve(qu, gravity=False).deflection[inv], st.compliance(qu)[inv])
        return self._statics


def sensor_streams(df: pd.DataFrame, sensors: dict, window_s: float = TEMPERATURE_WINDOW_S,
                   where: str = "data") -> dict:
    """Each sensor's stream smoothed causally (local linear fit over the past ``window_s``, as a
    controller could: a thermometer's mK noise times a CTE and a 0.35 m loop leg is tens of
    nm): {sensor name: (part, level degC (N,), rate K/s (N,))}."""
    t = df["t_s"].to_numpy(dtype=np.float64)
    order = np.argsort(t, kind="stable")
    out = {}
    for s, part in sensors.items():
        c = f"T_{s}_C"
        if c not in df:
            raise MissingColumnsError(f"{where}: metadata 'sensors' names sensor {s!r} (on {part!r}) but "
                                      f"the data has no column {c!r}")
        raw = df[c].to_numpy(dtype=np.float64)
        if not np.all(np.isfinite(raw)):
            raise CalibrationInputError(f"{where}: column {c!r}: row {int(np.flatnonzero(~np.isfinite(raw))[0])}"
                                        " is not a finite temperature")
        level, rate = np.empty_like(raw), np.empty_like(raw)
        level[order], rate[order] = causal_fit(t[order], raw[order], window_s, degree=1)[:2]
        out[s] = (part, level, rate)
    return out


def node_temperatures(sensor_T: dict, sensors: dict, T_ref_C: float, n: int) -> dict:
    """Part temperatures (degC, (n,) each) from the temperature each sensor stands for
    (``sensor_T``: sensor name -> (n,)): the mean of the sensors on a part; a part without a
    sensor takes the mean of its sensed siblings (arm1..3, rod1..3, ...), else ``T_ref_C``."""
    cols = {}
    for s, part in sensors.items():
        cols.setdefault(part, []).append(sensor_T[s])
    T = {p: np.mean(v, axis=0) for p, v in cols.items()}
    out = {}
    for node, _, _ in PART_NODES:
        if node in T:
            out[node] = T[node]
            continue
        kin = next((g for g in SIBLINGS.values() if node in g), ())
        sensed = [T[k] for k in kin if k in T]
        out[node] = np.mean(sensed, axis=0) if sensed else np.full(n, T_ref_C)
    for a in AXES:   # the interferometer's own air sensor sits in its beam's air
        out[f"sensor:comp_{a}"] = out[f"air_{a}"]
    return out


def check_sensors(effects, meas: "Measurements", where: str = "data") -> None:
    """A model whose effects read temperatures needs the data's sensors mapped to parts: without
    the map every part would sit at the reference temperature and the effect would silently do
    nothing."""
    thermal = [n for n in effects if LIBRARY[n].reads_temperatures]
    if thermal and not meas.sensors:
        present = temperature_columns(meas.df)
        raise CalibrationInputError(
            f"{where}: the model's effect(s) {thermal} read part temperatures, but the dataset's "
            f"metadata names no temperature sensor ('sensors': sensor -> part; temperature "
            f"columns present: {present}): map them in the metadata (the .meta.json beside a "
            "CSV, docs/data-format.md)")


def measurements(df: pd.DataFrame, meta: dict | None, params: RobotParams,
                 where: str = "data") -> Measurements:
    """Check the dataset's columns and build the conditions the model is evaluated on."""
    missing = [c for c in REQUIRED if c not in df.columns]
    if missing:
        raise MissingColumnsError(f"{where}: missing column(s) {missing} (data format: "
                                  "docs/data-format.md)")
    axes = [a for a in AXES if f"{a}_nm" in df.columns]
    if not axes:
        raise MissingColumnsError(f"{where}: no interferometer reading column (x_nm, y_nm, z_nm)")
    meta = meta or {}
    sensors = meta.get("sensors") or {}
    if not isinstance(sensors, dict):
        raise CalibrationInputError(f"{where}: metadata 'sensors' must map sensor name -> part")
    parts = {p for p, _, _ in PART_NODES}
    bad = {s: p for s, p in sensors.items() if p not in parts}
    if bad:
        raise CalibrationInputError(f"{where}: metadata 'sensors' puts {bad} on unknown parts; "
                                    f"parts: {sorted(parts)}")
    n = len(df)
    y = np.full((n, 3), np.nan)
    for a in axes:
        y[:, AXES.index(a)] = df[f"{a}_nm"].to_numpy(dtype=np.float64) * 1e-9
    cos = np.ones((n, 3))
    corrected = df["cosine_corrected"].to_numpy(dtype=bool) if "cosine_corrected" in df else \
        np.zeros(n, bool)
    if corrected.any():
        for a in axes:
            need = [f"{c}_arcsec" for c in COSINE_ANGLES[a]]
            if any(c not in df for c in need):
                raise MissingColumnsError(f"{where}: readings are cosine corrected but the "
                                          f"angle column(s) {need} are missing")
            ang = np.radians(df[need].to_numpy(dtype=np.float64) / 3600.0)
            f = return_factor(np.cos(ang[:, 0]) * np.cos(ang[:, 1]))
            cos[:, AXES.index(a)] = np.where(corrected, 1.0 / f, 1.0)
    session = df["session"].astype(str).to_numpy()
    groups, group = [], np.full((n, 3), -1)
    for s in dict.fromkeys(session):
        for k, a in enumerate(AXES):
            m = (session == s) & np.isfinite(y[:, k]) & np.isfinite(cos[:, k])
            if m.any():
                group[m, k] = len(groups)
                groups.append((s, a))
    split = df["split"].astype(str).to_numpy()
    q = df[["q1_rad", "q2_rad", "q3_rad"]].to_numpy(dtype=np.float64)
    if not np.all(np.isfinite(q)):
        bad_row = int(np.flatnonzero(~np.all(np.isfinite(q), axis=1))[0])
        raise CalibrationInputError(f"{where}: row {bad_row}: motor coordinates not finite")
    currents = np.zeros((n, 3))
    for i in range(3):
        if f"coil{i + 1}_A" in df:
            currents[:, i] = df[f"coil{i + 1}_A"].to_numpy(dtype=np.float64)
    T_ref = params.reference_temperature_C
    streams = sensor_streams(df, sensors, where=where)
    node_T = node_temperatures({k: v[1] for k, v in streams.items()}, sensors, T_ref, n)
    room = np.mean([node_T[f"air_{a}"] for a in AXES], axis=0)
    pressure = df["p_Pa"].to_numpy(dtype=np.float64) if "p_Pa" in df else np.full(n, 101325.0)
    t_s = df["t_s"].to_numpy(dtype=np.float64)
    # each session's zero: the robot at home with the coils off, in the conditions of the
    # session's first row (the zero is taken just before it)
    names = list(dict.fromkeys(session))
    first = np.array([np.flatnonzero(session == s_)[np.argmin(t_s[session == s_])] for s_ in names])
    zero_row = n + np.array([names.index(s_) for s_ in session], dtype=np.int64)
    with_zeros = lambda v: np.concatenate([v, v[first]])
    node_T = {k: with_zeros(v) for k, v in node_T.items()}
    pts = Points(t_s=with_zeros(t_s), q=np.concatenate([q, np.zeros((first.size, 3))]),
                 currents_A=np.concatenate([currents, np.zeros((first.size, 3))]),
                 node_T=node_T, room_C=with_zeros(room), pressure_Pa=with_zeros(pressure),
                 support_C={a: node_T["table"] for a in AXES}, params=params,
                 home_p=np.zeros(3),
                 sensor_readings={k: (part, with_zeros(T), with_zeros(r))
                                  for k, (part, T, r) in streams.items()})
    return Measurements(df=df, sensors=dict(sensors), y=y, cos_factor=cos, group=group,
                        groups=groups, cal=split == "cal", val=split == "val", points=pts,
                        zero_row=zero_row, T_ref_C=T_ref, sensor_node_T=node_T)


# ---------------------------------------------------------------------------------------------
# the model

@dataclass(frozen=True)
class FreeParameter:
    effect: str
    name: str
    unit: str
    shape: tuple
    start: np.ndarray
    scale: float
    sl: slice

    def labels(self) -> list[str]:
        """One label per scalar: effect.name[i,j]."""
        if not self.shape:
            return [f"{self.effect}.{self.name}"]
        return [f"{self.effect}.{self.name}[{','.join(map(str, idx))}]"
                for idx in np.ndindex(*self.shape)]


def model_effects() -> list[str]:
    """The library effects a physics model can hold (they change the robot, the part
    temperatures, the load or the optics)."""
    return [n for n, cls in LIBRARY.items() if cls.model_stages()]


class PhysicsModel:
    """Effects with values; ``predict`` evaluates the twin's stages on measured conditions."""

    def __init__(self, effects, params: RobotParams | None = None, values: dict | None = None,
                 where: str = "--effects"):
        names = list(dict.fromkeys(effects))
        values = values or {}
        for n in names:
            if n not in LIBRARY:
                make_effect(n, where=where)          # raises with a suggestion
            if not LIBRARY[n].model_stages():
                raise FitError(f"{where}: effect {n!r} has no model form: it acts through "
                               "the thermal network (heat or environment; in measurements its "
                               "consequences arrive through the temperature sensors, so model "
                               "what it drives instead) or at random (servo settling: part of "
                               f"the noise floor); model effects: {model_effects()}")
        unknown = sorted(set(values) - set(names))
        if unknown:
            raise FitError(f"{where}: values given for effect(s) {unknown} not in the model")
        self.params = params or load_params(None)
        self.effects, self.free, k = [], [], 0
        for n in names:
            cls = LIBRARY[n]
            given = dict(values.get(n, {}))
            start = {p.name: np.broadcast_to(p.fit_start, np.shape(p.default)).copy()
                     for p in cls.free_parameters() if p.fit_start is not None}
            try:
                # a fitted value may leave a parameter's physical range (reported, see fit)
                e = make_effect(n, {**start, **given}, where=where, check_minimum=False)
            except EffectError as exc:
                raise FitError(str(exc)) from exc
            for p in cls.free_parameters():
                size = int(np.prod(p.shape))
                self.free.append(FreeParameter(n, p.name, p.unit, p.shape,
                                               np.asarray(e.values[p.name], float).copy(),
                                               p.fit_scale, slice(k, k + size)))
                k += size
            self.effects.append(e)
        self.names = names

    # -- parameter vector ---------------------------------------------------------------------
    @property
    def n_free(self) -> int:
        return self.free[-1].sl.stop if self.free else 0

    @property
    def labels(self) -> list[str]:
        return [lab for f in self.free for lab in f.labels()]

    @property
    def scales(self) -> np.ndarray:
        return np.concatenate([np.full(f.sl.stop - f.sl.start, f.scale) for f in self.free]) \
            if self.free else np.zeros(0)

    def theta(self) -> np.ndarray:
        """The free parameters' current values, concatenated (SI)."""
        e = {x.name: x for x in self.effects}
        return np.concatenate([np.ravel(e[f.effect].values[f.name]) for f in self.free]) \
            if self.free else np.zeros(0)

    def set_theta(self, theta: np.ndarray) -> None:
        e = {x.name: x for x in self.effects}
        for f in self.free:
            v = np.asarray(theta[f.sl], dtype=np.float64).reshape(f.shape)
            v = float(v) if not f.shape else v.copy()
            e[f.effect].values[f.name] = v
            setattr(e[f.effect], f.name, v)

    def values(self) -> dict:
        """{effect: {parameter: value}} of every parameter (free or not), JSON/TOML-ready."""
        return {e.name: {k: np.asarray(v).tolist() for k, v in e.values.items()}
                for e in self.effects}

    def free_by_stage(self) -> dict[str, np.ndarray]:
        """Masks over theta by the first stage a parameter changes: ``robot`` (the geometry),
        ``temperatures`` (the part temperatures), or ``load_optics`` (the kinematics can be
        re-used)."""
        out = {k: np.zeros(self.n_free, bool) for k in ("robot", "temperatures", "load_optics")}
        for f in self.free:
            stages = LIBRARY[f.effect].model_stages()
            key = ("temperatures" if {"sensed_parts", "part_temperatures"} & set(stages) else
                   "robot" if "robot" in stages else "load_optics")
            out[key][f.sl] = True
        return out

    # -- evaluation ---------------------------------------------------------------------------
    def _robot(self):
        params = self.params
        for e in self.effects:
            params = e.robot(params, None)
        geom0 = build_geometry(params)
        return params, geom0, forward(geom0, np.zeros((1, 3))).p[0]

    def _kinematics(self, meas: Measurements):
        """The stage the load and optics are evaluated on: (robot parameters, geometry,
        kinematic pose, cube home, part temperatures), at the current values."""
        params, geom0, home = self._robot()
        pts = meas.points
        pts.params, pts.home_p = params, home
        pts.node_T = meas.part_temperatures(self.effects)
        geom, kin = kinematic_pose(params, geom0, self.effects, pts)
        return params, geom, kin, home + geom0.cube_offset, pts.node_T

    def _paths(self, meas: Measurements, stage) -> tuple[np.ndarray, np.ndarray]:
        """Optical path n s (m) and the index the instrument divides by, (N + S, 3) each, at the
        rows and at the session zeros."""
        params, geom, kin, cube_home, node_T = stage
        pts = meas.points
        # the stage's own temperatures: a stage re-used for a load or optics parameter was
        # computed before a later sensor parameter was stepped
        pts.params, pts.node_T = params, node_T
        preload, C = meas.statics(self.params)
        truth = observe(geom, kin, self.effects, pts, preload, C, cube_home,
                        params.mirror_cube_size_m)
        return (np.stack([truth.optical_path_m[a] for a in AXES], axis=1),
                np.stack([truth.n_comp[a] for a in AXES], axis=1))

    @staticmethod
    def _counted(meas: Measurements, path: np.ndarray, n_comp: np.ndarray) -> np.ndarray:
        """What the interferometers count from their session's zero, (n s - n0 s0) / n_comp, as
        the data show it (cosine corrected or not): (N, 3, ...) from paths (N + S, 3, ...)."""
        n = meas.n
        d = path[:n] - path[meas.zero_row]
        f = meas.cos_factor / n_comp[:n]
        return d * f.reshape(f.shape + (1,) * (d.ndim - 2))

    def _observe(self, meas: Measurements, stage) -> np.ndarray:
        return self._counted(meas, *self._paths(meas, stage))

    def predict_path(self, meas: Measurements, theta: np.ndarray | None = None) -> np.ndarray:
        """(N,3) the reading each row would show up to its session's zero (m)."""
        if theta is not None:
            self.set_theta(theta)
        return self._observe(meas, self._kinematics(meas))

    def jacobian(self, meas: Measurements, theta: np.ndarray, rel_step: float = 1e-3,
                 columns: np.ndarray | None = None):
        """(A, J): the prediction (N,3) and its forward-difference derivative (N,3,p) with
        respect to theta (only the ``columns`` mask when given, zeros elsewhere); steps of
        ``rel_step`` times each parameter's fit scale.

        Geometry parameters under per-point part temperatures go by the chain rule: the
        kinematic pose's derivative on the unique motor coordinates (at the reference
        temperature: the parts' expansion changes it by ~1e-5 of itself) times the optical
        paths' derivative with respect to the pose, so a fit costs a few exact evaluations, not
        one per parameter and point."""
        self.set_theta(theta)
        stage = self._kinematics(meas)
        path, n_comp = self._paths(meas, stage)
        A = self._counted(meas, path, n_comp)
        J = np.zeros(A.shape + (theta.size,))
        by = self.free_by_stage()
        steps = rel_step * self.scales
        wanted = np.ones(theta.size, bool) if columns is None else np.asarray(columns, bool)
        chain = by["robot"] & stage[1].batched & wanted
        for j in np.flatnonzero(~chain & wanted):
            th = theta.copy()
            th[j] += steps[j]
            self.set_theta(th)
            Aj = self._observe(meas, self._kinematics(meas) if not by["load_optics"][j] else stage)
            J[:, :, j] = (Aj - A) / steps[j]
        if chain.any():
            dpath = self._pose_chain(meas, theta, stage, path, np.flatnonzero(chain), steps)
            J[:, :, chain] = self._counted(meas, dpath, n_comp)
        self.set_theta(theta)
        return A, J

    def _pose_chain(self, meas, theta, stage, path, cols, steps):
        """d path / d theta (N + S, 3, len(cols)) for geometry parameters ``cols``."""
        params, geom, kin, cube_home, node_T = stage
        qu, inv = np.unique(meas.points.q, axis=0, return_inverse=True)
        inv = inv.reshape(-1)
        _, geom0, _ = self._robot()
        ku = forward(geom0, qu)
        dpose = np.zeros((qu.shape[0], 6, cols.size))      # d(position, rotation vector)/d theta
        for i, j in enumerate(cols):
            th = theta.copy()
            th[j] += steps[j]
            self.set_theta(th)
            kj = forward(self._robot()[1], qu)
            dpose[:, :3, i] = (kj.p - ku.p) / steps[j]
            dpose[:, 3:, i] = Rotation.from_matrix(kj.R @ np.swapaxes(ku.R, 1, 2)).as_rotvec() / steps[j]
        self.set_theta(theta)
        G = np.zeros(path.shape + (6,))                     # d path / d pose, per row
        eps = (1e-9, 1e-9, 1e-9, 1e-8, 1e-8, 1e-8)
        for d in range(6):
            if d < 3:
                p = kin.p.copy()
                p[:, d] += eps[d]
                moved = Pose(p, kin.R)
            else:
                w = np.zeros(3)
                w[d - 3] = eps[d]
                moved = Pose(kin.p, Rotation.from_rotvec(w).as_matrix() @ kin.R)
            moved_path = self._paths(meas, (params, geom, moved, cube_home, node_T))[0]
            G[:, :, d] = (moved_path - path) / eps[d]
        return np.einsum("nad,ndj->naj", G, dpose[inv])


# ---------------------------------------------------------------------------------------------
# residuals with the session zeros projected out

def group_offsets(meas: Measurements, pred: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """Per (session, axis) zero: mean of reading - prediction over ``rows`` (m)."""
    off = np.zeros(len(meas.groups))
    for g in range(len(meas.groups)):
        m = (meas.group == g) & rows[:, None]
        if m.any():
            off[g] = np.mean(meas.y[m] - pred[m])
    return off


def residuals(meas: Measurements, pred: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """(N,3) reading - (prediction + zero offset), m; NaN where no reading."""
    off = np.where(meas.group >= 0, offsets[np.maximum(meas.group, 0)], np.nan)
    return meas.y - pred - off


def _projected(meas: Measurements, rows: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Values v (N,3,...) on the readings of ``rows`` with each group's mean removed:
    (n_readings, ...)."""
    out = []
    for g in range(len(meas.groups)):
        m = (meas.group == g) & rows[:, None]
        if m.any():
            x = v[m]
            out.append(x - x.mean(axis=0))
    return np.concatenate(out) if out else np.zeros((0,) + v.shape[2:])


def figures_nm(res: np.ndarray, rows: np.ndarray) -> dict:
    """Error figures (nm) per axis and pooled, over ``rows``: 1.645 sigma and empirical
    90th percentile of |error|."""
    out = {}
    for k, a in enumerate(AXES):
        e = res[rows, k]
        e = e[np.isfinite(e)]
        if e.size:
            out[a] = error_figures(e)
    pooled = res[rows]
    out["all"] = error_figures(pooled[np.isfinite(pooled)])
    return out


# ---------------------------------------------------------------------------------------------
# the estimator

class PhysicsFit:
    """Fit a physics model's free parameters to a dataset's calibration rows.

    Parameters: ``effects`` (library names), ``params`` (the robot file; default nominal),
    ``start`` ({effect: {parameter: value}}: starting values, e.g. a previous fit),
    ``noise_nm`` (the readings' noise, nm: sets which directions are identifiable),
    ``identifiable_ratio`` (a direction is fitted if the data determine it to better than this
    fraction of its parameters' typical size), ``max_iterations`` (Gauss-Newton steps),
    ``progress`` (print the calibration rms after each step).

    Attributes after ``fit``: ``model_`` (PhysicsModel at the fitted values), ``offsets_`` (m per
    (session, axis)), ``residual_`` ((N,3) m), ``cal_``/``val_`` (error figures, nm),
    ``identifiability_`` (dict), ``converged_``, ``n_evaluations_``, ``parameters_`` (list of
    {label, value, start, unit, uncertainty, identified_fraction}).
    """

    def __init__(self, effects, params: RobotParams | None = None, start: dict | None = None,
                 noise_nm: float = 5.0, identifiable_ratio: float = 0.3,
                 max_iterations: int = 20, progress: bool = False):
        if noise_nm <= 0 or not math.isfinite(noise_nm):
            raise FitError(f"noise_nm = {noise_nm}: must be a positive number of nanometres")
        if not 0 < identifiable_ratio:
            raise FitError(f"identifiable_ratio = {identifiable_ratio}: must be positive")
        self.effects = list(effects)
        self.params = params
        self.start = start
        self.noise_nm = noise_nm
        self.identifiable_ratio = identifiable_ratio
        self.max_iterations = max_iterations
        self.progress = progress
        PhysicsModel(self.effects, params, start)      # validate names and values once

    def fit(self, df: pd.DataFrame, meta: dict | None = None, meas: Measurements | None = None,
            where: str = "data"):
        """Fit to the calibration rows of ``df`` (``where`` names the data in errors)."""
        model = PhysicsModel(self.effects, self.params, self.start)
        meas = meas or measurements(df, meta, model.params, where)
        check_sensors(model.names, meas, where)
        cal = meas.cal
        n_cal = int(np.sum((meas.group >= 0) & cal[:, None]))
        p = model.n_free
        if n_cal == 0:
            raise TooFewPointsError("no calibration reading (split == 'cal') in the data")
        if n_cal <= p + len(meas.groups):
            raise TooFewPointsError(f"{n_cal} calibration readings cannot identify {p} "
                                    f"parameters and {len(meas.groups)} zero offsets: take "
                                    "more points or fit fewer effects")
        theta0 = model.theta()
        S = model.scales
        sigma = self.noise_nm * 1e-9
        _, J0 = model.jacobian(meas, theta0)
        Js = _projected(meas, cal, J0 * S)
        if p:
            _, s, Vt = np.linalg.svd(Js, full_matrices=False)
        else:
            s, Vt = np.zeros(0), np.zeros((0, 0))
        keep = (s > sigma / self.identifiable_ratio) & (s > s.max(initial=0) * 1e-12)
        V = Vt[keep].T                                                   # (p, k)
        self.n_evaluations_ = p + 1
        # directions the data cannot determine are held at the prior (the effects' starting
        # values), not at a warm start's values: a previous fit may have pushed them anywhere
        # while standing in for an effect it lacked
        prior = PhysicsModel(self.effects, self.params).theta()
        z_start = V.T @ ((theta0 - prior) / S) if p else np.zeros(0)

        def theta_of(z):
            return prior + S * (V @ z)

        def fun(z):
            A = model.predict_path(meas, theta_of(z))
            self.n_evaluations_ += 1
            return _projected(meas, cal, meas.y - A) * NM

        def jac(z):
            th = theta_of(z)
            if np.array_equal(th, theta0):
                J = J0
            else:
                _, J = model.jacobian(meas, th)
                self.n_evaluations_ += p + 1
            return -_projected(meas, cal, J * S) @ V * NM

        # Gauss-Newton in the identified coordinates, halving a step that does not lower the
        # cost. The stopping rule is physical (a further step would move the predictions by
        # less than 1 % of the noise), which a solver's relative tolerances cannot express;
        # the problem is nearly linear in the parameters' small deviations, so it converges in
        # a few Jacobians.
        k = V.shape[1]
        z = z_start
        r = fun(z)
        Jz = jac(z)
        for _ in range(self.max_iterations if k else 0):
            step = scipy.linalg.lstsq(Jz, -r, lapack_driver="gelsd")[0]
            if np.sqrt(np.mean((Jz @ step) ** 2)) <= 0.01 * self.noise_nm:
                break
            cost = r @ r
            for _ in range(30):
                r_new = fun(z + step)
                if r_new @ r_new < cost:
                    break
                step = 0.5 * step
            else:
                break                                   # no descent left: checked below
            z, r = z + step, r_new
            Jz = jac(z)
            if self.progress:
                print(f"  fit {self.effects}: calibration rms {np.sqrt(np.mean(r ** 2)):.3f} nm")
        theta = theta_of(z)
        A, J = model.jacobian(meas, theta)
        self.n_evaluations_ += p + 1
        r = _projected(meas, cal, meas.y - A)
        Jz = -_projected(meas, cal, J * S) @ V
        # convergence: a further Gauss-Newton step from here must change the predictions by
        # less than 1 % of the readings' noise (rms over the calibration readings)
        step = np.linalg.lstsq(Jz, r, rcond=None)[0] if k else np.zeros(0)
        change = float(np.sqrt(np.mean((Jz @ step) ** 2))) if k else 0.0
        rms = float(np.sqrt(np.mean(r ** 2))) if r.size else 0.0
        self.converged_ = change <= 0.01 * sigma
        self.last_step_nm_ = change * 1e9
        if not self.converged_:
            raise FitError(f"the fit of {self.effects} did not converge in {self.max_iterations} "
                           f"Gauss-Newton steps: a further step would still move the predictions "
                           f"by {change * 1e9:.3g} nm rms (calibration rms {rms * 1e9:.3g} nm, "
                           f"limit {0.01 * sigma * 1e9:.3g} nm); check the data's units and the "
                           "effects, or raise max_iterations")
        self.model_ = model
        self.theta_ = theta
        self.measurements_ = meas
        self.offsets_ = group_offsets(meas, A, cal)
        self.residual_ = residuals(meas, A, self.offsets_)
        self.prediction_ = A
        self.reading_m_ = meas.y - self.residual_      # the model's reading per row (m)
        self.cal_ = figures_nm(self.residual_, meas.cal)
        self.val_ = figures_nm(self.residual_, meas.val)
        self.jacobian_ = J
        self.identified_directions_ = V
        self._identifiability(model, s, Vt, keep, J * S, meas, r, V, theta, prior)
        return self

    def _identifiability(self, model, s, Vt, keep, JS, meas, r, V, theta, theta0):
        p, k = model.n_free, int(keep.sum())
        labels = model.labels
        dof = max(r.size - k - len(meas.groups), 1)
        sigma_r = float(np.sqrt(np.sum(r ** 2) / dof))
        Jz = _projected(meas, meas.cal, JS) @ V if k else np.zeros((r.size, 0))
        cov_z = np.linalg.pinv(Jz.T @ Jz) * sigma_r ** 2 if k else np.zeros((0, 0))
        S = model.scales
        cov = (S[:, None] * V) @ cov_z @ (S[:, None] * V).T if k else np.zeros((p, p))
        frac = np.sum(V ** 2, axis=1) if k else np.zeros(p)
        units = [f.unit for f in model.free for _ in range(f.sl.stop - f.sl.start)]
        self.parameters_ = [
            {"label": labels[j], "value": float(theta[j]), "start": float(theta0[j]),
             "unit": units[j], "uncertainty": float(np.sqrt(max(cov[j, j], 0.0))),
             "identified_fraction": float(frac[j])} for j in range(p)]
        groups = []
        for i in np.flatnonzero(~keep):
            v = Vt[i]
            members = np.flatnonzero(v ** 2 > 0.05)
            members = members[np.argsort(-v[members] ** 2)]
            groups.append({"singular_value_nm": float(s[i] * 1e9),
                           "parameters": [labels[j] for j in members],
                           "weights": [round(float(v[j]), 3) for j in members]})
        self.identifiability_ = {
            "n_parameters": p, "n_identified_directions": k,
            "singular_values_nm": [float(x * 1e9) for x in s],
            "condition_number": float(s.max() / s.min()) if p and s.min() > 0 else math.inf,
            "condition_number_identified": float(s[keep].max() / s[keep].min()) if k else None,
            "threshold_nm": float(self.noise_nm / self.identifiable_ratio),
            "not_identifiable": [labels[j] for j in range(p) if frac[j] < 0.5],
            # fitted values outside a parameter's physical range: the effect is standing in
            # for something else (often a missing effect)
            "outside_physical_range": [f"{e.name}.{n}" for e in model.effects
                                       for n in e.outside_range()],
            "unidentified_groups": groups,
            "residual_sigma_nm": sigma_r * 1e9,
        }

    # -- use ----------------------------------------------------------------------------------
    def summary(self) -> dict:
        """JSON-ready result."""
        return {"effects": self.effects, "n_parameters": self.model_.n_free,
                "converged": bool(self.converged_), "n_evaluations": self.n_evaluations_,
                "cal": _axis_p90(self.cal_), "val": _axis_p90(self.val_),
                "val_err90_nm": self.val_["all"]["err_p90"],
                "offsets_nm": {f"{s}.{a}": o * 1e9 for (s, a), o in
                               zip(self.measurements_.groups, self.offsets_)},
                "identifiability": self.identifiability_, "parameters": self.parameters_,
                "values": self.model_.values()}


def _axis_p90(fig: dict) -> dict:
    return {k: v["err_p90"] for k, v in fig.items()}


# ---------------------------------------------------------------------------------------------
# fitted model files (TOML)

def _or_nan(x):
    return math.nan if x is None else x


def fitted_toml(fit: PhysicsFit, data: str) -> str:
    """The fitted model as TOML: effects and every parameter value (SI), the fit's figures."""
    lines = ["# deltatwin physics model (calibration/physics.py); load with "
             "`deltatwin compare DATA --model THIS`",
             "[model]", f"effects = {toml_value(fit.effects)}", f"data = {toml_value(data)}",
             f"noise_nm = {fit.noise_nm!r}", f"identifiable_ratio = {fit.identifiable_ratio!r}",
             # the sensor -> part map the temperatures were taken from (the data's metadata)
             "sensors = { " + ", ".join(f"{toml_value(s)} = {toml_value(p)}" for s, p in
                                        fit.measurements_.sensors.items()) + " }",
             "", "[fit]", f"val_err90_nm = {toml_value(_or_nan(fit.val_['all']['err_p90']))}",
             f"cal_err90_nm = {toml_value(_or_nan(fit.cal_['all']['err_p90']))}",
             f"n_parameters = {fit.model_.n_free}",
             f"n_identified_directions = {fit.identifiability_['n_identified_directions']}",
             f"not_identifiable = {toml_value(fit.identifiability_['not_identifiable'])}"]
    for name, vals in fit.model_.values().items():
        lines += ["", f"[effects.{name}]"] + [f"{k} = {toml_value(v)}" for k, v in vals.items()]
    return "\n".join(lines) + "\n"


def load_fitted(path) -> tuple[PhysicsModel, dict]:
    """(model, file contents) from a fitted-model TOML file."""
    path = Path(path)
    try:
        doc = tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise FitError(f"{path}: not a fitted-model TOML file ({exc})") from exc
    if "model" not in doc or "effects" not in doc.get("model", {}):
        raise FitError(f"{path}: no [model] effects = [...]: not a fitted physics model "
                       "(write one with `deltatwin fit DATA --effects ... -o FILE`)")
    try:
        model = PhysicsModel(doc["model"]["effects"], None, doc.get("effects", {}),
                             where=f"{path} [effects]")
    except EffectError as exc:
        raise FitError(str(exc)) from exc
    return model, doc
