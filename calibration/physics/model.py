"""A physics model: library effects with free parameters, evaluated through the twin's stages on
measured conditions; its prediction of the interferometer readings and their Jacobian."""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import NamedTuple

import numpy as np
import scipy.sparse
from scipy.spatial.transform import Rotation

from deltatwin.calibration.errors import FitError
from deltatwin.calibration.metrics import error_figures
from deltatwin.calibration.physics.measurements import Measurements
from deltatwin.models import batched
from deltatwin.models.geometry import build_geometry, part_scales
from deltatwin.models.kinematics import (
    Pose,
    forward,
    pose_adjoint,
    rod_residuals,
    rod_vectors,
    rotate_about_axis,
)
from deltatwin.models.params import RobotParams, load_params
from deltatwin.twin.effects import LIBRARY, EffectError, effect_class, effect_spec, make_effect
from deltatwin.twin.effects.base import WrenchDerivatives
from deltatwin.twin.instruments.optics import (
    AXES,
    Optics,
    double_pass_reading,
    optical_path,
    optical_path_pose_gradient,
)
from deltatwin.twin.world import (
    Truth,
    geometry_temperatures,
    instrument_optics,
    kinematic_pose,
    motor_positions,
    observe,
    platform_wrench,
    point_geometry,
)

POSE_STEP = 1e-6   # m and rad: the central-difference step of the optical paths in the pose
GEOMETRY_STEP = 0.1   # of a fit scale: central differences of the joint arrays (quadratic)
DERIVATIVE_TOL = 1e-8   # relative change of a column at which the step halving stops
# a reading's round-off over the evaluations a difference combines (the 0.3 m paths carry
# ~5e-17 m each): a column's change over its step below this is noise, 1e-6 nm
READING_ROUNDOFF_M = 1e-15
# a Jacobian makes its optics columns in a background process (``jacobian``) when they hold at
# least this many rows times columns: a column costs ~0.44 us a row (12 ms at full
# paper-thermal, 28,492 rows), the fork and the block's transfer ~40 ms there
BESIDE_ROW_COLUMNS = 200_000
# rows in fewer runs of one session than this are counted run by run (PhysicsModel._counted)
SESSION_RUNS = 64
# rows per chunk where a block of Jacobian columns is formed row by row (PhysicsModel._add_counted)
ROW_CHUNK = 2048


def richardson_derivative(evaluate, step: float, max_halvings: int = 8,
                          roundoff: float = 0.0, at_zero: tuple | None = None) -> tuple:
    """The derivative at 0 of ``evaluate(offset)`` (a tuple of arrays, the last one judged):
    fourth-order central differences (f(-2h) - 8 f(-h) + 8 f(h) - f(2h)) / 12h from h = ``step``
    (a parameter's fit scale: large steps keep the predictions' round-off, ~5e-17 m of a 0.3 m
    path, small against a column that moves the readings by nanometres), the step halved while
    the estimate still changes by more than DERIVATIVE_TOL of itself (a parameter whose effect
    is strongly nonlinear over its fit scale, such as a coil's offset) and the change still
    shrinks; once it grows, round-off has taken over and the estimate before it is kept.
    Most parameters move the readings nearly linearly over their fit scale: when the two
    central differences the first stencil combines, over h and 2h, already agree to
    DERIVATIVE_TOL, or differ over the step by less than the evaluations' ``roundoff`` (the
    last array's unit: below it a halving only measures round-off), the third derivative's
    share of the estimate is below that (the stencil removes it and leaves a fifth-derivative
    one, smaller still) and the stencil is kept without a halving (four evaluations instead of
    six or more). ``at_zero``: ``evaluate(0)`` when the caller has it (a model's prediction at
    theta): then f(h), f(-h) and f(2h) come first, and when the third difference
    f(2h) - 3 f(h) + 3 f(0) - f(-h) = h^3 f3 + O(h^4) (f3 the third derivative) says the
    central difference's error, h^2 f3 / 6, is below DERIVATIVE_TOL of it, that difference less
    this error estimate is kept (three evaluations; what remains is of order h^3 times the fourth
    derivative), or the difference alone when the third difference is below the ``roundoff``
    (so a column the parameter does not move stays exactly zero); else f(-2h) and the above."""
    f = {o * step: evaluate(o * step) for o in (1.0, -1.0, 2.0)}
    if at_zero is not None:
        h = step
        central = [(a - b) / (2 * h) for a, b in zip(f[h], f[-h])]
        error = [(c - 3 * a + 3 * z - b) / (6 * h) for a, b, c, z in
                 zip(f[h], f[-h], f[2 * h], at_zero)]
        largest = np.nanmax(np.abs(error[-1]))
        if largest * h < roundoff:
            return tuple(central)           # the third difference is round-off: nothing to remove
        if largest <= DERIVATIVE_TOL * np.nanmax(np.abs(central[-1])):
            return tuple(d - e for d, e in zip(central, error))
    f[-2.0 * step] = evaluate(-2.0 * step)

    def stencil(h):
        return tuple((8 * (a - b) - (c - d)) / (12 * h) for a, b, c, d in
                     zip(f[h], f[-h], f[2 * h], f[-2 * h]))

    def relative_change(new, old):
        size = np.nanmax(np.abs(new))
        return np.nanmax(np.abs(new - old)) / size if size > 0 else 0.0

    estimates, changes, h = [stencil(step)], [], step
    central = [(f[o * step][-1] - f[-o * step][-1]) / (2 * o * step) for o in (1.0, 2.0)]
    if (relative_change(*central) < DERIVATIVE_TOL
            or np.nanmax(np.abs(central[0] - central[1])) * step < roundoff):
        return estimates[0]
    for _ in range(max_halvings):
        h = h / 2
        f[h], f[-h] = evaluate(h), evaluate(-h)
        estimates.append(stencil(h))
        change = relative_change(estimates[-1][-1], estimates[-2][-1])
        if change < DERIVATIVE_TOL:
            return estimates[-2]                    # the larger step agrees: less round-off
        if changes and change >= changes[-1]:
            return estimates[-3]                    # round-off took over at the last halving
        changes.append(change)
    return estimates[-1]


def _checked_derivatives(effect, derivatives, n_rows: int, shapes: dict):
    """``effect.wrench_derivatives``' answer, checked (a researcher's hook may be wrong): None,
    or a WrenchDerivatives whose parameters are among the effect's (``shapes``: name -> shape)
    with (n_rows, 6) + that shape, and a pose of (n_rows, 6, 9) or None; else an EffectError
    naming the effect, the entry and both shapes."""
    if derivatives is None:
        return None
    where = f"{effect.name}.wrench_derivatives"
    if not isinstance(derivatives, WrenchDerivatives):
        raise EffectError(f"{where}: returned {type(derivatives).__name__}, expected "
                          "WrenchDerivatives(parameters, pose) or None")
    wanted = {name: (n_rows, 6) + tuple(shape) for name, shape in shapes.items()}
    if derivatives.pose is not None:
        wanted["pose"] = (n_rows, 6, 9)
    given = {**derivatives.parameters, **({"pose": derivatives.pose}
                                          if derivatives.pose is not None else {})}
    for name, value in given.items():
        if name not in wanted:
            raise EffectError(f"{where}: '{name}' is not a parameter of {effect.name} "
                              f"(its parameters: {sorted(shapes)})")
        if np.shape(value) != wanted[name]:
            raise EffectError(f"{where}: '{name}' has shape {np.shape(value)}, expected "
                              f"{wanted[name]} (rows, wrench, parameter)")
    return derivatives


def as_slice(index: np.ndarray):
    """Sorted column indices as a slice when they are one range: assigning an (N, ..., k)
    block through a slice is a strided copy, through an index array or a mask a gather and
    scatter ~30x slower."""
    if index.size and index[-1] - index[0] + 1 == index.size:
        return slice(int(index[0]), int(index[-1]) + 1)
    return index


class Stage(NamedTuple):
    """What the load and optics are evaluated on: robot parameters, the geometry at the points,
    their kinematic pose, the robot's home (where the instruments were aligned), the cube's
    centre there, and the part temperatures (degC per part, N + S rows)."""
    params: RobotParams
    geom: object
    kin: Pose
    home: np.ndarray
    cube_home: np.ndarray
    node_T: dict


class Linearisation(NamedTuple):
    """What ``PhysicsModel.jacobian`` computed at its parameters that no column owns: the stage,
    what the instruments look at, the counted readings A and the compensation index, where the
    motors sit and the rods, the paths' derivatives in the deflected pose and the wrench, and
    (when it had columns that move the pose) the paths' pose sensitivities and the rod
    equations' adjoint. Kept with the model's values and robot parameters it holds for, on
    ``meas``: a probe of the diagnosis (an effect appended at values where it changes nothing)
    re-uses it instead of recomputing the model's stage (``jacobian``'s ``extends``)."""
    meas: Measurements
    params: RobotParams
    classes: dict
    values: dict
    stage: Stage
    truth: Truth
    A: np.ndarray
    n_comp: np.ndarray
    q: np.ndarray
    rods: tuple | None
    gradient: np.ndarray
    response: np.ndarray
    sensitivity: tuple | None


@dataclass(frozen=True)
class FreeParameter:
    effect: str
    name: str
    unit: str
    shape: tuple
    start: np.ndarray
    scale: float
    sl: slice
    tolerance: float          # the prior's width (Parameter ``tolerance``), unit as above

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
        try:
            classes = list(dict.fromkeys(effect_class(n, where=where) for n in effects))
        except EffectError as exc:
            raise FitError(str(exc)) from exc
        names = [c.name for c in classes]
        values = values or {}
        for cls in classes:
            if not cls.model_stages():
                raise FitError(f"{where}: effect {cls.name!r} has no model form: it acts through "
                               "the thermal network (heat or environment; in measurements its "
                               "consequences arrive through the temperature sensors, so model "
                               "what it drives instead) or at random (servo settling: part of "
                               f"the noise floor); model effects: {model_effects()}")
        unknown = sorted(set(values) - set(names))
        if unknown:
            raise FitError(f"{where}: values given for effect(s) {unknown} not in the model")
        self.params = params or load_params(None)
        self.effects, self.free, k = [], [], 0
        self.classes = dict(zip(names, classes))
        for n, cls in self.classes.items():
            given = dict(values.get(n, {}))
            start = {p.name: np.broadcast_to(p.fit_start, np.shape(p.default)).copy()
                     for p in cls.free_parameters() if p.fit_start is not None}
            try:
                # a fitted value may leave a parameter's physical range (reported, see fit)
                e = make_effect(cls, {**start, **given}, where=where, check_minimum=False)
            except EffectError as exc:
                raise FitError(str(exc)) from exc
            for p in cls.free_parameters():
                size = int(np.prod(p.shape))
                self.free.append(FreeParameter(n, p.name, p.unit, p.shape,
                                               np.asarray(e.values[p.name], float).copy(),
                                               p.fit_scale, slice(k, k + size),
                                               p.tolerance))
                k += size
            self.effects.append(e)
        self.names = names
        # how each effect is named again in a file (a user effect: its file and class)
        self.specs = [effect_spec(c) for c in classes]

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

    @property
    def tolerances(self) -> np.ndarray:
        """(p,) the prior's width of every free parameter (its unit, SI)."""
        return np.concatenate([np.full(f.sl.stop - f.sl.start, f.tolerance) for f in self.free]) \
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
        re-used); and ``part_scales``, the ``temperatures`` parameters that change nothing but
        the part temperatures the geometry is scaled by (a CTE factor: not what the sensors
        read, nor where the motors sit); ``motor_angles``, the ``temperatures`` parameters that
        change nothing but where the motors sit (a backlash, an encoder's periodic error)."""
        out = {k: np.zeros(self.n_free, bool)
               for k in ("robot", "temperatures", "load_optics", "part_scales", "motor_angles")}
        for f in self.free:
            stages = self.classes[f.effect].model_stages()
            key = ("temperatures" if {"sensed_parts", "part_temperatures", "motor_angles"}
                   & set(stages) else
                   "robot" if "robot" in stages else "load_optics")
            out[key][f.sl] = True
            out["part_scales"][f.sl] = stages == ("part_temperatures",)
            out["motor_angles"][f.sl] = stages == ("motor_angles",)
        return out

    # -- evaluation ---------------------------------------------------------------------------
    def _robot_geometry(self):
        """The robot parameters under the effects' ``robot`` hooks and their geometry."""
        params = self.params
        for e in self.effects:
            params = e.robot(params, None)
        return params, build_geometry(params)

    def _robot(self):
        params, geom0 = self._robot_geometry()
        return params, geom0, forward(geom0, np.zeros((1, 3))).p[0]

    def _kinematics(self, meas: Measurements) -> Stage:
        """The stage the load and optics are evaluated on, at the current values."""
        params, geom0, home = self._robot()
        pts = meas.points
        pts.params, pts.home_p = params, home
        pts.node_T = meas.part_temperatures(self.effects)
        geom, kin = kinematic_pose(params, geom0, self.effects, pts)
        return Stage(params, geom, kin, home, home + geom0.cube_offset, pts.node_T)

    @staticmethod
    def _stage_points(meas: Measurements, stage: Stage):
        """The measurements' points set to ``stage`` (its parameters, temperatures, home and
        kinematic pose): what the load and optics hooks read."""
        pts = meas.points
        # the stage's own temperatures: a stage re-used for a load or optics parameter was
        # computed before a later sensor parameter was stepped
        pts.params, pts.node_T, pts.home_p = stage.params, stage.node_T, stage.home
        pts.pose = stage.kin
        return pts

    def _truth(self, meas: Measurements, stage: Stage, wrench: np.ndarray | None = None) -> Truth:
        """What the instruments look at on ``stage`` (``wrench``: the effects' wrench at the
        stage when known)."""
        pts = self._stage_points(meas, stage)
        preload, C = meas.statics(self.params)
        return observe(stage.geom, stage.kin, self.effects, pts, preload, C, stage.cube_home,
                       stage.params.mirror_cube_size_m, wrench)

    def _paths(self, meas: Measurements, stage: Stage,
               wrench: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Optical path n s (m) and the index the instrument divides by, (N + S, 3) each, at the
        rows and at the session zeros (``wrench``: the effects' wrench at the stage when known)."""
        truth = self._truth(meas, stage, wrench)
        return (np.stack([truth.optical_path_m[a] for a in AXES], axis=1),
                np.stack([truth.n_comp[a] for a in AXES], axis=1))

    def _optics_paths(self, meas: Measurements, stage: Stage, pose: Pose,
                      cube_home: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """``_paths`` with the platform held at ``pose`` (the deflected pose): the effects'
        optics alone, from the instruments aligned on ``cube_home`` (the stage's by default)."""
        pts = self._stage_points(meas, stage)
        optics = instrument_optics(self.effects, pts,
                                   stage.cube_home if cube_home is None else cube_home)
        size = stage.params.mirror_cube_size_m
        return (np.stack([optical_path(pose, stage.geom.cube_offset, size, optics, a)
                          for a in AXES], axis=1),
                np.stack([optics.n_comp[a] for a in AXES], axis=1))

    def _optics_at(self, meas: Measurements, stage: Stage, truth: Truth) -> dict:
        """What a step of one optics effect's parameter re-uses (``_stepped_optics_paths``):
        per effect, the optics the effects before it make at the stage (they do not change),
        and the geometric reading h cos(alpha) per axis at the deflected pose."""
        pts = self._stage_points(meas, stage)
        optics = Optics.nominal(stage.cube_home, pts.t_s.shape[0], n_nominal=1.0)
        before = {}
        for e in self.effects:
            before[e.name] = optics
            optics = instrument_optics([e], pts, stage.cube_home, start=optics)
        size = stage.params.mirror_cube_size_m
        return {"before": before,
                "reading": {a: double_pass_reading(truth.pose, stage.geom.cube_offset, size, a,
                                                   *truth.optics.beam(a)) for a in AXES}}

    def _stepped_optics_paths(self, meas: Measurements, stage: Stage, truth: Truth, effect,
                              optics_at: dict) -> tuple[np.ndarray, np.ndarray]:
        """``_optics_paths`` at the deflected pose after a step of a parameter of ``effect``:
        only that effect and those after it are applied, on the optics the ones before it make
        (``optics_at``), and a beam whose head, direction (and fold mirror) the step left as
        they were keeps its geometric reading (an index parameter: only n changes). Equal to
        ``_optics_paths`` bit for bit."""
        pts = self._stage_points(meas, stage)
        optics = instrument_optics(self.effects[self.names.index(effect.name):], pts,
                                   stage.cube_home, start=optics_at["before"][effect.name])
        at_theta, size = truth.optics, stage.params.mirror_cube_size_m
        paths = []
        for a in AXES:
            same_beam = (np.array_equal(optics.head[a], at_theta.head[a])
                         and np.array_equal(optics.direction[a], at_theta.direction[a])
                         and (a != "z" or np.array_equal(optics.fold, at_theta.fold)))
            paths.append(optics.n_air[a] * optics_at["reading"][a] if same_beam else
                         optical_path(truth.pose, stage.geom.cube_offset, size, optics, a))
        return np.stack(paths, axis=1), np.stack([optics.n_comp[a] for a in AXES], axis=1)

    @staticmethod
    def _counted(meas: Measurements, path: np.ndarray, n_comp: np.ndarray,
                 derivative: bool = False) -> np.ndarray:
        """What the interferometers count from their session's zero, (n L - n0 L0) / n_comp, as
        the data show it (cosine corrected or not): (N, 3, ...) from paths (N + S, 3, ...).
        ``derivative``: paths are derivatives, so the correction's constant term drops out."""
        n, zero = meas.n, meas.zero_row
        # the rows come in runs of one session (a campaign's sessions follow each other): each
        # run less its zero's row, broadcast (a gather of every row's zero copies (N, 3, ...))
        starts = np.flatnonzero(zero[1:] != zero[:-1]) + 1
        if n and starts.size < SESSION_RUNS:
            counted = np.empty((n,) + path.shape[1:])
            for a, b in zip([0, *starts], [*starts, n]):
                np.subtract(path[a:b], path[zero[a]], out=counted[a:b])
        else:
            counted = path[:n] - path[zero]
        f = meas.cos_scale / n_comp[:n]
        counted *= f.reshape(f.shape + (1,) * (counted.ndim - 2))   # in place: (N, 3, p) is big
        return counted if derivative else counted + meas.cos_offset

    @staticmethod
    def _add_counted(meas: Measurements, J: np.ndarray, cols, n_comp: np.ndarray,
                     path_rows) -> None:
        """``J[:, :, cols] +=`` what the interferometers count of a paths' derivative
        (``_counted(..., derivative=True)``, the same numbers), ``path_rows(rows)`` giving the
        derivative (rows, 3, k) at a slice of the N + S rows: chunk by chunk of ROW_CHUNK rows,
        so that no (N + S, 3, k) array is made (at full scale a block of 63 columns is 44 MB,
        and every new page a process touches costs it; a chunk's few MB stay in cache)."""
        n = meas.n
        zeros = path_rows(slice(n, None))                 # the session zeros' rows, (S, 3, k)
        for a in range(0, n, ROW_CHUNK):
            rows = slice(a, min(a + ROW_CHUNK, n))
            counted = path_rows(rows)
            counted -= zeros[meas.zero_row[rows] - n]
            counted *= (meas.cos_scale[rows] / n_comp[rows])[..., None]
            J[rows, :, cols] += counted

    def _observe(self, meas: Measurements, stage, wrench: np.ndarray | None = None) -> np.ndarray:
        return self._counted(meas, *self._paths(meas, stage, wrench))

    def predict_path(self, meas: Measurements, theta: np.ndarray | None = None) -> np.ndarray:
        """(N,3) the reading each row would show up to its session's zero (m)."""
        if theta is not None:
            self.set_theta(theta)
        return self._observe(meas, self._kinematics(meas))

    def jacobian(self, meas: Measurements, theta: np.ndarray, columns: np.ndarray | None = None,
                 extends: PhysicsModel | None = None):
        """(A, J): the prediction (N,3) and its derivative (N,3,p) with respect to theta (only
        the ``columns`` mask when given, zeros elsewhere). ``extends``: a model whose effects
        this one's begin with, its last Jacobian made on ``meas`` (a fitted model, for a probe
        of the diagnosis): where that Jacobian's values and robot parameters are this model's
        and the effects appended change nothing at ``theta`` (``_linearisation_of``), its
        stage, readings and pose sensitivities are re-used (the same numbers: the appended
        effects add zeros), else all is computed here.

        A parameter that changes the geometry (the robot, or the part temperatures that scale
        it) moves the kinematic pose: the rod equations' partial derivatives at each point's
        pose, under that point's own part temperatures (the corrected geometry), give the
        pose's derivative by the implicit function theorem (models.kinematics.pose_adjoint),
        times the readings' derivative with respect to the pose; plus the parameter's direct
        effect on the readings at the fixed pose (through the part temperatures the optics read,
        or, for the robot, through its home where the instruments were aligned). The readings'
        derivative in the pose is analytic at fixed optics (optical_path_pose_gradient), in the
        wrench the same through the compliance; a load parameter differences its effect's wrench
        alone, an optics parameter the optics alone. So a fit costs no kinematics per parameter
        and no load stage per optics parameter. The remaining partial derivatives are central
        differences of smooth functions: the joint arrays (quadratic in the rod equations) with
        steps of GEOMETRY_STEP fit scales, the wrench and the instruments in the kinematic pose
        and the home with steps of 1 um and 1 urad, the rest with the stencils of
        ``richardson_derivative`` over one fit scale (the kinematics' 1e-15 m and the paths'
        5e-17 m round-off set steps this large). Checked against central differences of the
        whole prediction to 1e-7 of each column in tests/calibration/test_physics_model.py."""
        self.drop_linearisation()        # the last one freed before this one is made
        self.set_theta(theta)
        by = self.free_by_stage()
        wanted = np.ones(theta.size, bool) if columns is None else np.asarray(columns, bool)
        pts = meas.points
        base = self._linearisation_of(extends, meas)
        if base is not None:
            stage, truth, A, n_comp, rods = base.stage, base.truth, base.A, base.n_comp, base.rods
            self._stage_points(meas, stage)
            q = motor_positions(self.effects, pts)
        else:
            stage = self._kinematics(meas)
            truth = self._truth(meas, stage)
            path = np.stack([truth.optical_path_m[a] for a in AXES], axis=1)
            n_comp = np.stack([truth.n_comp[a] for a in AXES], axis=1)
            A = self._counted(meas, path, n_comp)
            # where the motors sit: the encoders' readings, or those plus an effect's errors
            q = motor_positions(self.effects, pts)
            rods = None
        # a few columns asked for (a probe's, a candidate's): each column contiguous, so that the
        # columns not computed stay untouched zero pages (written column by column, an (N,3,p)
        # array in row order is touched throughout: ~70 MB at full scale, and every new page a
        # process touches costs it); the same values and shape either way
        few = 2 * np.count_nonzero(wanted) < theta.size
        J = (np.zeros((theta.size,) + A.shape).transpose(1, 2, 0) if few
             else np.zeros(A.shape + (theta.size,)))
        # the columns that move the kinematic pose, in blocks: (columns, the rod equations'
        # derivative at the fixed pose (N + S, 6, k) or the function giving it at a slice of
        # the rows, the home's (3, k) or None: it stays)
        moving = []
        # the rods (P - A) and platform hinges (R P0) at the points, (N + S, 3, 2, 3) each
        if rods is None and np.any(wanted & ~by["load_optics"]):
            rods = rod_vectors(stage.geom, q, stage.kin)
        owner = {j: self.effects[self.names.index(f.effect)] for f in self.free
                 for j in range(f.sl.start, f.sl.stop)}
        gradient, response = ((base.gradient, base.response) if base is not None else
                              self._pose_gradients(meas, stage, truth))
        # the load and optics columns need the stage alone: a Jacobian's optics columns (a
        # whole one's ~20, a third of its time, at full paper-thermal) are made on a second
        # core where the command has one (models.batched.in_background), beside the columns
        # that move the pose; the loads' stay here, where their exact wrench derivatives serve
        # the pose sensitivity too. A few columns (a probe's, a candidate's: diagnose makes
        # them while its attribution has the second core) are all made here
        loads_optics = np.flatnonzero(wanted & by["load_optics"])
        optics = np.array([j for j in loads_optics
                           if "optics" in self.classes[owner[j].name].model_stages()], int)
        # (in this process when there is no second core, the same way: batched.in_background)
        if few or optics.size * A.shape[0] < BESIDE_ROW_COLUMNS:
            optics = optics[:0]
        # the optics a step re-uses, for the optics columns wanted (a load's wrench needs none)
        optics_at = (self._optics_at(meas, stage, truth) if any(
            "optics" in self.classes[f.effect].model_stages() and wanted[f.sl].any()
            and by["load_optics"][f.sl].any() for f in self.free) else None)
        exact = {}           # the load effects' exact wrench derivatives, asked once each

        def load_optics_column(j):
            return self._load_optics_column(meas, theta, j, owner[j], stage, truth, response,
                                            n_comp, A, optics_at, exact)

        def optics_columns():
            return np.stack([load_optics_column(j) for j in optics], axis=-1)
        beside = batched.in_background(optics_columns) if optics.size else None
        for j in np.setdiff1d(loads_optics, optics):
            J[:, :, j] = load_optics_column(j)
        robot = wanted & by["robot"]
        if robot.any():
            moving.append((np.flatnonzero(robot), *self._robot_derivatives(
                meas, theta, stage, np.flatnonzero(robot), GEOMETRY_STEP * self.scales,
                rods[0])))
        scaling = wanted & by["part_scales"]
        if scaling.any():
            d_rods, direct = self._part_scale_derivatives(meas, theta, stage, truth, gradient,
                                                          np.flatnonzero(scaling), rods)
            moving.append((np.flatnonzero(scaling), d_rods, None))
            J[:, :, as_slice(np.flatnonzero(scaling))] = self._counted(meas, direct, n_comp,
                                                                        derivative=True)
        motors = wanted & by["motor_angles"]
        if motors.any():
            moving.append((np.flatnonzero(motors), self._motor_derivatives(
                meas, theta, stage, np.flatnonzero(motors), rods), None))
        if np.any(wanted & ~by["robot"] & ~by["load_optics"] & ~by["part_scales"] & ~motors):
            # theta's rod equations (~0 at the solved pose) and readings: the third
            # difference that lets a nearly linear column keep three evaluations
            pts = self._stage_points(meas, stage)
            at_theta = (rod_residuals(stage.geom, motor_positions(self.effects, pts), stage.kin),
                        A)
        for j in np.flatnonzero(wanted & ~by["robot"] & ~by["part_scales"] & ~motors
                                & ~by["load_optics"]):
            def evaluate(offset, j=j):
                # a part temperature: the geometry at the points and what the optics read
                th = theta.copy()
                th[j] += offset
                self.set_theta(th)
                pts.node_T = meas.part_temperatures(self.effects)
                geom_j = point_geometry(stage.params, stage.geom, self.effects, pts)
                # (or a motor angle error: where the motors sit)
                return (rod_residuals(geom_j, motor_positions(self.effects, pts), stage.kin),
                        self._observe(meas, stage._replace(geom=geom_j, node_T=pts.node_T)))

            d_rods, J[:, :, j] = richardson_derivative(
                evaluate, self.scales[j], roundoff=READING_ROUNDOFF_M, at_zero=at_theta)
            moving.append((np.array([j]), d_rods[..., None], None))
        self.set_theta(theta)
        sensitivity = base.sensitivity if base is not None else None
        if moving:
            if sensitivity is None:
                d_kin, d_home_path = self._pose_sensitivity(meas, stage, truth, gradient,
                                                            response, exact)
                # the chain rule per point: the paths' derivative through the kinematic pose
                # (adjoint: three right-hand sides, not one per parameter)
                sensitivity = (d_home_path, pose_adjoint(stage.geom, q, stage.kin, d_kin, rods))
            d_home_path, adjoint = sensitivity
            # block by block (no (N + S, 6, k) array of every column), and the home's (one
            # product per chunk of rows)
            for cols, d_rods, d_home in moving:
                # the robot's block comes as a function of the rows (its (N + S, 6, 63) array
                # would be 86 MB), the others as arrays
                rods_at = d_rods if callable(d_rods) else d_rods.__getitem__
                self._add_counted(meas, J, as_slice(cols), n_comp,
                                  lambda rows, rods_at=rods_at, d_home=d_home: _through_pose(
                                      adjoint[rows], rods_at(rows),
                                      None if d_home is None else d_home_path[rows], d_home))
        if beside is not None:
            J[:, :, as_slice(optics)] = beside()
        self._linearised = Linearisation(
            meas, self.params, dict(self.classes),
            {e.name: {k: np.array(v) for k, v in e.values.items()} for e in self.effects},
            stage, truth, A, n_comp, q, rods, gradient, response, sensitivity)
        return A, J

    def drop_linearisation(self) -> None:
        """Free the last Jacobian's linearisation (as large as the Jacobian: ~50 MB at full
        scale), kept for a probe of this model's diagnosis (``jacobian``'s ``extends``)."""
        self._linearised = None

    def _linearisation_of(self, extends: PhysicsModel | None,
                          meas: Measurements) -> Linearisation | None:
        """``extends``' last Jacobian's linearisation where it holds for this model at its
        current values on ``meas``: the same measurements, robot parameters, effect classes and
        values for the effects this model begins with; the effects appended act only through
        where the motors sit and the wrench, and change neither at the stage (the motors'
        positions equal, every appended wrench zero at the kinematic pose and at the moved
        poses and homes ``_pose_sensitivity`` differences). None otherwise."""
        base = getattr(extends, "_linearised", None)
        if base is None or base.meas is not meas or base.params is not self.params:
            return None
        n = len(base.classes)
        if (list(self.classes)[:n] != list(base.classes)
                or any(self.classes[k] is not c for k, c in base.classes.items())):
            return None
        for e in self.effects[:n]:
            kept = base.values[e.name]
            if set(kept) != set(e.values) or not all(np.array_equal(kept[k], np.asarray(v))
                                                      for k, v in e.values.items()):
                return None
        added = self.effects[n:]
        stages = {s for e in added for s in self.classes[e.name].model_stages()}
        if not stages <= {"motor_angles", "wrench"}:
            return None
        pts = self._stage_points(meas, base.stage)
        if not np.array_equal(motor_positions(self.effects, pts), base.q):
            return None
        loads = [e for e in added if "wrench" in self.classes[e.name].model_stages()]
        if loads:
            kin, home = base.stage.kin, base.stage.home
            # the stage, then the places _pose_sensitivity moves it to
            places = [(kin, home)] + [(pose, home_p) for d in range(9)
                                      for pose, home_p in _moved_places(kin, home, d)]
            try:
                for pose, home_p in places:
                    pts.pose, pts.home_p = pose, home_p
                    if np.any(platform_wrench(loads, pts)):
                        return None
            finally:
                pts.pose, pts.home_p = kin, home
        return base

    def _pose_gradients(self, meas: Measurements, stage: Stage,
                        truth: Truth) -> tuple[np.ndarray, np.ndarray]:
        """The optical paths' derivatives (N + S, 3, 6) with respect to the deflected pose
        (position, a rotation vector applied on its rotation; at fixed optics, analytic) and
        with respect to the wrench (through the compliance: the deflection y = preload + C w
        moves the position by y[:3] and rotates by exp(y[3:]), whose change the exponential
        map's left Jacobian turns into a rotation applied on the deflected one)."""
        size = stage.params.mirror_cube_size_m
        gradient = np.stack([optical_path_pose_gradient(truth.pose, stage.geom.cube_offset,
                                                        size, truth.optics, a) for a in AXES],
                            axis=1)
        _, C = meas.statics(self.params)
        turn = batched.left_jacobian(truth.deflection[:, 3:].T)        # (3, 3, N + S)
        d_path_d_y = np.concatenate(
            [gradient[:, :, :3], gradient[:, :, 3:] @ turn.transpose(2, 0, 1)], axis=2)
        return gradient, d_path_d_y @ C

    def _load_optics_column(self, meas: Measurements, theta, j: int, effect, stage: Stage,
                            truth: Truth, response: np.ndarray, n_comp: np.ndarray,
                            A: np.ndarray, optics_at: dict, exact: dict) -> np.ndarray:
        """(N,3) the readings' derivative in the load or optics parameter ``j`` of ``effect``:
        its wrench's derivative through the compliance (``response``: the paths' derivative
        in the wrench) plus its optics' derivative at the deflected pose. The wrench's is the
        effect's own exact derivative when it gives one (``_wrench_derivatives``); else each
        is a difference of that effect's wrench, or of the optics alone
        (``_stepped_optics_paths``, from ``optics_at``), never of a whole load stage."""
        stages = self.classes[effect.name].model_stages()
        pts = self._stage_points(meas, stage)
        n_rows = pts.t_s.shape[0]
        if stages == ("wrench",):
            derivatives = self._wrench_derivatives(meas, stage, effect, exact)
            free = next(f for f in self.free if f.sl.start <= j < f.sl.stop)
            if derivatives is not None and free.name in derivatives.parameters:
                d_wrench = derivatives.parameters[free.name].reshape(n_rows, 6, -1)
                return self._counted(meas, np.einsum("nak,nk->na", response,
                                                     d_wrench[:, :, j - free.sl.start]),
                                     n_comp, derivative=True)

        def evaluate(offset):
            th = theta.copy()
            th[j] += offset
            self.set_theta(th)
            pts.pose = stage.kin
            out = []
            if "wrench" in stages:
                w = effect.wrench(pts)
                out.append(np.zeros((n_rows, 6)) if w is None else w)
            if "optics" in stages:
                out.append(self._counted(meas, *self._stepped_optics_paths(
                    meas, stage, truth, effect, optics_at)))
            return tuple(out)

        at_zero = []                          # theta's: the effect's wrench, the readings A
        if "wrench" in stages:
            pts.pose = stage.kin
            w = effect.wrench(pts)
            at_zero.append(np.zeros((n_rows, 6)) if w is None else w)
        if "optics" in stages:
            at_zero.append(A)
        d = richardson_derivative(evaluate, self.scales[j],
                                  roundoff=READING_ROUNDOFF_M if "optics" in stages else 0.0,
                                  at_zero=tuple(at_zero))
        self.set_theta(theta)
        column = np.zeros(A.shape)
        if "wrench" in stages:
            column += self._counted(meas, np.einsum("nak,nk->na", response, d[0]), n_comp,
                                    derivative=True)
        if "optics" in stages:
            column += d[-1]
        return column

    def _wrench_derivatives(self, meas: Measurements, stage: Stage, effect,
                            exact: dict) -> WrenchDerivatives | None:
        """``effect``'s exact wrench derivatives at the stage's kinematic pose and the current
        values (``Effect.wrench_derivatives``), asked once per Jacobian: kept in ``exact``
        by effect name for its parameters' columns and the pose sensitivity."""
        if effect.name not in exact:
            pts = self._stage_points(meas, stage)
            exact[effect.name] = _checked_derivatives(
                effect, effect.wrench_derivatives(pts), pts.t_s.shape[0],
                {p.name: p.shape for p in effect.parameters})
        return exact[effect.name]

    def _part_scale_derivatives(self, meas, theta, stage: Stage, truth: Truth, gradient,
                                cols, rods: tuple) -> tuple[np.ndarray, np.ndarray]:
        """For parameters ``cols`` that change only the part temperatures the geometry is
        scaled by: the rod equations' derivative at the fixed pose (N + S, 6, k) and the paths'
        at the fixed deflected pose (N + S, 3, k), analytic in the parts' thermal factors.
        Every joint array of a part is its factor s times the robot's (build_geometry), so a
        parameter moving log s by g moves the platform hinges R P0, the base joints B, the
        arm vectors A - B and the rod lengths L by g times themselves: with the rod P - A,
        d f / 2 = (P - A) . (R P0 g_platform - B g_base - (A - B) g_arm) - L^2 g_rod, and the
        mirror cube (R times the cube offset, g_platform) moves the paths through their
        gradient in the deflected position. Only g is differenced, with the stencils of
        ``richardson_derivative`` on the factors alone (a CTE factor's are linear in it)."""
        pts = self._stage_points(meas, stage)
        n = pts.t_s.shape[0]
        shapes = ((n,), (n, 3), (n, 3, 2), (n,))          # base, arms, rods, platform

        def factors(offset=0.0, j=None):
            th = theta.copy()
            if j is not None:
                th[j] += offset
            self.set_theta(th)
            scales = part_scales(stage.params, geometry_temperatures(self.effects, pts) or None)
            return (np.concatenate([np.broadcast_to(s, shape).reshape(n, -1)
                                    for s, shape in zip(scales, shapes)], axis=1),)

        s = factors()
        g = np.stack([richardson_derivative(lambda o, j=j: factors(o, j), self.scales[j],
                                            at_zero=s)[0] for j in cols], axis=-1) / s[0][..., None]
        self.set_theta(theta)
        g_base, g_arm, g_rod, g_plat = (g[:, 0], g[:, 1:4], g[:, 4:10].reshape(n, 3, 2, -1),
                                        g[:, 10])
        geom = stage.geom
        rod, w = rods                                  # where the motors sit
        B, L, cube = ((geom.B, geom.L, geom.cube_offset) if geom.batched else
                      (geom.B[None], geom.L[None], geom.cube_offset[None]))   # (1|N, ...)
        B = B[:, :, None, :]
        arm = stage.kin.p[:, None, None, :] + w - rod - B             # A - B, (N, 3, 2, 3)
        rod_dot = lambda v: rod[..., 0] * v[..., 0] + rod[..., 1] * v[..., 1] \
            + rod[..., 2] * v[..., 2]
        d_rods = 2 * (rod_dot(w)[..., None] * g_plat[:, None, None]
                      - rod_dot(np.broadcast_to(B, rod.shape))[..., None] * g_base[:, None, None]
                      - rod_dot(arm)[..., None] * g_arm[:, :, None]
                      - (L ** 2)[..., None] * g_rod)
        cube = np.einsum("nij,nj->ni", truth.pose.R, np.broadcast_to(cube, (n, 3)))  # world
        direct = np.einsum("nai,ni->na", gradient[:, :, :3], cube)[..., None] * g_plat[:, None]
        return d_rods.reshape(n, 6, -1), direct

    def _motor_derivatives(self, meas, theta, stage: Stage, cols, rods: tuple) -> np.ndarray:
        """For the parameters ``cols`` that change nothing but where the motors sit: the rod
        equations' derivative at the fixed pose (N + S, 6, k). A motor turning its arm by d
        moves the elbow hinge A by (axis x (A - B)) d, so its two rod equations |P - A|^2 - L^2
        change by -2 (P - A) . (axis x (A - B)) d (analytic); the motors' angles' derivative in
        each parameter is a ``richardson_derivative`` of the effects' ``motor_angles`` hooks
        alone (no kinematics). At the fixed pose the readings do not depend on where the motors
        sit (the optics and the load read the pose), so these columns have no direct part."""
        pts = self._stage_points(meas, stage)
        rod, w = rods
        geom = stage.geom
        B, axis = (geom.B, geom.axis) if geom.batched else (geom.B[None], geom.axis[None])
        arm = stage.kin.p[:, None, None, :] + w - rod - B[:, :, None, :]     # A - B
        turn = np.cross(np.broadcast_to(axis[:, :, None, :], arm.shape), arm)
        per_rad = -2 * (rod[..., 0] * turn[..., 0] + rod[..., 1] * turn[..., 1]
                        + rod[..., 2] * turn[..., 2])                        # (N + S, 3, 2)
        at_theta = (motor_positions(self.effects, pts),)

        def angles(offset, j):
            th = theta.copy()
            th[j] += offset
            self.set_theta(th)
            return (motor_positions(self.effects, pts),)

        d_angles = np.stack([richardson_derivative(lambda o, j=j: angles(o, j), self.scales[j],
                                                   at_zero=at_theta)[0] for j in cols], axis=-1)
        self.set_theta(theta)
        return (per_rad[..., None] * d_angles[:, :, None, :]).reshape(rod.shape[0], 6, -1)

    def _robot_derivatives(self, meas, theta, stage: Stage, cols, steps, rod: np.ndarray):
        """For the robot parameters ``cols``: the function giving the rod equations' derivative
        at the fixed pose at a slice of the N + S rows, (rows, 6, k), and the home's (3, k).
        Each point's joint arrays are the robot's at its parameters' temperatures times the
        parts' thermal factors at the point (models.geometry.part_scales), so their derivatives
        are too: the joint arrays are differenced once per parameter (the elbow hinges on the
        distinct motor coordinates), then every parameter's rod equations are formed at once
        from the points' rod vectors, a slice of rows at a time (the caller's chunks)."""
        pts = meas.points
        q = motor_positions(self.effects, pts)     # with an effect's angle errors, where they sit
        qu, inv = pts.unique_q() if q is pts.q else np.unique(q, axis=0, return_inverse=True)
        inv = inv.reshape(-1)
        pts.node_T = stage.node_T
        temps = geometry_temperatures(self.effects, pts)
        s_base, s_arm, s_rod, s_plat = (
            np.asarray(s / s0) for s, s0 in zip(part_scales(stage.params, temps or None),
                                                part_scales(stage.params)))
        # (scales per point: (N+S,), (N+S,3), (N+S,3,2), (N+S,); else (), (3,), (3,2), ())
        # the joint arrays' central differences, one per parameter (last axis)
        geoms = []                                  # parameter + step, parameter - step, ...
        for j in cols:
            for sign in (1.0, -1.0):
                th = theta.copy()
                th[j] += sign * steps[j]
                self.set_theta(th)
                geoms.append(self._robot_geometry()[1])
        self.set_theta(theta)
        # every stepped robot's home in one forward kinematics (a batch of robot states)
        joints = ("B", "axis", "arm_vec", "elbow_vec", "P0", "L", "theta_zero", "cube_offset")
        homes = forward(replace(geoms[0], **{f: np.stack([getattr(g, f) for g in geoms])
                                             for f in joints}),
                        np.zeros((len(geoms), 3)), check=False).p
        diff = []
        for i, j in enumerate(cols):
            sides = [(g.B, g.P0, g.L, home)
                     for g, home in zip(geoms[2 * i:2 * i + 2], homes[2 * i:2 * i + 2])]
            diff.append([(a - b) / (2 * steps[j]) for a, b in zip(*sides)])
        dB, dP0, dL, d_home = (np.stack(x, axis=-1) for x in zip(*diff))
        # the arms (B -> elbow hinge, rotated by the arm angles of the distinct motor
        # coordinates): only the parameters that change an arm's axis, vector or zero angle
        # move them (a joint or rod error does not: zero), all stepped robots in one rotation
        arm_arrays = ("axis", "arm_vec", "theta_zero")
        turning = np.array([not all(np.array_equal(getattr(geoms[2 * i], f),
                                                   getattr(geoms[2 * i + 1], f))
                                    for f in arm_arrays) for i in range(cols.size)], bool)
        k, d_arm = cols.size, None
        if turning.any():
            moved = [g for i in np.flatnonzero(turning) for g in geoms[2 * i:2 * i + 2]]
            axis, arm_vec, theta_zero = (np.stack([getattr(g, f) for g in moved])
                                         for f in arm_arrays)
            arms = rotate_about_axis(axis[:, None, :, None, :],
                                     (qu[None] + theta_zero[:, None])[..., None],
                                     arm_vec[:, None])             # (2 k', M, 3, 2, 3)
            step = 2 * steps[cols[turning]]
            d_arm = np.moveaxis((arms[0::2] - arms[1::2]) / step[:, None, None, None, None],
                                0, -1).reshape(-1, int(turning.sum()))   # (M * 18, k')
        joint_terms = np.concatenate([dP0, np.broadcast_to(dB[:, None], (3, 2, 3, k)),
                                      dL[:, :, None]], axis=2)         # (3, 2, 7, k)
        # a part's factors (and the rod lengths) per point have one axis more than one part's
        at_rows = lambda a, rows, part_ndim: a[rows] if np.ndim(a) > part_ndim else a
        L = stage.geom.L * s_rod

        def rods_at(rows: slice) -> np.ndarray:
            """The rod equations' derivative (rows, 6, k) at a slice of the points."""
            rod_r, inv_r = rod[rows], inv[rows]
            n = rod_r.shape[0]
            d_rods = np.zeros((n, 3, 2, k))
            if d_arm is not None:
                # d f / d parameter / 2 = rod . (d platform hinge - d elbow hinge) - L s_rod
                # dL, each hinge its part's factor times the robot's: the elbow hinges first,
                # each point's rod against its motor coordinates' row of d_arm (a sparse
                # product, three entries per rod equation, instead of an (n, 6, 3, k') gather),
                # for the turning parameters alone (the others' are zero: 30 of 63)
                entries = scipy.sparse.csr_matrix(
                    ((-rod_r * at_rows(s_arm, rows, 1)[..., None, None]).reshape(-1),
                     (inv_r[:, None] * 18 + np.arange(18)).reshape(-1),  # (motor coordinates,
                     np.arange(0, 18 * n + 1, 3)), shape=(6 * n, d_arm.shape[0]))  # rod, xyz)
                d_rods[..., as_slice(np.flatnonzero(turning))] = (
                    entries @ d_arm).reshape(n, 3, 2, -1)
            # then the platform hinges R P0 (rod . R dP0 = R^T rod . dP0), the base joints and
            # the rod lengths: one product per rod over [R^T rod, rod, L] and the parameters
            point_terms = np.concatenate(
                [(rod_r.reshape(n, 6, 3) @ stage.kin.R[rows]).reshape(n, 3, 2, 3)
                 * at_rows(s_plat, rows, 0)[..., None, None, None],
                 -rod_r * at_rows(s_base, rows, 0)[..., None, None, None],
                 -np.broadcast_to(at_rows(L, rows, 2), (n, 3, 2))[..., None]], axis=-1)
            for i in range(3):
                for side in range(2):
                    d_rods[:, i, side] += point_terms[:, i, side] @ joint_terms[i, side]
            d_rods *= 2
            return d_rods.reshape(n, 6, k)
        return rods_at, d_home

    def _pose_sensitivity(self, meas, stage: Stage, truth: Truth, gradient,
                          response, derivatives: dict) -> tuple[np.ndarray, np.ndarray]:
        """The paths' derivatives (N + S, 3, 6) and (N + S, 3, 3) with respect to the kinematic
        pose (position, rotation vector applied on its rotation) and the home. A kinematic pose change
        moves the deflected pose with it (``gradient``: the paths' analytic derivative there; its
        rotation carried through the deflection's) and changes the effects' wrench (a coil's
        force grows as the gap closes: ``response``, the paths' derivative in the wrench);
        the home moves the instruments aligned there and what is placed relative to it (the
        coils). The wrench's derivatives are the loads' own exact ones where they give them
        (``_wrench_derivatives``, kept in ``derivatives``), else central differences of the
        wrench alone; the instruments' are central differences of the optics alone."""
        kin = stage.kin
        turn = batched.rotation_matrices(truth.deflection[:, 3:].T)    # (3, 3, N + S)
        d_kin = np.concatenate([gradient[:, :, :3],
                                gradient[:, :, 3:] @ turn.transpose(2, 0, 1)], axis=2)
        d_home_path = np.zeros(d_kin.shape[:2] + (3,))
        loads = [e for e in self.effects if "wrench" in self.classes[e.name].model_stages()]
        # the wrench's derivative in the pose and the home (N + S, 6, 9): the loads' own
        # exact derivatives where they give them, the others' differenced below
        exact = [self._wrench_derivatives(meas, stage, e, derivatives) for e in loads]
        d_wrench = np.zeros(d_kin.shape[:1] + (6, 9))
        for x in exact:
            if x is not None and x.pose is not None:
                d_wrench += x.pose
        differenced = [e for e, x in zip(loads, exact) if x is None or x.pose is None]
        pts = self._stage_points(meas, stage)
        for d in range(0 if differenced else 6, 9):    # else only the home's optics
            wrenches, paths = [], []
            for moved, home in _moved_places(kin, stage.home, d):
                pts.pose, pts.home_p = moved, home
                if differenced:
                    wrenches.append(platform_wrench(differenced, pts))
                if d >= 6:                                   # the instruments aligned there
                    paths.append(self._optics_paths(
                        meas, stage, truth.pose, stage.cube_home + (home - stage.home))[0])
            pts.pose, pts.home_p = kin, stage.home
            if differenced:
                d_wrench[:, :, d] += (wrenches[0] - wrenches[1]) / (2 * POSE_STEP)
            if paths:
                d_home_path[:, :, d - 6] = (paths[0] - paths[1]) / (2 * POSE_STEP)
        if loads:
            d_by_pose = response @ d_wrench                  # (N + S, 3, 9)
            d_kin += d_by_pose[:, :, :6]
            d_home_path += d_by_pose[:, :, 6:]
        return d_kin, d_home_path


def _through_pose(adjoint: np.ndarray, d_rods: np.ndarray, d_home_path: np.ndarray | None,
                  d_home: np.ndarray | None) -> np.ndarray:
    """The paths' derivative (rows, 3, k) through the kinematic pose (the ``adjoint`` (rows, 3,
    6) of the rod equations' derivative ``d_rods`` (rows, 6, k)) and through the home
    (``d_home_path`` (rows, 3, 3) times the home's derivative ``d_home`` (3, k), or none)."""
    out = adjoint @ d_rods
    np.negative(out, out=out)
    if d_home is not None:
        out += (d_home_path.reshape(-1, 3) @ d_home).reshape(out.shape)
    return out


def _moved_places(kin: Pose, home: np.ndarray, d: int):
    """The two places (kinematic pose, home), + then -, of ``PhysicsModel._pose_sensitivity``'s
    central difference in pose coordinate ``d``: the position (0-2), the rotation vector applied
    on the rotation (3-5) or the home (6-8), +-POSE_STEP (m or rad)."""
    for sign in (1.0, -1.0):
        step = np.zeros(3)
        step[d % 3] = sign * POSE_STEP
        if d < 3:
            yield Pose(kin.p + step, kin.R), home
        elif d < 6:
            yield Pose(kin.p, Rotation.from_rotvec(step).as_matrix() @ kin.R), home
        else:
            yield kin, home + step


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


def projected(meas: Measurements, rows: np.ndarray, v: np.ndarray,
               scale: np.ndarray | None = None) -> np.ndarray:
    """Values v (N,3,...) on the readings of ``rows`` with each group's mean removed:
    (n_readings, ...). ``scale``: v times it (broadcast on each reading's values), the same
    numbers as projecting ``v * scale`` without that (N,3,...) copy (a full-scale Jacobian's
    is 66 MB, and every new page a process touches costs it)."""
    masks = [m for m in ((meas.group == g) & rows[:, None] for g in range(len(meas.groups)))
             if m.any()]
    out = np.empty((sum(int(np.count_nonzero(m)) for m in masks),) + v.shape[2:])
    start = 0
    for m in masks:
        x = v[m]
        if scale is not None:
            x *= scale
        np.subtract(x, x.mean(axis=0), out=out[start:start + x.shape[0]])
        start += x.shape[0]
    return out


def projected_transpose(meas: Measurements, rows: np.ndarray, x: np.ndarray) -> np.ndarray:
    """The transpose of ``projected``: (N,3,...) weights w, zero off the readings of ``rows``,
    with sum(w * v) equal to sum(x * projected(meas, rows, v)) for every v (N,3,...), ``x``
    (n_readings, ...) laid out as ``projected`` lays out its output (a group's mean removal is
    its own transpose)."""
    out = np.zeros(meas.group.shape + x.shape[1:])
    start = 0
    for m in ((meas.group == g) & rows[:, None] for g in range(len(meas.groups))):
        count = int(np.count_nonzero(m))
        if count:
            block = x[start:start + count]
            out[m] = block - block.mean(axis=0)
            start += count
    return out


def reading_response(meas: Measurements, Jz: np.ndarray, information: np.ndarray) -> np.ndarray:
    """(N,3,k) how a fit's coordinates respond to a change of the readings: dz = sum over the
    entries of W * dA for a change dA (N,3) of the calibration readings (up to its sign), by
    the estimating equations dz = information^-1 Jz^T dr (``Jz`` (n, k) the projected
    calibration Jacobian, m per fit scale; ``information`` (k, k) the equations' derivative)
    and dr = projected(dA) (``projected_transpose``)."""
    return projected_transpose(meas, meas.cal, Jz @ np.linalg.pinv(information))


def projected_rows(meas: Measurements, rows: np.ndarray) -> np.ndarray:
    """The data row of each reading ``projected`` lays out on ``rows`` (n_readings,), in its
    order."""
    masks = [(meas.group == g) & rows[:, None] for g in range(len(meas.groups))]
    return np.concatenate([np.nonzero(m)[0] for m in masks if m.any()] or [np.zeros(0, int)])


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

