"""The second paper's direct inverse model: one stepwise fit per motor, q_i = f(X, Y, Z, F)."""
from __future__ import annotations

import numpy as np
import pandas as pd

from deltatwin.calibration.blackbox.estimator import MOTOR_COLUMNS, StepwiseModel
from deltatwin.calibration.blackbox.features import CARTESIAN_INPUTS, force_preset
from deltatwin.calibration.errors import CalibrationInputError


class DirectIGM(StepwiseModel):
    """Direct IGM per motor: ``q_i = f(X, Y, Z, F)`` (second paper).  Outputs in rad.

    ``features``: ``"force"`` (the preset: 19 geometric monomials of X, Y, Z; F, F^2, F^3;
    geometric x those) or a :class:`FeatureSet` over X, Y, Z, F (and temperatures).
    Rows need all of ``x_nm``, ``y_nm``, ``z_nm`` (rows with NaN are dropped with a warning).
    """
    kind = "DirectIGM"
    geo_inputs = CARTESIAN_INPUTS
    preset_name = "force"
    output_columns = MOTOR_COLUMNS
    output_noun = "motor(s)"

    def _default_features(self, sensors):
        return force_preset()

    def _output_specs(self, df):
        motors = self.outputs or list(MOTOR_COLUMNS)
        return [(m, "rad", MOTOR_COLUMNS[m], 1.0) for m in motors]

    def jacobian(self, values: dict[str, np.ndarray]) -> np.ndarray:
        """dq/dX of the fitted model at each point: (n, n_outputs, 3) in rad/m."""
        self._check_fitted()
        g = self._geo(values)
        C = self._eval.coefficients(values, g.shape[1])
        return self._eval.value_and_jacobian(C, g)[1].transpose(2, 0, 1)

    def _errors_and_jacobian(self, df):
        if self.output_names_ != list(MOTOR_COLUMNS):
            raise CalibrationInputError(f"{self.kind}: end-effector errors need the outputs "
                                        f"q1, q2, q3; this model has {self.output_names_}")
        vals = self.variables(df)
        dq = self.predict_values(vals) - self.targets(df)
        J = self.jacobian(vals)
        ok = np.all(np.isfinite(dq), axis=1) & np.all(np.isfinite(J), axis=(1, 2))
        ok[ok] &= np.abs(np.linalg.det(J[ok])) > 0
        return dq, J, ok

    def position_error(self, df: pd.DataFrame) -> np.ndarray:
        """End-effector error the model's motor-coordinate errors cause: ``J^-1 (q_pred -
        q_meas)`` with J = dq/dX of the model, (n, 3) in m; NaN where not available."""
        self._check_fitted()
        dq, J, ok = self._errors_and_jacobian(df)
        out = np.full(dq.shape, np.nan)
        out[ok] = np.linalg.solve(J[ok], dq[ok][:, :, None])[:, :, 0]
        return out

    def errors_m(self, df: pd.DataFrame) -> np.ndarray:
        """(n, 3) each motor's error expressed at the end-effector, m
        (``motor_error_at_effector``): what ``score`` takes the 90th percentile of."""
        return self.motor_error_at_effector(df)

    def motor_error_at_effector(self, df: pd.DataFrame) -> np.ndarray:
        """Each motor model's error expressed at the end-effector: dq_i * ||(J^-1)[:, i]||
        (signed like dq_i), (n, 3) in m: the displacement that motor's error alone causes, a
        per-motor figure in length units comparable with the paper's."""
        self._check_fitted()
        dq, J, ok = self._errors_and_jacobian(df)
        out = np.full(dq.shape, np.nan)
        Jinv = np.linalg.inv(J[ok])
        out[ok] = dq[ok] * np.linalg.norm(Jinv, axis=1)
        return out


# ----- load ------------------------------------------------------------------------------

