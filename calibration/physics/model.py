"""A physics model: library effects with free parameters, evaluated through the twin's stages on
measured conditions; its prediction of the interferometer readings and their Jacobian."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from deltatwin.calibration.errors import FitError
from deltatwin.calibration.metrics import error_figures
from deltatwin.calibration.physics.measurements import Measurements
from deltatwin.models.geometry import build_geometry
from deltatwin.models.kinematics import Pose, forward
from deltatwin.models.params import RobotParams, load_params
from deltatwin.twin.effects import LIBRARY, EffectError, make_effect
from deltatwin.twin.instruments.optics import AXES
from deltatwin.twin.world import kinematic_pose, observe


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
    def _counted(meas: Measurements, path: np.ndarray, n_comp: np.ndarray,
                 derivative: bool = False) -> np.ndarray:
        """What the interferometers count from their session's zero, (n L - n0 L0) / n_comp, as
        the data show it (cosine corrected or not): (N, 3, ...) from paths (N + S, 3, ...).
        ``derivative``: paths are derivatives, so the correction's constant term drops out."""
        n = meas.n
        d = path[:n] - path[meas.zero_row]
        f = meas.cos_scale / n_comp[:n]
        counted = d * f.reshape(f.shape + (1,) * (d.ndim - 2))
        return counted if derivative else counted + meas.cos_offset

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
            J[:, :, chain] = self._counted(meas, dpath, n_comp, derivative=True)
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

