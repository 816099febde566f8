"""``deltatwin campaign SCENARIO --instruments sim|serial``: a scenario's campaign, point by
point through the instrument interface, journaled, resumable, written as a dataset.

``sim``: the scenario's twin as simulated instruments, in this process. ``serial``: the serial
drivers (hw/lab.py) on the laboratory of ``--ports`` (the ports file of a real laboratory, or
the one ``deltatwin emulate --ports-out`` writes). Every accepted point is appended to the
journal (``OUT.journal``, fsync'ed) before the robot moves on; ``--resume`` continues a campaign
that stopped (crash, ``kill -9``, a persistent instrument fault) where it stopped, and the
dataset is written (atomically) once every point is in the journal, which is kept.
"""
from __future__ import annotations

import sys
import time
from pathlib import Path

from deltatwin.commands.output import strict_json
from deltatwin.commands.trust import add_trust_option, trust_of

# exit code of a campaign stopped by an instrument fault (2 = bad input, see deltatwin.cli)
EXIT_INSTRUMENT_FAULT = 3
EXIT_INTERRUPTED = 130      # Ctrl-C, as deltatwin.cli


def register(sub) -> None:
    p = sub.add_parser("campaign", help="run a scenario's campaign through the instruments "
                                        "(simulated or serial), journaled and resumable",
                       description=__doc__.split("\n\n")[1])
    p.add_argument("scenario", help="scenario TOML path or name in scenarios/")
    p.add_argument("--instruments", choices=("sim", "serial"), required=True,
                   help="sim: the scenario's simulated instruments; serial: the drivers on "
                        "the ports file's laboratory")
    p.add_argument("--ports", type=Path, default=None,
                   help="ports file (TOML) for --instruments serial")
    p.add_argument("-o", "--output", type=Path, default=None,
                   help="dataset (Parquet, or CSV by suffix; default SCENARIO.parquet)")
    p.add_argument("--journal", type=Path, default=None,
                   help="journal file (default: OUTPUT.journal)")
    p.add_argument("--resume", action="store_true",
                   help="continue the campaign of the existing journal")
    p.add_argument("--seed", type=int, default=None, help="override the scenario's seed")
    p.add_argument("--setup", type=Path, default=None, metavar="FILE",
                   help="the laboratory's setup file (TOML, docs/lab-setup.toml): its known "
                        "constants, baseline, instrument specifications and sensor map go into "
                        "the dataset, for fit, diagnose and compensate (default: the "
                        "scenario's)")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--reduced", action="store_true", help="the scenario's reduced scale")
    g.add_argument("--scale", type=float, default=None, help="fraction of the campaign's points, "
                   "0 < SCALE <= 1 (with serial: the same as `deltatwin emulate` was given)")
    p.add_argument("--json", action="store_true", help="print the summary as one JSON line")
    add_trust_option(p)
    p.set_defaults(func=run)


def journal_header(sc, scale: float, n_points: int, instruments: str) -> dict:
    """What identifies a campaign: a journal is only resumed by the same one."""
    return {**sc.identity(scale), "points": n_points, "instruments": instruments}


def check_world(instruments, sc, scale) -> None:
    """An emulated laboratory says on its clock port which world it simulates: refuse to run a
    campaign of another scenario, seed or scale through it (its data would say one seed and be
    another's). A laboratory without a clock port, or one that does not say, is not checked."""
    if getattr(instruments, "clock", None) is None or not hasattr(instruments.clock, "world"):
        return
    world = instruments.clock.world()
    if not world:
        return
    ours = sc.identity(scale)
    differ = [f"{k}: emulator {world.get(k)!r}, campaign {v!r}" for k, v in ours.items()
              if world.get(k) != v]
    if differ:
        raise ValueError("the emulated laboratory simulates another campaign ("
                         + "; ".join(differ) + "): start `deltatwin emulate` with the "
                         "campaign's scenario, --seed and --scale (or run this campaign with "
                         "the emulator's)")


def resumed_wall_clock_s(path: Path) -> float:
    """Campaign time for a wall clock after a resume: the last journaled point's time plus the
    wall time since it was journaled (the journal file's modification time); 0 without one."""
    from deltatwin.twin.journal import read_journal
    if not path.exists():
        return 0.0
    _, points = read_journal(path)
    if not points:
        return 0.0
    return points[max(points)]["t_s"] + max(0.0, time.time() - path.stat().st_mtime)


def zeros_taken(plan, points: dict) -> list[dict]:
    """The interferometer zeros the journaled points refer to: one per session start, one more
    after every resume inside a session."""
    out, last = [], None
    for k, p in points.items():
        if p["zero_t_s"] != last:
            out.append({"session": plan.sessions[plan.session[k]][0], "first_point": k,
                        "t_s": p["zero_t_s"], "after_resume": bool(p["rezero"])})
            last = p["zero_t_s"]
    return out


def run(args) -> int:
    from deltatwin.twin.campaign import run_campaign
    from deltatwin.twin.dataset import check_dataset_path, write_dataset
    from deltatwin.twin.instruments.interface import InstrumentError
    from deltatwin.twin.instruments.simulated import SimulatedLab
    from deltatwin.twin.journal import Journal
    from deltatwin.twin.lab_setup import describe, load_setup, with_setup
    from deltatwin.twin.scenario import Scenario, check_scale

    if args.instruments == "serial" and args.ports is None:
        raise ValueError("--instruments serial needs --ports FILE (a laboratory's ports file, or "
                        "the one `deltatwin emulate --ports-out FILE` writes)")
    if args.instruments == "sim" and args.ports is not None:
        raise ValueError("--ports is only for --instruments serial")
    check_scale(args.scale, "--scale")
    if args.output is not None:
        check_dataset_path(args.output, "-o")
    from deltatwin.twin.journal import journal_path as journal_file

    t0 = time.perf_counter()
    sc = Scenario.load(args.scenario, seed=args.seed, trust_effects=trust_of(args))
    # the setup file is checked before anything is measured (its sensors: the scenario's)
    setup = load_setup(args.setup) if args.setup is not None else None
    sensor_columns = [f"T_{s}_C" for s in sc.sensors]
    if setup is not None:
        with_setup({}, setup, str(args.setup), sensor_columns)
    scale = sc.reduced_scale if args.reduced else args.scale
    output = args.output or Path(f"{sc.name}.parquet")
    journal_path = journal_file(output, args.journal, args.resume)
    if args.instruments == "serial":
        from deltatwin.hw.ports import load_ports
        ports = load_ports(args.ports)

    twin, plan = sc.build(scale)
    header = journal_header(sc, 1.0 if scale is None else float(scale), len(plan),
                            args.instruments)
    if args.instruments == "sim":
        instruments = SimulatedLab(twin, sc.settings).instrument_set()
        described = {"kind": "sim", "world": "the scenario's twin (simulated instruments)"}
    else:
        from deltatwin.hw.lab import open_lab
        instruments = open_lab(ports, wall_clock_start_s=resumed_wall_clock_s(journal_path))
        described = {"kind": "serial", "ports_file": str(args.ports), "lab": ports.lab,
                     "clock": "wall" if ports.clock is None else "clock port",
                     "ports": {name: getattr(ports, name).url for name in
                               ("robot", "interferometers", "thermometers", "coils", "clock")
                               if getattr(ports, name) is not None}
                     | {f"autocollimator{k + 1}": port.url
                        for k, (port, _) in enumerate(ports.autocollimators)}}
    journal = None
    try:
        if args.instruments == "serial":
            # before the journal exists: a wrong port, a missing instrument or an emulator of
            # another scenario is reported and leaves nothing behind that blocks a rerun
            try:
                instruments.connect()
                check_world(instruments, sc, scale)
            except InstrumentError as exc:
                print(f"deltatwin campaign: cannot start: {exc}\n  nothing was measured"
                      f"{'' if args.resume else ' and no journal written'}; fix the cause and "
                      "run the same command again", file=sys.stderr)
                return EXIT_INSTRUMENT_FAULT
        journal = Journal.open(journal_path, header)
        before = len(journal.done())
        try:
            df = run_campaign(plan, instruments, sc.settings, sc.cosine, sc.dead_path(),
                              progress=not args.quiet, journal=journal,
                              replay=args.instruments == "sim")
        except (InstrumentError, KeyboardInterrupt) as exc:
            done = len(journal.done())
            if isinstance(exc, KeyboardInterrupt):
                what, code = "interrupted", EXIT_INTERRUPTED
            else:
                what, code = f"stopped by an instrument fault at point {done} of {len(plan)}: " \
                             f"{exc}", EXIT_INSTRUMENT_FAULT
            safe = (f"{done} point(s) are safe in the journal {journal_path} ({len(plan) - done}"
                    " to go); run the same command with --resume to continue" if done else
                    f"no point was journaled yet ({journal_path} removed): run the same "
                    "command again")
            print(f"deltatwin campaign: {what}\n  {safe}"
                  + ("" if code == EXIT_INTERRUPTED else " (fix the cause first)"),
                  file=sys.stderr)
            if not done and not args.resume:
                journal.close()
                journal_path.unlink()
            return code
        points = journal.points()
    finally:
        instruments.close()
        if journal is not None:
            journal.close()
    zeros = zeros_taken(plan, points)
    meta = sc.metadata(twin, scale)
    meta["source"] = "twin" if args.instruments == "sim" else "lab"
    # the instruments' specifications stay (a fit's noise model reads them), with how they
    # were reached
    meta["instruments"] = {**meta["instruments"], **described}
    if setup is not None:
        meta = with_setup(meta, setup, str(args.setup), sensor_columns)
    meta["campaign"] = {"points": len(plan), "journal": str(journal_path),
                        "taken_before_resume": before, "zeros": zeros}
    write_dataset(df, meta, output)
    summary = {"scenario": sc.name, "seed": sc.seed, "instruments": args.instruments,
               "points": len(df), "resumed_with": before, "output": str(output),
               "journal": str(journal_path) + " (kept)",
               "zeros_after_resume": sum(z["after_resume"] for z in zeros),
               "seconds": round(time.perf_counter() - t0, 2),
               "campaign_time_h": round(float(df["t_s"].max()) / 3600.0, 3),
               "setup": meta["setup"] if args.json else describe(meta)}
    print(strict_json(summary) if args.json else
          "\n".join(f"{k:>20}: {v}" for k, v in summary.items()))
    return 0
