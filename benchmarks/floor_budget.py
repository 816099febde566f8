"""The achievable floor's budget per source, measured in the twin: a scenario at a
scale, its dataset, the true model refitted, then each source alone switched on with the others
perfect (calibration/diagnosis/floor.py: measured_floor_budget). Prints the budget (nm, 90 %,
per axis), the thermometers per sensor (first order), how the sources add up in quadrature
against the floor (BUDGET_TOLERANCE) and the CPU time (user + sys, this process).

    python benchmarks/floor_budget.py paper-thermal            # its reduced scale (2 %)
    python benchmarks/floor_budget.py paper-force --scale 1    # full scale

With ``--air-seeds N`` it checks the predicted budget's air line (the scenario's stated wander
through the model's levers) against the twin's own air over N campaigns (seeds from
``--first-seed``; floor.py air_line_check) instead.
"""
from __future__ import annotations

import argparse
import resource

from deltatwin.calibration.diagnosis.floor import (
    BUDGET_TOLERANCE,
    air_line_check,
    budget_lines,
    record_achievable_floor,
)
from deltatwin.twin.scenario import Scenario


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenario", nargs="?", default="paper-thermal")
    ap.add_argument("--scale", type=float, default=None,
                    help="fraction of the campaign (default: the scenario's reduced scale)")
    ap.add_argument("--air-seeds", type=int, default=0,
                    help="check the air line over this many campaigns instead")
    ap.add_argument("--first-seed", type=int, default=100)
    args = ap.parse_args()
    sc = Scenario.load(args.scenario)
    scale = sc.reduced_scale if args.scale is None else args.scale
    if args.air_seeds:
        seeds = range(args.first_seed, args.first_seed + args.air_seeds)
        check = air_line_check(args.scenario, None if scale == 1 else scale, seeds)
        print(f"{sc.name} at scale {scale:g}, seeds {seeds.start}-{seeds.stop - 1}: the air's "
              f"line, nm (90 % over the validation rows) for {sc.air_wander()}")
        axes = list(check["budget"])
        print(f"  {'':<12}" + "".join(f"{a:>8}" for a in axes))
        for name, line in check.items():
            print(f"  {name:<12}" + "".join(f"{line[a]:8.2f}" for a in axes))
        print(f"budget / twin refit (pooled): {check['budget']['all'] / check['twin_refit']['all']:.3f}")
        _cpu()
        return
    df, meta = sc.simulate(None if scale == 1 else scale)
    record_achievable_floor(df, meta, sc, None if scale == 1 else scale)
    budget = meta["truth"]["floor_budget_nm"]
    print(f"{sc.name} at scale {scale:g}: {len(df)} rows; noise floor (interferometers and servo settling) "
          + ", ".join(f"{a} {v:.1f}" for a, v in meta["truth"]["noise_floor_nm"].items()) + " nm")
    print("\n".join(budget_lines(budget)))
    for c, d in budget["thermometers_by_sensor_nm"].items():
        print(f"  {c:<16}" + "".join(f"{a} {v:6.2f}  " for a, v in d.items()))
    ratio = budget["all"]["quadrature_sum_nm"] / budget["all"]["achievable_floor_nm"]
    print(f"sources in quadrature / achievable floor (pooled): {ratio:.3f} (target within "
          f"1 +- {BUDGET_TOLERANCE})")
    _cpu()


def _cpu() -> None:
    r = resource.getrusage(resource.RUSAGE_SELF)
    print(f"CPU {r.ru_utime + r.ru_stime:.1f} s (user + sys)")


if __name__ == "__main__":
    main()
