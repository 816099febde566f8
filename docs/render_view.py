"""Screenshots of a `deltatwin view` recording in the real Rerun viewer, headless.

    python docs/render_view.py [--scale 1] [--out docs] [--keep DIR] [--shots default,...]

Simulates the demo's campaign (scenarios/quiet/magnetic-force at ``--scale``), fits its
effect ladder (``deltatwin demo``'s: the geometric baseline, then + magnetic_force), writes the
recording with ``deltatwin.view.write_recording`` and opens it in the native viewer (the
``rerun`` binary of rerun-sdk) under Xvfb at 1600 x 1000, once per tab to show: the default
layout, the before/after view of the step, the robot, and the campaign's signals.  Each tab is
chosen by a copy of the recording's own default blueprint with other active tabs, sent as the
active blueprint of a second, blueprint-only file opened after the recording.  Writes
``view-<tab>.png`` (halved from the viewer's 2x pixels, 256 colours) into ``--out``;
docs/view.md shows them.

Needs ``xvfb-run`` and a Vulkan driver: ``apt-get install -y xvfb mesa-vulkan-drivers
libgl1-mesa-dri``.  Takes ~30 s per screenshot on llvmpipe.
"""
from __future__ import annotations

import argparse
import copy
import shutil
import subprocess
import sys
import tempfile
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from deltatwin.view import SCREEN_PX


def rerun_binary() -> Path:
    """The viewer that ships with rerun-sdk (``python -m rerun_cli`` would start it too)."""
    import rerun_cli
    return Path(rerun_cli.__file__).parent / "rerun"


def screenshot(rrd: Path, png: Path, blueprint=None, timeout_s: float = 240.0) -> Path:
    """Open ``rrd`` (with ``blueprint``, a rerun.blueprint.Blueprint, if given) in the native
    viewer under Xvfb, save its window as ``png`` and shrink it to SCREEN_PX (256 colours)."""
    import rerun as rr
    from PIL import Image
    if shutil.which("xvfb-run") is None:
        raise RuntimeError("xvfb-run not found: apt-get install -y xvfb mesa-vulkan-drivers "
                           "libgl1-mesa-dri")
    w, h = SCREEN_PX
    with tempfile.TemporaryDirectory() as tmp:
        files = [str(rrd)]
        if blueprint is not None:
            # a blueprint-only recording loaded after the file, activating its layout (an .rbl
            # beside it would only become the default, behind the file's own)
            layout = Path(tmp) / "layout.rrd"
            rec = rr.RecordingStream("deltatwin")
            rec.save(layout)
            rec.send_blueprint(blueprint, make_active=True)
            rec.flush()
            rec.disconnect()
            files.append(str(layout))
        raw = Path(tmp) / "raw.png"
        # Xvfb's pointer sits at the screen's centre and cannot be moved (XWarpPointer and
        # xdotool have no effect there); the viewer draws 2 pixels a point, so on a screen of
        # twice the window's size the pointer is at the window's centre, where the layouts
        # put a divider (no hover tooltip over the picture)
        done = subprocess.run(
            ["xvfb-run", "-a", "-s", f"-screen 0 {2 * w}x{2 * h}x24", str(rerun_binary()), *files,
             "--bind", "127.0.0.1", "--new", "--window-size", f"{w}x{h}",
             "--screenshot-to", str(raw)],
            capture_output=True, text=True, timeout=timeout_s)
        if done.returncode != 0 or not raw.exists():
            raise RuntimeError(f"rerun --screenshot-to failed ({done.returncode}):\n"
                               + done.stderr[-2000:])
        image = Image.open(raw).convert("RGB")
        image = image.resize((w, h), Image.LANCZOS) if image.size != (w, h) else image
        image.quantize(256, method=Image.Quantize.MEDIANCUT).save(png, optimize=True)
    return png


def with_tabs(blueprint, top: int, field: int | None = None):
    """A copy of a ``write_recording`` blueprint showing top tab ``top`` (0 error fields,
    1 campaign) and, in the error-field tab, 3D tab ``field``."""
    bp = copy.deepcopy(blueprint)
    bp.root_container.active_tab = top
    if field is not None:
        bp.root_container.contents[0].contents[0].active_tab = field
    return bp


def demo_recording(scale: float, folder: Path):
    """The demo's campaign, its effect ladder and their recording (``deltatwin demo``)."""
    from deltatwin.calibration.diagnosis.diagnose import effect_ladder
    from deltatwin.twin.scenario import Scenario
    from deltatwin.view import LadderStep, write_recording
    sc = Scenario.load("quiet/magnetic-force")
    df, meta = sc.simulate(scale)
    ladder, _, fits = effect_ladder(df, meta, sc.hidden["baseline"])
    steps = [LadderStep(r["model"], f.reading_m_, tuple(r["effects"]))
             for r, f in zip(ladder, fits)]
    return write_recording(df, meta, steps, folder / "demo.rrd", max_poses=200)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scale", type=float, default=1.0,
                   help="campaign scale (default 1: the 5 h, 1705-reading campaign)")
    p.add_argument("--out", default=str(Path(__file__).parent), help="folder of the PNGs")
    p.add_argument("--keep", help="also keep the recording in this folder")
    p.add_argument("--shots", default="default,before-after,robot,campaign",
                   help="which screenshots (comma separated; default all four)")
    args = p.parse_args(argv)
    out = Path(args.out)
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(args.keep) if args.keep else Path(tmp)
        folder.mkdir(parents=True, exist_ok=True)
        summary = demo_recording(args.scale, folder)
        n = len(summary.ladder)
        shots = {"default": None,
                 "before-after": with_tabs(summary.blueprint, 0, n),
                 "robot": with_tabs(summary.blueprint, 0, n + max(n - 1, 0)),
                 "campaign": with_tabs(summary.blueprint, 1)}
        wanted = [s for s in args.shots.split(",") if s]
        unknown = sorted(set(wanted) - set(shots))
        if unknown:
            p.error(f"--shots: unknown {unknown}; choose from {sorted(shots)}")
        with ThreadPoolExecutor(max_workers=2) as pool:      # one viewer per core
            pngs = pool.map(lambda s: screenshot(summary.path, out / f"view-{s}.png", shots[s]),
                            wanted)
            for png in pngs:
                print(f"{png} ({png.stat().st_size / 1024:.0f} kB)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
