"""Benchmark: the false-claim rate of the rule's tests (calibration/stats.py) on null data where
the truth is known, and the validation test's power.

For each residual correlation rho (AR(1) per axis, three axes, one session) and row count, draws
a residual and an unrelated change (the null) and prints how often the offset-immune block test
(``validation_p``) and the calibration F test with the serial factor (``f_test_p``,
``serial_inflation``) fall below 0.05, 0.01 and 0.001, beside those levels; then the block
test's power on a change that is half the residual's structure. A calibrated test's rates equal
its levels (the binomial scatter of ``--draws`` draws printed beside them).

    python benchmarks/rule_level.py --draws 1500
"""
from __future__ import annotations

import argparse
import sys

import numpy as np
from scipy.signal import lfilter

from deltatwin.calibration import stats

LEVELS = (0.05, 0.01, 0.001)


def ar1(rng: np.random.Generator, shape: tuple, rho: float) -> np.ndarray:
    """Stationary AR(1) series along axis 0, unit variance."""
    w = rng.standard_normal(shape) * np.sqrt(1 - rho ** 2)
    w[0] = rng.standard_normal(shape[1:])
    return lfilter([1.0], [1.0, -rho], w, axis=0)


def rates(p: np.ndarray) -> str:
    return "  ".join(f"{100 * np.mean(p < a):6.2f} %" for a in LEVELS)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--draws", type=int, default=1500)
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args(argv)
    if args.draws < 10:
        print(f"--draws {args.draws}: at least 10", file=sys.stderr)
        return 2
    rng = np.random.default_rng(args.seed)
    print(f"{'test':<11} {'rows':>5} {'rho':>5}   " + "  ".join(f"p<{a:<6g}" for a in LEVELS)
          + "   power (change = half the structure, p < 0.001)")
    for n in (300, 600):
        group = np.tile(np.arange(3), (n, 1))
        val, session, t = np.ones(n, bool), np.zeros(n, int), np.arange(n, dtype=float)
        for rho in (0.0, 0.5, 0.9, 0.97):
            p_val, p_cal, power = [], [], []
            for _ in range(args.draws):
                before, change = ar1(rng, (n, 3), rho), ar1(rng, (n, 3), rho)
                p_val.append(stats.validation_p(before, before - change, group, val, session, t))
                e, x = before[:, 0] - before[:, 0].mean(), change[:, 0] - change[:, 0].mean()
                e1 = e - x * (x @ e) / (x @ x)
                p_cal.append(stats.f_test_p(e @ e, e1 @ e1, 1, n - 2,
                                            stats.serial_inflation([n], e - e1, e1)))
            for _ in range(max(args.draws // 5, 10)):
                structure, noise = ar1(rng, (n, 3), rho), ar1(rng, (n, 3), rho)
                power.append(stats.validation_p(0.5 * structure + noise, noise, group, val,
                                                session, t))
            print(f"{'validation':<11} {n:5d} {rho:5.2f}   {rates(np.array(p_val))}   "
                  f"{100 * np.mean(np.array(power) < 1e-3):5.1f} %")
            print(f"{'calibration':<11} {n:5d} {rho:5.2f}   {rates(np.array(p_cal))}")
    sd = [np.sqrt(a * (1 - a) / args.draws) * 100 for a in LEVELS]
    print("levels:  " + "  ".join(f"{100 * a:g} % (+- {s:.2f})" for a, s in zip(LEVELS, sd))
          + f" over {args.draws} draws")
    return 0


if __name__ == "__main__":
    sys.exit(main())
