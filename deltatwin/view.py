"""A Rerun recording of a campaign: the robot, its workspace and the error fields of a ladder
of models, laid out for a researcher on a 1600 x 1000 screen (docs/view.md).

The recording holds (all static unless said)
* ``world/workspace/hull`` (+ ``hull_edges``): the hexagonal double pyramid;
  ``world/workspace/cal`` / ``world/workspace/val``: the commanded positions by split, all
  drawn where the mirror cube's centre is (the measured point), and the error arrows there;
* ``world/error/<k>_<step>``: model k's residual field, per position the arrow of the residual
  (model minus measurement, mean over the position's readings), at that model's own arrow
  scale, coloured by magnitude (``/arrows``: origins, vectors, class ids; the entity itself:
  the annotation context giving each class its colour and its label, the residual in nm);
  ``world/error/<k>_<step>/<axis>``: its x, y and z components alike;
* ``world/step/<k>_<step>/after`` (k >= 1): model k's residual field at model k-1's scale, to
  set beside ``world/error/<k-1>_...``: the residual before and after the step shown the same
  way;
* ``world/legend/<k>_<step>`` (and ``world/step/<k>_<step>/legend``): the colour legend of a
  scale, arrows labelled in nm (``/colours``), and the caption (``/caption``): the model, the
  scale, its validation p90 and the floor;
* ``world/axes/workspace``, ``world/axes/robot``: triads of the scene's axes, in mm;
* ``world/robot/<geom>``: every geom of the MuJoCo model (``models.mjcf``) as a mesh, posed
  along the campaign (``max_poses`` evenly spaced readings) on ``campaign_time``;
  ``world/instruments/<site>``: the interferometer and autocollimator beams;
* ``timeseries/...``: the residual per axis of each model, every temperature, the coil
  currents, the force, the reading std (acceptance) and the autocollimator angles, as points
  (one per reading) on ``campaign_time`` (s since the campaign's start);
* ``ladder/<k>_<step>`` (a bar chart each: the validation p90), ``ladder/floor``,
  ``ladder/table``, ``info`` (text), and the default blueprint (``_blueprint``): opens
  paused on the first model's field.

Ladder steps are named after their effects (``step_labels``): the first by its effects, each
later one by the effects it adds ("+ magnetic_force").  Each model's figure is the one
``deltatwin compare`` and ``diagnose`` print, the 90th percentile of |model - measurement| on
the validation rows (``calibration.physics.model.figures_nm``), and the floor beside it is
``calibration.diagnosis.floor.floor_of``'s (the achievable floor the data carry, else their
noise floor).

Units and frames (Rerun stores positions and vectors as float32): the 3D scene is in
millimetres, z up, relative to a local origin, the centre of the workspace's bounding box, so
positions keep ~1 nm.  Each field's arrows are drawn at ``1 mm = s nm`` with s a 1-2-5 step
chosen (``arrow_scale_nm_per_mm``) so the 90th-95th percentile arrow spans 15-20 % of the
workspace; the stored vector is the residual in units of s nm (float32's relative precision,
2^-24), and s is stated in the view's name, its legend and the ladder table.
"""
from __future__ import annotations

import os
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from deltatwin.files import atomic_write
from deltatwin.twin.dataset import AXES, SPLITS, temperature_columns, validate

__all__ = ["LadderStep", "RecordingSummary", "calibration_step", "model_file_step",
           "residuals_m", "position_field", "robot_meshes", "arrow_scale_nm_per_mm",
           "step_labels", "colour_legend", "tab_title", "p90_text", "floor_text",
           "write_recording", "CAMPAIGN_TIMELINE",
           "ARROW_SPAN_SHARE", "ARROW_SPAN_PERCENTILES", "AXIS_COLOURS", "SCREEN_PX"]

CAMPAIGN_TIMELINE = "campaign_time"
MM_PER_M = 1e3
NM_PER_M = 1e9
# The arrow scale: the 90th-95th percentile arrow of a field spans 15-20 % of the workspace's
# extent, with 1 mm of arrow = a 1-2-5 step of nm (a scale a reader can multiply in the head).
ARROW_SPAN_SHARE = (0.15, 0.20)
ARROW_SPAN_PERCENTILES = (90.0, 95.0)
_ARROW_STEPS = (1.0, 2.0, 5.0)
# Colours: the points are cool (blue, teal), the field's colour map warm (dark red for small,
# through orange, to light yellow for arrows at or above the 20 % span), so arrows never blend
# with points; time series cycle a qualitative palette (matplotlib tab10).
SPLIT_COLOURS = {"cal": (60, 120, 255), "val": (0, 200, 190)}
FIELD_COLOURMAP = ("YlOrRd_r", 0.0, 0.85)          # matplotlib name, used part of its range
BEAM_COLOURS = {"interferometer": (255, 40, 40), "autocollimator": (40, 200, 60)}
FLOOR_COLOUR = (150, 150, 150)                     # the floor's bar beside the models'
SCREEN_PX = (1600, 1000)     # the layout (shares, legend room) is planned for this window
AXIS_COLOURS = {"x": (214, 39, 40), "y": (44, 160, 44), "z": (31, 119, 180)}   # tab10's
# The 3D field views look at the workspace from the front right and above (azimuth from +x
# towards +y, elevation, deg), so the colour legend stands to the right of the workspace on
# the screen and the axes' triad to its left.
VIEW_DIRECTION_DEG = (-60.0, 25.0)
VIEW_FOV_Y_DEG = 55.0        # the viewer's vertical field of view (its default eye)
_ERROR_TAB_SHARES = (0.5, 0.5)                     # 3D field | residual series and ladder
_COIL_COLUMNS = ("coil1_A", "coil2_A", "coil3_A")
_STD_COLUMN = re.compile(r"^(.+)_std_([A-Za-z]+)$")
_AUTOCOLLIMATOR_COLUMN = re.compile(r"^ac\d+_r[xyz]_arcsec$")


@dataclass(frozen=True)
class LadderStep:
    """One model of the ladder: its name, the interferometer readings it predicts for every
    row of the dataset, ``reading_m`` (n_rows, 3) in m for x, y, z (NaN where it predicts
    none), and the effects (or feature families) it contains, which name it in the recording
    (``step_labels``).  The residual is ``reading_m`` minus the measured readings."""
    name: str
    reading_m: np.ndarray
    effects: tuple[str, ...] = ()


@dataclass
class RecordingSummary:
    """What was written: file, frames, and per ladder step its figures and arrow scale."""
    path: Path
    origin_m: np.ndarray                 # local origin of the 3D scene (world frame, m)
    extent_mm: float                     # largest extent of the workspace's bounding box
    pose_rows: np.ndarray                # dataset rows at which the robot is posed
    position_ids: np.ndarray             # pos_id of every commanded position (sorted)
    ladder: list[dict] = field(default_factory=list)   # per step: label, entity, rms_*_nm,
    #                                                     p90_nm, arrow_scale_nm_per_mm, ...
    floor_nm: dict | None = None         # the floor the models are judged against, by axis
    floor_kind: str = "none"             # "achievable", "noise" or "none" (floor_of)
    blueprint: object = None             # the default rerun.blueprint.Blueprint written


# ----- ladder steps -------------------------------------------------------------------------

def calibration_step(name: str, model, df: pd.DataFrame) -> LadderStep:
    """A ladder step from a fitted calibration model (``calibration.blackbox``), its effects
    being the model's feature families.

    DGM: its per-axis predictions.  DirectIGM (q = f(X, Y, Z, F)): the measured readings plus
    its end-effector error ``J^-1 (q_pred - q_meas)``, the reading its motor-coordinate error
    amounts to (first order)."""
    from deltatwin.calibration.blackbox.dgm import DGM
    from deltatwin.calibration.blackbox.direct_igm import DirectIGM
    from deltatwin.calibration.diagnosis.compare import dgm_reading_m
    if isinstance(model, DGM):
        reading = dgm_reading_m(model, df)
    elif isinstance(model, DirectIGM):
        reading = measured_m(df) + model.position_error(df)
    else:
        raise TypeError(f"ladder step {name!r}: {type(model).__name__} is not a calibration "
                        "model (DGM or DirectIGM)")
    return LadderStep(name, reading, tuple(f.name for f in model.features_.families))


def model_file_step(path: str | os.PathLike, df: pd.DataFrame, meta: dict | None,
                    trust_effects=False) -> LadderStep:
    """A ladder step from a model file, named after the model's effects (a physics model) or
    feature families (a calibration model), not after the file.

    ``.json``: a saved calibration model (``calibration_step``).  ``.toml``: a fitted physics
    model (``deltatwin fit -o``), evaluated on the dataset's conditions (``meta['sensors']``
    places the temperature sensors) with each (session, axis) zero re-estimated on the
    dataset's calibration rows, as ``deltatwin compare`` does (``calibration.diagnosis.
    compare.evaluate``): its residual field is the one ``compare`` reports. The user effects a
    physics model names run only with ``trust_effects`` (``load_fitted``)."""
    from deltatwin.calibration.blackbox.model_file import load_model
    from deltatwin.calibration.diagnosis.compare import evaluate, load_model_file
    from deltatwin.calibration.errors import CalibrationInputError
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in (".json", ".toml"):
        raise ValueError(f"{path}: unknown model file type {path.suffix!r}; expected a "
                         "calibration model (.json) or a fitted physics model (.toml)")
    model = load_model(path) if suffix == ".json" else load_model_file(path, trust_effects)
    try:
        if suffix == ".json":
            step = calibration_step(path.stem, model, df)
            return LadderStep(" + ".join(step.effects), step.reading_m, step.effects)
        effects = tuple(e.name for e in model.effects)
        return LadderStep(" + ".join(effects) or "nominal robot",
                          evaluate(df, meta, model).reading_m, effects)
    except CalibrationInputError as exc:
        raise ValueError(f"{path}: cannot be evaluated on this dataset: {exc}") from exc


def step_labels(ladder) -> list[str]:
    """The name of each step in the recording: a step with effects is named by them, "+ e"
    for the effects it adds when it holds all of the previous step's; without effects, by its
    ``name``."""
    labels, previous = [], ()
    for step in ladder:
        effects = tuple(step.effects)
        added = [e for e in effects if e not in previous]
        if not effects:
            labels.append(str(step.name))
        elif previous and added and set(previous) <= set(effects):
            labels.append("+ " + " + ".join(added))
        else:
            labels.append(" + ".join(effects))
        previous = effects
    return labels


def measured_m(df: pd.DataFrame) -> np.ndarray:
    """Interferometer readings (n, 3) in m; NaN where an axis was not measured."""
    out = np.full((len(df), 3), np.nan)
    for k, a in enumerate(AXES):
        if f"{a}_nm" in df.columns:
            out[:, k] = df[f"{a}_nm"].to_numpy(dtype=float) / NM_PER_M
    return out


def residuals_m(df: pd.DataFrame, step: LadderStep) -> np.ndarray:
    """Model minus measurement (n, 3) in m; NaN where either is missing."""
    return step.reading_m - measured_m(df)


def position_field(pos_id: np.ndarray, residual: np.ndarray):
    """Mean residual per commanded position, per axis, over its readings with a value.

    Returns ``(ids, field)``: the sorted position ids and (n_ids, 3) means, NaN on an axis
    without any finite residual at that position."""
    ids, inv = np.unique(pos_id, return_inverse=True)
    ok = np.isfinite(residual)
    sums = np.zeros((ids.size, 3))
    counts = np.zeros((ids.size, 3))
    for k in range(3):
        sums[:, k] = np.bincount(inv, np.where(ok[:, k], residual[:, k], 0.0), ids.size)
        counts[:, k] = np.bincount(inv, ok[:, k], ids.size)
    with np.errstate(invalid="ignore", divide="ignore"):
        return ids, np.where(counts > 0, sums / counts, np.nan)


# ----- geometry and scales ------------------------------------------------------------------

def robot_meshes(model) -> list[tuple[str, object, np.ndarray]]:
    """Every visible geom of a compiled MuJoCo model as ``(name, trimesh in the geom frame (m),
    rgba 0..1)``; the table under the robot is left out."""
    import mujoco
    import trimesh
    T = mujoco.mjtGeom
    out = []
    for g in range(model.ngeom):
        name = model.geom(g).name or f"geom{g}"
        if name == "table":
            continue
        kind, size = model.geom_type[g], model.geom_size[g]
        if kind == T.mjGEOM_BOX:
            mesh = trimesh.creation.box(extents=2.0 * size)
        elif kind == T.mjGEOM_CYLINDER:
            mesh = trimesh.creation.cylinder(radius=size[0], height=2.0 * size[1], sections=32)
        elif kind == T.mjGEOM_CAPSULE:
            mesh = trimesh.creation.capsule(height=2.0 * size[1], radius=size[0], count=[16, 16])
        elif kind == T.mjGEOM_SPHERE:
            mesh = trimesh.creation.icosphere(subdivisions=2, radius=size[0])
        elif kind == T.mjGEOM_ELLIPSOID:
            mesh = trimesh.creation.icosphere(subdivisions=2, radius=1.0)
            mesh.apply_scale(size)
        elif kind == T.mjGEOM_MESH:
            mid = model.geom_dataid[g]
            v0, nv = model.mesh_vertadr[mid], model.mesh_vertnum[mid]
            f0, nf = model.mesh_faceadr[mid], model.mesh_facenum[mid]
            mesh = trimesh.Trimesh(model.mesh_vert[v0:v0 + nv].copy(),
                                   model.mesh_face[f0:f0 + nf].copy(), process=False)
        else:
            raise ValueError(f"MuJoCo geom {name!r}: type {mujoco.mjtGeom(kind).name} has no "
                             "mesh conversion")
        out.append((name, mesh, model.geom_rgba[g].copy()))
    return out


def arrow_scale_nm_per_mm(magnitude_nm, extent_mm: float) -> float:
    """nm of residual per mm of arrow for a field of arrow magnitudes ``magnitude_nm`` (nm),
    in a workspace of ``extent_mm``: the 1-2-5 step (1, 2, 5 x 10^n) for which the
    90th-95th percentile arrows span ``ARROW_SPAN_SHARE`` (15-20 %) of the extent.

    The percentiles' lengths form an interval and so does the target; the chosen step is one
    where they overlap (the most central one if several do) or, when no 1-2-5 step makes them
    overlap (steps are 2-2.5x apart, the target band 1.33x wide), the nearest in log length."""
    m = np.asarray(magnitude_nm, dtype=float)
    m = m[np.isfinite(m)]
    if m.size == 0 or not np.max(m) > 0.0:
        return 1.0
    if not (np.isfinite(extent_mm) and extent_mm > 0):
        raise ValueError(f"workspace extent must be a positive number of mm, got {extent_mm}")
    lo_nm, hi_nm = np.percentile(m, ARROW_SPAN_PERCENTILES)
    if not hi_nm > 0.0:              # most positions exactly zero: scale on the largest
        lo_nm = hi_nm = float(np.max(m))
    lo_nm = max(lo_nm, hi_nm * 1e-12)
    share_lo, share_hi = ARROW_SPAN_SHARE
    decades = np.arange(np.floor(np.log10(lo_nm / (share_hi * extent_mm))) - 1,
                        np.ceil(np.log10(hi_nm / (share_lo * extent_mm))) + 2)
    best = None
    for step in (s * 10.0 ** d for d in decades for s in _ARROW_STEPS):
        span_lo, span_hi = lo_nm / step / extent_mm, hi_nm / step / extent_mm
        gap = max(0.0, np.log(share_lo / span_hi), np.log(span_lo / share_hi))
        off_centre = abs(np.log(np.sqrt(span_lo * span_hi) / np.sqrt(share_lo * share_hi)))
        if best is None or (gap, off_centre) < best[0]:
            best = ((gap, off_centre), step)
    return float(best[1])


def _field_colours(magnitude_nm: np.ndarray, scale: float, extent_mm: float) -> np.ndarray:
    """RGB of each arrow: the colour map from 0 to the magnitude whose arrow spans the top of
    ``ARROW_SPAN_SHARE`` at ``scale`` (saturating above), so colour and length agree."""
    import matplotlib
    name, lo, hi = FIELD_COLOURMAP
    top = scale * ARROW_SPAN_SHARE[1] * extent_mm
    c = matplotlib.colormaps[name](lo + (hi - lo) * np.clip(magnitude_nm / top, 0.0, 1.0))
    return (c[:, :3] * 255).round().astype(np.uint8)


def _screen_axes() -> tuple[np.ndarray, np.ndarray]:
    """From the scene towards the eye (``VIEW_DIRECTION_DEG``), and the screen's right (a
    horizontal unit vector)."""
    az, el = np.radians(VIEW_DIRECTION_DEG)
    to_eye = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    right = np.cross(-to_eye, (0.0, 0.0, 1.0))
    return to_eye, right / np.linalg.norm(right)


def _eye_on(framed_mm: np.ndarray) -> _Eye:
    """An eye from ``VIEW_DIRECTION_DEG`` on the centre of the box around ``framed_mm``, with
    their half width and height on the screen."""
    to_eye, right = _screen_axes()
    target = framed_mm.min(axis=0) / 2.0 + framed_mm.max(axis=0) / 2.0
    screen_up = np.cross(right, -to_eye)
    return _Eye(to_eye, target,
                (float(np.max(np.abs((framed_mm - target) @ right))),
                 float(np.max(np.abs((framed_mm - target) @ screen_up)))))


def _stage(vertices_mm: np.ndarray, extent_mm: float) -> _Stage:
    """The field views' stage around the workspace (its hull's ``vertices_mm``): seen from
    ``VIEW_DIRECTION_DEG``, the legend's column right of it, as tall as the workspace (up to
    8 rows), its caption above the workspace, the triad at its lower left, and the eye on
    them all."""
    _, right = _screen_axes()
    up = np.array([0.0, 0.0, 1.0])
    across = vertices_mm @ right
    bottom, top = float(vertices_mm[:, 2].min()), float(vertices_mm[:, 2].max())
    gap, row = 0.08 * extent_mm, (top - bottom) / 8.0
    legend_x = float(across.max()) + gap
    triad = _round_step_below(0.3 * extent_mm)
    triad_origin = (float(across.min()) - gap - triad) * right + bottom * up
    # what the eye frames: the workspace, the legend's arrows and room for their labels, the
    # caption's three lines, the triad
    legend_end = legend_x + (ARROW_SPAN_SHARE[1] + 0.1) * extent_mm
    caption_z = top + 2.5 * row
    eye = _eye_on(np.vstack([vertices_mm, legend_end * right + top * up,
                             legend_end * right + bottom * up, triad_origin,
                             triad_origin + triad * np.eye(3),
                             (caption_z + row) * up + across.min() * right,
                             (caption_z + row) * up + legend_end * right]))
    caption = (eye.target_mm - (eye.target_mm @ up) * up) + caption_z * up
    return _Stage(right=right, legend_x_mm=legend_x, legend_top_mm=top, row_mm=row,
                  caption_mm=caption, triad_origin_mm=triad_origin, triad_mm=triad, eye=eye)


def _round_step_below(x: float) -> float:
    """The largest round step (1, 2, 2.5, 5 x 10^n) not above ``x`` > 0."""
    d = np.floor(np.log10(x))
    return max(m * 10.0 ** e for e in (d - 1, d) for m in (1.0, 2.0, 2.5, 5.0)
               if m * 10.0 ** e <= x * (1.0 + 1e-9))


def colour_legend(scale: float, extent_mm: float) -> list[tuple[float, str]]:
    """The legend of a field drawn at ``scale`` nm per mm of arrow in a workspace of
    ``extent_mm``: ``(nm, label)`` from small to large, round values a round step apart (3 to
    7 of them), then the top of the colour map, the magnitude whose arrow spans
    ``ARROW_SPAN_SHARE[1]`` of the workspace, which every larger arrow shares."""
    top = scale * ARROW_SPAN_SHARE[1] * extent_mm
    step = _round_step_below(top / 4.0)
    n = int(np.floor(top / step * (1.0 - 1e-9)))
    values = [(k * step, f"{float(f'{k * step:.6g}'):g} nm") for k in range(1, n + 1)]
    return values + [(top, f"\u2265 {_three_digits(top)} nm")]


def _three_digits(v: float) -> str:
    """``v`` to three significant digits, without an exponent (0.0123, 3.72, 74.4, 3718)."""
    if v == 0 or not np.isfinite(v):
        return f"{v:g}"
    return f"{v:.{max(0, 2 - int(np.floor(np.log10(abs(v)))))}f}"


def _marker_sizes(n: int) -> np.ndarray:
    """Point sizes of a plot's n series, from 3 down to 1.5 (the later drawn over the earlier:
    series with equal values, such as three coils fed one current, show as nested dots)."""
    return np.linspace(3.0, 1.5, n) if n > 1 else np.array([2.0])


def _palette(n: int) -> list[tuple[int, int, int]]:
    """n distinct colours (tab10, or tab20 beyond ten)."""
    import matplotlib
    cmap = matplotlib.colormaps["tab10" if n <= 10 else "tab20"]
    return [tuple(int(round(255 * v)) for v in cmap(i % cmap.N)[:3]) for i in range(n)]


def _pose_robot(geom, model, q: np.ndarray, names: list[str], progress: bool):
    """Pose the MuJoCo model at motor coordinates ``q`` (F, 3); geom poses and cube centres."""
    import mujoco

    from deltatwin.models.kinematics import forward
    from deltatwin.models.mjcf import pose_model
    from deltatwin.progress import progress_bar
    data = mujoco.MjData(model)
    pose = forward(geom, q)
    gid = np.array([model.geom(n).id for n in names])
    cube = model.site("mirror_cube_centre").id
    F = len(q)
    gpos, gmat, cpos = np.empty((F, gid.size, 3)), np.empty((F, gid.size, 3, 3)), np.empty((F, 3))
    for f in progress_bar(range(F), desc="view: posing the robot", disable=not progress, leave=False):
        pose_model(model, data, q[f], pose.p[f], pose.R[f])
        gpos[f] = data.geom_xpos[gid]
        gmat[f] = data.geom_xmat[gid].reshape(-1, 3, 3)
        cpos[f] = data.site_xpos[cube]
    return gpos, gmat, cpos, data


def _beams(model, data, params, cube_centre: np.ndarray, cube_home: np.ndarray) -> dict:
    """Beam polylines (F, k, 3) of every instrument site, from its head to the mirror cube face
    it looks at.  A beam that passes above or below the cube (the Z interferometer) turns at a
    fixed 45 deg fold mirror under (or over) the cube's home and runs vertically to the cube's
    bottom (or top) face."""
    from deltatwin.models.mjcf import INSTRUMENT_SITES
    half = params.mirror_cube_size_m / 2.0
    out = {}
    for name in INSTRUMENT_SITES:
        s = model.site(name).id
        head = data.site_xpos[s].copy()
        d = data.site_xmat[s].reshape(3, 3)[:, 2]
        F = len(cube_centre)
        below = cube_home[2] - head[2]                  # > 0: the beam passes under the cube
        if abs(d[2]) < 1e-12 and abs(below) > half:
            mirror = head + d * np.dot(cube_home - head, d)
            face = np.column_stack([np.full(F, mirror[0]), np.full(F, mirror[1]),
                                    cube_centre[:, 2] - np.sign(below) * half])
            out[name] = np.stack([np.broadcast_to(head, (F, 3)), np.broadcast_to(mirror, (F, 3)),
                                  face], axis=1)
        else:
            length = (cube_centre - half * d - head) @ d
            out[name] = np.stack([np.broadcast_to(head, (F, 3)), head + length[:, None] * d],
                                 axis=1)
    return out


# ----- what is drawn ------------------------------------------------------------------------

def _slug(k: int, name: str) -> str:
    return f"{k}_" + (re.sub(r"[^A-Za-z0-9]+", "_", name).strip("_") or "model")


def _rms_nm(res: np.ndarray) -> float:
    v = res[np.isfinite(res)]
    return float(np.sqrt(np.mean(v ** 2)) * NM_PER_M) if v.size else float("nan")


@dataclass
class _Field:
    """One model's residual field: per position (ids sorted) the mean residual (nm) on the
    axes the model has (0 elsewhere), which positions have it, and its arrow scale."""
    vector_nm: np.ndarray
    keep: np.ndarray
    axes: np.ndarray
    scale: float

    @property
    def magnitude_nm(self) -> np.ndarray:
        return np.linalg.norm(self.vector_nm, axis=1)


@dataclass
class _Eye:
    """A 3D view's eye: its direction from the scene (unit), its target (mm) and the half
    width and height (mm, on the screen) of what it must frame."""
    to_eye: np.ndarray
    target_mm: np.ndarray
    half_mm: tuple[float, float]

    def position_mm(self, aspect: float) -> np.ndarray:
        """Where the eye frames it all (12 % margin) in a view of width / height ``aspect``
        (the viewer's vertical field of view: ``VIEW_FOV_Y_DEG``)."""
        t = np.tan(np.radians(VIEW_FOV_Y_DEG) / 2.0)
        half_w, half_h = self.half_mm
        return self.target_mm + 1.12 * max(half_h / t, half_w / (t * aspect)) * self.to_eye

    def controls(self, size_px: tuple[float, float]):
        """The blueprint's eye for a view of ``size_px`` (width, height)."""
        import rerun.blueprint as rrb
        return rrb.EyeControls3D(position=self.position_mm(size_px[0] / size_px[1]),
                                 look_target=self.target_mm, eye_up=(0.0, 0.0, 1.0))


@dataclass
class _Stage:
    """Where a 3D field view puts what it shows beside the workspace (mm, scene frame): the
    screen's right (``VIEW_DIRECTION_DEG``: a horizontal unit vector), the legend's column
    (left end along ``right``, height of its top and the rows' spacing), its caption's
    place, the axes' triad (origin and arrow length), and the eye."""
    right: np.ndarray
    legend_x_mm: float
    legend_top_mm: float
    row_mm: float
    caption_mm: np.ndarray
    triad_origin_mm: np.ndarray
    triad_mm: float
    eye: _Eye


@dataclass
class _Scene:
    """The 3D scene of the fields: the commanded positions (mm from the local origin), their
    ids and splits, the workspace's extent (mm) and the field views' stage."""
    pos_mm: np.ndarray
    ids: np.ndarray
    split: np.ndarray
    extent_mm: float
    stage: _Stage

    @property
    def class_ids(self) -> np.ndarray:
        """Each position's class in the fields' annotation contexts: its id where every id
        is a class id (0-65535), else its index."""
        ids = np.asarray(self.ids)
        fits = (np.issubdtype(ids.dtype, np.number) and np.all(ids == np.round(ids))
                and ids.min() >= 0 and ids.max() <= 65535)
        return (ids if fits else np.arange(ids.size)).astype(np.uint16)


@dataclass
class _Series:
    entity: str
    name: str
    values: np.ndarray
    colour: tuple
    marker_size: float       # the first of a plot's series largest: coincident ones stay seen


@dataclass
class _Panel:
    origin: str
    title: str
    series: list[_Series]


def _check_ladder(df: pd.DataFrame, ladder) -> list[LadderStep]:
    ladder = list(ladder)
    for k, step in enumerate(ladder):
        if not isinstance(step, LadderStep):
            raise TypeError(f"ladder entry {k} is a {type(step).__name__}, not a LadderStep")
        if not str(step.name).strip() and not step.effects:
            raise ValueError(f"ladder entry {k} has an empty name and no effects")
        r = np.asarray(step.reading_m)
        if r.shape != (len(df), 3):
            raise ValueError(f"ladder step {step.name!r}: reading_m has shape {r.shape}, "
                             f"expected ({len(df)}, 3) (one x, y, z per dataset row)")
        if not np.isfinite(residuals_m(df, step)).any():
            raise ValueError(f"ladder step {step.name!r}: no row has both a prediction and a "
                             "measured reading (x_nm, y_nm, z_nm)")
    return ladder


def _fields(pos_id, residuals, extent_mm, arrow_scale) -> list[_Field]:
    out = []
    for res in residuals:
        mean_nm = position_field(pos_id, res)[1] * NM_PER_M
        axes = np.isfinite(mean_nm).any(axis=0)          # axes this model has residuals on
        keep = np.all(np.isfinite(mean_nm[:, axes]), axis=1)
        vec = np.where(axes, mean_nm, 0.0)
        scale = (float(arrow_scale) if arrow_scale is not None else
                 arrow_scale_nm_per_mm(np.linalg.norm(vec[keep], axis=1), extent_mm))
        out.append(_Field(vec, keep, axes, scale))
    return out


def _residual_panels(labels, slugs, residuals) -> list[_Panel]:
    """One plot per model: its residual per reading, x, y, z in their usual red, green, blue
    (``AXIS_COLOURS``)."""
    panels = []
    for label, slug, res in zip(labels, slugs, residuals):
        series = [_Series(f"timeseries/residual_nm/{slug}/{a}", f"{a} (nm)",
                          res[:, k] * NM_PER_M, AXIS_COLOURS[a], size)
                  for (k, a), size in zip(enumerate(AXES), _marker_sizes(3))
                  if np.isfinite(res[:, k]).any()]
        panels.append(_Panel(f"timeseries/residual_nm/{slug}",
                             f"{label}: residual per reading (nm)", series))
    return panels


def _campaign_panels(df: pd.DataFrame) -> list[_Panel]:
    """The campaign's recorded signals, one panel per unit."""
    def panel(origin, title, cols, names):
        cols = [c for c in cols if np.isfinite(df[c].to_numpy(dtype=float)).any()]
        if not cols:
            return []
        return [_Panel(origin, title, [
            _Series(f"{origin}/{names(c)}", c, df[c].to_numpy(dtype=float), colour, size)
            for c, colour, size in zip(cols, _palette(len(cols)), _marker_sizes(len(cols)))])]

    std_units = {}
    for c in df.columns:
        m = _STD_COLUMN.match(c)
        if m:
            std_units.setdefault(m.group(2), []).append(c)
    return (panel("timeseries/temperature_C", "temperatures (degC)", temperature_columns(df),
                  lambda c: c[2:-2])
            + panel("timeseries/coil_current_A", "coil currents (A)",
                    [c for c in _COIL_COLUMNS if c in df.columns], lambda c: c[:-2])
            + panel("timeseries/force_N", "force simulator: nominal force (N)",
                    [c for c in ("F_N",) if c in df.columns], lambda c: c[:-2])
            + [p for unit, cols in std_units.items()
               for p in panel(f"timeseries/std_{unit}", f"std of each reading ({unit})", cols,
                              lambda c: c)]
            + panel("timeseries/autocollimator_arcsec", "autocollimator angles (arcsec)",
                    [c for c in df.columns if _AUTOCOLLIMATOR_COLUMN.match(c)],
                    lambda c: c[:-7]))


# ----- the recording ------------------------------------------------------------------------

def write_recording(df: pd.DataFrame, meta: dict, ladder=(), path="run.rrd", *, params=None,
                    max_poses: int = 500, arrow_scale: float | None = None,
                    progress: bool = False) -> RecordingSummary:
    """Write the Rerun recording of a dataset (and optional ladder of models) to ``path``.

    ``df``, ``meta``: a dataset (twin.dataset.read_dataset).  ``ladder``: LadderStep list, in
    the order the effects are added.  ``params``: robot parameters (default: the nominal set)
    for the MuJoCo model and the kinematics placing the positions.  ``max_poses``: the robot
    is posed at this many readings at most, evenly spaced over the campaign.
    ``arrow_scale``: nm of residual per mm of arrow for every field (default: per field, the
    1-2-5 step of ``arrow_scale_nm_per_mm``).  The file is written to a temporary name and
    renamed when complete.
    """
    import rerun as rr

    from deltatwin.calibration.diagnosis.floor import floor_of
    from deltatwin.models.geometry import build_geometry
    from deltatwin.models.kinematics import check_stroke
    from deltatwin.models.params import load_params
    from deltatwin.twin.workspace import hull

    df, ladder = _checked(df, ladder, max_poses, arrow_scale)
    params = params or load_params()
    geom = build_geometry(params)
    t_s = df["t_s"].to_numpy(dtype=float)
    q = df[["q1_rad", "q2_rad", "q3_rad"]].to_numpy(dtype=float)
    check_stroke(geom, q, "view: dataset motor coordinates (q1_rad, q2_rad, q3_rad) of row")

    # the workspace, the local origin and the commanded positions, all at the mirror cube's
    # centre (what the instruments measure; the platform origin lies inside the plate)
    ws = hull(geom, point=geom.cube_offset)
    origin = ws.bounds.mean(axis=0)
    scene = _scene(df, q, geom, ws, origin)

    # the ladder's fields, the panels of time series, the robot along the campaign
    labels = step_labels(ladder)
    slugs = [_slug(k, label) for k, label in enumerate(labels)]
    residuals = [residuals_m(df, s) for s in ladder]
    fields = _fields(df["pos_id"].to_numpy(), residuals, scene.extent_mm, arrow_scale)
    residual_panels = _residual_panels(labels, slugs, residuals)
    campaign_panels = _campaign_panels(df)
    robot = _robot(geom, params, q, origin, max_poses, progress)

    path = Path(path)
    floor = floor_of(meta)
    summary = RecordingSummary(path=path, origin_m=origin, extent_mm=scene.extent_mm,
                               pose_rows=robot.rows, position_ids=scene.ids,
                               floor_nm=floor[0], floor_kind=floor[1])
    summary.ladder = _ladder_rows(df, ladder, labels, slugs, residuals, fields)
    summary.blueprint = _blueprint(summary, scene, robot.eye, fields, residual_panels,
                                   campaign_panels, t_s)

    def write(tmp):
        rec = rr.RecordingStream("deltatwin")
        try:
            rec.set_log_time_enabled(False)
            rec.save(tmp, default_blueprint=summary.blueprint)
            _log_scene(rec, robot.meshes, ws, origin, scene)
            _log_robot(rec, robot, origin, t_s[robot.rows])
            _log_fields(rec, summary.ladder, fields, scene, floor)
            for p in residual_panels + campaign_panels:
                _log_panel(rec, p, t_s)
            _log_ladder(rec, summary.ladder, floor)
            _log_info(rec, df, meta, summary, len(df))
            rec.flush()
        finally:
            rec.disconnect()

    atomic_write(path, write)
    return summary


def _checked(df, ladder, max_poses: int, arrow_scale) -> tuple[pd.DataFrame, list]:
    """The dataset (rows renumbered) and the ladder, checked, with the options."""
    validate(df, "view: dataset")
    ladder = _check_ladder(df, ladder)
    if max_poses < 1:
        raise ValueError(f"max_poses must be >= 1, got {max_poses}")
    if arrow_scale is not None and not (np.isfinite(arrow_scale) and arrow_scale > 0):
        raise ValueError(f"arrow_scale must be a positive number of nm per mm, got {arrow_scale}")
    return df.reset_index(drop=True), ladder


def _scene(df, q, geom, ws, origin) -> _Scene:
    """The commanded positions (the kinematic position of the mirror cube's centre at each
    ``pos_id``'s mean motor coordinates, mm from ``origin``), their splits, and the stage."""
    from deltatwin.models.kinematics import forward
    ids, first, inv = np.unique(df["pos_id"].to_numpy(), return_index=True, return_inverse=True)
    q_mean = np.column_stack([np.bincount(inv, q[:, k], ids.size) for k in range(3)])
    q_mean /= np.bincount(inv, minlength=ids.size)[:, None]
    pos_mm = (forward(geom, q_mean).point(geom.cube_offset) - origin) * MM_PER_M
    extent_mm = float(np.max(ws.extents) * MM_PER_M)
    return _Scene(pos_mm=pos_mm, ids=ids, split=df["split"].astype(str).to_numpy()[first],
                  extent_mm=extent_mm, stage=_stage((ws.vertices - origin) * MM_PER_M, extent_mm))


@dataclass
class _Robot:
    """The MuJoCo robot posed at dataset ``rows``: its geoms (meshes, names, fixed to the
    room or not), their poses (F, G, 3) and (F, G, 3, 3) (m, world) and the beams."""
    meshes: list
    names: list
    fixed: np.ndarray
    rows: np.ndarray
    gpos: np.ndarray
    gmat: np.ndarray
    beams: dict
    triad_origin_mm: np.ndarray          # the robot view's triad and eye (_robot_framing)
    triad_mm: float
    eye: _Eye


def _robot_framing(meshes, gpos, gmat, origin) -> tuple[np.ndarray, float, _Eye]:
    """The robot view's triad, at the lower left of the robot posed at ``gpos``, ``gmat``
    (a round length near a quarter of the robot's extent), and its eye on both."""
    _, right = _screen_axes()
    up = np.array([0.0, 0.0, 1.0])
    corners = np.vstack([(mesh.bounding_box.vertices @ R.T + p - origin) * MM_PER_M
                         for (_, mesh, _), p, R in zip(meshes, gpos, gmat)])
    extent = float(np.max(np.ptp(corners, axis=0)))
    triad = _round_step_below(0.25 * extent)
    triad_origin = ((float(np.min(corners @ right)) - 0.05 * extent - triad) * right
                    + float(np.min(corners[:, 2])) * up)
    return triad_origin, triad, _eye_on(np.vstack([corners, triad_origin,
                                                    triad_origin + 1.25 * triad * np.eye(3)]))


def _robot(geom, params, q, origin, max_poses: int, progress: bool) -> _Robot:
    """The robot posed at ``max_poses`` readings at most, evenly spaced (first and last);
    ``origin``: the scene's local origin (world frame, m)."""
    from deltatwin.models.kinematics import forward
    from deltatwin.models.mjcf import build_model
    _, model = build_model(params)
    meshes = robot_meshes(model)
    names = [n for n, _, _ in meshes]
    rows = np.unique(np.linspace(0, len(q) - 1, min(max_poses, len(q))).round().astype(int))
    gpos, gmat, cube, data = _pose_robot(geom, model, q[rows], names, progress)
    cube_home = forward(geom, np.zeros((1, 3))).point(geom.cube_offset)[0]
    beams = _beams(model, data, params, cube, cube_home)
    fixed = np.array([model.body_weldid[model.geom(n).bodyid[0]] == 0 for n in names])
    return _Robot(meshes, names, fixed, rows, gpos, gmat, beams,
                  *_robot_framing(meshes, gpos[0], gmat[0], origin))


def _ladder_rows(df, ladder, labels, slugs, residuals, fields) -> list[dict]:
    """Per step its figures: RMS per split, and the statistic ``deltatwin compare`` and
    ``diagnose`` print, the 90th percentile of |model - measurement| per axis and pooled
    (``figures_nm``, the same function) over the validation rows (every row without any)."""
    from deltatwin.calibration.physics.model import figures_nm
    split = df["split"].astype(str).to_numpy()
    p90_rows = "val" if (split == "val").any() else "all"
    rows = []
    for k, (step, label, slug, res, f) in enumerate(zip(ladder, labels, slugs, residuals,
                                                        fields)):
        mag = f.magnitude_nm[f.keep]
        figures = figures_nm(res, split == "val" if p90_rows == "val" else np.ones(len(df), bool))
        entry = {"step": k, "name": step.name, "label": label, "effects": list(step.effects),
                 "entity": slug, "axes": [a for a, on in zip(AXES, f.axes) if on],
                 "n_positions": int(f.keep.sum()), "rms_nm": _rms_nm(res),
                 "p90_rows": p90_rows,
                 "p90_nm": {a: v["err_p90"] for a, v in figures.items()
                            if v["err_p90"] is not None},
                 "arrow_scale_nm_per_mm": f.scale,
                 "p95_position_nm": float(np.percentile(mag, 95)) if mag.size else float("nan"),
                 "max_position_nm": float(mag.max()) if mag.size else float("nan")}
        for s in SPLITS:
            entry[f"rms_{s}_nm"] = _rms_nm(res[split == s])
        rows.append(entry)
    return rows


def _log_arrows(rec, path: str, vector_nm, labels, f: _Field, scene: _Scene,
                scale: float) -> None:
    """A field's arrows at its positions, drawn at ``scale`` (``path/arrows``: origins,
    vectors and one class id per arrow, its position's id), and their colours (by length)
    and labels as the classes of an annotation context at ``path``.  The viewer's hover card
    lists an instance's components when there are at most three: so a pointer on an arrow
    shows its class, the label with its residual in nm (the view sets width and hidden
    labels as defaults, ``_field_view``)."""
    import rerun as rr
    keep = f.keep
    colours = _field_colours(np.linalg.norm(vector_nm[keep], axis=1), scale, scene.extent_mm)
    ids = scene.class_ids[keep]
    rec.log(path, rr.AnnotationContext([
        rr.ClassDescription(info=rr.AnnotationInfo(id=int(i), label=text, color=tuple(c)))
        for i, text, c in zip(ids, np.asarray(labels)[keep], colours.tolist())]), static=True)
    rec.log(f"{path}/arrows", rr.Arrows3D(origins=scene.pos_mm[keep],
                                          vectors=vector_nm[keep] / scale, class_ids=ids),
            static=True)


def _arrow_labels(f: _Field, scene: _Scene, axis: str | None = None) -> list[str]:
    """Per position its residual in nm first (the hover card shows ~30 characters): the
    length and the components on the model's axes, or (``axis``) that component alone."""
    where = [f"pos {i} ({s})" for i, s in zip(scene.ids, scene.split)]
    if axis is not None:
        k = AXES.index(axis)
        return [f"{axis} {v:+.1f} nm at {w}" for w, v in zip(where, f.vector_nm[:, k])]
    axes = [(k, a) for k, a in enumerate(AXES) if f.axes[k]]
    return [f"{m:.1f} nm at {w}: " + ", ".join(f"{a} {v[k]:+.1f}" for k, a in axes) + " nm"
            for w, m, v in zip(where, f.magnitude_nm, f.vector_nm)]


def _log_fields(rec, rows, fields, scene: _Scene, floor) -> None:
    """Each model's field at its own scale (``world/error/<entity>``), and its x, y and z
    components as fields of their own (``world/error/<entity>/<axis>``), with the colour
    legend of that scale; from the second model on, its field again at the previous model's
    scale (``world/step/<entity>/after``), to set beside the previous field (before / after
    the step), with the legend of that scale."""
    for k, (row, f) in enumerate(zip(rows, fields)):
        e = row["entity"]
        labels = _arrow_labels(f, scene)
        _log_arrows(rec, f"world/error/{e}", f.vector_nm, labels, f, scene, f.scale)
        for a in row["axes"]:
            component = np.where(np.arange(3) == AXES.index(a), f.vector_nm, 0.0)
            _log_arrows(rec, f"world/error/{e}/{a}", component, _arrow_labels(f, scene, a), f,
                        scene, f.scale)
        _log_legend(rec, f"world/legend/{e}", f.scale, scene, _caption(row, f.scale, floor))
        if k == 0:
            continue
        scale = fields[k - 1].scale
        _log_arrows(rec, f"world/step/{e}/after", f.vector_nm, labels, f, scene, scale)
        _log_legend(rec, f"world/step/{e}/legend", scale, scene, _caption(row, scale, floor))


def p90_text(p90_nm: dict) -> str:
    """'54.2 nm (x 50.1, y 60.2, z 30.3)': pooled, then per axis (nm)."""
    axes = ", ".join(f"{a} {p90_nm[a]:.1f}" for a in AXES if a in p90_nm)
    return (f"{p90_nm['all']:.1f} nm ({axes})" if "all" in p90_nm else f"({axes} nm)")


def floor_text(floor) -> str:
    """The floor line of a legend and of ``deltatwin view``'s output, in the ladder's
    statistic: ``floor`` = (nm by axis or None, kind), as ``RecordingSummary`` holds it."""
    values, kind = floor
    if not values:
        return "floor: none recorded with the data"
    return f"{kind} floor {p90_text(values)}"


def _caption(row: dict, scale: float, floor) -> str:
    """A field view's legend title: what the arrows are, the scale, the model's validation
    p90 and the floor in the same statistic (what ``deltatwin compare`` prints)."""
    rows = "validation" if row["p90_rows"] == "val" else "all readings'"
    return "\n".join([f"{row['label']}: |model - measurement|, 1 mm = {scale:g} nm",
                      f"{rows} p90 {p90_text(row['p90_nm'])}",
                      floor_text(floor)])


def _log_legend(rec, entity: str, scale: float, scene: _Scene, caption: str) -> None:
    """The colour legend of a field view: one arrow per legend value, drawn at ``scale`` and in
    its colour, labelled in nm, in a column right of the workspace; the caption above the
    workspace."""
    import rerun as rr
    st = scene.stage
    entries = colour_legend(scale, scene.extent_mm)
    nm = np.array([v for v, _ in entries])
    rows = st.legend_top_mm - st.row_mm * np.arange(nm.size)
    origins = st.legend_x_mm * st.right + rows[:, None] * np.array([0.0, 0.0, 1.0])
    rec.log(f"{entity}/colours", rr.Arrows3D(
        origins=origins, vectors=(nm / scale)[:, None] * st.right,
        colors=_field_colours(nm, scale, scene.extent_mm), radii=rr.Radius.ui_points(3.0),
        labels=[text for _, text in entries], show_labels=True), static=True)
    rec.log(f"{entity}/caption", rr.Points3D([st.caption_mm], radii=rr.Radius.ui_points(0.5),
                                             colors=[(200, 200, 200)], labels=[caption],
                                             show_labels=True), static=True)


def _log_axes(rec, entity: str, origin_mm: np.ndarray, length_mm: float) -> None:
    """A triad of the scene's axes, X red, Y green, Z blue, ``length_mm`` long, each labelled
    ("X 5 mm") past its tip."""
    import rerun as rr
    colours = [AXIS_COLOURS[a] for a in AXES]
    labels = [f"{a.upper()} {length_mm:g} mm" for a in AXES]
    rec.log(entity, rr.Arrows3D(
        origins=np.tile(origin_mm, (3, 1)), vectors=np.eye(3) * length_mm, colors=colours,
        radii=rr.Radius.ui_points(2.5), labels=labels, show_labels=False), static=True)
    rec.log(f"{entity}/labels", rr.Points3D(
        origin_mm + 1.25 * length_mm * np.eye(3), colors=colours,
        radii=rr.Radius.ui_points(0.5), labels=labels, show_labels=True), static=True)


def _log_panel(rec, panel: _Panel, t_s: np.ndarray) -> None:
    import rerun as rr
    for s in panel.series:
        ok = np.isfinite(s.values)
        if not ok.any():
            continue
        # every value is a reading (taken at one position, at one time): points, not lines
        # drawn between positions
        rec.log(s.entity, rr.SeriesPoints(names=s.name, colors=[s.colour],
                                          marker_sizes=[s.marker_size]), static=True)
        rec.send_columns(s.entity, indexes=[rr.TimeColumn(CAMPAIGN_TIMELINE, duration=t_s[ok])],
                         columns=rr.Scalars.columns(scalars=s.values[ok]))


def _log_ladder(rec, rows, floor) -> None:
    """The ladder as bars, each model's validation p90 of |model - measurement| (every axis
    pooled, as ``deltatwin compare`` and ``diagnose`` print it) and the floor's beside them
    (``ladder/floor``, grey), and as a table with the per-axis figures, the RMS and the
    arrow scale."""
    import rerun as rr
    if not rows:
        return
    for r, colour in zip(rows, _palette(len(rows))):
        rec.log(f"ladder/{r['entity']}",
                rr.BarChart([r["p90_nm"]["all"]], abscissa=[r["step"]], color=colour),
                static=True)
    values, kind = floor
    pooled = bool(values) and "all" in values
    if pooled:
        rec.log("ladder/floor", rr.BarChart([values["all"]], abscissa=[len(rows)],
                                            color=FLOOR_COLOUR), static=True)
    on = "validation split" if rows[0]["p90_rows"] == "val" else "dataset (no validation split)"
    floor_note = (f"grey: the {kind} floor." if pooled else
                  f"the {kind} floor (per axis only) in the table's last row." if values else
                  "no floor recorded with the data.")
    lines = [f"Bars: p90 of |model - measurement| over every reading and axis of the {on}, "
             f"as `deltatwin compare` prints it; {floor_note}", "",
             "| # | model | p90 nm | x | y | z | RMS val nm | RMS cal nm | 1 mm of arrow |",
             "|---:|---|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r['step']} | {r['label']} | " + _table_figures(r["p90_nm"])
                     + f" | {r['rms_val_nm']:.3g} | {r['rms_cal_nm']:.3g} | "
                     f"{r['arrow_scale_nm_per_mm']:g} nm |")
    if values:
        lines.append(f"| | **{kind} floor** | " + _table_figures(values) + " | | | |")
    rec.log("ladder/table", rr.TextDocument("\n".join(lines), media_type=rr.MediaType.MARKDOWN),
            static=True)


def _table_figures(p90_nm: dict) -> str:
    return " | ".join(f"{p90_nm[a]:.1f}" if a in p90_nm else "-" for a in ("all", *AXES))


def _log_scene(rec, meshes, ws, origin, scene: _Scene) -> None:
    """The scene's frame (mm, z up) and its triads, the robot's meshes, the workspace and the
    commanded positions by split."""
    import rerun as rr
    ids, pos_mm, split = scene.ids, scene.pos_mm, scene.split
    _log_axes(rec, "world/axes/workspace", scene.stage.triad_origin_mm, scene.stage.triad_mm)
    rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    for name, mesh, rgba in meshes:
        rec.log(f"world/robot/{name}",
                rr.Mesh3D(vertex_positions=mesh.vertices * MM_PER_M,
                          triangle_indices=mesh.faces, vertex_normals=mesh.vertex_normals,
                          albedo_factor=(rgba * 255).round().astype(np.uint8)), static=True)
    rec.log("world/workspace/hull",
            rr.Mesh3D(vertex_positions=(ws.vertices - origin) * MM_PER_M,
                      triangle_indices=ws.faces, vertex_normals=ws.vertex_normals,
                      albedo_factor=[150, 160, 190, 35]), static=True)
    sharp = ws.face_adjacency_edges[ws.face_adjacency_angles > 0.1]
    rec.log("world/workspace/hull_edges",
            rr.LineStrips3D((ws.vertices[sharp] - origin) * MM_PER_M,
                            radii=rr.Radius.ui_points(1.0), colors=[150, 160, 190]), static=True)
    for s, colour in SPLIT_COLOURS.items():
        sel = split == s
        rec.log(f"world/workspace/{s}",
                rr.Points3D(pos_mm[sel], colors=colour, radii=rr.Radius.ui_points(3.0),
                            labels=[f"pos {i}" for i in ids[sel]], show_labels=False),
                static=True)


def _log_robot(rec, robot: _Robot, origin, t_rows) -> None:
    """Geoms on moving bodies and the beams along the campaign; those fixed to the room
    (base, coils, instruments) once; a triad of the scene's axes at the robot's lower left."""
    import rerun as rr
    names, fixed, gpos, gmat = robot.names, robot.fixed, robot.gpos, robot.gmat
    _log_axes(rec, "world/axes/robot", robot.triad_origin_mm, robot.triad_mm)
    campaign = [rr.TimeColumn(CAMPAIGN_TIMELINE, duration=t_rows)]
    for g, name in enumerate(names):
        trans = (gpos[:, g] - origin) * MM_PER_M
        if fixed[g]:
            rec.log(f"world/robot/{name}", rr.Transform3D(translation=trans[0],
                                                          mat3x3=gmat[0, g]), static=True)
        else:
            rec.send_columns(f"world/robot/{name}", indexes=campaign,
                             columns=rr.Transform3D.columns(translation=trans, mat3x3=gmat[:, g]))
    for name, pts in robot.beams.items():
        kind = name.split("_")[0]
        strips = list((pts - origin) * MM_PER_M)
        rec.log(f"world/instruments/{name}", rr.LineStrips3D.from_fields(
            colors=BEAM_COLOURS.get(kind, (200, 200, 200)), radii=rr.Radius.ui_points(1.5)),
            static=True)
        rec.send_columns(f"world/instruments/{name}", indexes=campaign,
                         columns=rr.LineStrips3D.columns(strips=strips).partition(
                             [1] * len(strips)))


def _log_info(rec, df, meta, summary: RecordingSummary, n_rows) -> None:
    import rerun as rr
    o = summary.origin_m * MM_PER_M
    splits = ", ".join(f"{s} {n}" for s, n in df.groupby("split")["pos_id"].nunique().items())
    text = "\n".join([
        f"**{meta.get('scenario', 'dataset')}** ({meta.get('source', 'unknown source')}): "
        f"{n_rows} readings, {summary.position_ids.size} positions ({splits}).", "",
        "* Arrows: model - measurement, mean per position; **1 mm of arrow = the view's "
        "scale** (in its name and its legend), chosen so the 90-95th percentile arrow spans "
        f"{ARROW_SPAN_SHARE[0]:.0%}-{ARROW_SPAN_SHARE[1]:.0%} of the "
        f"{summary.extent_mm:.1f} mm workspace. Colour: the legend beside the workspace, "
        "in nm. The pointer on an arrow shows its residual in nm.",
        "* Above the workspace: the model's validation p90 of |model - measurement| and the "
        "floor, as `deltatwin compare` prints them. Tab *per axis*: x, y, z apart.",
        "* Points: calibration blue, validation teal.",
        f"* mm (the triad: X red, Y green, Z blue), z up, from the workspace centre "
        f"({o[0]:.2f}, {o[1]:.2f}, {o[2]:.2f}) mm. Robot posed at {summary.pose_rows.size} "
        f"readings along `{CAMPAIGN_TIMELINE}`."])
    rec.log("info", rr.TextDocument(text, media_type=rr.MediaType.MARKDOWN), static=True)


# ----- the default layout -------------------------------------------------------------------

# A tab bar in the viewer: per tab its title's characters and the icon and gaps around them,
# and at its right end the view's buttons (help, visibility, maximise).  Px at SCREEN_PX,
# with a margin over what screenshots of the viewer measured: 5.1-6.4 px a character,
# 40-41 px a tab's icon and gaps, 70 px the buttons
TAB_CHAR_PX, TAB_CHROME_PX, TAB_BUTTONS_PX = 7.0, 44.0, 80.0
# Heights (px at SCREEN_PX): the viewer's own bars (menu, top tabs, time panel collapsed), a
# plot's title or tab bar and x tick labels, and the least plot area with y tick labels at
# any data range (``_error_tab``)
WINDOW_CHROME_PX, PLOT_CHROME_PX, PLOT_MIN_PX = 100.0, 60.0, 240.0
TITLE_PX = 24.0              # a view's title bar, a tab bar


def tab_title(text: str, width_px: float, n_tabs: int) -> str:
    """``text`` as the title of one of ``n_tabs`` tabs sharing ``width_px``: cut, with an
    ellipsis, to the characters its share holds, so every tab's title shows."""
    chars = int(((width_px - TAB_BUTTONS_PX) / max(n_tabs, 1) - TAB_CHROME_PX) / TAB_CHAR_PX)
    return text if len(text) <= chars else text[:max(chars - 1, 1)].rstrip() + "\u2026"


def _field_view(name: str, entity: str | None, legend: str | None, stage: _Stage,
                size_px: tuple[float, float]):
    """A 3D view of the workspace (hull, points), its axes' triad, the arrows of the field
    ``entity`` (``_log_arrows``) and its ``legend`` (entities under ``world``) only, so the
    view frames them (the robot, 20 times larger, would shrink them to a few pixels); seen
    from the stage's eye, framed for the view's planned ``size_px`` (width, height).  The
    hull does not take the pointer: hovering an arrow shows the arrow's label."""
    import rerun as rr
    import rerun.blueprint as rrb
    contents = ["$origin/workspace/**", "$origin/axes/workspace/**"]
    contents += [f"$origin/{entity}/arrows"] if entity else []
    contents += [f"$origin/{legend}/**"] if legend else []
    passive = rrb.EntityBehavior(interactive=False)
    return rrb.Spatial3DView(
        origin="world", name=name, contents=contents, line_grid=rrb.LineGrid3D(visible=False),
        defaults=[rr.Arrows3D.from_fields(radii=rr.Radius.ui_points(2.0), show_labels=False)],
        eye_controls=stage.eye.controls(size_px),
        overrides={"world/workspace/hull": passive, "world/workspace/hull_edges": passive})


def _time_axis(panels_px: list, t_s: np.ndarray):
    """The x range every time-series plot shares: the whole campaign, and past its last
    reading room for the widest legend in the narrowest plot (``panels_px``: (panel, plot
    width px) pairs), where the legend (top right) covers no data.  Not linked: Rerun's
    link to a global range ignores a range set in the blueprint."""
    import rerun.blueprint as rrb
    t0, t1 = float(np.min(t_s)), float(np.max(t_s))
    room = 0.0
    for panel, width_px in panels_px:
        legend_px = 7.5 * max(len(s.name) for s in panel.series) + 45.0
        plot_px = max(width_px - 70.0, 2.0 * legend_px)           # minus the y axis labels
        room = max(room, legend_px / (plot_px - legend_px))
    span = max(t1 - t0, 1.0)
    return rrb.TimeAxis(view_range=rrb.TimeRange(
        start=rrb.TimeRangeBoundary.absolute(seconds=t0 - 0.01 * span),
        end=rrb.TimeRangeBoundary.absolute(seconds=t1 + (0.01 + room) * span)))


def _series_view(panel: _Panel, name: str, axis):
    import rerun.blueprint as rrb
    return rrb.TimeSeriesView(origin=panel.origin, name=name, axis_x=axis,
                              plot_legend=rrb.PlotLegend(corner=rrb.Corner2D.RightTop,
                                                         visible=True))


def _model_views(rows, fields, stage, size_px):
    """The error-field tab's 3D tabs: per model its field at its own scale."""
    return [_field_view(tab_title(f"{r['label']}: 1 mm = {f.scale:g} nm", size_px[0],
                                  len(rows)),
                        f"error/{r['entity']}", f"legend/{r['entity']}", stage, size_px)
            for r, f in zip(rows, fields)]


def _content_px() -> tuple[float, float]:
    """Width and height (px at SCREEN_PX) below the viewer's own bars and the top tabs."""
    return SCREEN_PX[0], SCREEN_PX[1] - WINDOW_CHROME_PX - TITLE_PX


def _axes_tab(rows, fields, stage):
    """Per model (a tab each) a 2 x 2 grid: its x, y and z residual fields and its field."""
    import rerun.blueprint as rrb
    width, height = _content_px()
    cell = (width / 2, (height - TITLE_PX) / 2 - TITLE_PX)
    grids = []
    for r, f in zip(rows, fields):
        e, scale = r["entity"], f.scale
        views = [_field_view(tab_title(f"{a} residual: {r['label']}, 1 mm = {scale:g} nm",
                                       cell[0], 1), f"error/{e}/{a}", f"legend/{e}", stage, cell)
                 for a in r["axes"]]
        views.append(_field_view(tab_title(f"|residual|: {r['label']}, 1 mm = {scale:g} nm",
                                           cell[0], 1), f"error/{e}", f"legend/{e}", stage,
                                 cell))
        grids.append(rrb.Grid(*views, grid_columns=2,
                              name=tab_title(r["label"], width, len(rows))))
    return rrb.Tabs(*grids, active_tab=0, name="per axis")


def _steps_tab(rows, fields, stage):
    """Per step (a tab each) the previous model's field above the new model's, both at the
    previous model's scale: the residual before and after the step shown the same way."""
    import rerun.blueprint as rrb
    width, height = _content_px()
    half, steps = (width, (height - TITLE_PX) / 2 - TITLE_PX), []
    for k in range(1, len(rows)):
        prev, r, s = rows[k - 1], rows[k], fields[k - 1].scale
        # one above the other: the views are wide, and the stage is wider than tall
        steps.append(rrb.Vertical(
            _field_view(f"before: {prev['label']}, 1 mm = {s:g} nm", f"error/{prev['entity']}",
                        f"legend/{prev['entity']}", stage, half),
            _field_view(f"after: {r['label']}, 1 mm = {s:g} nm", f"step/{r['entity']}/after",
                        f"step/{r['entity']}/legend", stage, half),
            name=tab_title(f"before/after {r['label']}", width, len(rows) - 1)))
    return rrb.Tabs(*steps, active_tab=0, name="before/after")


def _error_tab(summary, fields, stage, residual_panels, axis):
    """The 3D fields on the left (a tab per model); on the right the residual per reading (a
    tab per model), the ladder's bars, and its table and the info (a tab each).  Heights
    planned in px at SCREEN_PX: a plot's y tick labels show when the grid lines a power of
    ten apart are more than 20 px apart (egui_plot), one tenth of the plot's height at
    worst, so every plot keeps ``PLOT_MIN_PX``."""
    import rerun.blueprint as rrb
    rows = summary.ladder
    width, height = _content_px()
    right_px = width * _ERROR_TAB_SHARES[1]
    left = (width * _ERROR_TAB_SHARES[0], height - TITLE_PX)
    spatial = (_model_views(rows, fields, stage, left) if rows
               else [_field_view("workspace: calibration and validation positions", None, None,
                                 stage, left)])
    info = rrb.TextDocumentView(origin="info", name="info")
    side, heights = [info], [1.0]
    if rows:
        residuals = [_series_view(p, tab_title(p.title, right_px, len(rows)), axis)
                     for p in residual_panels]
        bars = rrb.BarChartView(origin="ladder", contents=["$origin/**", "- $origin/table"],
                                name="validation p90 |model - measurement| per model, and the "
                                     "floor (nm)", plot_legend=rrb.Corner2D.RightTop)
        text = rrb.Tabs(rrb.TextDocumentView(origin="ladder/table", name="ladder"), info,
                        active_tab=0)
        side = [rrb.Tabs(*residuals, active_tab=0), bars, text]
        plot_px = PLOT_MIN_PX + PLOT_CHROME_PX
        heights = [plot_px, plot_px, SCREEN_PX[1] - WINDOW_CHROME_PX - 2 * plot_px]
    return rrb.Horizontal(rrb.Tabs(*spatial, active_tab=0),
                          rrb.Vertical(*side, row_shares=heights),
                          column_shares=list(_ERROR_TAB_SHARES), name="error fields")


def _blueprint(summary, scene: _Scene, robot_eye: _Eye, fields, residual_panels,
               campaign_panels, t_s):
    """Top tabs: "error fields" (``_error_tab``), "per axis" (``_axes_tab``), "before/after"
    (``_steps_tab``, from two models on), "robot and beams", "campaign" (the recorded
    signals, one unit per plot, two columns from three plots on).  Every time-series plot
    has the same, linked, x axis (``_time_axis``).  Opens paused on the first model's field,
    side and time panels collapsed."""
    import rerun.blueprint as rrb
    width, rows, stage = SCREEN_PX[0], summary.ladder, scene.stage
    # at most three rows of plots: each keeps PLOT_MIN_PX
    rows_px = (SCREEN_PX[1] - WINDOW_CHROME_PX) / (PLOT_MIN_PX + PLOT_CHROME_PX)
    columns = max(1, int(np.ceil(len(campaign_panels) / max(int(rows_px), 1))))
    axis = _time_axis([(p, width * _ERROR_TAB_SHARES[1]) for p in residual_panels]
                      + [(p, width / columns) for p in campaign_panels], t_s)
    tabs = [_error_tab(summary, fields, stage, residual_panels, axis)]
    tabs += [_axes_tab(rows, fields, stage)] if rows else []
    tabs += [_steps_tab(rows, fields, stage)] if len(rows) > 1 else []
    tabs.append(rrb.Spatial3DView(
        origin="world", name="robot and beams",
        contents=["$origin/robot/**", "$origin/instruments/**", "$origin/workspace/**",
                  "$origin/axes/robot/**"], eye_controls=robot_eye.controls(_content_px())))
    if campaign_panels:
        tabs.append(rrb.Grid(*[_series_view(p, p.title, axis) for p in campaign_panels],
                             grid_columns=columns, name="campaign"))
    return rrb.Blueprint(rrb.Tabs(*tabs, active_tab=0),
                         rrb.TimePanel(state="collapsed", timeline=CAMPAIGN_TIMELINE,
                                       play_state="paused"),
                         rrb.BlueprintPanel(state="collapsed"),
                         rrb.SelectionPanel(state="collapsed"), collapse_panels=True)
