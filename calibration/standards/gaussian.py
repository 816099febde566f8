"""What the repeatability figures are for reading noise alone (isotropic Gaussian, standard
deviation sigma per axis): the predictions the noise-only twin is checked against
(benchmarks/iso_noise_only.py, tests/calibration/standards)."""
from __future__ import annotations

import math


def c4(n: int) -> float:
    """E[s] / sigma of the sample standard deviation (ddof 1) of ``n`` Gaussian draws."""
    return math.sqrt(2 / (n - 1)) * math.exp(math.lgamma(n / 2) - math.lgamma((n - 1) / 2))


def rp_gaussian(sigma_m: float, cycles: int) -> float:
    """E[l̄] + 3 E[S_l] of ISO 9283's RP (m) for ``cycles`` attained positions scattered with
    ``sigma_m`` per axis: the distance to the barycentre is sigma sqrt((n-1)/n) times a chi
    variable with 3 degrees of freedom (mean 2 sqrt(2/pi), standard deviation
    sqrt(3 - 8/pi)); S_l, a sample standard deviation, has the mean c4(n) times it (the
    distances treated as independent). For many cycles RP -> (2 sqrt(2/pi) + 3 sqrt(3 - 8/pi))
    sigma = 3.6161 sigma."""
    scale = sigma_m * math.sqrt((cycles - 1) / cycles)
    return scale * (2 * math.sqrt(2 / math.pi) + 3 * c4(cycles) * math.sqrt(3 - 8 / math.pi))


def r_gaussian(sigma_m: float, approaches: int) -> float:
    """E[R_i] of ISO 230-2's unidirectional repeatability 4 s_i (m) at a target approached
    ``approaches`` times with reading noise ``sigma_m``: 4 c4(n) sigma (-> 4 sigma)."""
    return 4.0 * c4(approaches) * sigma_m
