"""Benchmark: do the fitted physical parameters' 95 % intervals cover the twin's truth?

Generates campaigns in the papers' conditions (deltatwin.twin.cases, thermal and force, each
with its random hidden effects), simulates each at its reduced scale (5 % of the thermal
campaign, 30 % of the force one), fits the twin's complete
model from the library's starting values (calibration/diagnosis/floor.py ``true_fit``: what a
researcher could reach) and checks, for every parameter that is not a geometric error and that
the fit calls identified (``identified_fraction`` >= 0.5), whether value +- 1.96 uncertainty
contains the twin's value. Prints per campaign kind the coverage with its 95 % Clopper-Pearson
interval against the target (90-98 % of >= 200 parameter instances over >= 20 campaigns per
kind), the parameters most often missed, with their median |z| (error over uncertainty), and
how often the complete model's validation error 90 % lies within its 95 % prediction band
(``PhysicsFit.validation_band``; target >= 90 % of the campaigns).

    python benchmarks/coverage.py --campaigns 20 --seed 3801
"""
from __future__ import annotations

import argparse
import collections
import sys
import time

import numpy as np
from statsmodels.stats.proportion import proportion_confint

from deltatwin.calibration.diagnosis.floor import true_fit, true_model
from deltatwin.twin.cases import generate_cases
from deltatwin.twin.scenario import Scenario

Z95 = 1.959963984540054
TARGET = (0.90, 0.98)


def truth_of(values: dict, label: str) -> float | None:
    """The twin's value of the parameter labelled ``effect.name[i,j]`` (None if not kept)."""
    effect, _, rest = label.partition(".")
    name, _, index = rest.partition("[")
    if name not in values.get(effect, {}):
        return None
    arr = np.asarray(values[effect][name], dtype=float)
    idx = tuple(int(i) for i in index.rstrip("]").split(",")) if index else ()
    return float(arr[idx]) if arr.ndim == len(idx) else float(arr.ravel()[idx[0]])


def counted_parameters(fit, values: dict) -> dict:
    """{label: (value, uncertainty, twin's value)} of the parameters coverage counts: those of
    ``fit`` that are not geometric errors, that the fit calls identified (``identified_fraction``
    >= 0.5), with an uncertainty and a twin's value in ``values`` (``true_model``)."""
    out = {}
    for p in fit.parameters_:
        if p["label"].startswith("geometric_errors.") or p["identified_fraction"] < 0.5:
            continue
        truth = truth_of(values, p["label"])
        if truth is not None and p["uncertainty"] > 0:
            out[p["label"]] = (p["value"], p["uncertainty"], truth)
    return out


def campaign_instances(case, path) -> tuple[list[dict], bool]:
    """Every identified non-geometric parameter of the case's complete model, fitted (label,
    z, covered), and whether the model's validation error 90 % lies in its 95 % band."""
    path.write_text(case.toml())
    sc = Scenario.load(path)
    df, meta = sc.simulate(sc.reduced_scale)         # the tests' scale: 5 % thermal, 30 % force
    fit = true_fit(df, meta)
    _, values = true_model(meta)
    out = []
    for label, (value, u, truth) in counted_parameters(fit, values).items():
        z = (value - truth) / u
        out.append({"label": label, "z": z, "covered": abs(z) <= Z95})
    low, high = fit.validation_band(np.random.default_rng(case.seed))["all"]
    return out, bool(low <= fit.val_["all"]["err_p90"] <= high)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--campaigns", type=int, default=20, help="campaigns per kind (default 20)")
    ap.add_argument("--seed", type=int, default=3801, help="the cases' generator seed")
    args = ap.parse_args(argv)
    if args.campaigns < 1:
        print(f"--campaigns {args.campaigns}: at least 1", file=sys.stderr)
        return 2
    import tempfile
    from pathlib import Path

    rng = np.random.default_rng(args.seed)
    by_kind = collections.defaultdict(list)
    in_band = collections.defaultdict(list)
    start = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        for kind in ("thermal", "force"):
            for i, case in enumerate(generate_cases(rng, args.campaigns, kinds=(kind,))):
                t0 = time.perf_counter()
                found, inside = campaign_instances(case, Path(tmp) / f"{case.name}.toml")
                by_kind[kind].extend(found)
                in_band[kind].append(inside)
                print(f"{kind} {i + 1}/{args.campaigns} {case.name}: "
                      f"{sum(f['covered'] for f in found)}/{len(found)} covered "
                      f"({time.perf_counter() - t0:.1f} s)", file=sys.stderr, flush=True)
    for kind, rows in by_kind.items():
        n, k = len(rows), sum(r["covered"] for r in rows)
        lo, hi = proportion_confint(k, n, alpha=0.05, method="beta") if n else (0.0, 1.0)
        ok = n and TARGET[0] <= k / n <= TARGET[1]
        print(f"{kind}: {k}/{n} intervals cover the truth ({100 * k / max(n, 1):.1f} %, 95 % "
              f"interval {100 * lo:.1f}-{100 * hi:.1f} %) over {args.campaigns} campaigns; "
              f"target {100 * TARGET[0]:.0f}-{100 * TARGET[1]:.0f} %: "
              f"{'met' if ok else 'NOT met'}")
        band = in_band[kind]
        print(f"  the complete model's validation error within its 95 % prediction band: "
              f"{sum(band)}/{len(band)} campaigns (target >= 90 %)")
        misses = collections.defaultdict(list)
        for r in rows:
            misses[r["label"].split("[")[0]].append(r)
        for label, rs in sorted(misses.items(), key=lambda kv: -sum(not r["covered"]
                                                                     for r in kv[1])):
            print(f"  {label:<40} {sum(r['covered'] for r in rs):4d}/{len(rs):<4d} covered, "
                  f"median |z| {np.median([abs(r['z']) for r in rs]):.2f}")
    print(f"{time.perf_counter() - start:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
