"""Benchmark: stepwisefit (calibration/blackbox/stepwise.py) vs a plain loop of statsmodels OLS refits.

Paper-scale problem (first paper, one axis): 217 candidate terms x 9701 rows — the calibration
rows of the X/Y session of the twin's paper-thermal campaign at full scale (the paper's 9701):
19 cubic monomials of q, 9 temperatures near 21-25 °C taken in degC as the seeds did
(T_ref = 0 °C, so the temperature x geometric columns are ill-conditioned), their 171
products with the geometric terms, causal first and second derivatives; the response is the
twin's X reading (5 nm noise std).  Seeded (the scenario's seed unless --seed).

Runs both on the same data, checks the selections are identical step by step, and prints
both times and the speed-up.  Targets: stepwisefit <= 1 s and >= 100x faster.

    python benchmarks/bench_stepwise.py            # paper scale, both methods
    python benchmarks/bench_stepwise.py --rows 2000 --repeat 5

BLAS threads: unless OPENBLAS_NUM_THREADS / OMP_NUM_THREADS are set, this script sets them to
1 before numpy loads: on the 2-vCPU development machine, under other processes' load,
multi-threaded OpenBLAS made the same 9701 x 218 QR take anywhere from 0.1 s to 4.8 s.
Both methods run under the same setting.
"""
from __future__ import annotations

import argparse
import os
import sys

for _v in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import time  # noqa: E402
import warnings  # noqa: E402

import numpy as np  # noqa: E402

from deltatwin.calibration.blackbox.estimator import base_variables, thermal_sensors  # noqa: E402
from deltatwin.calibration.blackbox.features import thermal_preset  # noqa: E402
from deltatwin.calibration.blackbox.stepwise import stepwise_refit_loop, stepwisefit  # noqa: E402
from deltatwin.twin.scenario import Scenario  # noqa: E402

PAPER_XY_CAL_ROWS = 9701


def paper_scale_problem(seed: int | None = None, n_rows: int = PAPER_XY_CAL_ROWS):
    """(X, y, names): the thermal preset's 217 columns for the X axis, temperatures in degC,
    on the calibration rows of paper-thermal's X/Y session (``n_rows`` of them: the scenario is
    scaled so that its session has at least that many, then the first ``n_rows`` are kept)."""
    scale = min(1.0, (n_rows + 0.5) / PAPER_XY_CAL_ROWS)   # rounding never short
    df, meta = Scenario.load("paper-thermal", seed=seed, scale=scale).simulate(scale)
    sensors = thermal_sensors(df, meta)
    df = df[(df["session"] == "xy") & (df["split"] == "cal")].iloc[:n_rows]
    if len(df) < n_rows:
        raise SystemExit(f"paper-thermal's X/Y session has {len(df)} calibration rows, "
                         f"fewer than --rows {n_rows}")
    fs = thermal_preset(sensors)
    values = base_variables(df, fs.variables, sensors, 273.15, 600.0)
    X = fs.matrix(values)
    y = df["x_nm"].to_numpy(dtype=float) * 1e-9
    return X, y, fs.names


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rows", type=int, default=PAPER_XY_CAL_ROWS)
    ap.add_argument("--seed", type=int, default=None,
                    help="the twin's seed (default: paper-thermal's own)")
    ap.add_argument("--repeat", type=int, default=5, help="timed runs of stepwisefit (best kept)")
    ap.add_argument("--skip-loop", action="store_true", help="do not run the slow reference")
    args = ap.parse_args(argv)

    X, y, names = paper_scale_problem(args.seed, args.rows)
    Z = (X - X.mean(0)) / X.std(0)
    sv = np.linalg.svd(Z, compute_uv=False)
    print(f"problem: {X.shape[1]} candidates x {X.shape[0]} rows of paper-thermal, seed "
          f"{'scenario' if args.seed is None else args.seed}; "
          f"condition number of the standardised candidates {sv[0] / sv[-1]:.3g}")
    print(f"BLAS threads: OPENBLAS_NUM_THREADS={os.environ.get('OPENBLAS_NUM_THREADS')}")

    stepwisefit(X, y)                                     # warm-up (imports, caches)
    times = []
    for _ in range(args.repeat):
        t0 = time.perf_counter()
        res = stepwisefit(X, y, names=names)
        times.append(time.perf_counter() - t0)
    t_fast = min(times)
    print(f"stepwisefit: {t_fast:.3f} s (best of {args.repeat}; median "
          f"{np.median(times):.3f} s); {res.n_steps} steps, {int(res.inmodel.sum())} terms kept, "
          f"RMSE {res.rmse * 1e9:.2f} nm, final QR refit rel. RSS difference "
          f"{res.refit_rel_diff:.1e}")
    ok_target = t_fast <= 1.0
    print(f"target <= 1 s: {'met' if ok_target else 'NOT met'}")
    if args.skip_loop:
        return 0 if ok_target else 1

    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ref_in, ref_steps = stepwise_refit_loop(X, y)
    t_loop = time.perf_counter() - t0
    same = ref_steps == res.steps() and np.array_equal(ref_in, res.inmodel)
    print(f"plain statsmodels OLS refit loop: {t_loop:.1f} s; {len(ref_steps)} steps, "
          f"{int(ref_in.sum())} terms kept")
    print(f"same selections in the same order: {'yes' if same else 'NO'}")
    if not same:
        for i, (a, b) in enumerate(zip(ref_steps, res.steps())):
            if a != b:
                print(f"  first difference at step {i + 1}: loop {a}, stepwisefit {b}")
                break
    ratio = t_loop / t_fast
    print(f"speed-up: {ratio:.0f}x (target >= 100x: {'met' if ratio >= 100 else 'NOT met'})")
    return 0 if (same and ok_target and ratio >= 100) else 1


if __name__ == "__main__":
    sys.exit(main())
