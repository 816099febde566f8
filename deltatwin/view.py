"""A Rerun recording of a campaign: the robot, its workspace and the error fields of a ladder
of models, laid out for a researcher on a 1600 x 1000 screen (docs/view.md).

The recording holds (all static unless said)
* ``world/workspace/hull`` (+ ``hull_edges``): the hexagonal double pyramid;
  ``world/workspace/cal`` / ``world/workspace/val``: the commanded positions by split, all
  drawn where the mirror cube's centre is (the measured point), and the error arrows there;
* ``world/error/<k>_<step>``: model k's residual field, per position the arrow of the residual
  (model minus measurement, mean over the position's readings), at that model's own arrow
  scale, coloured by magnitude;
* ``world/step/<k>_<step>/after`` (k >= 1): model k's residual field at model k-1's scale, to
  set beside ``world/error/<k-1>_...``: the residual before and after the step shown the same
  way;
* ``world/robot/<geom>``: every geom of the MuJoCo model (``models.mjcf``) as a mesh, posed
  along the campaign (``max_poses`` evenly spaced readings) on ``campaign_time``;
  ``world/instruments/<site>``: the interferometer and autocollimator beams;
* ``timeseries/...``: the residual per axis of each model, every temperature, the coil
  currents, the force, the reading std (acceptance) and the autocollimator angles, as points
  (one per reading) on ``campaign_time`` (s since the campaign's start);
* ``ladder/<k>_<step>`` (a bar chart each: the RMS residual), ``ladder/table``, ``info`` (text), and the
  default blueprint (``_blueprint``): opens paused on the first model's field.

Ladder steps are named after their effects (``step_labels``): the first by its effects, each
later one by the effects it adds ("+ magnetic_force").

Units and frames (Rerun stores positions and vectors as float32): the 3D scene is in
millimetres, z up, relative to a local origin, the centre of the workspace's bounding box, so
positions keep ~1 nm.  Each field's arrows are drawn at ``1 mm = s nm`` with s a 1-2-5 step
chosen (``arrow_scale_nm_per_mm``) so the 90th-95th percentile arrow spans 15-20 % of the
workspace; the stored vector is the residual in units of s nm (float32's relative precision,
2^-24), and s is stated in the view's name and the ladder table.
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
           "step_labels", "write_recording", "CAMPAIGN_TIMELINE", "ARROW_SPAN_SHARE",
           "ARROW_SPAN_PERCENTILES", "SCREEN_PX"]

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
SCREEN_PX = (1600, 1000)     # the layout (shares, legend room) is planned for this window
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
    #                                                     arrow_scale_nm_per_mm, ...
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
    (tab10's)."""
    colours = {"x": (214, 39, 40), "y": (44, 160, 44), "z": (31, 119, 180)}
    panels = []
    for label, slug, res in zip(labels, slugs, residuals):
        series = [_Series(f"timeseries/residual_nm/{slug}/{a}", f"{a} (nm)",
                          res[:, k] * NM_PER_M, colours[a], size)
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

    from deltatwin.models.geometry import build_geometry
    from deltatwin.models.kinematics import check_stroke, forward
    from deltatwin.models.mjcf import build_model
    from deltatwin.models.params import load_params
    from deltatwin.twin.workspace import hull

    validate(df, "view: dataset")
    ladder = _check_ladder(df, ladder)
    if max_poses < 1:
        raise ValueError(f"max_poses must be >= 1, got {max_poses}")
    if arrow_scale is not None and not (np.isfinite(arrow_scale) and arrow_scale > 0):
        raise ValueError(f"arrow_scale must be a positive number of nm per mm, got {arrow_scale}")
    df = df.reset_index(drop=True)
    params = params or load_params()
    geom = build_geometry(params)
    t_s = df["t_s"].to_numpy(dtype=float)
    q = df[["q1_rad", "q2_rad", "q3_rad"]].to_numpy(dtype=float)
    check_stroke(geom, q, "view: dataset motor coordinates (q1_rad, q2_rad, q3_rad) of row")

    # the workspace, the local origin and the commanded positions, all at the mirror cube's
    # centre (what the instruments measure; the platform origin lies inside the plate)
    ws = hull(geom, point=geom.cube_offset)
    origin = ws.bounds.mean(axis=0)
    extent_mm = float(np.max(ws.extents) * MM_PER_M)
    pos_id = df["pos_id"].to_numpy()
    ids, first, inv = np.unique(pos_id, return_index=True, return_inverse=True)
    q_mean = np.column_stack([np.bincount(inv, q[:, k], ids.size) for k in range(3)])
    q_mean /= np.bincount(inv, minlength=ids.size)[:, None]
    pos_mm = (forward(geom, q_mean).point(geom.cube_offset) - origin) * MM_PER_M
    split = df["split"].astype(str).to_numpy()[first]

    # the ladder's fields and the panels of time series
    labels = step_labels(ladder)
    slugs = [_slug(k, label) for k, label in enumerate(labels)]
    residuals = [residuals_m(df, s) for s in ladder]
    fields = _fields(pos_id, residuals, extent_mm, arrow_scale)
    residual_panels = _residual_panels(labels, slugs, residuals)
    campaign_panels = _campaign_panels(df)

    # the robot along the campaign
    _, model = build_model(params)
    meshes = robot_meshes(model)
    names = [n for n, _, _ in meshes]
    rows = np.unique(np.linspace(0, len(df) - 1, min(max_poses, len(df))).round().astype(int))
    gpos, gmat, cube, data = _pose_robot(geom, model, q[rows], names, progress)
    cube_home = forward(geom, np.zeros((1, 3))).point(geom.cube_offset)[0]
    beams = _beams(model, data, params, cube, cube_home)
    fixed = np.array([model.body_weldid[model.geom(n).bodyid[0]] == 0 for n in names])

    path = Path(path)
    summary = RecordingSummary(path=path, origin_m=origin, extent_mm=extent_mm,
                               pose_rows=rows, position_ids=ids)
    summary.ladder = _ladder_rows(df, ladder, labels, slugs, residuals, fields)
    summary.blueprint = _blueprint(summary, fields, residual_panels, campaign_panels, t_s)

    def write(tmp):
        rec = rr.RecordingStream("deltatwin")
        try:
            rec.set_log_time_enabled(False)
            rec.save(tmp, default_blueprint=summary.blueprint)
            _log_scene(rec, meshes, ws, origin, ids, pos_mm, split)
            _log_robot(rec, names, fixed, gpos, gmat, beams, origin, t_s[rows])
            _log_fields(rec, summary.ladder, fields, pos_mm, extent_mm)
            for p in residual_panels + campaign_panels:
                _log_panel(rec, p, t_s)
            _log_ladder(rec, summary.ladder)
            _log_info(rec, df, meta, summary, len(df))
            rec.flush()
        finally:
            rec.disconnect()

    atomic_write(path, write)
    return summary


def _ladder_rows(df, ladder, labels, slugs, residuals, fields) -> list[dict]:
    split = df["split"].astype(str).to_numpy()
    rows = []
    for k, (step, label, slug, res, f) in enumerate(zip(ladder, labels, slugs, residuals,
                                                        fields)):
        mag = f.magnitude_nm[f.keep]
        entry = {"step": k, "name": step.name, "label": label, "effects": list(step.effects),
                 "entity": slug, "axes": [a for a, on in zip(AXES, f.axes) if on],
                 "n_positions": int(f.keep.sum()), "rms_nm": _rms_nm(res),
                 "arrow_scale_nm_per_mm": f.scale,
                 "p95_position_nm": float(np.percentile(mag, 95)) if mag.size else float("nan"),
                 "max_position_nm": float(mag.max()) if mag.size else float("nan")}
        for s in SPLITS:
            entry[f"rms_{s}_nm"] = _rms_nm(res[split == s])
        rows.append(entry)
    return rows


def _arrows(vector_nm, keep, pos_mm, scale, extent_mm):
    import rerun as rr
    mag = np.linalg.norm(vector_nm, axis=1)
    return rr.Arrows3D(origins=pos_mm[keep], vectors=vector_nm[keep] / scale,
                       colors=_field_colours(mag[keep], scale, extent_mm),
                       radii=rr.Radius.ui_points(2.0))


def _log_fields(rec, rows, fields, pos_mm, extent_mm) -> None:
    """Each model's field at its own scale; from the second model on, its field again at the
    previous model's scale, to set beside the previous field (before / after the step)."""
    for k, (row, f) in enumerate(zip(rows, fields)):
        rec.log(f"world/error/{row['entity']}",
                _arrows(f.vector_nm, f.keep, pos_mm, f.scale, extent_mm), static=True)
        if k == 0:
            continue
        rec.log(f"world/step/{row['entity']}/after",
                _arrows(f.vector_nm, f.keep, pos_mm, fields[k - 1].scale, extent_mm), static=True)


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


def _log_ladder(rec, rows) -> None:
    import rerun as rr
    if not rows:
        return
    key = "rms_val_nm" if np.isfinite(rows[0]["rms_val_nm"]) else "rms_nm"
    for r, colour in zip(rows, _palette(len(rows))):
        rec.log(f"ladder/{r['entity']}",
                rr.BarChart([r[key]], abscissa=[r["step"]], color=colour), static=True)
    lines = [f"Bars: RMS of model - measurement, every reading and axis of the "
             f"{'validation split' if key == 'rms_val_nm' else 'dataset'}.", "",
             "| # | model | RMS val nm | RMS cal nm | 1 mm of arrow |",
             "|---:|---|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r['step']} | {r['label']} | {r['rms_val_nm']:.3g} | "
                     f"{r['rms_cal_nm']:.3g} | {r['arrow_scale_nm_per_mm']:g} nm |")
    rec.log("ladder/table", rr.TextDocument("\n".join(lines), media_type=rr.MediaType.MARKDOWN),
            static=True)


def _log_scene(rec, meshes, ws, origin, ids, pos_mm, split) -> None:
    import rerun as rr
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


def _log_robot(rec, names, fixed, gpos, gmat, beams, origin, t_rows) -> None:
    """Geoms on moving bodies and the beams along the campaign; those fixed to the room
    (base, coils, instruments) once."""
    import rerun as rr
    campaign = [rr.TimeColumn(CAMPAIGN_TIMELINE, duration=t_rows)]
    for g, name in enumerate(names):
        trans = (gpos[:, g] - origin) * MM_PER_M
        if fixed[g]:
            rec.log(f"world/robot/{name}", rr.Transform3D(translation=trans[0],
                                                          mat3x3=gmat[0, g]), static=True)
        else:
            rec.send_columns(f"world/robot/{name}", indexes=campaign,
                             columns=rr.Transform3D.columns(translation=trans, mat3x3=gmat[:, g]))
    for name, pts in beams.items():
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
    name, lo, hi = FIELD_COLOURMAP
    splits = ", ".join(f"{s} {n}" for s, n in df.groupby("split")["pos_id"].nunique().items())
    text = "\n".join([
        f"**{meta.get('scenario', 'dataset')}** ({meta.get('source', 'unknown source')}): "
        f"{n_rows} readings, {summary.position_ids.size} positions ({splits}).", "",
        "* Arrows: model - measurement, mean per position; **1 mm of arrow = the view's "
        "scale** (in its name), chosen so the 90-95th percentile arrow spans "
        f"{ARROW_SPAN_SHARE[0]:.0%}-{ARROW_SPAN_SHARE[1]:.0%} of the "
        f"{summary.extent_mm:.1f} mm workspace. Colour: dark red (small) to light yellow "
        f"(spans {ARROW_SPAN_SHARE[1]:.0%} or more).",
        "* Points: calibration blue, validation teal.",
        f"* mm, z up, from the workspace centre ({o[0]:.2f}, {o[1]:.2f}, {o[2]:.2f}) mm. "
        f"Robot posed at {summary.pose_rows.size} readings along `{CAMPAIGN_TIMELINE}`."])
    rec.log("info", rr.TextDocument(text, media_type=rr.MediaType.MARKDOWN), static=True)


# ----- the default layout -------------------------------------------------------------------

def _field_view(name: str, entities: list[str]):
    """A 3D view of the workspace (hull, points) and ``entities`` only, so the viewer frames
    it on them (the robot, 20 times larger, would shrink them to a few pixels)."""
    import rerun.blueprint as rrb
    return rrb.Spatial3DView(origin="world", name=name,
                             contents=["$origin/workspace/**"] + [f"$origin/{e}" for e in entities],
                             line_grid=rrb.LineGrid3D(visible=False))


def _series_view(panel: _Panel, t_s: np.ndarray, width_px: float):
    """A time-series view spanning the whole campaign, with room on the right for the legend
    (the x range goes on past the last reading by the legend's width), so it covers no data."""
    import rerun.blueprint as rrb
    t0, t1 = float(np.min(t_s)), float(np.max(t_s))
    legend_px = 7.5 * max(len(s.name) for s in panel.series) + 45.0
    plot_px = max(width_px - 70.0, 2.0 * legend_px)               # minus the y axis labels
    room = legend_px / (plot_px - legend_px)
    span = max(t1 - t0, 1.0)
    return rrb.TimeSeriesView(
        origin=panel.origin, name=panel.title,
        axis_x=rrb.TimeAxis(view_range=rrb.TimeRange(
            start=rrb.TimeRangeBoundary.absolute(seconds=t0 - 0.01 * span),
            end=rrb.TimeRangeBoundary.absolute(seconds=t1 + (0.01 + room) * span))),
        plot_legend=rrb.PlotLegend(corner=rrb.Corner2D.RightTop, visible=True))


def _blueprint(summary, fields, residual_panels, campaign_panels, t_s):
    """Two top tabs: "error fields" (the 3D fields on the left, one tab per model, then one per
    step showing the residual before and after it at one scale, then the robot; residual series, the
    ladder and the info on the right) and "campaign" (the recorded signals, one unit per
    plot).  Opens paused on the first model's field, side and time panels collapsed."""
    import rerun.blueprint as rrb
    width = SCREEN_PX[0]
    right_px = width * _ERROR_TAB_SHARES[1]
    rows = summary.ladder
    spatial = []
    for r, f in zip(rows, fields):
        spatial.append(_field_view(f"{r['label']}: 1 mm = {f.scale:g} nm",
                                   [f"error/{r['entity']}"]))
    for k in range(1, len(rows)):
        prev, r, s = rows[k - 1], rows[k], fields[k - 1].scale
        # one above the other: the viewer frames a 3D view on its height, a narrow view would
        # cut the workspace at its sides
        spatial.append(rrb.Vertical(
            _field_view(f"before: {prev['label']}, 1 mm = {s:g} nm", [f"error/{prev['entity']}"]),
            _field_view(f"after: {r['label']}, 1 mm = {s:g} nm", [f"step/{r['entity']}/after"]),
            name=f"before/after {r['label']}"))
    if not rows:
        spatial.append(_field_view("workspace: calibration and validation positions", []))
    spatial.append(rrb.Spatial3DView(
        origin="world", name="robot and beams",
        contents=["$origin/robot/**", "$origin/instruments/**", "$origin/workspace/**"]))
    # right column, heights planned in px at SCREEN_PX: text at ~22 px a line
    side = [rrb.TextDocumentView(origin="info", name="info")]
    heights = [190.0]
    if rows:
        residuals = [_series_view(p, t_s, right_px) for p in residual_panels]
        side = [rrb.Tabs(*residuals, active_tab=0),
                rrb.BarChartView(origin="ladder", contents=["$origin/**", "- $origin/table"],
                                 name="RMS residual per model (nm)",
                                 plot_legend=rrb.Corner2D.RightTop),
                rrb.TextDocumentView(origin="ladder/table", name="ladder")] + side
        table_px = 22.0 * (len(rows) + 4) + 40.0
        heights = [SCREEN_PX[1] - 120.0 - 190.0 - 200.0 - table_px, 200.0, table_px] + heights
    error_tab = rrb.Horizontal(rrb.Tabs(*spatial, active_tab=0),
                               rrb.Vertical(*side, row_shares=heights),
                               column_shares=list(_ERROR_TAB_SHARES), name="error fields")
    columns = 2 if len(campaign_panels) > 2 else 1
    campaign_tab = rrb.Grid(*[_series_view(p, t_s, width / columns) for p in campaign_panels],
                            grid_columns=columns, name="campaign")
    tabs = [error_tab] + ([campaign_tab] if campaign_panels else [])
    return rrb.Blueprint(rrb.Tabs(*tabs, active_tab=0),
                         rrb.TimePanel(state="collapsed", timeline=CAMPAIGN_TIMELINE,
                                       play_state="paused"),
                         rrb.BlueprintPanel(state="collapsed"),
                         rrb.SelectionPanel(state="collapsed"), collapse_panels=True)
