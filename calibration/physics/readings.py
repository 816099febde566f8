"""A physics model's readings on a dataset, as its interferometers would count them.

A reading is relative to its session's zero, and a new campaign has new zeros: the model's
reading is its predicted optical path plus the (session, axis) zero re-estimated on the
dataset's calibration rows (a session without calibration readings takes its zero from its
own rows). ``session_zeros`` is that estimate (``deltatwin compare`` uses it too);
``predicted_readings`` and ``validation_error_p90`` are what ``PhysicsFit.predict`` and
``PhysicsFit.score`` return. Units: m.
"""
from __future__ import annotations

import numpy as np
import pandas as pd

from deltatwin.calibration.physics.measurements import Measurements, check_sensors, measurements
from deltatwin.calibration.physics.model import PhysicsModel, group_offsets, residuals
from deltatwin.twin.instruments.optics import AXES

READING_COLUMNS = tuple(f"{a}_m" for a in AXES)


def session_zeros(meas: Measurements, pred: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(offsets m per ``meas.groups`` entry, on_cal bool per entry): each (session, axis) zero,
    the mean of reading minus prediction over the calibration rows with a prediction, or over
    all its rows with one when it has no calibration reading (``on_cal`` False)."""
    predicted = np.isfinite(pred).any(axis=1)
    cal_readings = np.bincount(meas.group[(meas.group >= 0) & (meas.cal & predicted)[:, None]],
                               minlength=len(meas.groups))
    on_cal = group_offsets(meas, pred, meas.cal & predicted)
    on_own = group_offsets(meas, pred, predicted)
    return np.where(cal_readings > 0, on_cal, on_own), cal_readings > 0


def model_readings(model: PhysicsModel, df: pd.DataFrame, meta: dict | None,
                   where: str = "data") -> tuple[np.ndarray, Measurements, np.ndarray]:
    """(readings (N,3) m, the measurements, the zeros): ``model``'s reading of every row of
    ``df`` whose session reads that axis (NaN elsewhere), each (session, axis) zero
    re-estimated (``session_zeros``)."""
    meas = measurements(df.reset_index(drop=True), meta, model.params, where)
    check_sensors(model.names, meas, where)
    pred = model.predict_path(meas)
    offsets, _ = session_zeros(meas, pred)
    zero = {g: o for g, o in zip(meas.groups, offsets)}
    session = meas.df["session"].astype(str).to_numpy()
    out = np.full((meas.n, 3), np.nan)
    for k, a in enumerate(AXES):
        for s in dict.fromkeys(session):
            if (s, a) in zero:
                rows = session == s
                out[rows, k] = pred[rows, k] + zero[(s, a)]
    return out, meas, offsets


def predicted_readings(model: PhysicsModel, df: pd.DataFrame, meta: dict | None,
                       where: str = "data") -> pd.DataFrame:
    """The model's readings (m) as a DataFrame indexed like ``df``, columns ``x_m``, ``y_m``,
    ``z_m`` for the axes the data read (``model_readings``)."""
    reading, meas, _ = model_readings(model, df, meta, where)
    read = [k for k in range(3) if (meas.group[:, k] >= 0).any()]
    return pd.DataFrame(reading[:, read], index=df.index,
                        columns=[READING_COLUMNS[k] for k in read])


def validation_error_p90(model: PhysicsModel, df: pd.DataFrame, meta: dict | None,
                         where: str = "data") -> float:
    """The 90th percentile of |reading - model's reading| (m) over every axis's validation
    readings (every reading when the data have no validation row), the zeros re-estimated on
    the calibration rows: the figure the papers and ``deltatwin fit`` report, in metres."""
    meas = measurements(df.reset_index(drop=True), meta, model.params, where)
    check_sensors(model.names, meas, where)
    pred = model.predict_path(meas)
    res = residuals(meas, pred, session_zeros(meas, pred)[0])
    rows = meas.val if meas.val.any() else np.ones(meas.n, bool)
    e = np.abs(res[rows])
    e = e[np.isfinite(e)]
    return float(np.percentile(e, 90)) if e.size else float("nan")
