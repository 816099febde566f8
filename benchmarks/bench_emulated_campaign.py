"""Benchmark: ``deltatwin campaign`` through the serial drivers and the twin-backed emulators
(pseudo-terminals, pyserial; the emulators as ``deltatwin emulate`` serves them, in this process)
against ``deltatwin campaign --instruments sim``, both journaled (fsync per point) as the command
runs them. Target: the paper-force campaign through the emulators "in minutes at most".

Prints the points, both wall times, the serial overhead per point, the serial exchanges per
point, the cost of journaling one point (append + fsync, on the temporary folder's disk), and
the largest difference per column family (they must be within the instruments'
resolution: nm to 0.001, arcsec to 0.01, degC to 8 digits).

    python benchmarks/bench_emulated_campaign.py                      # paper-force, full
    python benchmarks/bench_emulated_campaign.py --reduced            # its reduced scale (0.1)
    python benchmarks/bench_emulated_campaign.py paper-thermal --scale 0.05
"""
from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from deltatwin.cli import main as deltatwin
from deltatwin.hw.emulators.lab import EmulatedLab
from deltatwin.hw.ports import write_ports
from deltatwin.twin.dataset import read_dataset
from deltatwin.twin.instruments.simulated import SimulatedLab
from deltatwin.twin.journal import Journal, read_journal
from deltatwin.twin.scenario import Scenario


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenario", nargs="?", default="paper-force")
    g = ap.add_mutually_exclusive_group()
    g.add_argument("--reduced", action="store_true")
    g.add_argument("--scale", type=float, default=None)
    args = ap.parse_args()
    sc = Scenario.load(args.scenario)
    scale = sc.reduced_scale if args.reduced else args.scale
    size = [] if scale is None else ["--scale", str(scale)]
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        t0 = time.perf_counter()
        assert deltatwin(["campaign", args.scenario, *size, "--instruments", "sim", "-o",
                          str(tmp / "sim.parquet"), "--quiet", "--json"]) == 0
        t_direct = time.perf_counter() - t0

        twin, _ = sc.build(scale)
        with EmulatedLab(SimulatedLab(twin, sc.settings).instrument_set(), tmp / "dev") as lab:
            write_ports(tmp / "ports.toml", lab.ports())
            t0 = time.perf_counter()
            assert deltatwin(["campaign", args.scenario, *size, "--instruments", "serial",
                              "--ports", str(tmp / "ports.toml"), "-o",
                              str(tmp / "serial.parquet"), "--json"]) == 0
            t_serial = time.perf_counter() - t0
            exchanges = sum(e.requests for e in lab.emulators.values())
        direct, _ = read_dataset(tmp / "sim.parquet")
        serial, _ = read_dataset(tmp / "serial.parquet")
        header, points = read_journal(tmp / "sim.parquet.journal")
        with Journal.open(tmp / "again.journal", header) as journal:
            t0 = time.perf_counter()
            for k, point in points.items():
                journal.append(k, point)
            t_journal = (time.perf_counter() - t0) / len(points)
    n = len(direct)
    print(f"{args.scenario} scale {scale or 1.0}: {n} points")
    print(f"  deltatwin campaign --instruments sim    : {t_direct:8.1f} s")
    print(f"  deltatwin campaign --instruments serial : {t_serial:8.1f} s "
          f"({'within' if t_serial <= 300 else 'ABOVE'} the 5-minute target)")
    print(f"  serial overhead                         : {(t_serial - t_direct) / n * 1e3:8.1f} "
          f"ms/point, {exchanges / n:.1f} exchanges/point")
    print(f"  journal append + fsync                  : {t_journal * 1e3:8.1f} ms/point "
          f"({t_journal * n:.1f} s of each run)")
    for suffix in ("_nm", "_arcsec", "_C", "_rad", "_A", "t_s"):
        cols = [c for c in direct.columns if c.endswith(suffix)]
        d = max(float(np.nanmax(np.abs(serial[c].to_numpy(float) - direct[c].to_numpy(float)),
                                initial=0.0)) for c in cols)
        same_nan = all((serial[c].isna() == direct[c].isna()).all() for c in cols)
        print(f"  max |serial - sim| {suffix:>7}: {d:.3g} (NaN pattern equal: {same_nan})")


if __name__ == "__main__":
    main()
