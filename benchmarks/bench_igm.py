"""Benchmark: IGM by Newton-Raphson on a fitted DGM, batch throughput and convergence.

Fits a thermal DGM (217 candidates, 9 sensors) on the twin's paper-thermal campaign (full
scale by default: 28,492 readings over three days, the scenario's seed), then solves a batch of
targets DGM(q_true, temperatures) for random q_true in the stroke and temperature
states (with their causal derivatives) drawn from the campaign's rows.  Prints points/s
(target >= 100,000), the share converged, the largest residual |DGM(q) - target| in nm
(target <= 0.001 nm) and the largest |q - q_true|.

    python benchmarks/bench_igm.py                 # 200,000 points
    python benchmarks/bench_igm.py --points 1000000 --scale 0.3

BLAS threads default to 1 as in bench_stepwise.py (set OPENBLAS_NUM_THREADS to override).
"""
from __future__ import annotations

import argparse
import os
import sys

for _v in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import time  # noqa: E402

import numpy as np  # noqa: E402

from deltatwin.calibration.blackbox.dgm import DGM  # noqa: E402
from deltatwin.calibration.blackbox.igm import IGM  # noqa: E402
from deltatwin.twin.scenario import Scenario  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, default=200_000)
    ap.add_argument("--seed", type=int, default=7, help="seed of the targets drawn")
    ap.add_argument("--scale", type=float, default=1.0,
                    help="share of paper-thermal's points simulated (1.0: the paper's campaign)")
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args(argv)
    rng = np.random.default_rng(args.seed)

    t0 = time.perf_counter()
    df, meta = Scenario.load("paper-thermal", scale=args.scale).simulate(args.scale)
    t_sim = time.perf_counter() - t0
    t0 = time.perf_counter()
    dgm = DGM().fit(df, meta)
    t_fit = time.perf_counter() - t0
    print(f"paper-thermal at scale {args.scale:g}: {len(df)} readings simulated in {t_sim:.1f} s; "
          f"DGM fitted in {t_fit:.1f} s")
    igm = IGM(dgm, tol_m=1e-12)
    print(f"DGM: terms kept {dgm.terms_kept_} of {len(dgm.features_)} candidates; IGM aux "
          f"variables: {len(igm.aux_variables)}")

    values = dgm.variables(df)
    rows = rng.integers(0, len(df), args.points)
    aux = {v: values[v][rows] for v in igm.aux_variables}
    q_true = rng.uniform(-0.045, 0.045, (args.points, 3))
    target = dgm.predict_values({**aux, "q1": q_true[:, 0], "q2": q_true[:, 1],
                                 "q3": q_true[:, 2]})
    target = target[:, [dgm.output_names_.index(a) for a in "xyz"]]

    igm.solve(target[:1000], {k: v[:1000] for k, v in aux.items()})       # warm-up
    times = []
    for _ in range(args.repeat):
        t0 = time.perf_counter()
        res = igm.solve(target, aux)
        times.append(time.perf_counter() - t0)
    t = min(times)
    rate = args.points / t
    # independent check of the residual with the DGM's own predict path
    back = dgm.predict_values({**aux, "q1": res.q[:, 0], "q2": res.q[:, 1], "q3": res.q[:, 2]})
    back = back[:, [dgm.output_names_.index(a) for a in "xyz"]]
    resid_nm = np.max(np.abs(back - target)) * 1e9
    conv = res.converged.mean()
    print(f"batch of {args.points} points: {t:.3f} s (best of {args.repeat}) -> "
          f"{rate:,.0f} points/s (target >= 100,000: {'met' if rate >= 1e5 else 'NOT met'})")
    print(f"converged: {conv * 100:.3f} % ({res.n_failed} reported not converged); Newton "
          f"iterations: max {res.iterations.max()}, mean {res.iterations.mean():.2f}")
    print(f"max residual |DGM(q) - target|: {res.residual_m[res.converged].max() * 1e9:.2e} nm "
          f"(solver), {resid_nm:.2e} nm (re-evaluated); target <= 0.001 nm: "
          f"{'met' if resid_nm <= 1e-3 else 'NOT met'}")
    print(f"max |q - q_true|: {np.abs(res.q - q_true).max():.2e} rad")
    stroke_ok = _unreachable_targets(dgm, igm, aux, rng)
    return 0 if (rate >= 1e5 and resid_nm <= 1e-3 and conv == 1.0 and stroke_ok) else 1


def _unreachable_targets(dgm, igm, aux, rng, n: int = 2000) -> bool:
    """Targets the IGM cannot reach in the stroke: angles up to 6x the stroke, and targets 1 mm, 1 cm, 10 cm
    (random direction) from reachable ones. Prints the statuses; every converged answer must
    lie in the stroke and reach its target to 0.001 nm."""
    lo, hi = igm.stroke_rad
    aux = {k: v[:n] for k, v in aux.items()}
    order = [dgm.output_names_.index(a) for a in "xyz"]
    reading = lambda q: dgm.predict_values({**aux, "q1": q[:, 0], "q2": q[:, 1],
                                            "q3": q[:, 2]})[:, order]
    cases = [("angles up to 6x the stroke", reading(rng.uniform(6 * lo, 6 * hi, (n, 3))))]
    base = reading(rng.uniform(lo, hi, (n, 3)))
    for d in (1e-3, 1e-2, 1e-1):
        u = rng.standard_normal((n, 3))
        cases.append((f"{d * 1e3:g} mm from reachable", base + d * u / np.linalg.norm(
            u, axis=1)[:, None]))
    ok = True
    for name, target in cases:
        r = igm.solve(target, aux)
        c = r.converged
        sound = bool(np.all(igm.in_stroke(r.q[c]))
                     and np.abs(reading(r.q)[c] - target[c]).max(initial=0) <= 1e-12)
        ok &= sound
        counts = {s: int((r.status == s).sum()) for s in ("converged", "out_of_stroke",
                                                          "out_of_reach", "not_finite")}
        print(f"targets {name:>28}: {counts} (converged ones in stroke and <= 0.001 nm: "
              f"{'yes' if sound else 'NO'})")
    return ok


if __name__ == "__main__":
    sys.exit(main())
