"""A Rerun recording of a campaign: the robot, its workspace and the error fields of a ladder
of models (docs/view.md).

The recording holds
* ``world/robot/<geom>``: every geom of the MuJoCo model (``models.mjcf``) as a mesh, posed
  along the campaign (an evenly spaced subsample of the readings, ``max_poses``);
  ``world/instruments/<site>``: the interferometer and autocollimator beams;
* ``world/workspace/hull`` (the hexagonal double pyramid) and ``world/workspace/cal`` /
  ``world/workspace/val``: the commanded positions coloured by split, all drawn where the
  mirror cube's centre is (the measured point), and the error arrows there too;
* ``world/error/residual``: per position, the arrow of the residual (model minus measurement,
  mean over the position's readings) coloured by magnitude, one ``ladder`` step per model;
  from the second model on, ``world/error/added_effect`` (what the model adds to the previous
  one) beside ``world/error/to_explain`` (measurement minus the previous model);
* ``timeseries/...``: every temperature sensor, coil currents, force, reading std
  (acceptance) and the residual per axis of every model, on the ``campaign_time`` timeline;
* ``ladder/rms_nm`` (bar chart), ``ladder/table`` and ``info`` (text), and a default blueprint.

Units and frames (Rerun stores positions and vectors as float32): the 3D scene is in
millimetres, z up, relative to a local origin, the centre of the workspace's bounding box, so
positions keep ~1 nm; an arrow of 1 mm stands for ``arrow_scale_nm_per_mm`` nm of residual
(a power of ten, stated in the 3D view's name and in ``info``), so its vector is the residual
in units of ``arrow_scale_nm_per_mm`` nm, kept to float32's relative precision (2^-24).

Two timelines: ``campaign_time`` (s since the campaign's start) and ``ladder`` (step k = the
k-th model).  The error-field rows also carry ``campaign_time`` = the first reading's time, so
the campaign timeline shows the last model's field; the robot has one ``ladder`` row (its
first pose) so it is drawn on the ladder timeline too.
"""
from __future__ import annotations

import os
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from deltatwin.files import atomic_write
from deltatwin.twin.dataset import AXES, temperature_columns, validate

__all__ = ["LadderStep", "RecordingSummary", "calibration_step", "model_file_step",
           "residuals_m", "position_field", "robot_meshes", "arrow_scale_nm_per_mm",
           "write_recording", "CAMPAIGN_TIMELINE", "LADDER_TIMELINE"]

CAMPAIGN_TIMELINE = "campaign_time"
LADDER_TIMELINE = "ladder"
MM_PER_M = 1e3
NM_PER_M = 1e9
ARROW_SHARE_OF_WORKSPACE = 0.2     # the largest arrow is at most this share of the extent
SPLIT_COLOURS = {"cal": (40, 110, 230), "val": (250, 140, 20)}
EFFECT_COLOUR = (230, 60, 160)
TO_EXPLAIN_COLOUR = (150, 150, 150)
BEAM_COLOURS = {"interferometer": (255, 40, 40), "autocollimator": (40, 200, 60)}
_COIL_COLUMNS = ("coil1_A", "coil2_A", "coil3_A")
_STD_COLUMN = re.compile(r"^(.+)_std_([A-Za-z]+)$")
_AUTOCOLLIMATOR_COLUMN = re.compile(r"^ac\d+_r[xyz]_arcsec$")


@dataclass(frozen=True)
class LadderStep:
    """One model of the ladder: its name and the interferometer readings it predicts for every
    row of the dataset, ``reading_m`` (n_rows, 3) in m for x, y, z (NaN where it predicts
    none).  The residual is ``reading_m`` minus the measured readings."""
    name: str
    reading_m: np.ndarray


@dataclass
class RecordingSummary:
    """What was written: file, frames and scales, and the ladder's figures."""
    path: Path
    origin_m: np.ndarray                 # local origin of the 3D scene (world frame, m)
    arrow_scale_nm_per_mm: float         # 1 mm of arrow = this many nm of residual
    pose_rows: np.ndarray                # dataset rows at which the robot is posed
    position_ids: np.ndarray             # pos_id of every commanded position (sorted)
    ladder: list[dict] = field(default_factory=list)   # per step: name, entity, rms_*_nm, ...


# ----- ladder steps -------------------------------------------------------------------------

def calibration_step(name: str, model, df: pd.DataFrame) -> LadderStep:
    """A ladder step from a fitted calibration model (``calibration.models``).

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
    return LadderStep(name, reading)


def model_file_step(path: str | os.PathLike, df: pd.DataFrame, meta: dict | None) -> LadderStep:
    """A ladder step named after the model file's stem.

    ``.json``: a saved calibration model (``calibration_step``).  ``.toml``: a fitted physics
    model (``deltatwin fit -o``), evaluated on the dataset's conditions (``meta['sensors']``
    places the temperature sensors) with each (session, axis) zero re-estimated on the
    dataset's calibration rows, as ``deltatwin compare`` does (``calibration.compare.
    evaluate``): its residual field is the one ``compare`` reports."""
    from deltatwin.calibration.blackbox.model_file import load_model
    from deltatwin.calibration.diagnosis.compare import evaluate, load_model_file
    from deltatwin.calibration.errors import CalibrationInputError
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in (".json", ".toml"):
        raise ValueError(f"{path}: unknown model file type {path.suffix!r}; expected a "
                         "calibration model (.json) or a fitted physics model (.toml)")
    model = load_model(path) if suffix == ".json" else load_model_file(path)
    try:
        if suffix == ".json":
            return calibration_step(path.stem, model, df)
        return LadderStep(path.stem, evaluate(df, meta, model).reading_m)
    except CalibrationInputError as exc:
        raise ValueError(f"{path}: cannot be evaluated on this dataset: {exc}") from exc


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


# ----- geometry -----------------------------------------------------------------------------

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


def arrow_scale_nm_per_mm(max_residual_nm: float, extent_mm: float) -> float:
    """The power of ten (nm of residual per mm of arrow) that keeps the largest arrow within
    ``ARROW_SHARE_OF_WORKSPACE`` of the workspace extent."""
    if not np.isfinite(max_residual_nm) or max_residual_nm <= 0.0:
        return 1.0
    return float(10.0 ** np.ceil(np.log10(max_residual_nm / (ARROW_SHARE_OF_WORKSPACE
                                                             * extent_mm))))


def _magnitude_colours(mag: np.ndarray, vmax: float) -> np.ndarray:
    import matplotlib
    c = matplotlib.colormaps["viridis"](np.clip(mag / vmax if vmax > 0 else 0 * mag, 0, 1))
    return (c[:, :3] * 255).round().astype(np.uint8)


def _pose_robot(geom, model, q: np.ndarray, names: list[str], progress: bool):
    """Pose the MuJoCo model at motor coordinates ``q`` (F, 3); geom poses and cube centres."""
    import mujoco
    from tqdm import tqdm

    from deltatwin.models.kinematics import forward
    from deltatwin.models.mjcf import pose_model
    data = mujoco.MjData(model)
    pose = forward(geom, q)
    gid = np.array([model.geom(n).id for n in names])
    cube = model.site("mirror_cube_centre").id
    F = len(q)
    gpos, gmat, cpos = np.empty((F, gid.size, 3)), np.empty((F, gid.size, 3, 3)), np.empty((F, 3))
    for f in tqdm(range(F), desc="view: posing the robot", disable=not progress, leave=False):
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


# ----- the recording ------------------------------------------------------------------------

def _slug(k: int, name: str) -> str:
    return f"{k}_" + (re.sub(r"[^A-Za-z0-9]+", "_", name).strip("_") or "model")


def _rms_nm(res: np.ndarray) -> float:
    v = res[np.isfinite(res)]
    return float(np.sqrt(np.mean(v ** 2)) * NM_PER_M) if v.size else float("nan")


def _check_ladder(df: pd.DataFrame, ladder) -> list[LadderStep]:
    ladder = list(ladder)
    for k, step in enumerate(ladder):
        if not isinstance(step, LadderStep):
            raise TypeError(f"ladder entry {k} is a {type(step).__name__}, not a LadderStep")
        if not str(step.name).strip():
            raise ValueError(f"ladder entry {k} has an empty name")
        r = np.asarray(step.reading_m)
        if r.shape != (len(df), 3):
            raise ValueError(f"ladder step {step.name!r}: reading_m has shape {r.shape}, "
                             f"expected ({len(df)}, 3) (one x, y, z per dataset row)")
        if not np.isfinite(residuals_m(df, step)).any():
            raise ValueError(f"ladder step {step.name!r}: no row has both a prediction and a "
                             "measured reading (x_nm, y_nm, z_nm)")
    return ladder


def write_recording(df: pd.DataFrame, meta: dict, ladder=(), path="run.rrd", *, params=None,
                    max_poses: int = 500, arrow_scale: float | None = None,
                    progress: bool = False) -> RecordingSummary:
    """Write the Rerun recording of a dataset (and optional ladder of models) to ``path``.

    ``df``, ``meta``: a dataset (twin.dataset.read_dataset).  ``ladder``: LadderStep list, in
    the order the effects are added.  ``params``: robot parameters (default: the nominal set)
    for the MuJoCo model and the kinematics placing the positions.  ``max_poses``: the robot
    is posed at this many readings at most, evenly spaced over the campaign.
    ``arrow_scale``: nm of residual per mm of arrow (default: a power of ten chosen from the
    largest residual).  The file is written to a temporary name and renamed when complete.
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

    # error fields of the ladder
    residuals = [residuals_m(df, s) for s in ladder]
    fields = [position_field(pos_id, r)[1] * NM_PER_M for r in residuals]
    peak = max((float(np.nanmax(np.linalg.norm(np.nan_to_num(f), axis=1))) for f in fields),
               default=0.0)
    scale = float(arrow_scale) if arrow_scale is not None else arrow_scale_nm_per_mm(peak,
                                                                                     extent_mm)
    # the robot along the campaign
    spec, model = build_model(params)
    meshes = robot_meshes(model)
    names = [n for n, _, _ in meshes]
    rows = np.unique(np.linspace(0, len(df) - 1, min(max_poses, len(df))).round().astype(int))
    gpos, gmat, cube, data = _pose_robot(geom, model, q[rows], names, progress)
    cube_home = forward(geom, np.zeros((1, 3))).point(geom.cube_offset)[0]
    beams = _beams(model, data, params, cube, cube_home)

    path = Path(path)
    summary = RecordingSummary(path=path, origin_m=origin, arrow_scale_nm_per_mm=scale,
                               pose_rows=rows, position_ids=ids)

    def write(tmp):
        rec = rr.RecordingStream("deltatwin")
        try:
            rec.set_log_time_enabled(False)
            has_effect = len(ladder) >= 2
            rec.save(tmp, default_blueprint=_blueprint(df, scale, has_effect, bool(ladder)))
            _log_scene(rec, meshes, ws, origin, ids, pos_mm, split)
            _log_robot(rec, names, gpos, gmat, beams, origin, t_s[rows])
            summary.ladder = _log_ladder(rec, df, ladder, residuals, fields, pos_mm, scale,
                                         peak, t_s, float(t_s.min()))
            _log_time_series(rec, df, t_s)
            _log_info(rec, df, meta, summary, extent_mm, peak, len(df))
            rec.flush()
        finally:
            rec.disconnect()

    atomic_write(path, write)
    return summary


def _blueprint(df: pd.DataFrame, scale: float, has_effect: bool, has_ladder: bool):
    import rerun.blueprint as rrb
    main = rrb.Spatial3DView(
        origin="world", name=f"robot, workspace, residual (arrow 1 mm = {scale:g} nm)",
        contents=["$origin/**", "- $origin/error/added_effect", "- $origin/error/to_explain"])
    spatial = [main]
    if has_effect:
        spatial.append(rrb.Spatial3DView(
            origin="world", name=f"added effect vs. what it explains (1 mm = {scale:g} nm)",
            contents=["$origin/workspace/**", "$origin/error/added_effect",
                      "$origin/error/to_explain"]))
    lower = [rrb.TextDocumentView(origin="info", name="info")]
    if has_ladder:
        lower = [rrb.BarChartView(origin="ladder/rms_nm", name="ladder: RMS residual (nm)"),
                 rrb.TextDocumentView(origin="ladder/table", name="ladder")] + lower
    series = [rrb.TimeSeriesView(origin="timeseries/temperature_C", name="temperatures (degC)")]
    if has_ladder:
        series.append(rrb.TimeSeriesView(origin="timeseries/residual_nm",
                                         name="residual, model - measurement (nm)"))
    if any(c in df.columns for c in _COIL_COLUMNS) or "F_N" in df.columns:
        series.append(rrb.TimeSeriesView(
            origin="timeseries", contents=["$origin/coil_A/**", "$origin/force_N"],
            name="coil currents (A), force (N)"))
    if any(_STD_COLUMN.match(c) for c in df.columns):
        series.append(rrb.TimeSeriesView(origin="timeseries/acceptance_std",
                                         name="std of each reading (acceptance)"))
    if any(_AUTOCOLLIMATOR_COLUMN.match(c) for c in df.columns):
        series.append(rrb.TimeSeriesView(origin="timeseries/autocollimator_arcsec",
                                         name="autocollimator angles (arcsec)"))
    left = rrb.Vertical(rrb.Tabs(*spatial) if len(spatial) > 1 else main,
                        rrb.Horizontal(*lower), row_shares=[3, 1])
    return rrb.Blueprint(rrb.Horizontal(left, rrb.Vertical(*series), column_shares=[3, 2]),
                         rrb.TimePanel(timeline=CAMPAIGN_TIMELINE), collapse_panels=False)


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
                      albedo_factor=[120, 170, 255, 50]), static=True)
    sharp = ws.face_adjacency_edges[ws.face_adjacency_angles > 0.1]
    rec.log("world/workspace/hull_edges",
            rr.LineStrips3D((ws.vertices[sharp] - origin) * MM_PER_M,
                            radii=rr.Radius.ui_points(1.0), colors=[90, 130, 220]), static=True)
    for s, colour in SPLIT_COLOURS.items():
        sel = split == s
        rec.log(f"world/workspace/{s}",
                rr.Points3D(pos_mm[sel], colors=colour, radii=rr.Radius.ui_points(3.0),
                            labels=[f"pos {i}" for i in ids[sel]], show_labels=False),
                static=True)


def _log_robot(rec, names, gpos, gmat, beams, origin, t_rows) -> None:
    import rerun as rr
    campaign = [rr.TimeColumn(CAMPAIGN_TIMELINE, duration=t_rows)]
    first = [rr.TimeColumn(LADDER_TIMELINE, sequence=[0])]
    for g, name in enumerate(names):
        trans = (gpos[:, g] - origin) * MM_PER_M
        for idx, sl in ((campaign, slice(None)), (first, slice(0, 1))):
            rec.send_columns(f"world/robot/{name}", indexes=idx,
                             columns=rr.Transform3D.columns(translation=trans[sl],
                                                            mat3x3=gmat[sl, g]))
    for name, pts in beams.items():
        kind = name.split("_")[0]
        strips = list((pts - origin) * MM_PER_M)
        colour = BEAM_COLOURS.get(kind, (200, 200, 200))
        rec.log(f"world/instruments/{name}", rr.LineStrips3D.from_fields(
            colors=colour, radii=rr.Radius.ui_points(1.5)), static=True)
        for idx, sl in ((campaign, slice(None)), (first, slice(0, 1))):
            rec.send_columns(f"world/instruments/{name}", indexes=idx,
                             columns=rr.LineStrips3D.columns(strips=strips[sl]).partition(
                                 [1] * len(strips[sl])))


def _log_ladder(rec, df, ladder, residuals, fields, pos_mm, scale, peak, t_s, t_first):
    import rerun as rr

    from deltatwin.twin.dataset import SPLITS
    split = df["split"].astype(str).to_numpy()
    rows = []
    prev = None
    for k, (step, res, fld) in enumerate(zip(ladder, residuals, fields)):
        slug = _slug(k, step.name)
        rec.set_time(LADDER_TIMELINE, sequence=k)
        rec.set_time(CAMPAIGN_TIMELINE, duration=t_first)
        axes = np.isfinite(fld).any(axis=0)             # axes this model has residuals on
        keep = np.all(np.isfinite(fld[:, axes]), axis=1)
        vec = np.where(axes, fld, 0.0)
        mag = np.linalg.norm(vec, axis=1)
        rec.log("world/error/residual",
                rr.Arrows3D(origins=pos_mm[keep], vectors=vec[keep] / scale,
                            colors=_magnitude_colours(mag[keep], peak),
                            radii=rr.Radius.ui_points(1.5)))
        if prev is not None:
            both = keep & prev[1]
            rec.log("world/error/added_effect",
                    rr.Arrows3D(origins=pos_mm[both], vectors=(vec - prev[0])[both] / scale,
                                colors=EFFECT_COLOUR, radii=rr.Radius.ui_points(1.5)))
            rec.log("world/error/to_explain",
                    rr.Arrows3D(origins=pos_mm[both], vectors=-prev[0][both] / scale,
                                colors=TO_EXPLAIN_COLOUR, radii=rr.Radius.ui_points(1.5)))
        rec.reset_time()
        prev = (vec, keep)
        entry = {"step": k, "name": step.name, "entity": slug,
                 "axes": [a for a, on in zip(AXES, axes) if on],
                 "n_positions": int(keep.sum()), "rms_nm": _rms_nm(res),
                 "max_position_nm": float(mag[keep].max()) if keep.any() else float("nan")}
        for s in SPLITS:
            entry[f"rms_{s}_nm"] = _rms_nm(res[split == s])
        rows.append(entry)
        for a, axis in enumerate(AXES):
            _send_series(rec, f"timeseries/residual_nm/{axis}/{slug}", t_s,
                         res[:, a] * NM_PER_M, f"{axis}: {step.name}")
    if not ladder:
        return rows
    key = "rms_val_nm" if np.isfinite(rows[0]["rms_val_nm"]) else "rms_nm"
    rec.log("ladder/rms_nm", rr.BarChart([r[key] for r in rows]), static=True)
    lines = [f"RMS of model - measurement over every reading and axis of the "
             f"{'validation split' if key == 'rms_val_nm' else 'dataset'} (bar chart); "
             "arrows: mean per position.", "",
             "| step | model | axes | RMS cal nm | RMS val nm | largest arrow nm | positions |",
             "|---:|---|---|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r['step']} | {r['name']} | {','.join(r['axes'])} | "
                     f"{r['rms_cal_nm']:.3g} | {r['rms_val_nm']:.3g} | "
                     f"{r['max_position_nm']:.3g} | {r['n_positions']} |")
    rec.log("ladder/table", rr.TextDocument("\n".join(lines), media_type=rr.MediaType.MARKDOWN),
            static=True)
    return rows


def _send_series(rec, entity: str, t_s: np.ndarray, values: np.ndarray, name: str) -> None:
    import rerun as rr
    ok = np.isfinite(values)
    if not ok.any():
        return
    rec.log(entity, rr.SeriesLines(names=name), static=True)
    rec.send_columns(entity, indexes=[rr.TimeColumn(CAMPAIGN_TIMELINE, duration=t_s[ok])],
                     columns=rr.Scalars.columns(scalars=values[ok]))


def _log_time_series(rec, df: pd.DataFrame, t_s: np.ndarray) -> None:
    for c in temperature_columns(df):
        _send_series(rec, f"timeseries/temperature_C/{c[2:-2]}", t_s,
                     df[c].to_numpy(dtype=float), c)
    for c in _COIL_COLUMNS:
        if c in df.columns:
            _send_series(rec, f"timeseries/coil_A/{c[:-2]}", t_s, df[c].to_numpy(dtype=float), c)
    if "F_N" in df.columns:
        _send_series(rec, "timeseries/force_N", t_s, df["F_N"].to_numpy(dtype=float), "F_N")
    for c in df.columns:
        if _STD_COLUMN.match(c):
            _send_series(rec, f"timeseries/acceptance_std/{c}", t_s,
                         df[c].to_numpy(dtype=float), c)
        elif _AUTOCOLLIMATOR_COLUMN.match(c):
            _send_series(rec, f"timeseries/autocollimator_arcsec/{c[:-7]}", t_s,
                         df[c].to_numpy(dtype=float), c)


def _log_info(rec, df, meta, summary: RecordingSummary, extent_mm, peak, n_rows) -> None:
    import rerun as rr
    o = summary.origin_m * MM_PER_M
    text = "\n".join([
        f"# {meta.get('scenario', 'dataset')} ({meta.get('source', 'unknown source')})", "",
        f"* {n_rows} readings, {summary.position_ids.size} positions "
        f"({', '.join(f'{s}: {n}' for s, n in df.groupby('split')['pos_id'].nunique().items())}).",
        f"* 3D scene: mm, z up, relative to the workspace centre at "
        f"({o[0]:.3f}, {o[1]:.3f}, {o[2]:.3f}) mm in the base frame; workspace extent "
        f"{extent_mm:.2f} mm.",
        (f"* Residual arrows (model - measurement, mean per position): "
         f"**1 mm of arrow = {summary.arrow_scale_nm_per_mm:g} nm**; colour = magnitude, "
         f"viridis from 0 to {peak:.3g} nm." if summary.ladder else
         "* No model given: no residual arrows."),
        f"* Robot posed at {summary.pose_rows.size} of {n_rows} readings, evenly spaced "
        f"(timeline `{CAMPAIGN_TIMELINE}`); the `{LADDER_TIMELINE}` timeline steps through "
        "the models and shows the robot at its first pose.",
        "* Points: calibration blue, validation orange."])
    rec.log("info", rr.TextDocument(text, media_type=rr.MediaType.MARKDOWN), static=True)
