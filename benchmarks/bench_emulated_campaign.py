"""Benchmark: a scenario's campaign through the serial drivers and the twin-backed emulators
(pseudo-terminals, pyserial) against the same campaign through the simulated instruments
directly. Target (issue 7): the paper-force campaign through the emulators "in minutes at most".

Prints the points, both wall times, the serial overhead per point, the serial exchanges per
point, and the largest difference per column family (they must be within the instruments'
resolution: nm to 0.001, arcsec to 0.01, degC to 8 digits).

    python benchmarks/bench_emulated_campaign.py                      # paper-force, full
    python benchmarks/bench_emulated_campaign.py paper-thermal --scale 0.05
"""
from __future__ import annotations

import argparse
import time

import numpy as np

from hw.emulators.lab import EmulatedLab
from hw.lab import open_lab
from twin.instruments.simulated import SimulatedLab
from twin.scenario import Scenario


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenario", nargs="?", default="paper-force")
    ap.add_argument("--scale", type=float, default=None)
    args = ap.parse_args()
    sc = Scenario.load(args.scenario)
    t0 = time.perf_counter()
    direct, _ = sc.run(args.scale, progress=False)
    t_direct = time.perf_counter() - t0

    twin, plan = sc.build(args.scale)
    with EmulatedLab(SimulatedLab(twin, sc.settings).instrument_set()) as lab:
        inst = open_lab(lab.ports())
        t0 = time.perf_counter()
        serial, _ = sc.run(args.scale, progress=True, instruments=inst)
        t_serial = time.perf_counter() - t0
        inst.close()
        exchanges = sum(e.requests for e in lab.emulators.values())
    n = len(direct)
    print(f"{args.scenario} scale {args.scale or 1.0}: {n} points")
    print(f"  simulated instruments directly : {t_direct:8.1f} s")
    print(f"  serial drivers + emulators     : {t_serial:8.1f} s "
          f"({'within' if t_serial <= 300 else 'ABOVE'} the 5-minute target)")
    print(f"  serial overhead                : {(t_serial - t_direct) / n * 1e3:8.1f} ms/point, "
          f"{exchanges / n:.1f} exchanges/point")
    for suffix in ("_nm", "_arcsec", "_C", "_rad", "_A", "t_s"):
        cols = [c for c in direct.columns if c.endswith(suffix)]
        d = max(float(np.nanmax(np.abs(serial[c].to_numpy(float) - direct[c].to_numpy(float)),
                                initial=0.0)) for c in cols)
        same_nan = all((serial[c].isna() == direct[c].isna()).all() for c in cols)
        print(f"  max |serial - direct| {suffix:>7}: {d:.3g} (NaN pattern equal: {same_nan})")


if __name__ == "__main__":
    main()
