"""The prediction band's noise (calibration/physics/band.py): a moving-block bootstrap of the
calibration residual keeps the residual's own 90 % point and serial correlation, where a
Gaussian of the same standard deviation overstates the 90 % point of a heavy-tailed residual."""
import numpy as np
import pytest

from deltatwin.calibration.physics.band import block_bootstrap, block_length


def _ar1(rng, n, rho):
    e = np.empty(n)
    e[0] = rng.standard_normal()
    for i in range(1, n):
        e[i] = rho * e[i - 1] + np.sqrt(1 - rho ** 2) * rng.standard_normal()
    return e


def test_the_bootstrap_keeps_a_heavy_tailed_residuals_90_percent_point():
    rng = np.random.default_rng(21)
    # mostly 10 nm white noise, 5 % of the readings 80 nm bursts: the standard deviation
    # (20 nm) is set by the bursts, the 90 % point by the bulk
    e = np.where(rng.random(4000) < 0.05, 80e-9, 10e-9) * rng.standard_normal(4000)
    drawn = block_bootstrap(rng, e, 500, 400)
    assert drawn.shape == (500, 400) and np.all(np.isin(drawn, e))
    p90 = np.quantile(np.abs(e), 0.9)
    assert np.median(np.quantile(np.abs(drawn), 0.9, axis=0)) == pytest.approx(p90, rel=0.05)
    assert 1.645 * e.std() > 1.3 * p90          # what a Gaussian of its sigma would claim


def test_the_blocks_span_the_correlation_and_keep_it():
    rng = np.random.default_rng(22)
    assert block_length(rng.standard_normal(1000)) <= 3          # white: blocks of 1 to 3
    e = _ar1(rng, 4000, 0.9)
    assert block_length(e) == pytest.approx(2 * 1.9 / 0.1, rel=0.15)     # 38 rows
    drawn = block_bootstrap(rng, e, 2000, 50)
    lag1 = np.mean(np.sum(drawn[1:] * drawn[:-1], axis=0) / np.sum(drawn ** 2, axis=0))
    assert lag1 == pytest.approx(0.9 * (1 - 1 / block_length(e)), abs=0.03)
    assert block_bootstrap(rng, np.zeros(0), 5, 3).shape == (5, 3)
