"""Every fuzz case of tests/fuzz_inputs.py (scenarios, datasets, model files, ports files): the
count of each outcome per target, and every case that is not a clean refusal or an acceptance.
Target: 0 tracebacks, 0 hangs, 0 silent acceptances of invalid input, 0 vague.

    python benchmarks/fuzz_inputs.py [--seed 17] [--per-target N]
"""
import argparse
import resource
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from tests.fuzz_inputs import fuzz, targets  # noqa: E402


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=17)
    ap.add_argument("--per-target", type=int, default=None, help="a sample (default: every case)")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as d:
        t0, c0 = time.perf_counter(), resource.getrusage(resource.RUSAGE_SELF)
        report = fuzz(targets(Path(d) / "bases"), np.random.default_rng(args.seed), Path(d),
                      per_target=args.per_target)
        c1 = resource.getrusage(resource.RUSAGE_SELF)
    print(report.table())
    cpu = c1.ru_utime + c1.ru_stime - c0.ru_utime - c0.ru_stime
    print(f"seed {args.seed}: {len(report.results)} cases, CPU {cpu:.1f} s (user+sys), wall "
          f"{time.perf_counter() - t0:.1f} s")
    faults = report.faults()
    if faults:
        print("not clean:\n" + report.faults_text())
    bad = [r for r in faults if r.outcome != "vague"]
    print(f"target 0 tracebacks, 0 hangs, 0 silent: {'met' if not bad else 'NOT met'}")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
