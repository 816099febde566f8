"""``deltatwin iso SCENARIO --test 9283|230-2|230-3 -o DIR``: a standard's acceptance test on the
scenario's robot: plan it, run it, evaluate it, report it.

The test's plan is a campaign of the scenario's robot and laboratory (twin/standard_tests.py;
DIR/scenario.toml is the scenario with that campaign, for `deltatwin campaign` and `deltatwin
emulate`). It runs through the simulated instruments (the twin's fast path) or the serial
drivers (``--instruments serial --ports FILE``), or a dataset of the test's campaign is
evaluated (``--data``, e.g. from the journaled, resumable `deltatwin campaign
DIR/scenario.toml`). ``--compensate MODEL`` (repeatable; simulated) runs the same test on the
same robot later (``--after-h`` hours after its calibration campaign at ``--cal-scale``),
uncompensated and commanded through each model. Writes DIR/report.md with its figures,
DIR/results.json and a dataset per arm; prints the figures with their expanded uncertainties.
"""
from __future__ import annotations

import sys
import time
from pathlib import Path

from deltatwin.commands.trust import add_trust_option, trust_of

TESTS = {"9283": "iso9283", "230-2": "iso230-2", "230-3": "iso230-3"}


def register(sub) -> None:
    p = sub.add_parser("iso", help="ISO 9283 / ISO 230-2 / ISO 230-3 acceptance test: plan, run, "
                                   "evaluate, report (before and after compensation)",
                       description=__doc__.split("\n\n")[1])
    p.add_argument("scenario", help="scenario TOML path or name in scenarios/ (its robot and "
                                    "laboratory)")
    p.add_argument("--test", choices=tuple(TESTS), required=True,
                   help="9283: pose accuracy and repeatability; 230-2: positioning along x, y, "
                        "z; 230-3: environmental temperature variation error")
    p.add_argument("-o", "--output", type=Path, required=True, help="report folder")
    p.add_argument("--cycles", type=int, default=None, help="ISO 9283 cycles (default 30)")
    p.add_argument("--targets", type=int, default=None,
                   help="ISO 230-2 target positions per axis (default 11)")
    p.add_argument("--approaches", type=int, default=None,
                   help="ISO 230-2 approaches per direction (default 5)")
    p.add_argument("--axes", default=None, help="ISO 230-2 axes, e.g. x,z (default x,y,z)")
    p.add_argument("--overrun", type=float, default=None,
                   help="ISO 230-2 overrun beyond the end targets, fraction of the travel "
                        "(default 0.05)")
    p.add_argument("--hours", type=float, default=None, help="ISO 230-3 duration (default 24)")
    p.add_argument("--interval", type=float, default=None, metavar="S",
                   help="ISO 230-3 time between readings, s (default: as often as the "
                        "laboratory's timing allows, ~8 s; a longer one lengthens its per-point "
                        "overhead_s)")
    p.add_argument("--wait", type=float, default=None, metavar="S",
                   help="waiting time after every move before the reading, s (default: the "
                        "laboratory's wait_s, the papers' 5 s)")
    p.add_argument("--drift-cycles", type=int, default=None, metavar="N",
                   help="ISO 9283: also the drift dAP, dRP between the first and the last N "
                        "cycles")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--reduced", action="store_true",
                   help="the scenario's reduced scale (fewer cycles, targets, hours)")
    g.add_argument("--scale", type=float, default=None, help="fraction of the test")
    p.add_argument("--instruments", choices=("sim", "serial"), default="sim",
                   help="sim: the scenario's twin (default); serial: the drivers on --ports")
    p.add_argument("--ports", type=Path, default=None, help="ports file for --instruments serial")
    p.add_argument("--data", type=Path, default=None,
                   help="evaluate this dataset of the test's campaign instead of running it")
    p.add_argument("--compensate", type=Path, action="append", default=None, metavar="MODEL",
                   help="also run the test commanded through this fitted model (physics TOML, "
                        "DGM or direct IGM JSON); repeatable")
    p.add_argument("--after-h", type=float, default=2.0,
                   help="with --compensate: hours after the calibration campaign (default 2)")
    p.add_argument("--cal-scale", type=float, default=None,
                   help="with --compensate: the calibration campaign's scale (sets when it "
                        "ended; default full)")
    p.add_argument("--tolerance", action="append", default=None, metavar="FIGURE=NM",
                   help="a tolerance for the ISO 14253-1 decision, e.g. AP=500 or R=40; "
                        "repeatable")
    p.add_argument("--json", action="store_true", help="print the results as one JSON line")
    add_trust_option(p)
    p.set_defaults(func=run)


def campaign_table(args) -> dict:
    """The scenario's [campaign] table of the test and the options given."""
    camp = {"kind": TESTS[args.test]}
    given = {"cycles": args.cycles, "targets": args.targets, "approaches": args.approaches,
             "overrun": args.overrun, "duration_h": args.hours,
             "axes": None if args.axes is None else [a.strip() for a in args.axes.split(",")]}
    allowed = {"iso9283": {"cycles"}, "iso230-2": {"targets", "approaches", "overrun", "axes"},
               "iso230-3": {"duration_h"}}[camp["kind"]]
    for k, v in given.items():
        if v is None:
            continue
        if k not in allowed:
            option = {"duration_h": "--hours"}.get(k, f"--{k}")
            raise ValueError(f"{option} is not an option of --test {args.test}")
        camp[k] = v
    return camp


def instrument_changes(args, sc) -> dict:
    """[instruments] settings the test changes: ``--wait`` the waiting time after a move,
    ``--interval`` the per-point overhead (the time at rest between ETVE readings)."""
    changes = {}
    if args.wait is not None:
        if not 0 <= args.wait <= 3600:
            raise ValueError(f"--wait must be in [0, 3600] s, got {args.wait}")
        changes["wait_s"] = float(args.wait)
    if args.interval is None:
        return changes
    if args.test != "230-3":
        raise ValueError(f"--interval is not an option of --test {args.test}")
    import dataclasses

    from deltatwin.twin.standard_tests import point_time_at_rest

    settings = dataclasses.replace(sc.settings, **changes)
    least = point_time_at_rest(settings)
    if not args.interval >= least:
        raise ValueError(f"--interval {args.interval:g} s: a reading at rest takes {least:g} s "
                         "in this laboratory; give at least that")
    return {**changes, "overhead_s": settings.overhead_s + args.interval - least}


def tolerances(items) -> dict:
    out = {}
    for item in items or []:
        name, _, value = item.partition("=")
        try:
            out[name.strip()] = float(value)
        except ValueError:
            raise ValueError(f"--tolerance {item!r}: expected FIGURE=NM, e.g. AP=500") from None
        if not name.strip() or not out[name.strip()] > 0:
            raise ValueError(f"--tolerance {item!r}: expected FIGURE=NM with NM > 0")
    return out


def check_args(args) -> None:
    if args.instruments == "serial" and args.ports is None:
        raise ValueError("--instruments serial needs --ports FILE")
    if args.instruments == "sim" and args.ports is not None:
        raise ValueError("--ports is only for --instruments serial")
    if args.scale is not None and not 0 < args.scale <= 1:
        raise ValueError(f"--scale must be in (0, 1], got {args.scale}")
    if args.cal_scale is not None and not 0 < args.cal_scale <= 1:
        raise ValueError(f"--cal-scale must be in (0, 1], got {args.cal_scale}")
    if not args.after_h >= 0:
        raise ValueError(f"--after-h must be >= 0 hours, got {args.after_h}")
    if args.compensate and (args.data is not None or args.instruments == "serial"):
        raise ValueError("--compensate runs on the simulated instruments; it takes neither "
                         "--data nor --instruments serial")
    if args.data is not None and args.instruments == "serial":
        raise ValueError("--data evaluates a dataset; it takes no --instruments serial")
    if args.drift_cycles is not None and args.test != "9283":
        raise ValueError(f"--drift-cycles is not an option of --test {args.test}")
    if args.data is not None and not args.data.exists():
        raise FileNotFoundError(f"--data {args.data}: no such dataset")
    for m in args.compensate or []:
        if not m.exists():
            raise FileNotFoundError(f"--compensate {m}: no such model file")


def run_arms(args, sc, sci, test, scale) -> dict:
    """{arm: dataset} of the test: measured (``--data``), the run (sim or serial), or
    uncompensated and each model's (``--compensate``)."""
    from deltatwin.twin.campaign import run_campaign, simulate_campaign
    from deltatwin.twin.dataset import read_dataset

    if args.data is not None:
        df, meta = read_dataset(args.data)
        check_dataset(args.data, meta, sci, scale)
        return {"measured": df}
    if args.instruments == "serial":
        from deltatwin.commands.campaign import check_world
        from deltatwin.hw.lab import open_lab
        from deltatwin.hw.ports import load_ports
        inst = open_lab(load_ports(args.ports))
        try:
            inst.connect()
            check_world(inst, sci, scale)
            return {"serial": run_campaign(test.plan, inst, sci.settings, sci.cosine,
                                           sci.dead_path(), progress=not args.quiet)}
        finally:
            inst.close()
    if not args.compensate:
        twin, plan = sci.build(scale)
        return {"uncompensated": simulate_campaign(plan, twin, sci.settings, sci.cosine,
                                                   sci.dead_path())}
    return compensated_arms(args, sc, sci, test)


def check_dataset(path, meta: dict, sci, scale) -> None:
    """A dataset that says which campaign it is (deltatwin's metadata) must be this test's: the
    same scenario text (robot, laboratory, the test's campaign) and scale."""
    text = meta.get("scenario_toml")
    if text is not None and text != sci.text:
        raise ValueError(f"--data {path}: its campaign is not this test's (another scenario, "
                         "test or test option); run `deltatwin campaign` on the scenario.toml "
                         "this test writes")
    given = 1.0 if scale is None else float(scale)
    if "scale" in meta and meta["scale"] is not None and float(meta["scale"]) != given:
        raise ValueError(f"--data {path}: a campaign at scale {meta['scale']:g}, this test's is "
                         f"{given:g} (--scale / --reduced)")


def compensated_arms(args, sc, sci, test) -> dict:
    """The test on the scenario's robot ``--after-h`` after its calibration campaign:
    uncompensated (the plan's nominal motor coordinates), then through each model (its inverse
    fed with the conditions read at each point), each in the same world from the same time,
    every session zero the mean of `deltatwin compensate`'s ZERO_SETTLES home settles."""
    import numpy as np

    from deltatwin.calibration.compensation import LoopController, load_compensator
    from deltatwin.commands.compensate import ZERO_SETTLES, compensation_world
    from deltatwin.twin.campaign import run_campaign

    arms = {}
    n = len(test.plan)
    for model in [None, *args.compensate]:
        _, lab = compensation_world(sc, args.cal_scale, args.after_h, test.plan, sci.seed,
                                    lab=sci)
        inst = lab.instrument_set()
        controller, name = None, "uncompensated"
        if model is not None:
            comp = load_compensator(model, trust_of(args))
            name = f"{comp.kind} ({model.name})"
            loop = LoopController({"model": comp}, ["model"] * n, test.targets_m, (),
                                  scan_period_s=sci.settings.scan_period_s)
            loop.log.sensors = tuple(inst.thermometers.sensors)
            controller = StatusLog(loop)
        if not args.quiet:
            print(f"deltatwin iso: running {name} ({n} points)", file=sys.stderr)
        df = run_campaign(test.plan, inst, sci.settings, sci.cosine, sci.dead_path(),
                          progress=not args.quiet, controller=controller,
                          zero_settles=ZERO_SETTLES)
        if controller is not None:
            df["status"] = controller.status
            bad = int(np.sum(np.array(controller.status) != "converged"))
            if bad:
                print(f"deltatwin iso: {name}: {bad} of {n} decisions did not converge",
                      file=sys.stderr)
        arms[name] = df
    return arms


class StatusLog:
    """A loop controller whose decisions' solver status is kept (``status``, per point)."""

    def __init__(self, controller):
        self.controller, self.status = controller, []

    def command(self, k, inst, zero):
        q, record = self.controller.command(k, inst, zero)
        self.status.append(record["status"])
        return q, record

    def replayed(self, k, point):
        self.controller.replayed(k, point)


def run(args) -> int:
    from deltatwin.calibration.standards import report
    from deltatwin.calibration.standards.campaign import evaluate_test
    from deltatwin.calibration.standards.uncertainty import spec_from_scenario
    from deltatwin.commands.output import strict_json
    from deltatwin.files import check_writable
    from deltatwin.twin.scenario import Scenario
    from deltatwin.twin.world import random_streams

    check_args(args)
    tol = tolerances(args.tolerance)
    check_writable(args.output, folder=True)
    t0 = time.perf_counter()
    sc = Scenario.load(args.scenario, trust_effects=trust_of(args))
    sci = sc.with_campaign(campaign_table(args), instruments=instrument_changes(args, sc),
                           trust_effects=trust_of(args))
    scale = sci.reduced_scale if args.reduced else args.scale
    test = sci.standard_test(random_streams(sci.seed)["campaign"], scale)
    arms = run_arms(args, sc, sci, test, scale)
    results = {arm: evaluate_test(test, df, drift_block=args.drift_cycles)
               for arm, df in arms.items()}
    specs = {a: spec_from_scenario(sci, a) for a in ("x", "y", "z")}
    rows = [r for arm, res in results.items()
            for r in report.figure_rows(test, arm, res, specs, tol)]
    doc = {"test": test.test, "scenario": sc.name, "seed": sci.seed,
           "parameters": test.parameters,
           "arms": {arm: result_json(res) for arm, res in results.items()},
           "figures": rows, "report": str(args.output / "report.md")}
    write_outputs(args, sc, sci, scale, test, arms, results, rows)
    doc["seconds"] = round(time.perf_counter() - t0, 2)
    if args.json:
        print(strict_json(doc))
    else:
        print(f"{'arm':>28} {'figure':>14} {'value nm':>10} {'U nm':>8}  decision")
        for r in rows:
            print(f"{r['arm']:>28} {r['figure']:>14} {r['value_nm']:10.1f} {r['U_nm']:8.1f}  "
                  f"{r.get('decision', '')}")
        print(f"report: {args.output / 'report.md'}")
    return 0


def result_json(result) -> dict:
    """A standard's result (or {axis: result} of ISO 230-2) as JSON data."""
    import json

    if hasattr(result, "to_json"):
        return json.loads(result.to_json())
    return {a: json.loads(r.to_json()) for a, r in result.items()}


def write_outputs(args, sc, sci, scale, test, arms, results, rows) -> None:
    """The report folder: scenario.toml, the figures, one dataset per arm, report.md,
    results.json (written last)."""
    import json

    from deltatwin.calibration.standards import report
    from deltatwin.commands.output import strict_json
    from deltatwin.files import atomic_write_text
    from deltatwin.twin.dataset import write_dataset

    out = args.output
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / "scenario.toml", sci.text)
    figures = write_figures(test, arms, results, out)
    for k, (arm, df) in enumerate(arms.items()):
        meta = sci.metadata(None, scale) if args.data is None else {"source": "lab"}
        meta["standard_test"] = {"test": test.test, "arm": arm, **test.parameters}
        write_dataset(df, json.loads(strict_json(meta)), out / f"arm{k}.parquet")
    title = report.TITLES[test.test]
    intro = (f"{title} on {sc.name} (seed {sci.seed}), "
             f"{'dataset ' + str(args.data) if args.data else args.instruments}; "
             f"{len(test.plan)} points; parameters {strict_json(test.parameters)}. "
             + (f"Every arm {args.after_h:g} h after the robot's calibration campaign (scale "
                f"{args.cal_scale or 1:g}), from the same time in the same climate. "
                if args.compensate else "")
             + f"deltatwin {__import__('deltatwin').__version__}.")
    extra = ("## Per target\n\n" + report.per_target_tables(results)
             if test.test == "iso230-2" else "")
    report.write_markdown(out / "report.md", report.markdown(f"{title} report", rows, figures,
                                                             intro, extra))
    doc = {"test": test.test, "scenario": sc.name, "seed": sci.seed,
           "parameters": test.parameters,
           "arms": {arm: result_json(res) for arm, res in results.items()}, "figures": rows}
    atomic_write_text(out / "results.json", strict_json(doc))


def write_figures(test, arms, results, out: Path) -> list[str]:
    """The test's figures in ``out``; their file names."""
    from deltatwin.calibration.standards import report
    from deltatwin.calibration.standards.campaign import readings_m
    from deltatwin.twin.standard_tests import POSE_NAMES

    if test.test == "iso230-2":
        report.plot_iso230_2(results, out / "iso230-2.png")
        return ["iso230-2.png"]
    if test.test == "iso9283":
        clusters = {arm: {POSE_NAMES[k]: readings_m(df, test)[test.item == k]
                          for k in range(len(POSE_NAMES)) if (test.item == k).any()}
                    for arm, df in arms.items()}
        report.plot_iso9283(clusters, results, out / "iso9283.png")
        return ["iso9283.png"]
    series = {arm: (df["t_s"].to_numpy(), {a: readings_m(df, test)[:, k] - test.targets_m[:, k]
                                            for k, a in enumerate("xyz")})
              for arm, df in arms.items()}
    df = next(iter(arms.values()))
    temps = {c[2:-2]: (df["t_s"].to_numpy(), df[c].to_numpy()) for c in df.columns
             if c.startswith("T_") and c.endswith("_C")}
    report.plot_etve(series, temps, out / "iso230-3.png")
    return ["iso230-3.png"]
