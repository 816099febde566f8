"""When the missing effect is outside the library: the scores on generated cases.

Seven cases whose missing term is injected into simulated data by an effect outside the library
(tests/calibration/outside_effects.py): a periodic encoder error in q1, a slow laser wavelength
drift in time, a backlash depending on the direction of motor 2's last move, a 40 nm X mirror
step at one moment (quiet laboratory, quiet/gravity-sag, baseline geometric_errors +
gravity_sag), a quadratic force term on Y (quiet/magnetic-force, baseline geometric_errors +
magnetic_force), and the wavelength drift and the mirror step again in paper-thermal's climbing
room on a symmetric portal frame (baseline: every library effect of the scenario with a model
form, the laboratory's constants known), where time and temperatures rise together.

For each case the researcher's loop runs (``run_case``): fit the baseline, diagnose (a claimed
library effect is added and the diagnosis repeated, at most twice), write the effect the
diagnosis proposes (``deltatwin effect new --from``) and fit with it, and fit with the
researcher's own effect (the injected class, its constants known). Scores, as the issue's
targets:

* no library effect claimed (first diagnosis): target 100 %;
* the variable the term depends on named first (the diagnosis that claims none): >= 80 %;
* the proposed form explains >= 80 % of the term's power (for the terms with a closed form in
  the candidate library: all of them): the effect ``deltatwin effect new --from`` writes from
  the form, fitted, carries that share of the correction the injected effect itself makes
  when fitted (its projection on it, validation readings; ``term_share`` in
  tests/calibration/outside_effects.py); the share of the largest axis'
  validation residual the form explains is printed beside it. Scored where the term is
  visible (fitting the injected effect lowers the baseline's val err90 by 10 % or more; a term
  the baseline's parameters absorb has no power of its own left: its share is printed as nan);
* with the researcher's effect added, val err90 within 1.1x the achievable floor. The
  achievable floor is the model with the injected effect itself fitted (``own``: on the quiet
  cases it is at the twin's noise floor, printed beside it; in paper-thermal's climbing room at
  reduced scale the baseline itself stays above the noise floor); the researcher's effect
  scored is the one ``deltatwin effect new --from`` writes from the proposed form
  (``proposed``): ratio = proposed / own. Where the diagnosis proposes no form (it finds the
  residual noise-like) the researcher has nothing to add and keeps the baseline: ratio =
  baseline / own. That is within 1.1x only where the term is not visible (the injected effect
  itself, fitted, lowers the baseline's error by less than 10 %: a wavelength drift on the
  paper-force campaigns, whose parameters and 45 nm repeatability take it, e.g. seed 523 g02:
  baseline 287.2 nm, with the injected effect 291.8), and never where it is: a visible term
  without a form is a loss. The score is printed for the visible and the invisible terms
  apart, as benchmarks/discovery.py scores separable rounds apart; so is the variable named
  first (the data do not show an invisible term: nothing can name it).

Beyond the seven fixed cases, ``--generated N`` cases are drawn from ``--seed``
(tests/calibration/outside_effects.py ``generate_cases``: periodic encoder errors with random
motor, period, amplitude and phase, wavelength drifts, hysteresis of a random motor, steps of a
random axis at random moments, force powers along random axes; on the quiet laboratories and on
the papers' thermal and force campaigns, on a portal frame and on the papers' hanging arm); the
scores are printed for each set.

    python benchmarks/outside_library.py                       # fixed + 8 generated (seed 16)
    python benchmarks/outside_library.py --cases '' --generated 10 --seed 7   # held-back seed
    python benchmarks/outside_library.py --cases periodic-encoder,backlash --generated 0
    python benchmarks/outside_library.py --cases '' --generated 12 --seed 99 --only g09
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))   # the repository's tests/
from tests.calibration.outside_effects import (  # noqa: E402
    CASES,
    PORTAL_CASES,
    VISIBLE,
    generate_cases,
    run_case,
)

PORTAL_SCALE = 0.03     # paper-thermal: 855 rows, 2.7 h (0-3900 s: its X/Y session)
TARGETS = {"unclaimed": 1.0, "named_first": 0.8, "form": 0.8, "floor_ratio": 1.1}


def _final(r: dict) -> dict:
    """The researcher's final val err90 (``final_err90_nm``: with the effect written from the
    proposed form, or the model kept where no form is proposed: the baseline with any library
    effect claimed, nothing to add) and its ratio to the achievable floor (``floor_ratio``),
    set in the case's result ``r``."""
    r["final_err90_nm"] = r["proposed_err90_nm"] if r["form"] else r["kept_err90_nm"]
    r["floor_ratio"] = r["final_err90_nm"] / r["own_err90_nm"]
    return r


def _run(label: str, cases: dict, work: str) -> list[dict]:
    """Run and print the cases {name: (case, scale)}; their results."""
    print(f"\n{label}")
    print(f"{'case':<34} {'rows':>5} {'base':>6} {'claimed':<18} {'named (first 3)':<44} "
          f"{'form':>5} {'term':>5} {'own':>6} {'noise':>6} {'proposed':>8} {'ratio':>6} "
          f"{'s':>4}")
    rows = []
    for name, (case, scale) in cases.items():
        t0 = time.perf_counter()
        r = run_case(case, work, scale=scale)
        _final(r)
        rows.append(r)
        named = ", ".join(f"{v['variable']} {v['explained_nm']:.1f}"
                          for v in r["diagnosis"]["unexplained"]["depends_on"][:3])
        print(f"{name:<34} {r['rows']:5d} {r['baseline_err90_nm']:6.1f} "
              f"{','.join(r['claimed']) or '-':<18} {named:<44} "
              f"{100 * r['form_explained']:4.0f}% {100 * r['term_share']:4.0f}% "
              f"{r['own_err90_nm']:6.1f} "
              f"{r['floor_nm']:6.1f} {r['proposed_err90_nm']:8.1f} {r['floor_ratio']:6.2f} "
              f"{time.perf_counter() - t0:4.0f}", flush=True)
        print(f"{'':<34} injected: {case[2].name} "
              + ", ".join(f"{k}={v:.4g}" for k, v in case[3].items())
              + f"; expected first: {case[4]}", flush=True)
        if r["diagnosis"]["unexplained"].get("form"):
            print(f"{'':<34} form: " + "; ".join(
                f"{f['axis']}: " + " + ".join(t["formula"] for t in f["terms"])
                + f" ({100 * f['explained_fraction']:.0f} %)"
                for f in r["diagnosis"]["unexplained"]["form"]), flush=True)
    return rows


def _scores(label: str, rows: list[dict]) -> dict:
    n = len(rows)
    ratios = [r["floor_ratio"] for r in rows]
    scores = {"unclaimed": sum(not r["claimed"] for r in rows) / n,
              "named_first": sum(r["named_first"] for r in rows) / n,
              "form": sum(r["form_explained"] >= TARGETS["form"] for r in rows) / n,
              "visible": sum(r["term_visible"] for r in rows),
              "term": (sum(r["term_visible"] and r["term_share"] >= TARGETS["form"] for r in rows)
                       / max(sum(r["term_visible"] for r in rows), 1)),
              "within": sum(x <= TARGETS["floor_ratio"] for x in ratios) / n,
              "floor_ratio": max(ratios),
              "no_form": sum(not r["form"] for r in rows)}
    visible = [r for r in rows if r["term_visible"]]
    hidden = [r for r in rows if not r["term_visible"]]
    count = lambda subset, ok: f"{sum(map(ok, subset))}/{len(subset)}"
    within = lambda r: r["floor_ratio"] <= TARGETS["floor_ratio"]
    met = lambda ok: "MET" if ok else "NOT MET"
    print(f"\n{label} ({n} cases, the term visible in {len(visible)}: the injected effect "
          f"fitted lowers the baseline's val err90 by >= {100 * VISIBLE:.0f} %):")
    print(f"  no library effect claimed: {100 * scores['unclaimed']:.0f} % (target 100 %): "
          f"{met(scores['unclaimed'] >= TARGETS['unclaimed'])}")
    print(f"  variable named first: {100 * scores['named_first']:.0f} % (target >= 80 %): "
          f"{met(scores['named_first'] >= TARGETS['named_first'])}; where the term is visible "
          f"{count(visible, lambda r: r['named_first'])}, where it is not "
          f"{count(hidden, lambda r: r['named_first'])}")
    print(f"  the effect written from the proposed form explains >= 80 % of the term's power: "
          f"{100 * scores['term']:.0f} % of the {scores['visible']} cases where the term is "
          f"visible (target: every case with a closed form, all here): "
          f"{met(scores['term'] >= 1.0)}; the form explains >= 80 % of the largest axis' "
          f"validation residual in {100 * scores['form']:.0f} % of all {n}")
    print(f"  with the researcher's effect within 1.1x the achievable floor: "
          f"{100 * scores['within']:.0f} % of the cases, worst ratio {scores['floor_ratio']:.2f} "
          f"(target <= 1.1; {scores['no_form']} without a proposed form: the baseline kept): "
          f"{met(scores['within'] >= 1.0)}; where the term is visible {count(visible, within)}, "
          f"where it is not (the baseline near the floor) {count(hidden, within)}")
    return scores


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    every = {**CASES, **PORTAL_CASES}
    ap.add_argument("--cases", default=",".join(every),
                    help="comma-separated fixed case names ('' for none)")
    ap.add_argument("--generated", type=int, default=8,
                    help="number of cases generated from --seed (default 8)")
    ap.add_argument("--seed", type=int, default=16, help="seed of the generated cases")
    ap.add_argument("--only", default="",
                    help="comma-separated prefixes of the generated cases to run (e.g. g05,g09; "
                         "default all): rerun a few of a seed's cases, drawn as in the full set")
    args = ap.parse_args(argv)
    names = [c.strip() for c in args.cases.split(",") if c.strip()]
    unknown = [c for c in names if c not in every]
    if unknown:
        ap.error(f"unknown case(s) {unknown}; cases: {sorted(every)}")
    if args.generated < 0:
        ap.error(f"--generated {args.generated}: must be >= 0")
    fixed = {n: (every[n], PORTAL_SCALE if n in PORTAL_CASES else None) for n in names}
    generated = generate_cases(np.random.default_rng(args.seed), args.generated)
    only = [c.strip() for c in args.only.split(",") if c.strip()]
    unmatched = [o for o in only if not any(n.startswith(o) for n in generated)]
    if unmatched:
        ap.error(f"--only {','.join(unmatched)}: no generated case of seed {args.seed} starts so; "
                 f"cases: {sorted(generated)}")
    if only:
        generated = {n: c for n, c in generated.items() if any(n.startswith(o) for o in only)}
    t_all = time.perf_counter()
    results = {}
    with tempfile.TemporaryDirectory() as work:
        if fixed:
            results["fixed"] = _run("the fixed cases", fixed, work)
        if generated:
            results["generated"] = _run(f"{len(generated)} cases generated from seed "
                                        f"{args.seed}", generated, work)
    print(f"\n{sum(map(len, results.values()))} cases in {time.perf_counter() - t_all:.0f} s "
          "(base, own, proposed: val err90 nm of the baseline, with the injected effect fitted "
          "(the achievable floor), with the effect written from the proposed form; noise: the "
          "twin's noise floor, max over axes; ratio: proposed / own (baseline / own where no "
          "form is proposed: the baseline kept); form: share of the largest "
          "axis' validation residual the form explains; term: share of the term's power the "
          "effect written from it explains, d_proposed . d_own / |d_own|^2 with d = r_base - r "
          "on the validation readings; nan where the term is not visible)")
    for label, rows in results.items():
        _scores(f"{label} cases" if label == "fixed" else
                f"cases generated from seed {args.seed}", rows)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
