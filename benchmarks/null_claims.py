"""Benchmark: the diagnosis' false-claim rate on null campaigns, where the model is complete.

Generates null campaigns in the papers' conditions (deltatwin.twin.cases with nothing hidden:
the baseline is the twin's whole model, the frame arm a known constant), simulates each at the
discovery benchmark's scale (2 % of the thermal campaign, 30 % of the force one), fits the
complete model from the library's starting values (the achievable floor's fit) and diagnoses
it against that floor. Every candidate row the
diagnosis calls significant is a false claim: the effect is absent from the data. Prints per
campaign kind

* the rows' false-claim rate against the rule's alpha (calibration/stats.py ``ALPHA``), with
  its 95 % Clopper-Pearson interval: a calibrated test claims at most its alpha (the target:
  <= 1.5 alpha);
* the campaigns with any claim, against what independent rows at alpha would give;
* the campaigns whose diagnosis names a missing effect, or proposes a form or a variable for
  a missing term, though nothing is missing;
* the rows whose calibration F test alone falls below alpha (what the rule's other conditions
  stand against).

    python benchmarks/null_claims.py --campaigns 100 --seed 3802 --jobs 2
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from multiprocessing import get_context
from pathlib import Path

import numpy as np
from statsmodels.stats.proportion import proportion_confint

from deltatwin.calibration.diagnosis.diagnose import diagnose
from deltatwin.calibration.diagnosis.floor import achievable_floor, true_fit
from deltatwin.calibration.stats import ALPHA
from deltatwin.twin.cases import generate_cases
from deltatwin.twin.scenario import Scenario

SCALE = {"thermal": 0.02, "force": 0.3}


def null_campaign(case) -> dict:
    """One null campaign's diagnosis: its rows' verdicts and what it names or proposes."""
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / f"{case.name}.toml"
        path.write_text(case.toml())
        df, meta = Scenario.load(path).simulate(SCALE[case.kind])
    # the complete model from the library's starting values, which is also the achievable
    # floor's fit: the diagnosis judges the model against that floor, as on any twin data
    fit = true_fit(df, meta)
    meta["truth"]["achievable_floor_nm"] = achievable_floor(df, meta, fit=fit)[
        "achievable_floor_nm"]
    d = diagnose(fit, case.name)
    rows = [(c["effect"], bool(c["significant"]), float(c["p_value"])) for c in d["ranking"]]
    return {"case": case.name, "kind": case.kind, "rows": rows,
            "named": d["missing_effect"], "form": bool((d.get("unexplained") or {}).get("form")),
            "converged": fit.converged_}


def _interval(k: int, n: int) -> str:
    lo, hi = proportion_confint(k, n, alpha=0.05, method="beta") if n else (0.0, 1.0)
    return f"{k}/{n} ({100 * k / max(n, 1):.2f} %, 95 % interval {100 * lo:.2f}-{100 * hi:.2f} %)"


def report(results: list[dict]) -> None:
    for kind in ("thermal", "force"):
        rs = [r for r in results if r["kind"] == kind]
        if not rs:
            continue
        rows = [row for r in rs for row in r["rows"]]
        claims = sum(sig for _, sig, _ in rows)
        per_campaign = np.mean([len(r["rows"]) for r in rs])
        expected = 1 - (1 - ALPHA) ** per_campaign
        print(f"{kind}: {len(rs)} null campaigns, {len(rows)} candidate rows")
        print(f"  rows called significant: {_interval(claims, len(rows))}; alpha "
              f"{100 * ALPHA:.2f} %, target <= {150 * ALPHA:.2f} %: "
              f"{'met' if claims / max(len(rows), 1) <= 1.5 * ALPHA else 'NOT met'}")
        claimed = sum(any(s for _, s, _ in r["rows"]) for r in rs)
        print(f"  campaigns with a claim: {_interval(claimed, len(rs))} (independent rows at "
              f"alpha: {100 * expected:.2f} %)")
        print(f"  a missing effect named: {sum(bool(r['named']) for r in rs)}; a form proposed: "
              f"{sum(r['form'] for r in rs)}; fits not converged: "
              f"{sum(not r['converged'] for r in rs)}")
        raw = sum(p < ALPHA for _, _, p in rows)
        print(f"  rows whose calibration F test alone is below alpha: {_interval(raw, len(rows))}"
              " (the rule asks more: the BIC falls, and the candidate explains enough)")
        small = sorted((p, e, r["case"]) for r in rs for e, _, p in r["rows"])[:3]
        print("  smallest p-values: " + "; ".join(f"{e} {p:.2g} ({c})" for p, e, c in small))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--campaigns", type=int, default=20, help="null campaigns per kind")
    ap.add_argument("--seed", type=int, default=3802, help="the cases' generator seed")
    ap.add_argument("--jobs", type=int, default=1, help="worker processes")
    args = ap.parse_args(argv)
    if args.campaigns < 1 or args.jobs < 1:
        print(f"--campaigns {args.campaigns}, --jobs {args.jobs}: at least 1 each",
              file=sys.stderr)
        return 2
    rng = np.random.default_rng(args.seed)
    cases = [c for kind in ("thermal", "force")
             for c in generate_cases(rng, args.campaigns, kinds=(kind,), null_fraction=1.0)]
    start, results = time.perf_counter(), []
    with ProcessPoolExecutor(args.jobs, mp_context=get_context("spawn")) as pool:
        for i, r in enumerate(pool.map(null_campaign, cases)):
            results.append(r)
            print(f"{i + 1}/{len(cases)} {r['case']}: "
                  f"{sum(s for _, s, _ in r['rows'])} of {len(r['rows'])} rows significant",
                  file=sys.stderr, flush=True)
    report(results)
    print(f"{time.perf_counter() - start:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
