"""Benchmark: which error source do the fitted parameters' uncertainties miss?

For generated campaigns of one kind (deltatwin.twin.cases, the papers' conditions, the tests'
scale), the twin's complete model is fitted from the library's starting values (floor.py
``true_fit``) on the same campaign three ways, with the same seed and so the same timeline and
draws (``Scenario.with_perfect``):

- every instrument perfect: the fit's error against the twin's truth is the **model's
  discrepancy** alone (the parts' temperatures the sensors do not see, the sensors' lag);
- one source alone (interferometers, thermometers, servo settling, the air where it moves):
  the fit minus the all-perfect fit is that **source's part** of the error;
- every source as it is.

Each part is divided by the reported uncertainty of its fit (the discrepancy also by that of
the fit as it is: what it adds to a real campaign's error). For honest 95 % intervals a part
lies within 1.96 uncertainties in 95 % of the parameter instances and its median |z| is 0.67;
a median |z| above that says by how much the uncertainty misses that source.

    python benchmarks/coverage_sources.py --kind force --campaigns 10 --seed 3801
"""
from __future__ import annotations

import argparse
import collections
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from deltatwin.calibration.diagnosis.floor import true_fit, true_model
from deltatwin.twin.cases import generate_cases
from deltatwin.twin.scenario import Scenario

sys.path.insert(0, str(Path(__file__).resolve().parent))
from coverage import Z95, counted_parameters  # noqa: E402

MEDIAN_ABS_Z = 0.6745     # the median |z| of a standard normal
DISCREPANCY_AS_IS = "discrepancy / u as is"


def campaign_parts(sc: Scenario) -> dict:
    """{part: [z, ...]}: the campaign's parameter errors split by part (module docstring)."""
    present = sc.sources()
    fits = {"discrepancy": sc.with_perfect(present),
            **{s: sc.with_perfect([x for x in present if x != s]) for s in present},
            "as is": sc}
    values = None
    kept = {}
    for part, scenario in fits.items():
        df, meta = scenario.simulate(sc.reduced_scale)
        values = true_model(meta)[1]
        kept[part] = counted_parameters(true_fit(df, meta), values)
    perfect = kept["discrepancy"]
    out = collections.defaultdict(list)
    for part, params in kept.items():
        for label, (value, u, truth) in params.items():
            if part in ("discrepancy", "as is"):
                out[part].append((value - truth) / u)
            elif label in perfect:
                out[part].append((value - perfect[label][0]) / u)
    # what the discrepancy adds to the campaign as it is, in that fit's uncertainty
    out[DISCREPANCY_AS_IS] = [(perfect[label][0] - truth) / u for label, (_, u, truth)
                              in kept["as is"].items() if label in perfect]
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--kind", choices=("thermal", "force"), default="force")
    ap.add_argument("--campaigns", type=int, default=10, help="campaigns (default 10)")
    ap.add_argument("--seed", type=int, default=3801, help="the cases' generator seed")
    args = ap.parse_args(argv)
    if args.campaigns < 1:
        print(f"--campaigns {args.campaigns}: at least 1", file=sys.stderr)
        return 2
    parts = collections.defaultdict(list)
    start = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        cases = generate_cases(np.random.default_rng(args.seed), args.campaigns,
                               kinds=(args.kind,))
        for i, case in enumerate(cases):
            path = Path(tmp) / f"{case.name}.toml"
            path.write_text(case.toml())
            for part, z in campaign_parts(Scenario.load(path)).items():
                parts[part].extend(z)
            print(f"{i + 1}/{args.campaigns} {case.name} ({time.perf_counter() - start:.0f} s)",
                  file=sys.stderr, flush=True)
    print(f"{args.kind}, {args.campaigns} campaigns (seed {args.seed}): each part of the "
          "parameters' error over the reported uncertainty")
    print(f"  {'part':<22} {'instances':>9} {'within 1.96':>12} {'median |z|':>11} "
          f"{'uncertainty short by':>21}")
    for part, z in parts.items():
        z = np.abs(np.asarray(z))
        print(f"  {part:<22} {z.size:9d} {100 * np.mean(z <= Z95):11.0f} % "
              f"{np.median(z):11.2f} {np.median(z) / MEDIAN_ABS_Z:20.2f}x")
    print(f"{time.perf_counter() - start:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
