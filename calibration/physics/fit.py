"""Fitting a physics model to measurements (scikit-learn style: ``fit``, attributes ending in ``_``):
Gauss-Newton on the identified directions, with the identifiability report."""
from __future__ import annotations

import logging
import math

import numpy as np
import pandas as pd
import scipy.linalg

from deltatwin.calibration.errors import FitError, TooFewPointsError
from deltatwin.calibration.physics.measurements import Measurements, check_sensors, measurements
from deltatwin.calibration.physics.model import (
    PhysicsModel,
    _projected,
    figures_nm,
    group_offsets,
    residuals,
)
from deltatwin.models.params import RobotParams
from deltatwin.twin.instruments.optics import AXES

NM = 1e9   # the solver works on residuals in nm, where its tolerances are meaningful

log = logging.getLogger(__name__)


class PhysicsFit:
    """Fit a physics model's free parameters to a dataset's calibration rows.

    Parameters: ``effects`` (library names), ``params`` (the robot file; default nominal),
    ``start`` ({effect: {parameter: value}}: starting values, e.g. a previous fit),
    ``noise_nm`` (the readings' noise, nm: sets which directions are identifiable),
    ``identifiable_ratio`` (a direction is fitted if the data determine it to better than this
    fraction of its parameters' typical size), ``max_iterations`` (Gauss-Newton steps),
    ``progress`` (print the calibration rms after each step).

    Attributes after ``fit``: ``model_`` (PhysicsModel at the fitted values), ``offsets_`` (m per
    (session, axis)), ``residual_`` ((N,3) m), ``cal_``/``val_`` (error figures, nm),
    ``identifiability_`` (dict), ``converged_``, ``n_evaluations_``, ``parameters_`` (list of
    {label, value, start, unit, uncertainty, identified_fraction}).
    """

    def __init__(self, effects, params: RobotParams | None = None, start: dict | None = None,
                 noise_nm: float = 5.0, identifiable_ratio: float = 0.3,
                 max_iterations: int = 20, progress: bool = False):
        if noise_nm <= 0 or not math.isfinite(noise_nm):
            raise FitError(f"noise_nm = {noise_nm}: must be a positive number of nanometres")
        if not 0 < identifiable_ratio:
            raise FitError(f"identifiable_ratio = {identifiable_ratio}: must be positive")
        self.effects = list(effects)
        self.params = params
        self.start = start
        self.noise_nm = noise_nm
        self.identifiable_ratio = identifiable_ratio
        self.max_iterations = max_iterations
        self.progress = progress
        PhysicsModel(self.effects, params, start)      # validate names and values once

    def fit(self, df: pd.DataFrame, meta: dict | None = None, meas: Measurements | None = None,
            where: str = "data"):
        """Fit to the calibration rows of ``df`` (``where`` names the data in errors)."""
        model = PhysicsModel(self.effects, self.params, self.start)
        meas = meas or measurements(df, meta, model.params, where)
        check_sensors(model.names, meas, where)
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
        S = model.scales
        sigma = self.noise_nm * 1e-9
        _, J0 = model.jacobian(meas, theta0)
        Js = _projected(meas, cal, J0 * S)
        if p:
            _, s, Vt = np.linalg.svd(Js, full_matrices=False)
        else:
            s, Vt = np.zeros(0), np.zeros((0, 0))
        keep = (s > sigma / self.identifiable_ratio) & (s > s.max(initial=0) * 1e-12)
        V = Vt[keep].T                                                   # (p, k)
        self.n_evaluations_ = p + 1
        # directions the data cannot determine are held at the prior (the effects' starting
        # values), not at a warm start's values: a previous fit may have pushed them anywhere
        # while standing in for an effect it lacked
        prior = PhysicsModel(self.effects, self.params).theta()
        z_start = V.T @ ((theta0 - prior) / S) if p else np.zeros(0)

        def theta_of(z):
            return prior + S * (V @ z)

        def fun(z):
            A = model.predict_path(meas, theta_of(z))
            self.n_evaluations_ += 1
            return _projected(meas, cal, meas.y - A) * NM

        def jac(z):
            th = theta_of(z)
            if np.array_equal(th, theta0):
                J = J0
            else:
                _, J = model.jacobian(meas, th)
                self.n_evaluations_ += p + 1
            return -_projected(meas, cal, J * S) @ V * NM

        # Gauss-Newton in the identified coordinates, halving a step that does not lower the
        # cost. The stopping rule is physical (a further step would move the predictions by
        # less than 1 % of the noise), which a solver's relative tolerances cannot express;
        # the problem is nearly linear in the parameters' small deviations, so it converges in
        # a few Jacobians.
        k = V.shape[1]
        z = z_start
        r = fun(z)
        Jz = jac(z)
        for _ in range(self.max_iterations if k else 0):
            step = scipy.linalg.lstsq(Jz, -r, lapack_driver="gelsd")[0]
            if np.sqrt(np.mean((Jz @ step) ** 2)) <= 0.01 * self.noise_nm:
                break
            cost = r @ r
            for _ in range(30):
                r_new = fun(z + step)
                if r_new @ r_new < cost:
                    break
                step = 0.5 * step
            else:
                break                                   # no descent left: checked below
            z, r = z + step, r_new
            Jz = jac(z)
            if self.progress:
                log.info("fit %s: calibration rms %.3f nm", self.effects, np.sqrt(np.mean(r ** 2)))
        theta = theta_of(z)
        A, J = model.jacobian(meas, theta)
        self.n_evaluations_ += p + 1
        r = _projected(meas, cal, meas.y - A)
        Jz = -_projected(meas, cal, J * S) @ V
        # convergence: a further Gauss-Newton step from here must change the predictions by
        # less than 1 % of the readings' noise (rms over the calibration readings)
        step = np.linalg.lstsq(Jz, r, rcond=None)[0] if k else np.zeros(0)
        change = float(np.sqrt(np.mean((Jz @ step) ** 2))) if k else 0.0
        rms = float(np.sqrt(np.mean(r ** 2))) if r.size else 0.0
        self.converged_ = change <= 0.01 * sigma
        self.last_step_nm_ = change * 1e9
        if not self.converged_:
            raise FitError(f"the fit of {self.effects} did not converge in {self.max_iterations} "
                           f"Gauss-Newton steps: a further step would still move the predictions "
                           f"by {change * 1e9:.3g} nm rms (calibration rms {rms * 1e9:.3g} nm, "
                           f"limit {0.01 * sigma * 1e9:.3g} nm); check the data's units and the "
                           "effects, or raise max_iterations")
        self.model_ = model
        self.theta_ = theta
        self.measurements_ = meas
        self.offsets_ = group_offsets(meas, A, cal)
        self.residual_ = residuals(meas, A, self.offsets_)
        self.prediction_ = A
        self.reading_m_ = meas.y - self.residual_      # the model's reading per row (m)
        self.cal_ = figures_nm(self.residual_, meas.cal)
        self.val_ = figures_nm(self.residual_, meas.val)
        self.jacobian_ = J
        self.identified_directions_ = V
        self._identifiability(model, s, Vt, keep, J * S, meas, r, V, theta, prior)
        return self

    def _identifiability(self, model, s, Vt, keep, JS, meas, r, V, theta, theta0):
        p, k = model.n_free, int(keep.sum())
        labels = model.labels
        dof = max(r.size - k - len(meas.groups), 1)
        sigma_r = float(np.sqrt(np.sum(r ** 2) / dof))
        Jz = _projected(meas, meas.cal, JS) @ V if k else np.zeros((r.size, 0))
        cov_z = np.linalg.pinv(Jz.T @ Jz) * sigma_r ** 2 if k else np.zeros((0, 0))
        S = model.scales
        cov = (S[:, None] * V) @ cov_z @ (S[:, None] * V).T if k else np.zeros((p, p))
        frac = np.sum(V ** 2, axis=1) if k else np.zeros(p)
        units = [f.unit for f in model.free for _ in range(f.sl.stop - f.sl.start)]
        self.parameters_ = [
            {"label": labels[j], "value": float(theta[j]), "start": float(theta0[j]),
             "unit": units[j], "uncertainty": float(np.sqrt(max(cov[j, j], 0.0))),
             "identified_fraction": float(frac[j])} for j in range(p)]
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

    # -- use ----------------------------------------------------------------------------------
    def summary(self) -> dict:
        """JSON-ready result."""
        return {"effects": self.effects, "n_parameters": self.model_.n_free,
                "converged": bool(self.converged_), "n_evaluations": self.n_evaluations_,
                "cal": _axis_p90(self.cal_), "val": _axis_p90(self.val_),
                "val_err90_nm": self.val_["all"]["err_p90"],
                "offsets_nm": {f"{s}.{a}": o * 1e9 for (s, a), o in
                               zip(self.measurements_.groups, self.offsets_)},
                "identifiability": self.identifiability_, "parameters": self.parameters_,
                "values": self.model_.values()}

    # -- tables (pandas) ----------------------------------------------------------------------
    def parameter_table(self) -> pd.DataFrame:
        """One row per free parameter (index ``effect.parameter[i]``): fitted ``value``,
        ``start``, ``unit``, 1-sigma ``uncertainty`` (same unit) and ``identified_fraction``
        (the share of the parameter the data determine)."""
        return pd.DataFrame(self.parameters_).set_index("label")

    def residual_table(self) -> pd.DataFrame:
        """Residual per axis in nm (reading minus model, after each session's zero offset),
        indexed like the data's rows; NaN where an axis was not read; ``split`` beside it."""
        meas = self.measurements_
        out = pd.DataFrame(self.residual_ * 1e9, index=meas.df.index,
                           columns=[f"{a}_nm" for a in AXES])
        out["split"] = meas.df["split"].to_numpy()
        return out


def _axis_p90(fig: dict) -> dict:
    return {k: v["err_p90"] for k, v in fig.items()}


# ---------------------------------------------------------------------------------------------
# fitted model files (TOML)

def _or_nan(x):
    return math.nan if x is None else x


