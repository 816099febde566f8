"""``deltatwin sweep SPEC.toml``: many simulated campaigns (simulate -> fit -> diagnose), one
Parquet record per case, on a local process pool or a dask.distributed cluster
(calibration/design/sweep.py)."""
from __future__ import annotations

from deltatwin.commands.output import strict_json
from deltatwin.commands.trust import add_trust_option, trust_of


def register(sub) -> None:
    p = sub.add_parser("sweep", help="run a sweep of simulated campaigns (scenario x magnitude x "
                       "design x seed) into a partitioned Parquet dataset",
                       description=__doc__.split("\n\n")[0].replace("``", ""))
    p.add_argument("spec", help="sweep specification (TOML: [sweep], [[study]], [designs.*])")
    p.add_argument("-o", "--out", default="sweep-results",
                   help="results folder (Parquet dataset, one file per case; default "
                        "sweep-results)")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--workers", type=int, default=1, help="local worker processes (default 1)")
    g.add_argument("--scheduler", metavar="ADDRESS",
                   help="run on this dask.distributed scheduler, e.g. tcp://127.0.0.1:8786")
    p.add_argument("--resume", action="store_true",
                   help="continue a sweep in the results folder: finished cases are skipped")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    add_trust_option(p)
    p.set_defaults(func=run_sweep)


def run_sweep(args) -> int:
    from deltatwin.calibration.design.sweep import SweepError, SweepSpec
    from deltatwin.calibration.design.sweep import run_sweep as run
    from deltatwin.progress import progress_bar

    if args.workers < 1:
        raise SweepError(f"--workers {args.workers}: expected at least 1")
    spec = SweepSpec.load(args.spec, trust_of(args))
    with progress_bar(total=len(spec.cases), desc=f"sweep {spec.name}", unit="case",
                      disable=args.quiet or args.json) as bar:
        def progress(i, n):
            bar.total = n
            bar.update()
        summary = run(spec, args.out, args.workers, args.scheduler, args.resume, progress)
    summary = {"sweep": spec.name, "results": str(args.out), **summary}
    if args.json:
        print(strict_json(summary))
    else:
        print(f"sweep {spec.name}: {summary['ran']} cases run, {summary['skipped']} already "
              f"finished, in {summary['wall_s']:.1f} s ({summary['cases_per_s']:.3g} cases/s, "
              f"{summary['cpu_s_per_case']:.3g} CPU s per case, load average "
              f"{summary['load_average_start']:.1f} -> {summary['load_average_end']:.1f}); "
              f"records in {args.out}")
    return 0
