"""The first paper's direct geometric model: one stepwise fit per interferometer axis,
reading = f(q1, q2, q3, temperatures, their derivatives)."""
from __future__ import annotations

import numpy as np

from deltatwin.calibration.blackbox.estimator import (
    AXIS_COLUMNS,
    NM,
    StepwiseModel,
    thermal_sensors,
)
from deltatwin.calibration.blackbox.features import JOINT_INPUTS, thermal_preset
from deltatwin.calibration.errors import MissingColumnsError


class DGM(StepwiseModel):
    """Direct geometric model per axis: ``reading = f(q, T, dT/dt, d2T/dt2)`` (first paper).

    ``features``: ``"thermal"`` (the preset: 19 geometric, temperatures, geometric x
    temperature, first and second derivatives) or any :class:`FeatureSet` over q1..q3 and
    temperature variables.  ``sensors``: temperature sensor names (default: the metadata's
    non-air sensors).  ``outputs``: axes to fit (default: every one of x, y, z measured in the
    calibration rows).  Outputs are in metres.
    """
    kind = "DGM"
    geo_inputs = JOINT_INPUTS
    preset_name = "thermal"
    output_columns = AXIS_COLUMNS
    output_noun = "axis(es)"

    def _sensors_for(self, df, meta):
        return thermal_sensors(df, meta, self.sensors)

    def _default_features(self, sensors):
        return thermal_preset(sensors)

    def _output_specs(self, df):
        if self.outputs is not None:
            axes = self.outputs
            missing = [AXIS_COLUMNS[a] for a in axes if AXIS_COLUMNS[a] not in df.columns]
            if missing:
                raise MissingColumnsError(f"DGM: axis column(s) {missing} not in the data")
        else:
            axes = [a for a, c in AXIS_COLUMNS.items()
                    if c in df.columns and np.isfinite(df[c].to_numpy(dtype=float)).any()]
            if not axes:
                raise MissingColumnsError("DGM: no interferometer reading (x_nm, y_nm, z_nm) "
                                          "with a finite value in the data")
        return [(a, "m", AXIS_COLUMNS[a], NM) for a in axes]


