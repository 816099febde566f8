"""Benchmark: the standards' tests on paper-thermal's robot before and after compensation.

Simulates paper-thermal's calibration campaign (``--scale``), fits the first paper's stepwise
DGM and the physics model (the scenario's effects that have a model form, with the laboratory's
known constants, as benchmarks/bench_compensation.py does), then runs ``deltatwin iso`` with
both models on each test of ``--tests``: the same robot ``--after-h`` hours after its calibration,
uncompensated, through the stepwise black box and through the physics model. Prints per test
the standard's figures side by side with their expanded uncertainties, and for ISO 9283 the
target AP(physics) <= AP(uncompensated) / 10 (the largest AP over the five poses):

    python benchmarks/iso_before_after.py                         # full scale, ISO 9283
    python benchmarks/iso_before_after.py --scale 0.25 --tests 9283 230-2
    python benchmarks/iso_before_after.py --tests 230-3 --hours 24 --interval 60

Every figure printed is measured here.
"""
from __future__ import annotations

import argparse
import contextlib
import io
import json
import sys
import tempfile
import time
from pathlib import Path

from deltatwin.calibration.blackbox.dgm import DGM
from deltatwin.calibration.physics.fit import PhysicsFit
from deltatwin.calibration.physics.model import model_effects
from deltatwin.calibration.physics.model_file import fitted_toml
from deltatwin.cli import main as cli
from deltatwin.twin.dataset import write_dataset
from deltatwin.twin.scenario import Scenario

SCENARIO = "paper-thermal"


def fit_models(sc, scale: float, d: Path) -> list[Path]:
    df, meta = sc.simulate(None if scale >= 1 else scale)
    write_dataset(df, meta, d / "cal.parquet")
    effects = [e.name for e in sc.effects if e.name in model_effects()]
    known = {e.name: {p.name: e.values[p.name] for p in e.parameters if p.fit_scale is None}
             for e in sc.effects if e.name in effects}
    t0 = time.perf_counter()
    fit = PhysicsFit(effects, start=known).fit(df, meta)
    (d / "physics.toml").write_text(fitted_toml(fit, str(d / "cal.parquet")))
    dgm = DGM()
    dgm.fit(df, meta)
    dgm.save(d / "stepwise.json")
    print(f"calibration: {len(df)} rows at scale {scale:g}; physics ({', '.join(effects)}) and "
          f"stepwise DGM fitted in {time.perf_counter() - t0:.0f} s", flush=True)
    return [d / "stepwise.json", d / "physics.toml"]


def run_iso(test: str, models, scale: float, after_h: float, d: Path, extra) -> dict:
    out = io.StringIO()
    args = ["iso", SCENARIO, "--test", test, "-o", str(d / f"iso{test}"), "--after-h",
            str(after_h), "--json", "--quiet", *extra]
    for m in models:
        args += ["--compensate", str(m)]
    if scale < 1:
        args += ["--cal-scale", str(scale)]
    with contextlib.redirect_stdout(out):
        code = cli(args)
    if code != 0:
        raise SystemExit(f"deltatwin {' '.join(args)}: exit {code}")
    return json.loads(out.getvalue().strip().splitlines()[-1])


def print_rows(doc: dict, keep) -> None:
    arms = list(doc["arms"])
    figures = list(dict.fromkeys(r["figure"] for r in doc["figures"] if keep(r["figure"])))
    table = {(r["arm"], r["figure"]): r for r in doc["figures"]}
    print(f"{'figure':>16} " + " ".join(f"{a[:26]:>26}" for a in arms) + "   (nm, +- U k=2)")
    for f in figures:
        cells = [table[(a, f)] for a in arms]
        print(f"{f:>16} " + " ".join(f"{c['value_nm']:14.1f} +- {c['U_nm']:7.1f}"
                                      for c in cells))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scale", type=float, default=1.0, help="calibration campaign's scale")
    ap.add_argument("--tests", nargs="+", default=["9283"], choices=("9283", "230-2", "230-3"))
    ap.add_argument("--after-h", type=float, default=2.0)
    ap.add_argument("--hours", type=float, default=None, help="ISO 230-3 duration")
    ap.add_argument("--interval", type=float, default=None, help="ISO 230-3 sampling (s)")
    args = ap.parse_args(argv)
    sc = Scenario.load(SCENARIO)
    status = 0
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        models = fit_models(sc, args.scale, d)
        for test in args.tests:
            t0 = time.perf_counter()
            extra = []
            if test == "230-3":
                extra += ["--hours", str(args.hours)] if args.hours else []
                extra += ["--interval", str(args.interval)] if args.interval else []
            doc = run_iso(test, models, args.scale, args.after_h, d, extra)
            print(f"\nISO {test}, {args.after_h:g} h after the calibration "
                  f"({time.perf_counter() - t0:.0f} s):")
            if test == "9283":
                print_rows(doc, lambda f: f.split()[0] in ("AP", "RP"))
                ap_max = {a: r["AP_max_nm"] for a, r in doc["arms"].items()}
                unc = ap_max.pop("uncompensated")
                for arm, v in ap_max.items():
                    print(f"AP max {arm}: {v:.1f} nm = 1/{unc / v:.1f} of uncompensated "
                          f"{unc:.1f} nm")
                phys = next(v for a, v in ap_max.items() if a.startswith("physics"))
                ok = phys <= unc / 10
                status |= not ok
                print(f"target AP(physics) <= AP(uncompensated) / 10: {'met' if ok else 'NOT met'}")
            elif test == "230-2":
                print_rows(doc, lambda f: f.split()[0] in ("E", "M", "A", "R", "B"))
            else:
                print_rows(doc, lambda f: f.split()[0] in ("ETVE", "drift", "slope"))
    return status


if __name__ == "__main__":
    sys.exit(main())
