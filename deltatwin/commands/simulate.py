"""`deltatwin simulate SCENARIO -o OUT.parquet` and `deltatwin effects`."""
from __future__ import annotations

import time

from deltatwin.commands.output import strict_json
from deltatwin.commands.trust import add_trust_option, trust_of


def run_simulate(args) -> int:
    import numpy as np

    from deltatwin.progress import progress_bar
    from deltatwin.twin.dataset import check_dataset_path, write_dataset
    from deltatwin.twin.lab_setup import describe
    from deltatwin.twin.scenario import Scenario, check_scale

    check_scale(args.scale, "--scale")
    check_dataset_path(args.output, "-o")
    t0 = time.perf_counter()
    with progress_bar(total=4, desc="simulate", unit="stage", disable=args.quiet) as bar:
        bar.set_postfix_str("scenario")
        sc = Scenario.load(args.scenario, seed=args.seed, trust_effects=trust_of(args))
        scale = sc.reduced_scale if args.reduced else args.scale
        bar.update()
        bar.set_postfix_str("campaign")
        if args.through_interface:
            df, meta = sc.run(scale, progress=not args.quiet)
        else:
            df, meta = sc.simulate(scale)
        bar.update()
        if not args.no_floor:
            bar.set_postfix_str("achievable floor and its budget")
            from deltatwin.calibration.diagnosis.floor import record_achievable_floor
            record_achievable_floor(df, meta, sc, scale)
        bar.update()
        bar.set_postfix_str("write")
        write_dataset(df, meta, args.output)
        bar.update()
    summary = {"scenario": sc.name, "seed": sc.seed, "points": len(df), "output": str(args.output),
               "seconds": round(time.perf_counter() - t0, 2),
               "sessions": df["session"].value_counts().to_dict(),
               "split": df["split"].value_counts().to_dict(),
               "duration_h": round(float(df["t_s"].max()) / 3600.0, 2)}
    if "achievable_floor_nm" in meta["truth"]:
        summary["achievable_floor_nm"] = {a: round(v, 1) for a, v in
                                          meta["truth"]["achievable_floor_nm"].items()}
        summary["noise_floor_nm"] = {a: round(v, 1) for a, v in
                                     meta["truth"]["noise_floor_nm"].items()}
        budget = meta["truth"]["floor_budget_nm"]
        summary["floor_budget_nm"] = {a: {k: round(v, 1) for k, v in budget[a].items()}
                                      for a in ("x", "y", "z", "all") if a in budget}
    T = df[[c for c in df.columns if c.startswith("T_")]].to_numpy()
    summary["temperature_range_C"] = [round(float(np.nanmin(T)), 3), round(float(np.nanmax(T)), 3)]
    # what fit, diagnose and compensate will take as given (twin/lab_setup.py)
    summary["setup"] = meta["setup"] if args.json else describe(meta)
    print(strict_json(summary) if args.json else
          "\n".join(f"{k:>20}: {v}" for k, v in summary.items()))
    return 0


def run_effects(args) -> int:
    from deltatwin.twin.effects import LIBRARY


    info = {name: cls().describe() for name, cls in LIBRARY.items()}
    if args.json:
        print(strict_json(info, indent=1))
        return 0
    for name, d in info.items():
        print(f"{name}: {d['summary']}")
        for p, v in d["parameters"].items():
            print(f"    {p} [{v['unit']}] = {v['default']}  {v['doc']}")
    return 0


def register(sub) -> None:
    p = sub.add_parser("simulate", help="run a scenario's campaign on the twin and write its dataset",
                       description="Simulate a scenario (a TOML path or a name in scenarios/) and "
                                   "write the dataset (Parquet, or CSV by suffix) atomically.")
    p.add_argument("scenario", help="a scenario TOML path, or a shipped name (paper-thermal, "
                   "paper-force, hidden/...)")
    p.add_argument("-o", "--output", required=True,
                   help="dataset to write: .parquet, or .csv (with a .meta.json beside it); "
                        "another suffix is refused")
    p.add_argument("--seed", type=int, default=None, help="override the scenario's seed")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--reduced", action="store_true", help="the scenario's reduced scale (tests)")
    g.add_argument("--scale", type=float, default=None,
                   help="fraction of the campaign's points, 0 < SCALE <= 1 (default 1: the full "
                        "campaign)")
    p.add_argument("--through-interface", action="store_true",
                   help="run point by point through the instrument interface (same data, slower)")
    p.add_argument("--no-floor", action="store_true",
                   help="do not refit the twin's complete model for the achievable floor "
                        "(the floor a model is judged against) and its budget per source (one "
                        "simulation and fit per source)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    add_trust_option(p)
    p.set_defaults(func=run_simulate)
    e = sub.add_parser("effects", help="list the physical effects and their parameters")
    e.add_argument("--json", action="store_true", help="print one JSON object")
    e.set_defaults(func=run_effects)
