"""The achievable floor's budget per source (issue 15), measured in the twin: a scenario at a
scale, its dataset, the true model refitted, then each source alone switched on with the others
perfect (calibration/diagnosis/floor.py: measured_floor_budget). Prints the budget (nm, 90 %,
per axis), the thermometers per sensor (first order), how the sources add up in quadrature
against the floor (BUDGET_TOLERANCE) and the CPU time (user + sys, this process).

    python benchmarks/floor_budget.py paper-thermal            # its reduced scale (2 %)
    python benchmarks/floor_budget.py paper-force --scale 1    # full scale
"""
from __future__ import annotations

import argparse
import resource

from deltatwin.calibration.diagnosis.floor import (
    BUDGET_TOLERANCE,
    budget_lines,
    record_achievable_floor,
)
from deltatwin.twin.scenario import Scenario


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenario", nargs="?", default="paper-thermal")
    ap.add_argument("--scale", type=float, default=None,
                    help="fraction of the campaign (default: the scenario's reduced scale)")
    args = ap.parse_args()
    sc = Scenario.load(args.scenario)
    scale = sc.reduced_scale if args.scale is None else args.scale
    df, meta = sc.simulate(None if scale == 1 else scale)
    record_achievable_floor(df, meta, sc, None if scale == 1 else scale)
    budget = meta["truth"]["floor_budget_nm"]
    print(f"{sc.name} at scale {scale:g}: {len(df)} rows; noise floor (interferometers) "
          + ", ".join(f"{a} {v:.1f}" for a, v in meta["truth"]["noise_floor_nm"].items()) + " nm")
    print("\n".join(budget_lines(budget)))
    for c, d in budget["thermometers_by_sensor_nm"].items():
        print(f"  {c:<16}" + "".join(f"{a} {v:6.2f}  " for a, v in d.items()))
    ratio = budget["all"]["quadrature_sum_nm"] / budget["all"]["achievable_floor_nm"]
    print(f"sources in quadrature / achievable floor (pooled): {ratio:.3f} (target within "
          f"1 +- {BUDGET_TOLERANCE})")
    r = resource.getrusage(resource.RUSAGE_SELF)
    print(f"CPU {r.ru_utime + r.ru_stime:.1f} s (user + sys)")


if __name__ == "__main__":
    main()
