"""The standards' repeatability figures on the twin with reading noise only, against their
Gaussian predictions: ISO 9283 RP and ISO 230-2 R_i up / down, over >= 20 simulated tests.

The twin: the nominal robot, no effect, interferometers with isotropic Gaussian reading noise
sigma per axis (``noise_floor_m``) and nothing else (no resolution, no window noise, no cosine
correction). Each test is a campaign of the standard's plan (twin/standard_tests.py) through the
simulated instruments (the vectorised fast path), evaluated by calibration/standards.

Predictions:
* RP of a pose (n cycles): the distance to the barycentre is sigma sqrt((n-1)/n) times a chi
  variable with 3 degrees of freedom, so RP -> (2 sqrt(2/pi) + 3 sqrt(3 - 8/pi)) sigma
  sqrt((n-1)/n) (``rp_gaussian``); per test the mean over its 5 poses;
* R_i up = 4 s_i up of a target (n approaches): E[s] = c4(n) sigma, so 4 c4(n) sigma
  (-> 4 sigma for many approaches; ``gaussian.r_gaussian``); per test the mean over its targets and axes, both
  directions (each direction's R_i are draws of the same law).

And the expanded uncertainty (k = 2) of the AP components (calibration/standards/uncertainty,
the noise-only laboratory's specifications): how often it covers the value a perfect
instrument gives on the same timeline (the twin's noise-free readings), against the 95 % it
claims.

Run: ``python benchmarks/iso_noise_only.py [--tests 20]``; prints each test's measured figures
beside the predictions, and whether each is within 10 %, then the coverage.
"""
from __future__ import annotations

import argparse
import sys

import numpy as np

from deltatwin.calibration.standards.campaign import evaluate_test
from deltatwin.calibration.standards.gaussian import c4, r_gaussian, rp_gaussian
from deltatwin.calibration.standards.report import figure_rows
from deltatwin.calibration.standards.uncertainty import spec_from_scenario
from deltatwin.twin.campaign import simulate_campaign
from deltatwin.twin.scenario import Scenario
from deltatwin.twin.world import random_streams

SIGMA_M = 5e-9
TEXT = """
[scenario]
name = "noise-only"
seed = {seed}
[effects]
on = []
[sensors]
air_x = "air_x"
[instruments]
noise_floor_m = {sigma}
sample_noise_m = 0.0
resolution_m = 0.0
cosine_correction = false
[campaign]
{campaign}
"""


def run_test(seed: int, campaign: str):
    """(result, the result a perfect instrument gives on the same timeline, rows with U)."""
    sc = Scenario.from_text(TEXT.format(seed=seed, sigma=SIGMA_M, campaign=campaign),
                            "noise-only.toml")
    test = sc.standard_test(random_streams(sc.seed)["campaign"])
    twin, plan = sc.build()
    df, clean = simulate_campaign(plan, twin, sc.settings, sc.cosine, sc.dead_path(),
                                  noise_free=True)
    result = evaluate_test(test, df)
    specs = {a: spec_from_scenario(sc, a) for a in "xyz"}
    return result, evaluate_test(test, clean), figure_rows(test, "", result, specs)


def ap_covered(result, truth, rows) -> list[bool]:
    """|APx - true APx| <= U, likewise y and z, per pose."""
    U = {r["figure"]: r["U_nm"] * 1e-9 for r in rows}
    return [abs(getattr(p, k) - getattr(t, k)) <= U[f"{k} {p.name}"]
            for p, t in zip(result.poses, truth.poses) for k in ("APx", "APy", "APz")]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--tests", type=int, default=20)
    args = ap.parse_args(argv)
    cycles, approaches, targets = 30, 5, 21
    rp_pred = rp_gaussian(SIGMA_M, cycles)
    r_pred = r_gaussian(SIGMA_M, approaches)
    print(f"sigma {SIGMA_M * 1e9:.2f} nm per axis; predicted RP {rp_pred * 1e9:.3f} nm "
          f"({rp_pred / SIGMA_M:.4f} sigma; limit {rp_gaussian(1.0, 10**9):.4f} sigma), "
          f"R_i up {r_pred * 1e9:.3f} nm (4 c4({approaches}) = {4 * c4(approaches):.4f} sigma; "
          "limit 4 sigma)")
    print(f"{'seed':>5} {'RP nm':>8} {'/pred':>7} {'R_i nm':>8} {'/pred':>7}")
    fails, rps, rs, covered = 0, [], [], []
    for seed in range(1, args.tests + 1):
        r9283, truth, rows = run_test(seed, f'kind = "iso9283"\ncycles = {cycles}')
        covered += ap_covered(r9283, truth, rows)
        r230 = run_test(seed, f'kind = "iso230-2"\ntargets = {targets}\n'
                              f'approaches = {approaches}')[0]
        rp = float(np.mean([p.RP for p in r9283.poses]))
        r_i = float(np.mean(np.concatenate([np.r_[r.R_up_i, r.R_down_i]
                                            for r in r230.values()])))
        ok = abs(rp / rp_pred - 1) <= 0.1 and abs(r_i / r_pred - 1) <= 0.1
        fails += not ok
        rps.append(rp)
        rs.append(r_i)
        print(f"{seed:>5} {rp * 1e9:8.3f} {rp / rp_pred:7.3f} {r_i * 1e9:8.3f} "
              f"{r_i / r_pred:7.3f}{'' if ok else '  OUTSIDE 10 %'}")
    print(f"mean over {args.tests} tests: RP {np.mean(rps) / rp_pred:.4f} x predicted, R_i "
          f"{np.mean(rs) / r_pred:.4f} x predicted; {args.tests - fails} of {args.tests} tests "
          "within 10 % on both")
    print(f"expanded uncertainty (k = 2) of APx, APy, APz: covers the perfect instrument's value "
          f"in {sum(covered)} of {len(covered)} ({100 * np.mean(covered):.1f} %; 95 % claimed)")
    return 1 if fails else 0


if __name__ == "__main__":
    sys.exit(main())
