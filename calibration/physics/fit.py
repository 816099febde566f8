"""Fitting a physics model to measurements (scikit-learn style: ``fit``, attributes ending in ``_``):
a trust-region least-squares fit on the identified directions, with the identifiability report."""
from __future__ import annotations

import copy
import logging
import math

import numpy as np
import pandas as pd
from scipy import linalg, special

from deltatwin.calibration.errors import FitError, TooFewPointsError
from deltatwin.calibration.physics.air import air_covariance
from deltatwin.calibration.physics.measurements import (
    Measurements,
    check_sensors,
    data_sha256,
    measurements,
)
from deltatwin.calibration.physics.model import (
    PhysicsModel,
    figures_nm,
    group_offsets,
    projected,
    projected_rows,
    reading_response,
    residuals,
)
from deltatwin.calibration.physics.thermometers import (
    MAX_NOISE_SHARE,
    ThermometerNoise,
    thermometer_covariance,
    thermometer_noise,
)
from deltatwin.calibration.stats import sandwich_covariance
from deltatwin.models.kinematics import KinematicsError
from deltatwin.models.params import ParameterError, RobotParams
from deltatwin.twin.effects import EffectError, effect_class
from deltatwin.twin.instruments.optics import AXES
from deltatwin.twin.lab_setup import SetupError, check_known, known_constants, merged, with_known

NM = 1e9   # the solver works on residuals in nm
RADIUS_MIN = 1e-9   # fit scales: a trust region this small has only round-off left
# two trust-region steps on one radius have lengths equal to this relative round-off (the
# damping's bisection): "longer" is judged beyond it, not by round-off's sign
LENGTH_ROUND_OFF = 1e-9
# a parameter whose identified directions' weights are below this (squared, summed) is unseen by
# the fit: its column changes the fitted directions' Jacobian by < 1e-8 of a fitted column
UNSEEN_FRACTION = 1e-16
STEP_SIGMA = 0.1   # converged: a further step moves the parameters by < 0.1 of their uncertainty
# at most this many Newton steps (and Jacobians) of the score corrected for the thermometers'
# noise: a bound, not a tuning (most corrections take two; along a direction where the
# corrected objective is flat the descent creeps, a few tenths of an uncertainty a step)
CORRECTION_STEPS = 16
LINE_SEARCH_HALVINGS = 5   # a correction step is halved at most this many times
log = logging.getLogger(__name__)


class _FromCovariance:
    """A fitted attribute of the parameters' uncertainty, computed with the others on first
    read (PhysicsFit ``_uncertainty``); an assigned value (a model file's) stands."""
    NAMES = ("covariance_z_", "consider_", "covariance_", "parameters_")

    def __set_name__(self, owner, name):
        self.name = name

    def __get__(self, fit, owner=None):
        if fit is None:
            return self
        if "_uncertainty_inputs" not in fit.__dict__:
            raise AttributeError(f"{self.name}: the model is not fitted")
        fit._uncertainty()
        return fit.__dict__[self.name]


class PhysicsFit:
    """Fit a physics model's free parameters to a dataset's calibration rows.

    Parameters: ``effects`` (library names), ``params`` (the robot file; default nominal),
    ``start`` ({effect: {parameter: value}}: starting values, e.g. a previous fit, or known
    constants; those of effects outside the model are kept in ``known_`` for the candidates a
    diagnosis adds; ``fit`` puts them over the known constants of the data's setup,
    twin/lab_setup.py, parameter by parameter),
    ``noise_nm`` (the readings' noise, nm: sets which directions are identifiable),
    ``identifiable_ratio`` (a direction is fitted if the data determine it to better than this
    fraction of its parameters' typical size), ``max_evaluations`` (the points the solver
    evaluates, the start included; a Jacobian, many evaluations' work, is not one),
    ``progress`` (a callable given a message after each evaluation, or None), ``seed`` (of the
    draws of the thermometers' noise that tell which directions the data determine and
    correct the estimate for that noise: calibration/physics/thermometers.py).

    Attributes after ``fit``: ``model_`` (PhysicsModel at the fitted values), ``offsets_`` (m per
    (session, axis)), ``residual_`` ((N,3) m), ``cal_``/``val_`` (error figures, nm),
    ``identifiability_`` (dict), ``converged_`` and ``status_`` (a misspecified model that
    stops short returns its best fit with ``converged_`` False, the reason in ``status_``, and a
    logged warning), ``n_evaluations_`` (model evaluations, a Jacobian counting one per column
    it computes and one), ``n_jacobians_`` (exact Jacobians computed, the start's included),
    ``parameters_`` (list of {label, value, start, unit, uncertainty, identified_fraction}),
    ``covariance_z_`` ((k, k): the covariance of the fit along its ``identified_directions_``,
    in fit scales: the sandwich of calibration/stats.py, its bread the information beyond the
    thermometers' when corrected), ``thermometer_noise_`` (ThermometerNoise: what the
    thermometers' noise alone puts into the calibration Jacobian's information and score;
    ``thermometer_information_`` its information), ``thermometer_corrected_`` (whether the
    estimate is corrected for that noise in the variables: ``_corrected_for_thermometers``)
    and ``thermometer_correction_`` (the share of ``thermometer_noise_`` it corrected for),
    ``least_squares_residual_`` ((N,3) m: the residual where least squares ended, before that
    correction: what tests of nested models compare), ``fitted_again_`` (whether
    ``fitted_again_where_it_ended`` replaced it by its refit), ``consider_`` ((p, p - k), fit
    scales: how the parameters' error depends on the held directions' deviation from the
    prior, the prior's width each: ``_considered``), ``covariance_`` ((p, p), SI: the
    parameters' covariance, the identified directions' and the held ones' through
    ``consider_``, whose diagonal gives ``parameters_``' uncertainties).

    Use: ``summary()`` (a table object: text, HTML, ``as_dict``), ``predict(df)`` (the model's
    readings, m), ``score(df)`` (minus the validation error 90 %, m: higher is better),
    ``save(path)`` and ``PhysicsFit.load(path)`` (the file ``deltatwin fit -o`` writes).
    """

    # the parameters' uncertainty, computed on first use (``_uncertainty``)
    covariance_z_ = _FromCovariance()
    consider_ = _FromCovariance()
    covariance_ = _FromCovariance()
    parameters_ = _FromCovariance()

    def __init__(self, effects, params: RobotParams | None = None, start: dict | None = None,
                 noise_nm: float = 5.0, identifiable_ratio: float = 0.3,
                 max_evaluations: int = 20, progress: bool = False, prior: dict | None = None,
                 seed: int = 0):
        if noise_nm <= 0 or not math.isfinite(noise_nm):
            raise FitError(f"noise_nm = {noise_nm}: must be a positive number of nanometres")
        if not 0 < identifiable_ratio:
            raise FitError(f"identifiable_ratio = {identifiable_ratio}: must be positive")
        # the model's effects by name (a user effect, file.py:Class, is known by its name after)
        self.effects = PhysicsModel(effects, params).names
        self.params = params
        # values for effects outside the model are the laboratory's known constants (e.g. a
        # frame arm): kept for the candidates a diagnosis adds, checked against the library
        start = dict(start or {})
        self.known = {e: v for e, v in start.items() if e not in self.effects}
        for name, values in self.known.items():
            _check_known_constant(name, values, params)
        self.known_ = self.known        # with the data's setup once fitted
        self.start = {e: v for e, v in start.items() if e in self.effects} or None
        self.prior = prior
        self.noise_nm = noise_nm
        self.identifiable_ratio = identifiable_ratio
        if max_evaluations < 1:
            raise FitError(f"max_evaluations = {max_evaluations}: must be at least 1")
        self.max_evaluations = int(max_evaluations)
        self.progress = progress
        self.seed = int(seed)
        PhysicsModel(self.effects, params, self.start)   # validate names and values once

    def fit(self, df: pd.DataFrame, meta: dict | None = None, meas: Measurements | None = None,
            where: str = "data", keep_converged_start: bool = False,
            start_directions: np.ndarray | None = None, fitted_on: str | None = None,
            start_corrected: bool = True):
        """Fit to the calibration rows of ``df`` (``where`` names the data in errors).
        ``keep_converged_start``: a start that is already converged on these data (a fitted
        model diagnosed on its own data: the Gauss-Newton step left from it moves the
        parameters by less than STEP_SIGMA of their uncertainty) is kept as it is, with its
        Jacobian, instead of being refined by the solver (which would only confirm it, at a
        few Jacobians' cost). ``start_directions`` ((p, k), a fitted model's
        ``identified_directions_``, saved in its file): the directions the start was fitted
        in. Convergence is judged in them, as the fit that made the start judged it: the
        directions identified at the fitted values differ from those identified at the fit's
        own start (the same threshold, other singular vectors), and in them a converged fit
        can have a step of a few tenths of an uncertainty left along directions it held. A
        kept start keeps these directions; one that is not converged is refined in the
        directions identified here (a start fitted to other data is not converged on these:
        their noise alone moves the optimum by ~sqrt(k) uncertainties). ``fitted_on``: the
        fingerprint (``data_sha256``) of the data the start was fitted on, saved in its file:
        on those very data the start is kept as it is, converged or not (with
        ``start_directions``): refining it would diagnose another model than the file's, and
        the diagnosis takes the model's own remaining linear step as its reference anyway;
        its status says how far from converged it is; ``start_corrected``: whether that start
        was corrected for the thermometers' noise (its file's ``thermometer_corrected``): kept,
        it is judged as it was fitted."""
        # the laboratory's constants the data's setup gives, where the start does not
        setup = known_constants(meta, where)
        self.known_ = merged({e: v for e, v in setup.items() if e not in self.effects},
                             self.known)
        stated = {e: v for e, v in setup.items() if e in self.effects}
        model = PhysicsModel(self.effects, self.params, merged(stated, self.start) or None)
        # the laboratory's constants the fit was given reach the conditions too (the set point
        # of held supports)
        meas = meas or measurements(df, with_known(meta, self.known_), model.params, where)
        check_sensors(model.names, meas, where)
        self.data_sha256_ = data_sha256(meas)
        cal = meas.cal
        n_cal = int(np.sum((meas.group >= 0) & cal[:, None]))
        p = model.n_free
        if n_cal == 0:
            raise TooFewPointsError("no calibration reading (split == 'cal') in the data")
        if n_cal <= p + len(meas.groups):
            raise TooFewPointsError(f"{n_cal} calibration readings cannot identify {p} "
                                    f"parameters and {len(meas.groups)} zero offsets: take "
                                    "more points or fit fewer effects")
        theta0 = model.theta()
        # directions the data cannot determine are held at the prior: the values the
        # laboratory's setup states (an aluminium frame's expansion coefficient), else the
        # effects' starting values; never at a warm start's values: a previous fit may have
        # pushed them anywhere while standing in for an effect it lacked
        prior_theta = PhysicsModel(self.effects, self.params,
                                   merged(stated, self.prior) or None).theta()
        S = model.scales
        A0, J0 = model.jacobian(meas, theta0)
        Js = projected(meas, cal, J0, scale=S)
        # on the data it was fitted on, the start is kept in the directions it was fitted in
        # (below): no SVD chooses directions here, V's report is made from Js alone
        same_data = (fitted_on is not None and fitted_on == self.data_sha256_
                     and start_directions is not None)
        # estimated at the prior: the same for every start of these effects on these data,
        # and for the fit that made a kept start
        noise = thermometer_noise(model, meas, meta, prior_theta, self.seed,
                                  (A0, J0) if np.array_equal(prior_theta, theta0) else None)
        if same_data:
            V = checked_directions(start_directions, p)
            s, Vt, keep = _directions_report(Js, V)
        else:
            s, Vt, keep, V = _determined_directions(Js, noise.information, self.noise_nm,
                                                    self.identifiable_ratio)
        self.n_evaluations_, self.n_jacobians_ = p + 1, 1
        self.fitted_again_ = False
        prior = prior_theta
        z_start = V.T @ ((theta0 - prior) / S) if p else np.zeros(0)

        def theta_of(z):
            return prior + S * (V @ z)

        def fun(z):
            """The projected calibration residual (nm) at z and the prediction (N,3) there."""
            A = model.predict_path(meas, theta_of(z))
            self.n_evaluations_ += 1
            return projected(meas, cal, meas.y - A) * NM, A

        # the parameters the identified directions hold (the others' columns, e.g. a coil's
        # in a campaign without current, are orthogonal to them: weights < 1e-8): the solver's
        # Jacobians need only these; the fitted model's is completed at the end
        seen = np.sum(V ** 2, axis=1) > UNSEEN_FRACTION

        def jac(z):
            """The residual's exact Jacobian in z (nm per fit scale) and the model's (N,3,p),
            its columns outside ``seen`` left zero."""
            J = model.jacobian(meas, theta_of(z), seen)[1]
            self.n_evaluations_ += int(seen.sum()) + 1
            self.n_jacobians_ += 1
            return -projected(meas, cal, J, scale=S) @ V * NM, J

        k = V.shape[1]
        n_res = int(np.sum((meas.group >= 0) & cal[:, None]))
        dof = meas.residual_dof(n_res, k)
        self.solver_message_ = "nothing to fit: no identified direction"
        Jz0 = -Js @ V * NM
        r0 = projected(meas, cal, meas.y - A0) * NM
        # convergence of the start is judged in the directions it was fitted in, when given
        V_test = (V if start_directions is None or same_data
                  else checked_directions(start_directions, p))
        keep_start = same_data or (
            keep_converged_start and V_test.shape[1] > 0
            and _remaining_step_sigma(-Js @ V_test * NM, r0,
                                      meas.residual_dof(n_res, V_test.shape[1]),
                                      noise.restricted(V_test, Js @ V_test).terms(
                                          V_test, theta0 / S, NM))
            <= STEP_SIGMA)
        if keep_start and V_test is not V:
            V = V_test
            s, Vt, keep = _directions_report(Js, V)
        theta, J, A = theta0, J0, A0
        A_least_squares = None
        # a kept start was fitted with it (or is judged so)
        used = (noise.restricted(V, Js @ V) if start_corrected or not same_data
                else ThermometerNoise.none(p))
        if keep_start:
            self.solver_message_ = ("the start was fitted on these data: kept as fitted"
                                    if same_data else
                                    "the start is converged on these data: kept")
        elif k:
            z, J, A, self.solver_message_ = _gauss_newton(
                fun, jac, z_start, Jz0, dof, self.max_evaluations,
                # the start's prediction and exact Jacobian when z_start is the start itself
                (r0, A0, J0) if np.array_equal(theta_of(z_start), theta0) else None,
                progress=(lambda r: log.info(
                    "fit %s: calibration rms %.3f nm", "+".join(self.effects),
                    np.sqrt(np.mean(r ** 2)), extra={"progress": "fit"}))
                if self.progress else None)
            # the correction's share of the noise (none if it is not made)
            A_least_squares = A
            used = noise.restricted(V, projected(meas, cal, J, scale=S) @ V)
            if not self.solver_message_.startswith("converged"):
                # corrected from the least-squares solution only: a fit stopped short (its
                # evaluations spent) returns its best least-squares point, as it says
                used = ThermometerNoise.none(p)
            elif used.terms(V, prior / S) is not None:
                z, A, J, corrected = _corrected_for_thermometers(
                    fun, jac, z, A, J, lambda J: -projected(meas, cal, J, scale=S) @ V * NM,
                    lambda z: used.terms(V, prior / S + V @ z, NM),
                    meas.y, lambda a: projected(meas, cal, a) * NM,
                    (self.noise_nm / self.identifiable_ratio) ** 2, dof)
                self.solver_message_ += (
                    "; corrected for the thermometers' noise in the variables" if corrected
                    else "; not corrected for the thermometers' noise: the corrected "
                         "estimating equation is not defined, or has no root, near where "
                         "least squares ended")
                if not corrected:
                    used = ThermometerNoise.none(p)
            theta = theta_of(z)
            if J is not J0 and not seen.all():
                J[:, :, ~seen] = model.jacobian(meas, theta, ~seen)[1][:, :, ~seen]
                self.n_evaluations_ += int((~seen).sum()) + 1
        # a kept start was fitted so (on these data, or judged converged with the correction)
        self.thermometer_noise_ = noise
        self.thermometer_information_ = noise.information
        self.thermometer_corrected_ = bool(used)
        self.thermometer_correction_ = used
        model.set_theta(theta)          # the solver's last evaluation may have been a trial
        r = projected(meas, cal, meas.y - A)
        Js_end = Js if J is J0 else projected(meas, cal, J, scale=S)
        Jz = -Js_end @ V
        dof = meas.residual_dof(n_res, V.shape[1])
        self.remaining_step_sigma_ = _remaining_step_sigma(
            Jz, r, dof, used.terms(V, theta / S))
        change = self.remaining_step_sigma_ * float(np.linalg.norm(r)) / np.sqrt(dof)
        self.converged_ = bool(self.remaining_step_sigma_ <= STEP_SIGMA)
        self.last_step_nm_ = change / np.sqrt(max(r.size, 1)) * 1e9
        self.status_ = "converged" if self.converged_ else (
            f"not converged: a further step would still move the parameters by "
            f"{self.remaining_step_sigma_:.2g} of their uncertainty (limit {STEP_SIGMA}); "
            f"solver: {self.solver_message_}")
        if not self.converged_ and keep_start:
            # nothing was iterated: the saved model is not converged, as when it was fitted
            log.warning("the model of %s, kept as fitted on these data, is %s (calibration rms "
                        "%.3g nm)", self.effects, self.status_,
                        float(np.sqrt(np.mean(r ** 2))) * 1e9 if r.size else 0.0)
        elif not self.converged_:
            log.warning("the fit of %s did not converge: %s; the best fit found is returned "
                        "(calibration rms %.3g nm)", self.effects, self.status_,
                        float(np.sqrt(np.mean(r ** 2))) * 1e9 if r.size else 0.0)
        self.model_ = model
        self.meta_ = meta or {}
        self.theta_ = theta
        self.measurements_ = meas
        self.offsets_ = group_offsets(meas, A, cal)
        self.residual_ = residuals(meas, A, self.offsets_)
        # what the tests of nested models compare (the F test's theory is least squares'):
        # the residual where least squares ended, before the correction for the thermometers
        self.least_squares_residual_ = (
            residuals(meas, A_least_squares, group_offsets(meas, A_least_squares, cal))
            if self.thermometer_corrected_ and A_least_squares is not None
            else self.residual_)
        self.prediction_ = A
        self.reading_m_ = meas.y - self.residual_      # the model's reading per row (m)
        self.cal_ = figures_nm(self.residual_, meas.cal)
        self.val_ = figures_nm(self.residual_, meas.val)
        self.jacobian_ = J
        self.identified_directions_ = V
        self._identifiability(model, s, Vt, keep, Js_end, meas, r, V, theta, prior,
                              V.T @ used.information @ V)
        return self

    def _identifiability(self, model, s, Vt, keep, Js, meas, r, V, theta, theta0, noise_z):
        """The identifiability report (``identifiability_``) now, and the parameters'
        uncertainty (``covariance_z_``, ``consider_``, ``covariance_``, ``parameters_``) on
        first use (``_uncertainty``: most of the fits a diagnosis makes never read it, and
        its slow sources cost a few predictions per sensor). ``Js``: the projected
        calibration Jacobian in fit scales (n, p) where the fit ended; ``noise_z`` (k, k):
        the thermometers' share of its information in the directions ``V``
        (ThermometerNoise ``information``)."""
        p, k = model.n_free, int(keep.sum())
        labels = model.labels
        dof = meas.residual_dof(r.size, k)
        sigma_r = float(np.sqrt(np.sum(r ** 2) / dof))
        frac = np.sum(V ** 2, axis=1) if k else np.zeros(p)
        self._uncertainty_inputs = (model, Js, meas, r, V, theta, theta0, noise_z, frac)
        for name in _FromCovariance.NAMES:
            self.__dict__.pop(name, None)
        groups = []
        for i in np.flatnonzero(~keep):
            v = Vt[i]
            members = np.flatnonzero(v ** 2 > 0.05)
            members = members[np.argsort(-v[members] ** 2)]
            groups.append({"singular_value_nm": float(s[i] * 1e9),
                           "parameters": [labels[j] for j in members],
                           "weights": [round(float(v[j]), 3) for j in members]})
        self.identifiability_ = {
            "n_parameters": p, "n_identified_directions": k,
            "singular_values_nm": [float(x * 1e9) for x in s],
            "condition_number": float(s.max() / s.min()) if p and s.min() > 0 else math.inf,
            "condition_number_identified": float(s[keep].max() / s[keep].min()) if k else None,
            "threshold_nm": float(self.noise_nm / self.identifiable_ratio),
            "not_identifiable": [labels[j] for j in range(p) if frac[j] < 0.5],
            # fitted values outside a parameter's physical range: the effect is standing in
            # for something else (often a missing effect)
            "outside_physical_range": [f"{e.name}.{n}" for e in model.effects
                                       for n in e.outside_range()],
            "unidentified_groups": groups,
            "residual_sigma_nm": sigma_r * 1e9,
        }

    def _uncertainty(self):
        """Sets ``covariance_z_`` (the identified directions' covariance, ``_covariance_z``),
        ``consider_`` (what the held directions' deviation from the prior, its width each,
        does to the identified), ``covariance_`` (p, p; SI) and ``parameters_`` from the
        fit's ``_uncertainty_inputs``."""
        model, Js, meas, r, V, theta, theta0, noise_z, frac = self._uncertainty_inputs
        p, k = model.n_free, V.shape[1]
        S = model.scales
        cov_z = self._covariance_z(model, meas, Js @ V, r, theta, V, noise_z)
        consider = _considered(Js, V, model.tolerances / S)
        cov = (S[:, None] * V) @ cov_z @ (S[:, None] * V).T if k else np.zeros((p, p))
        cov += (S[:, None] * consider) @ (S[:, None] * consider).T
        units = [f.unit for f in model.free for _ in range(f.sl.stop - f.sl.start)]
        self.__dict__.update(
            covariance_z_=cov_z, consider_=consider, covariance_=cov,
            parameters_=[{"label": label, "value": float(theta[j]),
                          "start": float(theta0[j]), "unit": units[j],
                          "uncertainty": float(np.sqrt(max(cov[j, j], 0.0))),
                          "identified_fraction": float(frac[j])}
                         for j, label in enumerate(model.labels)])

    def _covariance_z(self, model, meas, Jz, r, theta, V, noise_z) -> np.ndarray:
        """(k, k) the covariance of the coordinates in the identified directions ``V``: the
        residual's serially correlated share (the sandwich); the slow sources', which move the
        parameters and hardly the residual, propagated from the data's instrument
        specifications (the thermometers' noise through the temperature levels and rates, the
        air's unrecorded wander through the interferometers' index); and the attenuation by
        the thermometers' noise in the variables that the fit left uncorrected, as an
        uncorrected systematic effect (its estimate's outer product)."""
        information = (Jz.T @ Jz - noise_z if np.any(noise_z)
                       and _correction_defined(Jz.T @ Jz - noise_z, 0.0) else Jz.T @ Jz)
        cov = sandwich_covariance(Jz, r, projected_rows(meas, meas.cal),
                                  meas.df["t_s"].to_numpy(), information)
        response = reading_response(meas, Jz, information)
        cov = cov + thermometer_covariance(model, meas, self.meta_, theta, response)
        cov = cov + air_covariance(model, meas, self.meta_, response)
        left = _uncorrected_attenuation(Jz, V, theta / model.scales, self.thermometer_noise_,
                                        self.thermometer_correction_)
        return cov + np.outer(left, left)

    # -- use ----------------------------------------------------------------------------------
    def summary(self):
        """The fit's summary (calibration/physics/table.py ``FitSummary``): ``str()`` prints
        the figures and the parameter table, ``_repr_html_`` shows it in a notebook,
        ``as_dict()`` is the JSON-ready result."""
        from deltatwin.calibration.physics.table import summary_of
        return summary_of(self)

    def predict(self, df: pd.DataFrame, meta: dict | None = None) -> pd.DataFrame:
        """The model's readings (m) of every row of ``df``: columns ``x_m``, ``y_m``, ``z_m``
        for the axes the data read, indexed like ``df``; each (session, axis) zero re-estimated
        on ``df``'s calibration rows (readings are relative to a session's zero, so ``df``
        needs its readings). ``meta``: the data's metadata (default: the fit's sensor map)."""
        from deltatwin.calibration.physics.readings import predicted_readings
        return predicted_readings(self.model_, df, self._meta_for(meta))

    def score(self, df: pd.DataFrame, meta: dict | None = None) -> float:
        """Minus the validation error 90 % in metres (higher is better, as scikit-learn's
        ``score``): the 90th percentile of |reading - model's reading| over every axis's
        validation rows of ``df`` (all rows without a validation split), the zeros
        re-estimated on its calibration rows (``predict``)."""
        from deltatwin.calibration.physics.readings import validation_error_p90
        return -validation_error_p90(self.model_, df, self._meta_for(meta))

    def _meta_for(self, meta: dict | None) -> dict:
        return meta if meta is not None else {"sensors": dict(self.meta_.get("sensors") or {}),
                                              "setup": {"known": self.known_}}

    def save(self, path, data: str | None = None):
        """Write the fitted model as the TOML file ``deltatwin fit -o`` writes (atomically);
        ``data``: the fitted data's name recorded in it (default: the name a file this fit was
        read from recorded, else empty). Returns the path."""
        from deltatwin.calibration.physics.model_file import fitted_toml
        from deltatwin.files import atomic_write_text
        data = getattr(self, "data_", "") if data is None else data
        return atomic_write_text(path, fitted_toml(self, str(data)))

    @classmethod
    def load(cls, path, trust_effects=False) -> PhysicsFit:
        """A fitted model read back from its file (``save``, ``deltatwin fit -o``):
        calibration/physics/model_file.py ``load_fit``."""
        from deltatwin.calibration.physics.model_file import load_fit
        return load_fit(path, trust_effects)

    def __repr__(self) -> str:
        effects = ", ".join(self.effects) or "the nominal robot"
        if not hasattr(self, "model_"):
            return (f"PhysicsFit([{effects}], noise_nm={self.noise_nm:g}, "
                    f"identifiable_ratio={self.identifiable_ratio:g}) (not fitted)")
        val = self.val_.get("all", {}).get("err_p90")
        return (f"PhysicsFit([{effects}]: {self.model_.n_free} parameters, "
                f"{self.identifiability_.get('n_identified_directions')} directions identified, "
                f"validation error 90 % {'-' if val is None else f'{val:.1f}'} nm, "
                f"{self.status_})")

    # -- tables (pandas) ----------------------------------------------------------------------
    def validation_band(self, rng: np.random.Generator | None = None) -> dict:
        """{axis or "all": (low, high) nm}: the 95 % band of the validation error 90 % if the
        model is right (calibration/physics/band.py), drawn with ``rng`` (default seeded 0)."""
        from deltatwin.calibration.physics.band import validation_band
        return validation_band(self, rng if rng is not None else np.random.default_rng(0))

    def parameter_table(self) -> pd.DataFrame:
        """One row per free parameter (index ``effect.parameter[i]``): fitted ``value``,
        ``start``, ``unit``, 1-sigma ``uncertainty`` (same unit: along the directions the data
        determine, the residual's sandwich covariance and the slow sources propagated
        (``_covariance_z``); along those held at the start, the prior's width, Parameter
        ``tolerance``) and ``identified_fraction`` (the share of the parameter the data
        determine)."""
        return pd.DataFrame(self.parameters_).set_index("label")

    def residual_table(self) -> pd.DataFrame:
        """Residual per axis in nm (reading minus model, after each session's zero offset),
        indexed like the data's rows; NaN where an axis was not read; ``split`` beside it."""
        meas = self.measurements_
        out = pd.DataFrame(self.residual_ * 1e9, index=meas.df.index,
                           columns=[f"{a}_nm" for a in AXES])
        out["split"] = meas.df["split"].to_numpy()
        return out


def _check_known_constant(name: str, values: dict, params: RobotParams | None) -> None:
    """A known constant of effect ``name`` checked: a model effect's as a model would take it;
    one without a model form's (a condition of the laboratory, e.g. the set point of held
    supports, which the measurements read) against the library; FitError otherwise."""
    try:
        if not effect_class(name, where="known constants").model_stages():
            check_known({name: values}, "known constants")
            return
    except (EffectError, SetupError) as exc:
        raise FitError(str(exc)) from exc
    PhysicsModel([name], params, {name: values}, where="known constants")


def _gauss_newton(fun, jac, z, Jz, dof: int, max_evaluations: int, at_start=None,
                  progress=None):
    """Minimise |r(z)|^2 by Gauss-Newton steps that re-use a Jacobian while they are accepted.

    ``fun(z)`` -> (r, prediction), ``jac(z)`` -> (exact dr/dz, the model's full Jacobian);
    ``Jz``: dr/dz near the start; ``at_start``: (r, prediction, full Jacobian) when ``Jz`` is
    exact at z (no evaluation needed there). Returns (z, the full Jacobian at z, the prediction
    at z, a message).

    Most parameters move the readings nearly linearly, so the Jacobian changes little between
    steps while an exact one costs as many evaluations as there are parameters: a step is taken
    with the Jacobian at hand (Broyden-updated by each accepted step's residual change), costing
    one evaluation. A Jacobian is recomputed only where it must be exact: when its step says the
    fit has converged (the Gauss-Newton step left moves the parameters by < STEP_SIGMA of their
    uncertainty, the test ``converged_`` applies, so convergence is always judged with an exact
    Jacobian), when an updated one fails a step no longer than one that succeeded (a longer
    one may only have outrun the trust region), or when an updated one's step is accepted but
    lowers the cost by less than a quarter of its prediction: the updates are wrong in the
    directions the step went (Broyden's updates correct the Jacobian only along the steps
    taken; in weakly determined directions it can be 50-290 % off; a
    paper-force case's fit crawled along them at gains of 0.03-0.5 until its evaluations ran
    out, seed 99 g01: 42.8 nm val err90, 37.4 with this rule). Steps stay within a trust
    region (fit scales) that a failed step shrinks and a well-predicted one widens (a curved
    valley of weakly determined directions: the Gauss-Newton step overshoots it); a model that
    cannot be evaluated at a trial point (its kinematics fail) counts as a failed step there.
    ``max_evaluations`` counts the points evaluated, the start included.

    The steps' algebra is done in a ``_ResidualBasis`` (coordinates B, c of Jz and r on an
    orthonormal basis of their span, exact): a thin SVD of the (n, k) Jacobian at every step
    cost more than an evaluation at full scale (0.1 s at 85,000 readings by 39 directions)."""
    def exact_at(z, r):
        """The exact Jacobian at ``z``: the model's (N,3,p) and the solver's basis."""
        Jz, J = jac(z)
        return J, _ResidualBasis(Jz, r), True

    if at_start is None:
        r, A = fun(z)
        J, exact = None, False
    else:
        r, A, J = at_start
        exact = True
    basis = _ResidualBasis(Jz, r)
    evaluations, radius, message, accepted = 1, math.inf, None, 0.0
    cost = float(basis.c @ basis.c)
    while True:
        if progress:
            progress(r)
        if _remaining_step_sigma(basis.B, basis.c, dof) <= STEP_SIGMA:
            if exact:
                message = ("converged: the Gauss-Newton step left moves the parameters by < "
                           f"{STEP_SIGMA} of their uncertainty")
                break
            J, basis, exact = exact_at(z, r)
            continue
        if radius < RADIUS_MIN:
            message = "no step lowers the cost any further (round-off)"
            break
        if evaluations >= max_evaluations:
            message = (f"stopped at the limit of {max_evaluations} trial points (max_evaluations; "
                       "a Jacobian is not counted)")
            break
        step = _trust_region_step(basis.B, basis.c, radius)
        length = float(np.linalg.norm(step))
        predicted = cost - float(np.sum((basis.c + basis.B @ step) ** 2))
        evaluations += 1
        try:
            r_new, A_new = fun(z + step)
            c_new = basis.coordinates(r_new)
            cost_new = float(c_new @ c_new)
        except KinematicsError:
            cost_new = math.inf
        if log.isEnabledFor(logging.DEBUG):
            # the actual over the predicted fall, and where the step goes: a curved valley
            # of weakly determined directions shows as steps into the last directions (the
            # start's identified ones, strongest first) whose gain falls with their length
            share = step ** 2 / max(length * length, 1e-300)
            most = int(np.argmax(share)) if step.size else 0
            log.debug("evaluation %d: cost %.6g -> %.6g (predicted %.6g, gain %.3g; Jacobian %s, "
                      "|step| %.3g of radius %.3g, %.0f %% along direction %d of %d)",
                      evaluations, cost, cost_new, cost - predicted,
                      (cost - cost_new) / predicted if predicted > 0 else math.nan,
                      "exact" if exact else "re-used", length, radius,
                      100 * share[most] if step.size else 0.0, most + 1, step.size)
        if math.isfinite(cost_new) and cost_new < cost:
            gain = (cost - cost_new) / predicted if predicted > 0 else 0.0
            # Broyden's update: the Jacobian that reproduces the step's residual change
            basis.B += np.outer((c_new - basis.c) - basis.B @ step, step / (length * length))
            basis.c = c_new
            updated = not exact
            z, r, A, cost, exact, accepted = z + step, r_new, A_new, cost_new, False, length
            if gain < 0.25:
                radius = 0.5 * length
                if updated:         # the updated Jacobian mispredicted: recomputed
                    J, basis, exact = exact_at(z, r)
            elif gain > 0.75:
                radius = max(radius, 2.0 * length)
        elif exact:
            radius = 0.25 * length          # the exact Jacobian's model fails this far out
        elif length > (1.0 + LENGTH_ROUND_OFF) * accepted:
            radius = 0.5 * length           # a step longer than the last one that succeeded
        else:
            # no longer than a step that succeeded: the updated Jacobian is what failed (a
            # strongly nonlinear parameter, such as a coil's offset, outruns Broyden's
            # updates): recomputed, in a smaller region
            radius = 0.5 * length
            J, basis, exact = exact_at(z, r)
    if not exact:
        J = jac(z)[1]
    return z, J, A, message


class _ResidualBasis:
    """The solver's Jacobian Jz (n, k) and current residual r (n,) held as coordinates on an
    orthonormal basis Q (n, m) of their span: Jz = Q B and r = Q c exactly. Every residual the
    solver meets is added to the span (Gram-Schmidt, a second pass for round-off), and a Broyden
    update of Jz is a combination of residuals and Jz, so stays in it: the trust-region step,
    its predicted cost and the step left are computed on (m, k) matrices, equal to those on
    the (n, k) ones to round-off. The basis is re-made from Jz and r when it has grown to
    twice their columns (a long run of steps re-using one Jacobian)."""

    def __init__(self, Jz: np.ndarray, r: np.ndarray):
        Q, R = np.linalg.qr(np.column_stack([Jz, r]))
        self.Q, self.B, self.c = Q, R[:, :-1], R[:, -1]

    def coordinates(self, r: np.ndarray) -> np.ndarray:
        """The coordinates of residual r (n,), its part outside the span added to the basis
        (B and c keep their matrices, in the basis' possibly re-made coordinates)."""
        if self.Q.shape[1] >= 2 * (self.B.shape[1] + 1):
            U, R = np.linalg.qr(np.column_stack([self.B, self.c]))
            self.Q, self.B, self.c = self.Q @ U, R[:, :-1], R[:, -1]
        a = self.Q.T @ r
        rest = r - self.Q @ a
        a2 = self.Q.T @ rest
        rest -= self.Q @ a2
        a += a2
        norm = float(np.linalg.norm(rest))
        if norm > 1e-13 * float(np.linalg.norm(r)):     # more than r's round-off: a new column
            self.Q = np.column_stack([self.Q, rest / norm])
            self.B = np.vstack([self.B, np.zeros((1, self.B.shape[1]))])
            self.c = np.append(self.c, 0.0)
            a = np.append(a, norm)
        return a


def _determined_directions(Js: np.ndarray, noise_info: np.ndarray, noise_nm: float,
                           identifiable_ratio: float):
    """(s, Vt, keep, V): the directions the data determine, V (p, k), and the report of all
    (singular values s, directions Vt, ``keep`` marking V's): those whose information beyond
    the thermometers' noise is above the fit's threshold (``_information_directions``,
    ``_identified``), and of these the combinations where that noise is less than
    MAX_NOISE_SHARE of the information (Fuller's reliability ratio above one half: where the
    noise gives more, least squares would halve the coefficient, and the corrected estimate
    would more than double its noise; the data do not determine it)."""
    s, Vt = _information_directions(Js, noise_info)
    keep = _identified(s, noise_nm, identifiable_ratio)
    V = Vt[keep].T                                                       # (p, k)
    if not np.any(noise_info) or not V.shape[1]:
        return s, Vt, keep, V
    share, X = linalg.eigh(V.T @ noise_info @ V, V.T @ Js.T @ Js @ V)
    reliable = share < MAX_NOISE_SHARE
    if reliable.all():
        return s, Vt, keep, V
    V = V @ np.linalg.qr(X[:, reliable])[0]
    return (*_directions_report(Js, V), V)


def _information_directions(Js: np.ndarray, noise_info: np.ndarray):
    """(s, Vt): the singular values (m per fit scale) and directions of the calibration
    Jacobian ``Js`` (n, p) with the thermometers' share of its information (``noise_info``)
    taken out: the eigen-decomposition of Js^T Js - noise_info (a share above the column's own
    information leaves it at zero), largest first; the SVD of ``Js`` when there is none."""
    p = Js.shape[1]
    if not p:
        return np.zeros(0), np.zeros((0, 0))
    if not np.any(noise_info):
        return np.linalg.svd(Js, full_matrices=False)[1:]
    w, U = np.linalg.eigh(Js.T @ Js - noise_info)
    order = np.argsort(-w, kind="stable")
    return np.sqrt(np.clip(w[order], 0.0, None)), U[:, order].T


def _considered(Js: np.ndarray, V: np.ndarray, width: np.ndarray) -> np.ndarray:
    """(p, p - k) in fit scales: how the parameters' error depends on the held directions'
    deviation from the prior (the Schmidt consider covariance: Tapley, Schutz & Born 2004,
    Statistical Orbit Determination, 6.3). A held direction H's true value is not the
    prior's, and least squares in the identified directions ``V`` takes up what its column
    ``Js H`` shares with theirs: the error is (V B - H) d, B the regression of ``Js H`` on
    ``Js V`` (``Js`` (n, p) the projected calibration Jacobian), d the held directions'
    deviation in fit scales, of covariance H^T diag(width^2) H (``width`` (p,) the prior's
    width of each parameter in fit scales). Returns (V B - H) R with R R^T that covariance:
    its product with standard normal draws is the error (sign immaterial)."""
    p, k = V.shape
    H = linalg.null_space(V.T) if k else np.eye(p)
    if not H.size:
        return H
    prior = (H * width[:, None] ** 2).T @ H
    value, vector = np.linalg.eigh(0.5 * (prior + prior.T))
    root = vector * np.sqrt(np.clip(value, 0.0, None))
    if not k:
        return -H @ root
    B = np.linalg.lstsq(Js @ V, Js @ H, rcond=None)[0]
    return (V @ B - H) @ root


def checked_directions(directions, p: int) -> np.ndarray:
    """``directions`` (p, k) as a float array, refused unless it has one row per parameter and
    orthonormal columns (a fitted model's saved directions: the SVD's, exact to round-off)."""
    V = np.asarray(directions, dtype=float)
    if V.ndim != 2 or V.shape[0] != p or not np.all(np.isfinite(V)):
        raise FitError(f"start_directions: shape {V.shape}, expected {p} finite rows (one per "
                       "parameter) by the identified directions")
    if np.max(np.abs(V.T @ V - np.eye(V.shape[1])), initial=0.0) > 1e-9:
        raise FitError("start_directions: the identified directions are not orthonormal")
    return V


def _directions_report(Js: np.ndarray, V: np.ndarray):
    """(s, Vt, keep) for the identifiability report of a fit held to the directions ``V``
    (p, k; orthonormal) rather than those the SVD of ``Js`` identifies: V's singular values in
    ``Js`` and, for the directions outside them, the SVD of ``Js`` on V's orthogonal
    complement; sorted by singular value, ``keep`` marking V's."""
    p, k = V.shape
    s_in = np.linalg.svd(Js @ V, compute_uv=False)
    complement = np.linalg.qr(V, mode="complete")[0][:, k:]               # (p, p - k)
    _, s_out, Wt = np.linalg.svd(Js @ complement, full_matrices=False)
    s = np.concatenate([s_in, s_out])
    Vt = np.vstack([V.T, Wt @ complement.T])
    keep = np.arange(p) < k
    order = np.argsort(-s, kind="stable")
    return s[order], Vt[order], keep[order]


def _trust_region_step(Jz: np.ndarray, r: np.ndarray, radius: float) -> np.ndarray:
    """The step dz minimising |r + Jz dz| with |dz| <= ``radius`` (fit scales): the
    Gauss-Newton step when it is that short, else the Levenberg-Marquardt step
    -(Jz^T Jz + mu)^-1 Jz^T r whose length is the radius (mu by bisection on its logarithm)."""
    U, s, Vt = np.linalg.svd(Jz, full_matrices=False)
    g = U.T @ r
    keep = s > s.max(initial=0.0) * 1e-12
    s, g, Vt = s[keep], g[keep], Vt[keep]
    if np.linalg.norm(g / s) <= radius:
        return -Vt.T @ (g / s)
    lo, hi = -40.0, 40.0          # log10 of mu / s_max^2: the step's length falls with mu
    s2 = s.max() ** 2
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        if np.linalg.norm(s * g / (s ** 2 + s2 * 10.0 ** mid)) > radius:
            lo = mid
        else:
            hi = mid
    return -Vt.T @ (s * g / (s ** 2 + s2 * 10.0 ** hi))


def _identified(s: np.ndarray, noise_nm: float, identifiable_ratio: float) -> np.ndarray:
    """Which directions of singular values ``s`` (the scaled calibration Jacobian's, m per fit
    scale) the data determine: those above the noise (nm) over ``identifiable_ratio``, and
    above round-off of the largest."""
    return (s > noise_nm * 1e-9 / identifiable_ratio) & (s > s.max(initial=0) * 1e-12)


def fitted_again_where_it_ended(fit: PhysicsFit) -> PhysicsFit:
    """``fit`` fitted once more from where it ended, in the directions identified there, when
    it converged in the directions identified at its start but those identified where it
    ended still leave a step above STEP_SIGMA; the refit (its evaluations and Jacobians added
    to ``fit``'s, ``fitted_again_`` True) is returned when its calibration cost is lower,
    else ``fit`` (its counts including the refit's).

    A fit chooses its identified directions once, from the Jacobian at its start: where an
    effect's columns scale with a parameter that moves far (a coil's offsets with its moment,
    0.16 A*m^2/A at the library's start, 2.2 where a force case hiding magnetic force x10
    ends, seed 6363 case001) other directions are identified where it ends, and the fit
    stops "converged" in its start's (137 nm validation against the achievable floor's 61.2;
    fitted again in the ladder, 66.6). Only the ladder's rungs that add an effect are
    fitted again (``effect_ladder``): done in every fit, the shipped quiet
    loop-drift baseline moved to a lower calibration cost where loop drift's linearised
    candidate was no longer significant, and 12 cases cost a third more CPU. Once: up to
    three times left every case of two seeds' 24 as once did."""
    if not fit.converged_ or not fit.model_.n_free:
        return fit
    meas = fit.measurements_
    Js = projected(meas, meas.cal, fit.jacobian_, scale=fit.model_.scales)
    noise = fit.thermometer_noise_
    V = _determined_directions(Js, noise.information, fit.noise_nm, fit.identifiable_ratio)[3]
    r = projected(meas, meas.cal, meas.y - fit.prediction_)
    terms = fit.thermometer_correction_.terms(V, fit.theta_ / fit.model_.scales)
    if _remaining_step_sigma(-Js @ V, r, meas.residual_dof(r.size, V.shape[1]),
                             terms) <= STEP_SIGMA:
        return fit
    again = PhysicsFit(fit.effects, fit.params, start={**fit.model_.values(), **fit.known_},
                       noise_nm=fit.noise_nm, identifiable_ratio=fit.identifiable_ratio,
                       max_evaluations=fit.max_evaluations, progress=fit.progress,
                       prior=fit.prior).fit(meas.df, fit.meta_, meas=meas)
    kept = calibration_cost(again) < calibration_cost(fit)
    out, other = (again, fit) if kept else (fit, again)
    out.n_evaluations_ += other.n_evaluations_
    out.n_jacobians_ += other.n_jacobians_
    out.fitted_again_ = kept
    if kept:
        for name in ("start_label_", "start_costs_", "start_fits_"):   # fit_from_starts'
            if hasattr(fit, name):
                setattr(again, name, getattr(fit, name))
        fit.model_.drop_linearisation()
    else:
        again.model_.drop_linearisation()
    return out


def _remaining_step_sigma(Jz: np.ndarray, r: np.ndarray, dof: int,
                          thermometers: tuple | None = None) -> float:
    """The Gauss-Newton step left from where the residual is ``r`` and its Jacobian in the
    identified directions ``Jz``, in standard deviations of the fitted directions
    (|Jz step| / sigma_r): converged when below STEP_SIGMA. With ``thermometers`` ((C_z, g)
    of ``_thermometer_terms``, in r's units squared), the step of the corrected score
    (``_corrected_for_thermometers``). A misspecified model's best fit is a result, reported
    with its status, never an error."""
    if not Jz.shape[1]:
        return 0.0
    H = None if thermometers is None else Jz.T @ Jz - thermometers[0]
    if H is None or not _correction_defined(H, 0.0):
        step = np.linalg.lstsq(Jz, r, rcond=None)[0]
    else:
        step = np.linalg.solve(H, -Jz.T @ r + thermometers[1])
    sigma_r = float(np.linalg.norm(r)) / np.sqrt(dof)
    return float(np.linalg.norm(Jz @ step)) / sigma_r if sigma_r > 0 else 0.0


def _corrected_for_thermometers(fun, jac, z, A, J, jz_of, terms_at, y, projected_nm,
                                least_nm2: float, dof: int):
    """(z, prediction, model Jacobian, corrected): the least-squares solution ``z``
    (prediction ``A``, the model's Jacobian ``J`` there) moved to the root of the corrected
    score -Jz^T r(z) + g(z) (Fuller 1987, errors in the variables, the method of moments;
    ``jz_of(J)`` = dr/dz in nm per fit scale, ``terms_at(z)`` = (C_z, g(z)) of
    ThermometerNoise.terms in nm^2, r = ``projected_nm(y - prediction)``): the thermometers'
    noise in a coefficient's column adds C_z = E[N^T N] to J^T J and so attenuates the
    coefficient by (J^T J + C_z)^-1 J^T J (a frame's expansion coefficient 18.9e-6 /K at 3 mK
    against 22.6e-6 with perfect thermometers, a reduced thermal campaign); adding back the
    noise's share of the score removes that in expectation (the share is ThermometerNoise
    ``restricted`` to the directions where the correction is stable). Defined where
    J^T J - C_z, the information beyond the thermometers', exceeds ``least_nm2`` (the fit's
    threshold of a determined direction, squared) in every direction: a model that moved
    far from where its directions were chosen (a misspecified one standing in for a missing
    effect) may have left that, at the start or on the way; then the least-squares solution
    stays (``corrected`` False).

    The corrected score is minus the gradient of Q(z) = |r(z)|^2 / 2 - G(z), G the integral of
    g (quadratic: g is linear in z), so its root is a minimum of Q, and Q judges each step:
    Newton steps with the exact Jacobian (``jac``; a Jacobian carried over from the
    least-squares solution or Broyden-updated finds another root, by 2.5-6 uncertainties on
    reduced paper-thermal), halved until Q falls (at most LINE_SEARCH_HALVINGS times), until
    the step left is below STEP_SIGMA (the converged fit's test), at most CORRECTION_STEPS of
    them. Without the merit function, full Newton steps overshoot along a direction where Q is
    flat and oscillate away from the least-squares solution
    (tests/calibration/test_thermometer_noise.py). Where Q falls no further, or the steps run
    out, the corrected score has no root found near the least-squares solution (the
    correction's moment equation need not have one where the noise's share is large: Fuller
    1987, 2.5.1), and the least-squares solution stays (``corrected`` False)."""
    Jz = jz_of(J)
    least_squares = z, A, J
    r = projected_nm(y - A)
    z_least, (C_least, g_least) = z, terms_at(z)

    def merit(z, r):
        d = z - z_least
        return 0.5 * float(r @ r) - float(g_least @ d + 0.5 * d @ C_least @ d)

    q = merit(z, r)
    for _ in range(CORRECTION_STEPS + 1):
        C_z, g = terms_at(z)
        if not _correction_defined(Jz.T @ Jz - C_z, least_nm2):
            break
        step = np.linalg.solve(Jz.T @ Jz - C_z, -Jz.T @ r + g)
        sigma = float(np.linalg.norm(r)) / np.sqrt(dof)
        moved = float(np.linalg.norm(Jz @ step)) / sigma if sigma > 0 else 0.0
        log.debug("thermometer correction: a step of %.3g uncertainties", moved)
        if moved < STEP_SIGMA:
            return z, A, J, True
        trial = _descent(fun, merit, z, step, q)
        if trial is None:
            break
        z, r, A, q = trial
        Jz, J = jac(z)
    return (*least_squares, False)


def _descent(fun, merit, z, step, q):
    """(z, r, prediction, merit) at the first of z + step, z + step / 2, ... (at most
    LINE_SEARCH_HALVINGS halvings) where ``merit`` falls below ``q``; None where none does or
    the model cannot be evaluated there."""
    for k in range(LINE_SEARCH_HALVINGS + 1):
        trial = z + step / 2 ** k
        try:
            r, A = fun(trial)
        except (KinematicsError, ParameterError) as exc:
            log.debug("the correction for the thermometers' noise stopped: %s", exc)
            return None
        value = merit(trial, r)
        if value < q:
            return trial, r, A, value
    return None


def _uncorrected_attenuation(Jz: np.ndarray, V: np.ndarray, t: np.ndarray,
                             noise: ThermometerNoise, used: ThermometerNoise) -> np.ndarray:
    """(k,) fit scales: the shift of the coordinates in the directions ``V`` that the
    thermometers' ``noise`` gives least squares and the correction the fit made (``used``,
    ThermometerNoise ``restricted``) did not take out, to first order (J^T J)^-1 g at the
    parameters ``t`` (fit scales; ``Jz`` (n, k) the projected calibration Jacobian in ``V``,
    m per fit scale): the coefficients of temperatures in every direction, less what the
    correction took out (none where it was not made, or in the directions where the noise's
    share was too large to correct stably)."""
    if not noise or not V.shape[1]:
        return np.zeros(V.shape[1])
    shift = noise.restricted(V, Jz, max_share=np.inf).terms(V, t)[1]
    if used:
        shift = shift - used.terms(V, t)[1]
    return np.linalg.pinv(Jz.T @ Jz) @ shift


def _correction_defined(H: np.ndarray, least: float) -> bool:
    """Whether the corrected information ``H`` (J^T J less the thermometers' share) exceeds
    ``least`` in every direction (units of H)."""
    return bool(H.size == 0 or np.linalg.eigvalsh(H).min() > least)


def calibration_cost(fit: PhysicsFit) -> float:
    """Sum of squared calibration residuals (m^2, after each session's zero) where least
    squares ended (``least_squares_residual_``, before the correction for the thermometers):
    what every fit minimises, so fits of one model from different starts compare on it."""
    res = fit.least_squares_residual_[fit.measurements_.cal]
    return float(np.nansum(res ** 2))


def fit_from_starts(effects, starts: dict, df: pd.DataFrame, meta: dict | None = None,
                    made=(), chance_alpha: float | None = None, **options) -> PhysicsFit:
    """Fit ``effects`` from each of ``starts`` ({label: PhysicsFit keyword arguments, e.g.
    ``start`` and ``prior``}) and return the fit of lowest calibration cost (of the first
    start unless another is lower beyond chance, with ``chance_alpha``), with
    ``start_label_`` (which start it came from), ``start_costs_`` ({label: calibration
    rms, nm}) and ``start_fits_`` ({label: the fit from that start}). ``made``: fits already
    made on the rows of ``df`` (another call's ``start_fits_`` values): a start whose fit is
    among them (the same effects, robot, starting values, prior and options) is taken from
    there instead of being fitted again (a copy: its labels are this call's).

    A model whose thermometer terms multiply its expansion coefficients (sensor_contact's leak
    scales every part's temperature excursion by 1 + leak / glue, a product with every CTE)
    has more than one basin: a generated loop-drift case fitted from the library's starting
    values stops, converged, at 12.2 nm calibration rms with a negative leak; from the
    previous model's fitted values, at 8.5 nm, and the straight line between the two climbs
    to 17 nm. A step-limited local fit cannot cross that ridge; trying the starts a researcher
    has and keeping the lowest cost can. The choice uses the calibration rows only.

    ``chance_alpha``: when given, the first start's fit is kept unless another lowers the
    calibration cost by more than chance would at that level (the fall, in units of the first
    fit's residual variance, above the chi-square quantile of one degree of freedom; among the
    starts that do, the lowest cost is kept): fits
    the calibration rows cannot tell apart are not chosen between by round-off (a force case's
    five starts ended within 0.07 % of one another in calibration rms and 68-93 nm apart in
    validation error)."""
    if not starts:
        raise FitError("fit_from_starts: no start given")
    if chance_alpha is not None and not 0 < chance_alpha < 1:
        raise FitError(f"fit_from_starts: chance_alpha = {chance_alpha}: must be a probability "
                       "between 0 and 1")
    best, costs, fits, meas = None, {}, {}, None
    for label, kwargs in starts.items():
        fit = PhysicsFit(effects, **{**options, **kwargs})
        done = next((f for f in made if _same_problem(f, fit)), None)
        fit = copy.copy(done) if done else fit.fit(df, meta, meas=meas)
        fits[label] = fit
        meas = fit.measurements_
        cost = calibration_cost(fit)
        n_res = int(np.sum(np.isfinite(fit.residual_[meas.cal])))
        costs[label] = float(np.sqrt(cost / max(n_res, 1))) * 1e9
        if best is None:
            first = cost
            chance = 0.0 if chance_alpha is None else cost / meas.residual_dof(
                n_res, fit.identifiability_["n_identified_directions"]
            ) * float(special.chdtri(1, chance_alpha))   # chi2.isf(alpha, 1)
        if best is None or (cost < best[0] and first - cost > chance):
            best = (cost, label, fit)
    _, label, fit = best
    for other in fits.values():
        if other.model_ is not fit.model_:
            other.model_.drop_linearisation()  # a probe's cache: kept for the chosen fit only
    fit.start_label_, fit.start_costs_, fit.start_fits_ = label, costs, fits
    return fit


def _same_problem(a: PhysicsFit, b: PhysicsFit) -> bool:
    """Whether fits ``a`` and ``b`` (of the same rows) solve the same problem: the same
    effects, robot, starting values, prior and options, so the same solver path."""
    def values(fit, start):
        return PhysicsModel(fit.effects, fit.params, start).values()
    return (a.effects == b.effects and a.params is b.params and a.known == b.known
            and (a.noise_nm, a.identifiable_ratio, a.max_evaluations)
            == (b.noise_nm, b.identifiable_ratio, b.max_evaluations)
            and values(a, a.start) == values(b, b.start)
            and values(a, a.prior) == values(b, b.prior))
