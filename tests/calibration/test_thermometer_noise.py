"""The correction for the thermometers' noise in the variables (calibration/physics/fit.py
``_corrected_for_thermometers``, calibration/physics/thermometers.py), checked against the
textbook case it generalises: a straight line through the origin whose regressor is read with
noise, where least squares is attenuated by the reliability ratio var(x) / (var(x) + u^2) and
the method-of-moments estimator x^T y / (x^T x - n u^2) is not (Fuller 1987, section 1.1)."""
import numpy as np
import pytest

from deltatwin.calibration.diagnosis.floor import true_fit, true_model
from deltatwin.calibration.physics.fit import _corrected_for_thermometers
from deltatwin.calibration.physics.thermometers import ThermometerNoise
from deltatwin.twin.scenario import Scenario

SLOPE, N, SPREAD, U, E = 2.0, 400, 1.0, 0.7, 0.05


def _line(rng):
    """(fun, jac, z, A, J, terms_at, y, dof) of one draw: readings y = SLOPE x + e, the model
    z * x_read with x read with noise U (reliability 1 / (1 + 0.49) = 0.67); z at least
    squares."""
    x = rng.normal(0.0, SPREAD, N)
    x_read = x + rng.normal(0.0, U, N)
    y = SLOPE * x + rng.normal(0.0, E, N)

    def fun(z):
        return y - z[0] * x_read, z[0] * x_read

    def jac(z):
        return -x_read[:, None], x_read[:, None]
    z_ls = np.array([x_read @ y / (x_read @ x_read)])
    noise = ThermometerNoise(np.array([[N * U * U]]), np.zeros(1), np.zeros(1),
                             np.ones(1, bool))
    return (fun, jac, z_ls, z_ls[0] * x_read, x_read[:, None],
            lambda z: noise.terms(np.eye(1), z), y, N - 1)


def test_the_corrected_slope_is_unbiased_where_least_squares_is_attenuated():
    rng = np.random.default_rng(20261128)
    ls, corrected = [], []
    for _ in range(300):
        fun, jac, z, A, J, terms_at, y, dof = _line(rng)
        z_c, _, _, done = _corrected_for_thermometers(
            fun, jac, z, A, J, lambda J: -J, terms_at, y, lambda a: a, 0.0, dof)
        assert done
        ls.append(z[0])
        corrected.append(z_c[0])
    reliability = SPREAD ** 2 / (SPREAD ** 2 + U ** 2)
    se = np.std(corrected) / np.sqrt(len(corrected))
    assert abs(np.mean(ls) - SLOPE * reliability) < 0.02          # attenuated, as theory says
    assert abs(np.mean(corrected) - SLOPE) < 4 * se                # the truth, within 4 s.e.
    # the closed form: x^T y / (x^T x - n u^2), the root of the corrected score
    fun, jac, z, A, J, terms_at, y, dof = _line(np.random.default_rng(5))
    z_c = _corrected_for_thermometers(fun, jac, z, A, J, lambda J: -J, terms_at, y,
                                      lambda a: a, 0.0, dof)[0]
    x_read = J[:, 0]
    np.testing.assert_allclose(z_c[0], x_read @ y / (x_read @ x_read - N * U * U), rtol=1e-12)


def test_no_correction_where_the_noise_leaves_too_little_information():
    """Where J^T J - C is below the fit's threshold the corrected estimate is not defined: the
    least-squares one is returned, marked not corrected."""
    fun, jac, z, A, J, terms_at, y, dof = _line(np.random.default_rng(6))
    least = float(J[:, 0] @ J[:, 0]) - N * U * U + 1.0
    z_c, A_c, _, done = _corrected_for_thermometers(fun, jac, z, A, J, lambda J: -J, terms_at,
                                                    y, lambda a: a, least, dof)
    assert not done and z_c is z and A_c is A


def test_restricted_keeps_only_the_coefficients_of_temperatures_and_reliable_directions():
    """ThermometerNoise.restricted: a parameter that is not a coefficient of a temperature (a
    sensor's contact) gets no correction; a direction where the noise gives more than
    MAX_NOISE_SHARE of the information gets none either."""
    info = np.array([[4.0, 1.0], [1.0, 9.0]])
    noise = ThermometerNoise(info, np.array([1.0, 2.0]), np.zeros(2), np.array([True, False]))
    Jz = np.diag([10.0, 10.0])                           # information 100 in each direction
    kept = noise.restricted(np.eye(2), Jz)
    np.testing.assert_allclose(kept.information, [[4.0, 0.0], [0.0, 0.0]])
    np.testing.assert_allclose(kept.score, [1.0, 0.0])
    weak = noise.restricted(np.eye(2), np.diag([2.5, 10.0]))      # share 4 / 6.25 > 0.5
    assert not np.any(weak.information) and not np.any(weak.score)


def test_no_correction_where_the_corrected_score_has_no_root():
    """A saturating model, readings y = tanh(z) + e: the corrected score n sech^2(z) (mean(y) -
    tanh z) + g has no root when the noise's share g exceeds what the model can take up
    (n sech^2 tanh <= 0.385 n); Newton's steps then grow, and the least-squares solution is
    returned, marked not corrected (not the point where the steps were stopped)."""
    rng = np.random.default_rng(11)
    n = 10
    y = rng.normal(0.0, 0.1, n)
    z = np.array([np.arctanh(y.mean())])                       # least squares

    def fun(z):
        return y - np.tanh(z[0]) * np.ones(n), np.tanh(z[0]) * np.ones(n)

    def jac(z):
        return -np.ones((n, 1)) / np.cosh(z[0]) ** 2, np.ones((n, 1)) / np.cosh(z[0]) ** 2

    r, A = fun(z)
    Jz, J = jac(z)
    terms = (np.array([[0.1]]), np.array([1.0 * n]))            # g = n > 0.385 n: no root
    z_c, A_c, _, done = _corrected_for_thermometers(
        fun, jac, z, A, J, lambda J: -J, lambda z: terms, y, lambda a: a, 0.0, n - 1)
    assert not done and z_c is z and A_c is A
    # where the share is small enough a root exists and is found
    small = (np.array([[0.1]]), np.array([0.1 * n]))
    z_c, A_c, _, done = _corrected_for_thermometers(
        fun, jac, z, A, J, lambda J: -J, lambda z: small, y, lambda a: a, 0.0, n - 1)
    score = n / np.cosh(z_c[0]) ** 2 * (y.mean() - np.tanh(z_c[0])) + 0.1 * n
    assert done and abs(score) < 1e-3 * n


@pytest.mark.slow
def test_the_correction_descends_where_full_newton_steps_oscillate():
    """Reduced paper-thermal with seed 1: full Newton steps of the corrected score overshoot
    along a direction where the corrected objective is flat (steps of 4.9, 3.9, 3.0, 2.6,
    2.9 uncertainties, each nearly opposite the last) and the fit gave up, left with the
    loop's expansion coefficients 5.4 (Mahalanobis, three of them) from the twin's. Halving
    each step until the objective falls finds the root: corrected, and within the 99 % region
    (chi-square, 3 degrees of freedom: 3.37) of the twin's values."""
    sc = Scenario.load("paper-thermal", seed=1)
    df, meta = sc.simulate(sc.reduced_scale)
    fit = true_fit(df, meta)
    values = true_model(meta)[1]["loop_drift"]
    names = ("table_cte_per_K", "frame_cte_per_K", "support_cte_per_K")
    labels = list(fit.model_.labels)
    at = [labels.index(f"loop_drift.{n}") for n in names]
    error = fit.theta_[at] - np.array([values[n] for n in names])
    distance = np.sqrt(error @ np.linalg.solve(fit.covariance_[np.ix_(at, at)], error))
    assert fit.thermometer_corrected_ and fit.converged_, fit.status_
    assert distance < 3.37, distance
