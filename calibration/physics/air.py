"""The air's wander in the readings of a physics fit.

An interferometer counts wavelengths in the air: where the air's pressure (and water vapour)
moves between a session's zero and a reading and the laboratory does not record it, the
reading moves with it by the index change over the beam's dead path and displacement (~0.27
ppm per 100 Pa). A wander over a day looks, over a session of hours, like a slow drift, which
a fit's temperature and drift parameters take up: it enters the parameters and hardly the
residual. Here the laboratory's statement of its air (the data's instrument specifications)
is propagated exactly, to first order, into a fit's parameter covariance.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from deltatwin.calibration.errors import FitError
from deltatwin.calibration.physics.measurements import Measurements
from deltatwin.calibration.physics.model import PhysicsModel
from deltatwin.calibration.stats import exponential_kernel_sums
from deltatwin.twin.lab_setup import AIR_SPECS, INSTRUMENT_SPECS

STEP_PA = 100.0          # the lever's step: the index is linear in both fields to ~1e-5


def stated_air(meta: dict | None, df) -> dict:
    """{"pressure_Pa": (std Pa, correlation time s), "vapour_Pa": (...)}: the air a reading
    sees against its session's zero, as the data's instrument specifications state it
    (``meta["instruments"]``, twin/lab_setup.py ``AIR_SPECS``: the field's standard deviation
    and its correlation time, 0 for a record's white noise); what
    they do not state is the papers' laboratory's (twin.scenario ``air_wander`` with the
    instrument defaults: the room's wander where the data record no pressure or humidity, the
    record's noise, white, where they do)."""
    from deltatwin.twin.instruments.simulated import InstrumentSettings
    from deltatwin.twin.scenario import air_wander

    spec = (meta or {}).get("instruments") or {}
    default = air_wander(InstrumentSettings(), None, "p_Pa" in df, "RH_pct" in df)
    out = {}
    for field, keys in AIR_SPECS.items():
        values = []
        for key, given in zip(keys, default[field]):
            v = spec.get(key, given)
            unit, largest = INSTRUMENT_SPECS[key]        # the ranges a setup file is held to
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0 <= v < largest:
                raise FitError(f"metadata 'instruments' {key!r} = {v!r}: expected a number in "
                               f"{unit}, 0 to {largest:g}")
            values.append(float(v))
        out[field] = tuple(values)
    return out


def air_levers(model: PhysicsModel, meas: Measurements, field: str
               ) -> tuple[np.ndarray, np.ndarray]:
    """((N,3), (N,3)) m per Pa: the change of each reading of ``model`` (at its values, with
    air_refraction added) with the air's ``field`` ("pressure_Pa" or "vapour_Pa") raised at
    that reading, and with it raised at its session's zero (first-order differences): the
    index change over each beam's dead path and displacement, at the reading and at the zero
    it is counted from."""
    air = PhysicsModel(list(dict.fromkeys(model.names + ["air_refraction"])),
                       model.params, model.values())
    pts = meas.points
    level = getattr(pts, field)
    if level is None:       # no humidity record: the model's air has the vapour it assumes
        level = np.full(pts.t_s.size, float(air.values()["air_refraction"]["vapour_pressure_Pa"]))
    at_readings = np.arange(pts.t_s.size) < meas.n
    predict = lambda v: air.predict_path(dataclasses.replace(
        meas, points=dataclasses.replace(pts, **{field: v})))
    base = predict(level)
    return tuple((predict(level + STEP_PA * at) - base) / STEP_PA
                 for at in (at_readings, ~at_readings))


def air_covariance(model: PhysicsModel, meas: Measurements, meta: dict | None,
                   response: np.ndarray) -> np.ndarray:
    """(k, k) the covariance the air's unrecorded wander (``stated_air``: a stationary
    Ornstein-Uhlenbeck process of that std and correlation time) gives a fit's coordinates in
    its identified directions: through each reading's and its zero's levers (``air_levers``)
    into the calibration residual and through the estimating equations (``response``
    (N,3,k), model.py ``reading_response``), exactly under
    the wander's covariance std^2 exp(-|dt| / time) (``exponential_kernel_sums``)."""
    k = response.shape[2]
    cov = np.zeros((k, k))
    if not k:
        return cov
    t = meas.points.t_s
    for field, (std, time_s) in stated_air(meta, meas.df).items():
        if std <= 0:
            continue
        row_lever, zero_lever = (np.nan_to_num(v) for v in air_levers(model, meas, field))
        at_times = np.zeros((t.size, k))
        at_times[:meas.n] = np.einsum("na,nak->nk", row_lever, response)
        np.add.at(at_times, meas.zero_row, np.einsum("na,nak->nk", zero_lever, response))
        cov += std ** 2 * at_times.T @ exponential_kernel_sums(t, at_times, time_s)
    return cov
