"""The slow noise sources' share of a physics fit's parameter covariance
(calibration/physics/thermometers.py ``thermometer_covariance``, calibration/physics/air.py
``air_covariance``), each an exact first-order propagation, checked against a Monte Carlo of
the source itself through the whole nonlinear pipeline (fresh readings, the causal smoothing
rebuilt, the model predicted again): the GUM's Supplement 1 against its law of propagation.
And the linear maps they rest on against the functions they stand for."""
import dataclasses

import numpy as np
import pytest

from deltatwin.calibration.physics.air import air_covariance, air_levers, stated_air
from deltatwin.calibration.physics.fit import PhysicsFit
from deltatwin.calibration.physics.measurements import measurements
from deltatwin.calibration.physics.model import (
    PhysicsModel,
    projected,
    projected_transpose,
    reading_response,
)
from deltatwin.calibration.physics.thermometers import (
    thermometer_covariance,
    thermometer_u_K,
)
from deltatwin.calibration.streams import causal_fit, causal_weights
from deltatwin.twin.scenario import Scenario

DRAWS = 120


@pytest.fixture(scope="module")
def fitted():
    """A small force campaign of the papers' laboratory (its air wanders 80 Pa over a day)
    and a model whose parameters multiply temperatures."""
    sc = Scenario.load("paper-force", scale=0.05)
    df, meta = sc.simulate(0.05)
    fit = PhysicsFit(["geometric_errors", "thermal_expansion", "loop_drift"]).fit(df, meta)
    meas = fit.measurements_
    Jz = projected(meas, meas.cal, fit.jacobian_, scale=fit.model_.scales) @ \
        fit.identified_directions_
    return df, meta, fit, Jz, Jz.T @ Jz


def _agrees(exact: np.ndarray, draws: np.ndarray):
    """The draws (D, k), whitened by the propagated covariance ``exact`` in its eigenbasis,
    have unit second moments: their mean squared norm is k within 4 standard errors
    (sqrt(2 / (k D)) relative, for Gaussian draws), each coordinate's between 0.5 and 1.6
    (D = 120: one coordinate's standard error is 0.13)."""
    value, vector = np.linalg.eigh(exact)
    kept = value > value.max() * 1e-12
    white = draws @ vector[:, kept] / np.sqrt(value[kept])
    per_coordinate = np.mean(white ** 2, axis=0)
    k, d = per_coordinate.size, draws.shape[0]
    assert abs(per_coordinate.mean() - 1.0) < 4 * np.sqrt(2.0 / (k * d)), per_coordinate.mean()
    assert np.all((per_coordinate > 0.5) & (per_coordinate < 1.6)), per_coordinate


def test_causal_weights_are_the_causal_fits_linear_map():
    rng = np.random.default_rng(11)
    t = np.sort(np.concatenate([rng.uniform(0, 5000, 300), np.full(5, 1000.0),
                                np.arange(3000.0, 3100.0, 7.0)]))
    v = rng.standard_normal((t.size, 3))
    for degree in (1, 2):
        level_map, rate_map = causal_weights(t, 600.0, degree)
        level, rate = causal_fit(t, v, 600.0, degree)[:2]
        np.testing.assert_allclose(level_map @ v, level, atol=1e-12)
        np.testing.assert_allclose(rate_map @ v, rate, atol=1e-15)


def test_projected_transpose_is_the_adjoint_of_projected(fitted):
    meas = fitted[2].measurements_
    rng = np.random.default_rng(12)
    v = rng.standard_normal(meas.group.shape + (2,))
    x = rng.standard_normal(projected(meas, meas.cal, v).shape)
    w = projected_transpose(meas, meas.cal, x)
    assert np.sum(w * v) == pytest.approx(np.sum(x * projected(meas, meas.cal, v)), rel=1e-12)


def test_thermometer_covariance_agrees_with_a_monte_carlo_of_the_thermometers(fitted):
    df, meta, fit, Jz, information = fitted
    model, meas = fit.model_, fit.measurements_
    exact = thermometer_covariance(model, meas, meta, fit.theta_,
                                   reading_response(meas, Jz, information))
    u = thermometer_u_K(meta)
    columns = [f"T_{s}_C" for s in meas.sensors]
    base = model.predict_path(meas, fit.theta_)
    solve = np.linalg.pinv(information) @ Jz.T
    rng = np.random.default_rng(13)
    draws = []
    for _ in range(DRAWS):
        noisy = df.copy()
        noisy[columns] = df[columns].to_numpy() + u * rng.standard_normal((len(df), len(columns)))
        moved = model.predict_path(measurements(noisy, meta, model.params), fit.theta_)
        draws.append(solve @ projected(meas, meas.cal, moved - base))
    _agrees(exact, np.array(draws))


def _wander(rng, t: np.ndarray, std: float, time_s: float) -> np.ndarray:
    """A stationary Ornstein-Uhlenbeck path at the times ``t`` (any order)."""
    order = np.argsort(t, kind="stable")
    out, x = np.empty(t.size), std * rng.standard_normal()
    out[order[0]] = x
    for a, b in zip(order[:-1], order[1:]):
        decay = np.exp(-(t[b] - t[a]) / time_s)
        x = decay * x + std * np.sqrt(1 - decay ** 2) * rng.standard_normal()
        out[b] = x
    return out


def test_air_covariance_agrees_with_a_monte_carlo_of_the_wander(fitted):
    df, meta, fit, Jz, information = fitted
    model, meas = fit.model_, fit.measurements_
    std, time_s = stated_air(meta, df)["pressure_Pa"]
    assert std == 80.0 and time_s == 86400.0          # the papers' laboratory, as simulated
    exact = air_covariance(model, meas, meta, reading_response(meas, Jz, information))
    air = PhysicsModel(model.names + ["air_refraction"], model.params, model.values())
    pts = meas.points
    base = air.predict_path(meas)
    solve = np.linalg.pinv(information) @ Jz.T
    rng = np.random.default_rng(14)
    draws = []
    for _ in range(DRAWS):
        moved = dataclasses.replace(meas, points=dataclasses.replace(
            pts, pressure_Pa=pts.pressure_Pa + _wander(rng, pts.t_s, std, time_s)))
        draws.append(solve @ projected(meas, meas.cal, air.predict_path(moved) - base))
    _agrees(exact, np.array(draws))
    # the levers: 0.27 ppm of the displacement per 100 Pa, the zero's the opposite sign
    row, zero = air_levers(model, meas, "pressure_Pa")
    assert np.nanmax(np.abs(row)) > 0 and np.nanmax(np.abs(zero)) > 0


def test_stated_air_reads_the_specifications_and_refuses_nonsense(fitted):
    df, meta = fitted[0], fitted[1]
    stated = {**meta, "instruments": {**meta["instruments"], "air_pressure_u_Pa": 5.0,
                                      "air_pressure_time_s": 0.0}}
    assert stated_air(stated, df)["pressure_Pa"] == (5.0, 0.0)
    from deltatwin.calibration.errors import FitError
    with pytest.raises(FitError, match="air_pressure_u_Pa"):
        stated_air({"instruments": {"air_pressure_u_Pa": -1.0}}, df)
