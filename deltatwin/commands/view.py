"""``deltatwin view``: a Rerun recording of a campaign, its robot and its error fields.

    deltatwin view DATA [--model MODEL.json|fitted.toml ...] [-o run.rrd] [--spawn]
                        [--max-poses N] [--arrow-scale NM_PER_MM] [--params PARAMS.toml]

Writes the recording (no viewer or display needed); ``--spawn`` then opens the Rerun viewer
on it.  Each ``--model`` (a calibration model .json, or a fitted physics model .toml whose
session zeros are re-estimated on DATA as ``deltatwin compare`` does) adds one step to the
ladder, in the order given, named after the model's effects.  See docs/view.md.
"""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from deltatwin.commands.trust import add_trust_option, trust_of


def register(sub) -> None:
    p = sub.add_parser(
        "view", help="write a Rerun recording: robot, workspace, error fields, time series",
        description="Write a Rerun recording (.rrd) of a dataset: the robot posed along the "
                    "campaign, the workspace and its cal/val points, the residual field of "
                    "each model (one 'ladder' step per --model) and the time series; see "
                    "docs/view.md.")
    p.add_argument("data", metavar="DATA", help="dataset file (.parquet, or .csv + .meta.json)")
    p.add_argument("--model", action="append", default=[], metavar="MODEL",
                   help="a calibration model (.json from 'deltatwin calibrate -o') or a fitted "
                        "physics model (.toml from 'deltatwin fit -o') whose residual field "
                        "to show; repeat to build the ladder, in order")
    p.add_argument("-o", "--output", metavar="RUN.rrd",
                   help="recording to write (default: DATA with the suffix .rrd)")
    p.add_argument("--spawn", action="store_true",
                   help="open the Rerun viewer on the recording once it is written")
    p.add_argument("--max-poses", type=int, default=500,
                   help="pose the robot at most at this many readings, evenly spaced (500)")
    p.add_argument("--arrow-scale", type=float, metavar="NM_PER_MM",
                   help="nm of residual per mm of arrow for every model (default: per model, "
                        "the 1-2-5 step for which the 90-95th percentile arrow spans 15-20 %% "
                        "of the workspace)")
    p.add_argument("--params", metavar="PARAMS.toml",
                   help="robot parameter file (default: the nominal set)")
    add_trust_option(p)
    p.set_defaults(func=run)


def run(args) -> int:
    from deltatwin.models.params import load_params
    from deltatwin.twin.dataset import read_dataset
    from deltatwin.view import floor_text, model_file_step, p90_text, write_recording

    df, meta = read_dataset(args.data)
    ladder = [model_file_step(m, df, meta, trust_of(args)) for m in args.model]
    out = Path(args.output) if args.output else Path(args.data).with_suffix(".rrd")
    params = load_params(args.params) if args.params else None
    s = write_recording(df, meta, ladder, out, params=params, max_poses=args.max_poses,
                        arrow_scale=args.arrow_scale, progress=True)
    print(f"deltatwin view: wrote {s.path} ({len(df)} readings, {s.position_ids.size} "
          f"positions, robot posed at {s.pose_rows.size} readings)")
    print("  3D scene in mm relative to the workspace centre")
    for r in s.ladder:
        rows = "validation" if r["p90_rows"] == "val" else "all readings'"
        print(f"  ladder {r['step']}: {r['label']}: {rows} p90 {p90_text(r['p90_nm'])}; "
              f"RMS residual cal {r['rms_cal_nm']:.3g} nm, val {r['rms_val_nm']:.3g} nm; "
              f"residual arrows: 1 mm = {r['arrow_scale_nm_per_mm']:g} nm")
    if s.ladder:
        print(f"  {floor_text((s.floor_nm, s.floor_kind))}")
    if args.spawn:
        subprocess.Popen([sys.executable, "-m", "rerun_cli", str(s.path)],
                         start_new_session=True)
        print("  opened the Rerun viewer")
    else:
        print(f"  open it with: rerun {s.path}")
    return 0
