"""The physics fit's solver (calibration.physics.fit): Gauss-Newton steps that re-use a
Broyden-updated Jacobian, an exact Jacobian wherever convergence is judged, a trust region where
steps fail, and the fitted model's Jacobian complete."""
import numpy as np
import pytest
import scipy.optimize

from deltatwin.calibration.physics.fit import (
    STEP_SIGMA,
    PhysicsFit,
    _gauss_newton,
    _remaining_step_sigma,
    _ResidualBasis,
    _trust_region_step,
    calibration_cost,
    fitted_again_where_it_ended,
)
from deltatwin.calibration.physics.measurements import measurements
from deltatwin.twin.scenario import Scenario


def _decay_problem(rng):
    """Readings a exp(-b t) + c with noise: nonlinear in b (a curved valley in (a, b))."""
    t = np.linspace(0.0, 4.0, 400)
    y = 2.0 * np.exp(-1.3 * t) + 0.5 + rng.normal(0.0, 0.01, t.size)

    def residual(z):
        a, b, c = z
        return a * np.exp(-b * t) + c - y

    def jacobian(z):
        a, b, _ = z
        e = np.exp(-b * t)
        return np.stack([e, -a * t * e, np.ones_like(t)], axis=1)
    return residual, jacobian, t.size - 3


def test_gauss_newton_converges_where_scipy_does_with_few_exact_jacobians():
    residual, jacobian, dof = _decay_problem(np.random.default_rng(7))
    calls = {"jac": 0, "fun": 0}

    def fun(z):
        calls["fun"] += 1
        return residual(z), None

    def jac(z):
        calls["jac"] += 1
        return jacobian(z), jacobian(z)

    z0 = np.array([0.5, 4.0, 0.0])                   # far: b three times off
    z, J, _, message = _gauss_newton(fun, jac, z0, jacobian(z0), dof, 100,
                                     (residual(z0), None, jacobian(z0)))
    assert message.startswith("converged"), message
    # judged with the exact Jacobian at the returned point
    np.testing.assert_array_equal(J, jacobian(z))
    assert _remaining_step_sigma(jacobian(z), residual(z), dof) <= STEP_SIGMA
    reference = scipy.optimize.least_squares(residual, z0, jac=jacobian, xtol=1e-15,
                                             ftol=1e-15, gtol=1e-15).x
    # the same minimum, to a small part of the parameters' uncertainty
    r = residual(reference)
    cov = np.linalg.inv(jacobian(reference).T @ jacobian(reference)) * (r @ r) / dof
    assert np.all(np.abs(z - reference) < 0.1 * np.sqrt(np.diag(cov))), (z, reference)
    assert calls["jac"] < calls["fun"]          # steps mostly re-use the Jacobian


def test_gauss_newton_stops_at_its_evaluation_limit_with_a_message():
    residual, jacobian, dof = _decay_problem(np.random.default_rng(8))
    z0 = np.array([0.5, 4.0, 0.0])
    z, J, _, message = _gauss_newton(lambda z: (residual(z), None),
                                     lambda z: (jacobian(z), jacobian(z)), z0, jacobian(z0),
                                     dof, 4, (residual(z0), None, jacobian(z0)))
    assert "limit of 4" in message
    np.testing.assert_array_equal(J, jacobian(z))    # still the exact one where it stopped
    assert residual(z) @ residual(z) < residual(z0) @ residual(z0)


def test_trust_region_step_is_gauss_newton_inside_and_the_best_on_the_boundary():
    rng = np.random.default_rng(1)
    J = rng.normal(size=(50, 4)) * np.array([1.0, 10.0, 0.1, 3.0])
    r = rng.normal(size=50)
    gn = np.linalg.lstsq(J, -r, rcond=None)[0]
    np.testing.assert_allclose(_trust_region_step(J, r, 2 * np.linalg.norm(gn)), gn,
                               rtol=1e-10)
    radius = 0.3 * np.linalg.norm(gn)
    step = _trust_region_step(J, r, radius)
    assert abs(np.linalg.norm(step) - radius) < 1e-9 * radius

    def cost(d):
        return np.sum((r + J @ d) ** 2)
    # no other step of that length does better (random directions on the sphere)
    others = rng.normal(size=(2000, 4))
    others *= radius / np.linalg.norm(others, axis=1, keepdims=True)
    assert cost(step) <= min(cost(d) for d in others)


def test_fitted_jacobian_is_complete_where_the_solver_skipped_unseen_columns():
    """A thermal campaign's coils carry no current: their columns are unseen by the fitted
    directions and the solver's Jacobians skip them; the fitted model's Jacobian has them,
    as the model's own full Jacobian at the fitted values."""
    df, meta = Scenario.load("quiet/loop-drift").simulate(0.02)
    effects = ["geometric_errors", "thermal_expansion", "loop_drift", "magnetic_force"]
    known = {"loop_drift": {"frame_arm_m": [-0.6, 0.0]}}
    fit = PhysicsFit(effects, start=known).fit(df, meta)
    unseen = np.sum(fit.identified_directions_ ** 2, axis=1) <= 1e-16
    assert unseen.any() and fit.n_evaluations_ > 0
    meas = measurements(df, meta, fit.model_.params)
    _, J = fit.model_.jacobian(meas, fit.theta_)
    scale = np.nanmax(np.abs(J), axis=(0, 1))
    error = np.nanmax(np.abs(fit.jacobian_ - J), axis=(0, 1))
    assert np.all(error <= 1e-9 * scale + 1e-30), error / np.maximum(scale, 1e-300)


def test_a_fit_converged_in_its_starts_directions_is_fitted_again_in_those_where_it_ended(
        force_data):
    """The coil offsets' columns scale with the coil moment: started at 1/14 of it, the
    directions identified at the start are not those where the fit ends, and in them the fit
    stops "converged" far above the calibration rms the library's start reaches (9.3x, 5.8x
    its validation error); fitted again from where it ended, in the directions identified
    there, it comes close to it (1.36x, 1.14x; measured). A fit whose end's directions leave
    no step is returned as it is."""
    df, meta = force_data
    effects = ["geometric_errors", "magnetic_force"]
    weak = {"magnetic_force": {"coil_moment_per_A": 0.16 / 14}}
    held = PhysicsFit(effects, start=weak, max_evaluations=80).fit(df, meta)
    usual = PhysicsFit(effects, max_evaluations=80).fit(df, meta)
    held_cost, n_held = calibration_cost(held), held.n_evaluations_
    again = fitted_again_where_it_ended(held)
    assert held.converged_ and again is not held and again.converged_ and again.fitted_again_
    assert calibration_cost(held) == held_cost and not held.fitted_again_
    assert calibration_cost(again) < 0.1 * held_cost
    assert calibration_cost(again) < 1.5 ** 2 * calibration_cost(usual)
    assert again.val_["all"]["err_p90"] < 1.25 * usual.val_["all"]["err_p90"]
    assert again.n_evaluations_ > n_held
    # the library's start converges in the directions identified where it ends: kept as it is
    assert fitted_again_where_it_ended(usual) is usual and not usual.fitted_again_


def test_residual_basis_holds_the_jacobian_and_residuals_exactly_as_it_grows_and_is_remade():
    """The solver's algebra on (B, c) equals that on (Jz, r): the coordinates reproduce every
    residual added, a Broyden update made on B is the one made on Jz, and the trust-region
    step and the step left are the same, also after the basis is re-made (it has grown to
    twice the columns of Jz and r)."""
    rng = np.random.default_rng(11)
    n, k = 500, 4
    Jz = rng.normal(size=(n, k)) * np.array([100.0, 10.0, 1.0, 0.02])
    r = rng.normal(size=n)
    basis = _ResidualBasis(Jz, r)
    np.testing.assert_allclose(basis.Q @ basis.B, Jz, atol=1e-12 * np.abs(Jz).max())
    np.testing.assert_allclose(basis.Q @ basis.c, r, atol=1e-12)
    remade = False
    for _ in range(3 * (k + 1)):
        step = rng.normal(size=k)
        r_new = r + Jz @ step + rng.normal(size=n) * 0.1      # off the span: a new column
        columns = basis.Q.shape[1]
        c_new = basis.coordinates(r_new)
        remade |= basis.Q.shape[1] <= columns
        np.testing.assert_allclose(basis.Q @ c_new, r_new, atol=1e-10)
        np.testing.assert_allclose(basis.Q.T @ basis.Q, np.eye(basis.Q.shape[1]), atol=1e-12)
        # Broyden's update in both forms
        Jz = Jz + np.outer((r_new - r) - Jz @ step, step / (step @ step))
        basis.B += np.outer((c_new - basis.c) - basis.B @ step, step / (step @ step))
        basis.c, r = c_new, r_new
        np.testing.assert_allclose(basis.Q @ basis.B, Jz, atol=1e-10 * np.abs(Jz).max())
        np.testing.assert_allclose(basis.Q @ basis.c, r, atol=1e-10)
        for radius in (0.01, 1e3):
            np.testing.assert_allclose(_trust_region_step(basis.B, basis.c, radius),
                                       _trust_region_step(Jz, r, radius), rtol=1e-8, atol=1e-12)
        assert abs(_remaining_step_sigma(basis.B, basis.c, n - k)
                   - _remaining_step_sigma(Jz, r, n - k)) < 1e-9
    assert remade


def _solver_calls(seed: int, trials: list) -> list:
    """What ``_gauss_newton`` asks for, in order ("fun": an evaluation, "jac": a Jacobian), on
    a two-parameter problem whose Jacobian is the identity on its first two readings (plus 48
    readings of seeded noise, 1 % of the residual), starting exactly at a residual of (1, 1):
    its evaluations return ``trials``' first two readings in turn, then (0.1, 0.1)."""
    noise = np.random.default_rng(seed).normal(0.0, 0.01, 48)
    r0 = np.concatenate([[1.0, 1.0], noise])
    J0 = np.zeros((50, 2))
    J0[0, 0] = J0[1, 1] = 1.0
    calls = []
    readings = iter([np.concatenate([t, noise]) for t in trials] + [
        np.concatenate([[0.1, 0.1], noise])] * 4)

    def fun(z):
        calls.append("fun")
        return next(readings), None

    def jac(z):
        calls.append("jac")
        return J0, J0
    _gauss_newton(fun, jac, np.zeros(2), J0, 48, 4, (r0, None, J0))
    return calls


def test_a_failed_step_as_long_as_the_last_accepted_one_recomputes_the_jacobian(monkeypatch):
    """Two trust-region steps on one radius have lengths equal to round-off (the damping's
    bisection): a failed re-used-Jacobian step that long is "no longer than one that
    succeeded", so the updated Jacobian is blamed and recomputed, whatever the sign of the
    round-off (it was a coin flip: a force case's floor fit went 57.4 or 37.1 nm by it)."""
    from deltatwin.calibration.physics import fit as fit_module
    lengths = iter(0.5 * (1.0 + np.array([0.0, 3e-16, 6e-16, 9e-16])))
    monkeypatch.setattr(fit_module, "_trust_region_step",
                        lambda Jz, r, radius: -np.ones(2) / np.sqrt(2.0) * next(lengths))
    # the first step falls half as far as predicted (accepted, the radius kept), the second
    # fails
    calls = _solver_calls(5, [[0.85, 0.85], [9.0, 9.0], [0.7, 0.7]])
    assert calls[:3] == ["fun", "fun", "jac"], calls


def test_an_accepted_step_the_updated_jacobian_predicted_poorly_recomputes_it():
    """A step taken with a Broyden-updated Jacobian that lowers the cost by less than a quarter
    of its prediction is accepted, and the Jacobian recomputed before the next step: the
    updated one is wrong in the directions the step went (a force case's fit crawled along
    them by steps of gain 0.03-0.4 until its 20 evaluations ran out, seed 99 g01: 42.8 nm
    against 37.4 from exact Jacobians). A step the exact Jacobian predicted poorly only shrinks
    the trust region."""
    # the exact Jacobian's step falls half as far as predicted; the updated one's, 1 % as far
    assert _solver_calls(6, [[0.5, 0.5], [0.497, 0.497]])[:3] == ["fun", "fun", "jac"]
    # the exact Jacobian's step predicted poorly (3 % of its fall): no Jacobian before the next
    assert _solver_calls(6, [[0.985, 0.985], [0.5, 0.5]])[:3] == ["fun", "fun", "fun"]


def _frame_column_beyond_the_others(df, meta) -> float:
    """The frame's expansion column of the complete model's calibration Jacobian (scaled,
    session zeros out) beyond the span of every other column, m."""
    from deltatwin.calibration.diagnosis.floor import true_model
    from deltatwin.calibration.physics.model import PhysicsModel, projected

    effects, values = true_model(meta)
    model = PhysicsModel(effects, None, {"loop_drift": {"frame_arm_m": [-0.6, 0.0]}})
    meas = measurements(df, meta, model.params)
    Js = projected(meas, meas.cal, model.jacobian(meas, model.theta())[1], scale=model.scales)
    j = model.labels.index("loop_drift.frame_cte_per_K")
    Q = np.linalg.qr(np.delete(Js, j, axis=1))[0]
    return float(np.linalg.norm(Js[:, j] - Q @ (Q.T @ Js[:, j])))


@pytest.mark.slow
def test_a_direction_the_thermometers_noise_alone_determines_is_not_fitted():
    """The force campaign in the papers' conditions (hidden/magnetic-force, 30 %): with
    perfect thermometers (the twin's same timeline and draws) the frame's expansion column
    lies within the other columns' span to below the fit's threshold (noise / identifiable
    ratio); with the papers' 3 mK thermometers it reaches far above it, all of it noise. A
    fit that counted it regressed on the noise; the fit counts information beyond the
    thermometers' own, and holds the frame's coefficient as the perfect-thermometer fit does."""
    from deltatwin.calibration.diagnosis.floor import true_fit

    sc = Scenario.load("hidden/magnetic-force")
    noisy, perfect = sc, sc.with_perfect(["thermometers"])
    (df, meta), (df_p, meta_p) = (s.simulate(sc.reduced_scale) for s in (noisy, perfect))
    threshold = 5e-9 / 0.3
    perfect_beyond = _frame_column_beyond_the_others(df_p, meta_p)
    noisy_beyond = _frame_column_beyond_the_others(df, meta)
    # measured: 1.98x the threshold with 3 mK thermometers, 121x what perfect ones leave
    assert perfect_beyond < 0.5 * threshold
    assert noisy_beyond > 1.5 * threshold and noisy_beyond > 20 * perfect_beyond
    fraction = {}
    for name, (d, m) in {"noisy": (df, meta), "perfect": (df_p, meta_p)}.items():
        table = true_fit(d, m).parameter_table()
        fraction[name] = table.loc["loop_drift.frame_cte_per_K", "identified_fraction"]
    assert fraction["perfect"] < 0.5 and fraction["noisy"] < 0.5, fraction
    assert meta_p["instruments"]["T_noise_C"] == 0.0 and meta["instruments"]["T_noise_C"] > 0


def test_the_band_draws_from_a_covariance_that_round_off_left_indefinite():
    """The sandwich covariance is positive semi-definite only to round-off: its square root
    for the band's draws takes a slightly negative eigenvalue as zero (a Cholesky
    factorisation refused one on a generated force case)."""
    from deltatwin.calibration.physics.band import square_root

    rng = np.random.default_rng(3)
    A = rng.standard_normal((6, 3))
    cov = A @ A.T                                    # rank 3: three zero eigenvalues
    cov[0, 0] -= 1e-12                               # one of them slightly negative
    assert np.linalg.eigvalsh(cov).min() < 0
    L = square_root(cov)
    assert np.allclose(L @ L.T, cov, atol=1e-10)


def test_the_band_s_square_root_keeps_parameters_of_every_unit():
    """Parameters in SI differ in variance by twenty orders of magnitude (an expansion
    coefficient's 1e-12 /K^2 beside a coil moment's 1): the square root is taken on the
    correlation matrix, so L L^T gives back every variance and correlation; on the covariance
    itself the small ones are round-off of the large."""
    from deltatwin.calibration.physics.band import square_root

    rng = np.random.default_rng(1)
    A = rng.standard_normal((12, 8))                  # rank 8: held directions, as a fit's
    corr = A @ A.T / np.outer(np.linalg.norm(A, axis=1), np.linalg.norm(A, axis=1))
    sigma = 10.0 ** rng.uniform(-20, 0, 12)
    cov = corr * np.outer(sigma, sigma)
    L = square_root(cov)
    np.testing.assert_allclose((L @ L.T) / np.outer(sigma, sigma), corr, atol=1e-12)
    w, U = np.linalg.eigh(cov)                        # what the unscaled root would keep
    unscaled = U * np.sqrt(np.clip(w, 0.0, None))
    assert np.max(np.abs(np.diag(unscaled @ unscaled.T) / np.diag(cov) - 1)) > 1e-3


def test_the_fits_new_inputs_are_refused_in_one_line(tmp_path, capsys):
    """``deltatwin fit --max-evaluations 0`` and a dataset whose thermometer specification is
    not a temperature: one line naming it, exit 2, no model written."""
    from deltatwin.cli import main
    from deltatwin.twin.dataset import write_dataset

    sc = Scenario.load("hidden/loop-drift")
    df, meta = sc.simulate(0.01)
    data, bad = tmp_path / "data.parquet", tmp_path / "bad.parquet"
    write_dataset(df, meta, data)
    write_dataset(df, {**meta, "instruments": {"T_noise_C": "three"}}, bad)
    out = tmp_path / "model.toml"
    for args, words in (([str(data), "--max-evaluations", "0"], "max_evaluations = 0"),
                        ([str(bad)], "'T_noise_C' = 'three'")):
        capsys.readouterr()
        assert main(["fit", *args, "--effects", "geometric_errors,thermal_expansion",
                     "-o", str(out)]) == 2
        err = capsys.readouterr().err.strip()
        assert words in err and len(err.splitlines()) == 1, err
        assert not out.exists()
