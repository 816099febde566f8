"""Synthetic residual series for the statistical tests' calibration checks."""
import numpy as np


def ar1(rng: np.random.Generator, n: int, rho: float) -> np.ndarray:
    """A stationary AR(1) series of ``n`` values, unit variance, lag-1 correlation ``rho``."""
    e = np.empty(n)
    e[0] = rng.standard_normal()
    for i in range(1, n):
        e[i] = rho * e[i - 1] + np.sqrt(1 - rho ** 2) * rng.standard_normal()
    return e
