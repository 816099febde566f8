"""Screenshots of a `deltatwin view` recording in the real Rerun viewer, headless.

    python docs/render_view.py [--scale 1] [--out docs] [--keep DIR] [--shots default,...]

Simulates the demo's campaign (scenarios/quiet/magnetic-force at ``--scale``), records its
achievable floor and fits its effect ladder as ``deltatwin demo`` does (the geometric baseline,
then + magnetic_force), writes the recording with ``deltatwin.view.write_recording`` and opens
it in the native viewer (the ``rerun`` binary of rerun-sdk) under Xvfb at 1600 x 1000, once
per shot: the default layout, each other top tab (per axis, before/after, robot, campaign),
and ``hover``: the first model's field view alone, its eye set so that the pointer, which
Xvfb keeps at the window's centre, rests on the middle of the field's longest arrow.  A shot
other than the default activates the recording's own blueprint with another active tab (or
that one view), sent as the active blueprint of a second, blueprint-only file opened after
the recording.  Writes ``view-<shot>.png`` (halved from the viewer's 2x pixels, 256
colours) into ``--out``; docs/view.md shows them.

Needs ``xvfb-run`` and a Vulkan driver: ``apt-get install -y xvfb mesa-vulkan-drivers
libgl1-mesa-dri``.  Takes ~30 s per screenshot on llvmpipe, one viewer at a time.
"""
from __future__ import annotations

import argparse
import shutil
import socket
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from deltatwin.view import SCREEN_PX, VIEW_FOV_Y_DEG

SHOTS = {"default": None, "per-axis": "per axis", "before-after": "before/after",
         "robot": "robot and beams", "campaign": "campaign", "hover": None}


def rerun_binary() -> Path:
    """The viewer that ships with rerun-sdk (``python -m rerun_cli`` would start it too)."""
    import rerun_cli
    return Path(rerun_cli.__file__).parent / "rerun"


def free_port() -> int:
    """A free TCP port for one viewer's server (two viewers started at once both found
    Rerun's default port free with ``--new``, and one failed)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def layout_file(blueprint, path: Path) -> Path:
    """A blueprint-only recording making ``blueprint`` the active layout when opened after
    the recording (an .rbl beside it would only become the default, behind the file's own).
    The blueprint is used as it is: a deep copy of one whose views hold 3D vectors (the
    eye) no longer merges with the recording's blueprint in the viewer (a schema clash of
    non-null and nullable float lists)."""
    import rerun as rr
    rec = rr.RecordingStream("deltatwin")
    rec.save(path)
    rec.send_blueprint(blueprint, make_active=True)
    rec.flush()
    rec.disconnect()
    return path


def screenshot(rrd: Path, png: Path, layout: Path | None = None,
               timeout_s: float = 240.0) -> Path:
    """Open ``rrd`` (and the blueprint-only file ``layout``, if given) in the native viewer
    under Xvfb, save its window as ``png`` and shrink it to SCREEN_PX (256 colours)."""
    from PIL import Image
    if shutil.which("xvfb-run") is None:
        raise RuntimeError("xvfb-run not found: apt-get install -y xvfb mesa-vulkan-drivers "
                           "libgl1-mesa-dri")
    w, h = SCREEN_PX
    with tempfile.TemporaryDirectory() as tmp:
        files = [str(rrd)] + ([str(layout)] if layout is not None else [])
        raw = Path(tmp) / "raw.png"
        # Xvfb's pointer sits at the screen's centre and cannot be moved (XWarpPointer and
        # xdotool have no effect there); the viewer draws 2 pixels a point, so on a screen of
        # twice the window's size the pointer is at the window's centre, where the layouts
        # put a divider (no hover tooltip over the picture) and the hover shot an arrow
        done = subprocess.run(
            ["xvfb-run", "-a", "-s", f"-screen 0 {2 * w}x{2 * h}x24", str(rerun_binary()), *files,
             "--bind", "127.0.0.1", "--port", str(free_port()), "--window-size", f"{w}x{h}",
             "--screenshot-to", str(raw)],
            capture_output=True, text=True, timeout=timeout_s)
        if done.returncode != 0 or not raw.exists():
            raise RuntimeError(f"rerun --screenshot-to failed ({done.returncode}):\n"
                               + done.stderr[-2000:])
        image = Image.open(raw).convert("RGB")
        image = image.resize((w, h), Image.LANCZOS) if image.size != (w, h) else image
        image.quantize(256, method=Image.Quantize.MEDIANCUT).save(png, optimize=True)
    return png


def tab_layout(summary, name: str, path: Path) -> Path:
    """The recording's own blueprint with top tab ``name`` active, as a layout file."""
    root = summary.blueprint.root_container
    names = [c.name for c in root.contents]
    active = root.active_tab
    root.active_tab = names.index(name)
    try:
        return layout_file(summary.blueprint, path)
    finally:
        root.active_tab = active


def longest_arrow(rrd: Path, entity: str) -> tuple[np.ndarray, np.ndarray]:
    """(origin, vector) in mm of the longest arrow of ``entity``, read from the file."""
    from rerun.chunk import RrdReader
    for chunk in RrdReader(str(rrd)).stream().to_chunks():
        if chunk.entity_path != entity:
            continue
        b = chunk.to_record_batch()
        cols = {n.split(":")[-1]: b.column(n).to_pylist()[0] for n in b.schema.names
                if n.startswith("Arrows3D:")}
        if "vectors" in cols:
            origins, vectors = np.array(cols["origins"]), np.array(cols["vectors"])
            k = int(np.argmax(np.linalg.norm(vectors, axis=1)))
            return origins[k], vectors[k]
    raise ValueError(f"{rrd}: no arrows at {entity}")


def hover_layout(summary, path: Path) -> Path:
    """The first model's field view of the recording's blueprint alone in the window, its
    eye outside the workspace looking at the middle of the field's longest arrow, the
    arrow upright on the screen: the pointer (the window's centre) rests on it, behind the
    workspace's hull."""
    import rerun.blueprint as rrb
    view = summary.blueprint.root_container.contents[0].contents[0].contents[0]
    origin, vector = longest_arrow(summary.path,
                                   f"/world/error/{summary.ladder[0]['entity']}/arrows")
    middle, up = origin + vector / 2.0, vector / np.linalg.norm(vector)
    side = np.cross(up, (0.0, 0.0, 1.0))
    side = side / np.linalg.norm(side) if np.linalg.norm(side) > 1e-6 else np.array([1.0, 0, 0])
    # far enough to be outside the workspace, near enough for the arrow to span a fifth of
    # the view's height
    distance = max(1.2 * summary.extent_mm,
                   np.linalg.norm(vector) / (0.4 * np.tan(np.radians(VIEW_FOV_Y_DEG) / 2)))
    eye = rrb.EyeControls3D(position=middle + distance * side, look_target=middle, eye_up=up)
    saved = view.properties.get("EyeControls3D")
    view.properties["EyeControls3D"] = eye
    try:
        return layout_file(rrb.Blueprint(view, rrb.TimePanel(state="collapsed",
                                                              play_state="paused"),
                                          collapse_panels=True), path)
    finally:
        view.properties["EyeControls3D"] = saved


def demo_recording(scale: float, folder: Path):
    """The demo's campaign, its achievable floor, its effect ladder and their recording
    (``deltatwin demo``'s steps)."""
    from deltatwin.calibration.diagnosis.diagnose import effect_ladder
    from deltatwin.calibration.diagnosis.floor import record_achievable_floor
    from deltatwin.twin.scenario import Scenario
    from deltatwin.view import LadderStep, write_recording
    sc = Scenario.load("quiet/magnetic-force")
    df, meta = sc.simulate(scale)
    _, floor_fit = record_achievable_floor(df, meta)
    ladder, _, fits = effect_ladder(df, meta, sc.hidden["baseline"],
                                    made=list(floor_fit.start_fits_.values()))
    steps = [LadderStep(r["model"], f.reading_m_, tuple(r["effects"]))
             for r, f in zip(ladder, fits)]
    return write_recording(df, meta, steps, folder / "demo.rrd", max_poses=200)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scale", type=float, default=1.0,
                   help="campaign scale (default 1: the 5 h, 1705-reading campaign)")
    p.add_argument("--out", default=str(Path(__file__).parent), help="folder of the PNGs")
    p.add_argument("--keep", help="also keep the recording in this folder")
    p.add_argument("--shots", default=",".join(SHOTS),
                   help=f"which screenshots (comma separated; default all: {','.join(SHOTS)})")
    args = p.parse_args(argv)
    out = Path(args.out)
    wanted = [s for s in args.shots.split(",") if s]
    unknown = sorted(set(wanted) - set(SHOTS))
    if unknown:
        p.error(f"--shots: unknown {unknown}; choose from {list(SHOTS)}")
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(args.keep) if args.keep else Path(tmp)
        folder.mkdir(parents=True, exist_ok=True)
        summary = demo_recording(args.scale, folder)
        layouts = {s: (hover_layout(summary, Path(tmp) / f"{s}.rrd") if s == "hover" else
                       tab_layout(summary, SHOTS[s], Path(tmp) / f"{s}.rrd") if SHOTS[s]
                       else None) for s in wanted}
        # one viewer at a time: two at once on the 2-core machine once took the campaign's
        # screenshot before its plots had all their points
        for shot in wanted:
            png = screenshot(summary.path, out / f"view-{shot}.png", layouts[shot])
            print(f"{png} ({png.stat().st_size / 1024:.0f} kB)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
