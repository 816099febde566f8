"""Benchmark: the find-the-missing-effect loop on generated cases, and its scores.

Generates cases in the papers' laboratory conditions (deltatwin.twin.cases: a thermal or force
campaign hiding zero to three effects at random magnitudes; the frame arm a known constant),
simulates each at a reduced scale, records its achievable floor (the twin's complete model
refitted on the data, calibration/diagnosis/floor.py) and runs the researcher's loop
(``effect_ladder``: fit the baseline, diagnose, add the effect named, refit; at most three
additions). Prints per case and then the issue's scores against its targets:

* crashes (any exception in the loop): target 0;
* detection rounds: the hidden effect named first, target >= 90 %. A round (one diagnosis of
  the ladder) is a detection round when a hidden effect still missing from its model is
  *separable* (``separability``, decided from its candidate row and the model's error before
  looking at the verdict): it adds a direction beyond the model's span that the data determine
  (the fit's identifiability rule), and the model is above 1.1x the achievable floor (at the
  floor there is nothing left to find); printed also over the detection rounds whose data show
  the complete model (``shown_by_data``: the true model fitted on the same rows, the floor's
  fit, beats the round's model on the calibration rows or the validation rows at ALPHA, the
  diagnosis' own tests): a round where neither does is one no rule on these rows can decide;
* hidden effects absorbed by the model in a round (no direction beyond its span, >= 90 % of
  their signature in it): reported as absorbed (or found significant: not reported as absent),
  target >= 90 %;
* final validation error within 1.1x the achievable floor, target >= 90 % of the cases;
* null cases (nothing hidden): no effect named (kept by the ladder or not: it keeps only
  an effect whose refit lowers the validation error), target 0 false claims;
* the full-scale paper-thermal fit + diagnose (its baseline with the frame arm), target <= 60 s
  (wall; the CPU time and load average are printed beside it: the machine is shared).

    python benchmarks/discovery.py --cases 18 --seed 2611 --skip-full   # docs/calibration.md
    python benchmarks/discovery.py --cases 18 --seed 4242 --skip-full   # held-back: another seed
    python benchmarks/discovery.py                      # 8 cases, seed 15, and the full-scale time
    python benchmarks/discovery.py --cases 12 --seed 1234 --skip-full --only case010   # one case
    python benchmarks/discovery.py --cases 12 --seeds 10501-10548 --jobs 2 --skip-full
        # 576 cases pooled: each score with its 95 % interval (docs/calibration.md)
"""
from __future__ import annotations

import argparse
import collections
import os
import pickle
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from multiprocessing import get_context
from pathlib import Path

import numpy as np
import pandas as pd
from statsmodels.stats.proportion import proportion_confint

from deltatwin.calibration.diagnosis.diagnose import diagnose, effect_ladder, nested_verdict
from deltatwin.calibration.diagnosis.floor import achievable_floor, true_fit
from deltatwin.calibration.physics.fit import PhysicsFit
from deltatwin.calibration.stats import ABSORBED, ALPHA, AT_FLOOR
from deltatwin.twin.cases import FRAME_ARM_M, generate_cases
from deltatwin.twin.scenario import Scenario

SCALE = {"thermal": 0.02, "force": 0.3}
TARGETS = {"named_first": 0.9, "absorbed_reported": 0.9, "at_floor": 0.9}
FULL_TARGET_S = 60.0


def run_case(case, directory: Path, max_added: int, dump: Path | None = None) -> dict:
    path = directory / f"{case.name}.toml"
    path.write_text(case.toml())
    df, meta = Scenario.load(path).simulate(SCALE[case.kind])
    complete = true_fit(df, meta)
    floor = achievable_floor(df, meta, fit=complete)
    meta["truth"]["achievable_floor_nm"] = floor["achievable_floor_nm"]
    ladder, diagnoses, fits = effect_ladder(df, meta, list(case.baseline), data=str(path),
                                            max_added=max_added, known=case.known)
    # the ladder diagnoses every model it fits, in order: one test per diagnosis
    shown = [shown_by_data(fit, complete) for fit in fits]
    if dump:
        with open(dump / f"{case.name}.pkl", "wb") as fh:
            pickle.dump({"case": case, "floor": floor, "ladder": ladder, "diagnoses": diagnoses,
                         "shown": shown}, fh)
    return score(case, floor, ladder, diagnoses, len(df), shown)


def shown_by_data(fit: PhysicsFit, complete: PhysicsFit) -> dict:
    """Whether the data show that ``fit``'s model lacks something: the complete (true) model
    fitted on the same rows (``complete``, the achievable floor's fit) against it, by the
    diagnosis' own tests (``nested_verdict``): the calibration residual sums of squares (session means
    out), the F test over the directions the complete model identifies beyond the model's (at
    least one) with the rows' serial factor, and the one-sided validation test of the complete
    model's change. {p_calibration, p_validation, shown: either below ALPHA}. An oracle, for
    scoring only: on a force campaign in the papers' order the complete model fitted from the
    twin's values or the library's can fit the calibration rows *worse* than a model lacking
    loop drift (4646 case011: 1.047x the residual sum of squares; validation p = 0.04): no
    rule on the rows could name it there."""
    v = nested_verdict(fit, complete)
    return {"p_calibration": v["p_value"], "p_validation": v["p_validation"],
            "shown": v["p_value"] < ALPHA or v["p_validation"] < ALPHA}


def score(case, floor: dict, ladder: list, diagnoses: list, rows: int, shown: list) -> dict:
    """One case's results and score flags from its achievable floor, ladder, diagnoses and
    whether each diagnosis' data show the complete model (``shown_by_data``)."""
    hidden = set(case.hidden_effects)
    rounds, rounds_shown, absorbed, wrong = [], [], [], []
    seen = collections.Counter()
    for d, data in zip(diagnoses, shown):
        missing = hidden - set(d["effects"])
        # two effects named together (``_pair``) are two claims
        wrong += [e for e in _named(d) if e not in hidden]
        if not missing:
            continue
        by_effect = {c["effect"]: c for c in d["ranking"]}
        kinds = {e: separability(by_effect[e], d["at_floor"]) for e in missing}
        seen.update(kinds.values())
        absorbed += [by_effect[e]["significant"] or any(v.startswith(f"{e}:") for v in d["absorbed"])
                     for e, k in kinds.items() if k == "absorbed"]
        if "separable" in kinds.values():
            rounds.append(d["missing_effect"] in missing)
            if data["shown"]:
                rounds_shown.append(rounds[-1])
    final = ladder[-1]["val_err90_nm"]
    return {"case": case, "rows": rows, "floor_nm": floor["achievable_floor_nm"]["all"],
            "baseline_nm": ladder[0]["val_err90_nm"], "final_nm": final,
            "added": [r["added"] for r in ladder[1:]], "named_first": rounds,
            "named_first_shown": rounds_shown,
            "absorbed_reported": absorbed, "wrong": wrong, "separability": seen,
            # a named effect is a claim, kept or not (the ladder keeps only refits that lower
            # the validation error)
            "false_claim": not hidden and any(_named(d) for d in diagnoses),
            "at_floor": final <= AT_FLOOR * floor["achievable_floor_nm"]["all"]}


def _named(diagnosis: dict) -> list:
    """The effects a diagnosis names: its missing effect, and the one named with it when the
    ladder added two together (``diagnosis["pair"]``)."""
    return ([diagnosis["missing_effect"]] if diagnosis["missing_effect"] else []) + \
        diagnosis.get("pair", {}).get("effects", [])[1:]


def separability(row: dict, at_floor: bool) -> str:
    """How a hidden effect still missing from a round's model stands on this campaign, from its
    candidate row (the model linearised at its fit) and the round's model error, decided before
    looking at the verdict:

    * ``separable``: the candidate adds at least one direction beyond the span of the model's
      identified directions that the data determine (``new_directions``: the fit's own
      identifiability rule, a singular value above noise / identifiable_ratio), and the model
      is above AT_FLOOR (1.1x) the achievable floor: a detection round;
    * ``absorbed``: no such direction and >= ABSORBED (90 %) of its signature in the model's
      span: the model's parameters take its place on this campaign;
    * ``at floor``: it adds a determined direction, but the model is already within 1.1x the
      achievable floor: what the effect adds is below a tenth of the floor (a claim would fit
      the floor's noise);
    * ``weak``: no determined direction and less than 90 % absorbed: its signature beyond the
      model's span is below the noise;
    * ``failed``: its candidate could not be evaluated."""
    if "failed" in row:
        return "failed"
    if row["new_directions"] >= 1:
        return "at floor" if at_floor else "separable"
    return "absorbed" if row["absorbed_fraction"] >= ABSORBED else "weak"


def full_scale_time() -> dict:
    """Wall and CPU seconds of a full-scale paper-thermal fit + diagnose (simulation apart)."""
    df, meta = Scenario.load("paper-thermal").simulate()
    wall, cpu = time.perf_counter(), time.process_time()
    known = {"loop_drift": {"frame_arm_m": list(FRAME_ARM_M)}}
    fit = PhysicsFit(["geometric_errors", "thermal_expansion", "loop_drift", "sensor_contact"],
                     start=known).fit(df, meta)
    d = diagnose(fit, "paper-thermal")
    return {"wall_s": time.perf_counter() - wall, "cpu_s": time.process_time() - cpu,
            "load": os.getloadavg()[0], "rows": len(df), "converged": fit.converged_,
            "val_err90_nm": fit.val_["all"]["err_p90"], "missing": d["missing_effect"]}


def _flags(flags: list) -> str:
    return "".join("y" if f else "n" for f in flags) or "-"


def _share(flags: list) -> str:
    return f"{sum(flags)}/{len(flags)}" + (f" ({100 * np.mean(flags):.0f} %)" if flags else "")


def _seeds(text: str) -> list[int]:
    """``--seeds``: "A-B" (A to B inclusive) or "A,B,C"."""
    try:
        if "-" in text.strip("-"):
            a, b = (int(x) for x in text.split("-", 1))
            if b < a or a < 0:
                raise ValueError
            return list(range(a, b + 1))
        seeds = [int(x) for x in text.split(",") if x.strip()]
        if seeds and min(seeds) >= 0:
            return seeds
    except ValueError:
        pass
    raise argparse.ArgumentTypeError(f"{text!r}: give seeds (integers >= 0) as A-B (A <= B) "
                                     "or A,B,C")


def _scored(job: tuple) -> dict:
    """One case through ``run_case`` in its own folder, its table row (or its crash): the
    unit a worker runs. ``job``: (seed, case, max_added, dump)."""
    seed, case, max_added, dump = job
    start = time.process_time()
    with tempfile.TemporaryDirectory() as tmp:
        try:
            r = run_case(case, Path(tmp), max_added,
                         dump / str(seed) if dump else None)
        except Exception as exc:        # a crash is the score being measured
            return {"seed": seed, "case": case.name, "crash": f"{type(exc).__name__}: {exc}",
                    "cpu_s": time.process_time() - start}
    row = {"seed": seed, "case": case.name.split("-")[0], "kind": case.kind,
           "hidden": ", ".join(f"{e} x{m:.2g}" for e, m in case.hidden) or "-",
           "baseline_nm": r["baseline_nm"], "added": ", ".join(r["added"]) or "-",
           "final_nm": r["final_nm"], "floor_nm": r["floor_nm"],
           "ratio": r["final_nm"] / r["floor_nm"], "named_first": _flags(r["named_first"]),
           "shown": _flags(r["named_first_shown"]),
           "absorbed_reported": _flags(r["absorbed_reported"]),
           "wrong_claims": ", ".join(r["wrong"]) or "-",
           "missing_effects_by_round": " ".join(
               f"{k}:{n}" for k, n in sorted(r["separability"].items())) or "-",
           "cpu_s": time.process_time() - start}
    return {"seed": seed, "case": case.name, "result": r, "row": row, "cpu_s": row["cpu_s"]}


def _interval(flags: list) -> str:
    """The share's 95 % Clopper-Pearson interval (statsmodels), for pooled figures."""
    if not flags:
        return ""
    lo, hi = proportion_confint(sum(flags), len(flags), alpha=0.05, method="beta")
    return f", 95 % interval {100 * lo:.0f}-{100 * hi:.0f} %"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cases", type=int, default=8, help="cases per seed")
    ap.add_argument("--seed", type=int, default=15)
    ap.add_argument("--seeds", type=_seeds, help="several seeds, A-B or A,B,C (instead of "
                    "--seed): the scores pooled over all their cases, with 95 %% intervals")
    ap.add_argument("--jobs", type=int, default=1, help="cases run at once (processes)")
    ap.add_argument("--max-added", type=int, default=3)
    ap.add_argument("--dump", type=Path, help="write each case's ladder and diagnoses here "
                    "(pickle, one folder per seed) to study its failures")
    ap.add_argument("--skip-full", action="store_true", help="skip the full-scale timing")
    ap.add_argument("--only", default="",
                    help="run only the cases whose names start so (comma separated, e.g. "
                    "case003,case010) of those the seed generates, to study one failure")
    args = ap.parse_args()
    if args.jobs < 1:
        ap.error(f"--jobs {args.jobs}: need at least 1")
    if args.dump:
        # a bad --dump is the command line's error, not a crash of every case being scored
        if args.dump.exists() and not args.dump.is_dir():
            ap.error(f"--dump {args.dump}: not a folder")
    seeds = args.seeds or [args.seed]
    only = [c.strip() for c in args.only.split(",") if c.strip()]
    jobs = []
    for seed in seeds:
        cases = generate_cases(np.random.default_rng(seed), args.cases)
        unmatched = [o for o in only if not any(c.name.startswith(o) for c in cases)]
        if unmatched:
            ap.error(f"--only {','.join(unmatched)}: no case of seed {seed} starts so; its "
                     "cases: " + ", ".join(c.name for c in cases))
        # the cases are generated from the seed first: a case is the same with or without --only
        jobs += [(seed, c, args.max_added, args.dump) for c in cases
                 if not only or any(c.name.startswith(o) for o in only)]
    # the folders once every seed's --only is known to match: a refused run writes nothing
    for seed in seeds if args.dump else ():
        (args.dump / str(seed)).mkdir(parents=True, exist_ok=True)
    print(f"{len(jobs)} cases from seed(s) {_seed_text(seeds)}, simulated at scale {SCALE} of "
          "the papers' campaigns (their noise, sensors and climate unchanged)", flush=True)
    t0 = time.perf_counter()
    done = []
    for out in _run(jobs, args.jobs):
        done.append(out)
        if "crash" in out:
            print(f"seed {out['seed']} {out['case']}: CRASH {out['crash']}", flush=True)
        else:
            print(", ".join(f"{k} {v:.3g}" if isinstance(v, float) else f"{k} {v}"
                            for k, v in out["row"].items()), flush=True)
    results = [o["result"] for o in done if "result" in o]
    crashes = [(o["seed"], o["case"], o["crash"]) for o in done if "crash" in o]
    table = [o["row"] for o in done if "row" in o]
    with pd.option_context("display.width", 250, "display.max_columns", 20,
                           "display.max_colwidth", 60):
        print("\n" + pd.DataFrame(table).to_string(index=False, float_format="{:.1f}".format))
    pooled = len(seeds) > 1
    if pooled:
        print("\nper seed:")
        for seed in seeds:
            print(f"  {seed}: " + _summary_line(
                [o["result"] for o in done if o["seed"] == seed and "result" in o]))
    print(f"\n{len(jobs)} cases (seed(s) {_seed_text(seeds)}, scale {SCALE}): "
          f"{sum(o['cpu_s'] for o in done):.0f} s CPU, {time.perf_counter() - t0:.0f} s wall "
          f"({args.jobs} job(s)), load {os.getloadavg()[0]:.1f}")
    named, named_shown, absorbed, at_floor, nulls = _flags_of(results).values()
    ci = _interval if pooled else (lambda flags: "")
    print(f"  crashes: {len(crashes)} (target 0)"
          + "".join(f"\n    seed {s} {n}: {m}" for s, n, m in crashes))
    print(f"  hidden effect named first in separable rounds: {_share(named)}{ci(named)} "
          "(target >= 90 %)")
    print(f"    of those whose data show the complete model (calibration or validation rows, p < "
          f"{ALPHA:g}): {_share(named_shown)}{ci(named_shown)}")
    print(f"  absorbed effects reported as absorbed (or significant): {_share(absorbed)}"
          f"{ci(absorbed)} (target >= 90 %)")
    print(f"  final error within {AT_FLOOR}x the achievable floor: {_share(at_floor)}"
          f"{ci(at_floor)} (target >= 90 %)")
    print(f"  null cases with a false claim: {sum(r['false_claim'] for r in nulls)} of "
          f"{len(nulls)} (target 0); effects named that were not hidden, all cases: "
          f"{sum(len(r['wrong']) for r in results)}")
    if not args.skip_full:
        f = full_scale_time()
        print(f"  full-scale paper-thermal fit + diagnose ({f['rows']} rows): {f['wall_s']:.1f} s "
              f"wall, {f['cpu_s']:.1f} s CPU, load {f['load']:.1f} (target <= {FULL_TARGET_S:.0f} "
              f"s: {'met' if f['wall_s'] <= FULL_TARGET_S else 'NOT met'}); converged "
              f"{f['converged']}, val err90 {f['val_err90_nm']:.1f} nm, names {f['missing']}")


def _run(jobs: list, workers: int):
    """``_scored`` of every job, in order; in ``workers`` fresh processes when more than one
    (spawn: no forked copy of a threaded parent)."""
    if workers == 1:
        yield from map(_scored, jobs)
        return
    with ProcessPoolExecutor(workers, mp_context=get_context("spawn")) as pool:
        yield from pool.map(_scored, jobs)


def _seed_text(seeds: list) -> str:
    """The seeds as the command line gives them: A-B for a run of three or more, else A,B."""
    run = len(seeds) > 2 and seeds == list(range(seeds[0], seeds[-1] + 1))
    return f"{seeds[0]}-{seeds[-1]}" if run else ",".join(map(str, seeds))


def _flags_of(results: list) -> dict:
    """The scores' flags over ``results`` (``score``'s dicts): the detection rounds named first,
    those of them the data show, the absorbed effects reported, each case at its floor, and
    the null cases (their ``false_claim``)."""
    return {"named": [x for r in results for x in r["named_first"]],
            "named_shown": [x for r in results for x in r["named_first_shown"]],
            "absorbed": [x for r in results for x in r["absorbed_reported"]],
            "at_floor": [r["at_floor"] for r in results],
            "nulls": [r for r in results if not r["case"].hidden]}


def _summary_line(results: list) -> str:
    """A seed's scores in one line: named first, absorbed, at the floor, null false claims."""
    f = _flags_of(results)
    return (f"named {sum(f['named'])}/{len(f['named'])}, "
            f"absorbed {sum(f['absorbed'])}/{len(f['absorbed'])}, "
            f"floor {sum(f['at_floor'])}/{len(f['at_floor'])}, "
            f"null claims {sum(r['false_claim'] for r in f['nulls'])}/{len(f['nulls'])}")


if __name__ == "__main__":
    main()
