"""Uncertainty budget of a fitted physics model, in the spirit of the GUM: the error at the tool
point (nm, 90 % over the workspace) contributed by each effect's parameter uncertainty and by
each noise source, propagated to first order through the model.

The workspace is the dataset's points (calibration and validation rows, with their recorded
conditions). Per point and axis a source gives a standard uncertainty u (m); its figure is the
90 % error of the mixture over the points, x with mean_points P(|N(0, u_point)| <= x) = 0.9, so a
source that matters only in a corner of the workspace counts as much as it covers.

* Parameters: the fit's covariance of its identified directions (sigma of the calibration
  residual, as the fit reports it) and, on the directions the data leave undetermined, the
  prior (one fit scale), J_e C_ee J_e^T per effect; the combined line uses the whole
  covariance (the effects' correlations included), so the effects' lines need not add up to it.
* Interferometer: the readings' standard deviation (the validation readings carry it).
* Thermometers: each sensor's reading uncertainty ``T_u_K`` through its lever (the model's
  prediction with that column shifted, a first-order difference), independent sensors.
* Pressure: the air's pressure at each reading ``pressure_u_Pa`` off the one at its session's
  zero (the air_refraction effect's index change times the dead path: what an unrecorded
  wander, or a barometer's noise, leaves; a constant offset of every reading and of the zero
  would only scale the displacement).
* Servo settling: each motor's settled angle off by ``servo_u_rad``, independent motors.
"""
from __future__ import annotations

import dataclasses

import numpy as np
import pandas as pd
from scipy import optimize, stats

from deltatwin.calibration.physics.fit import PhysicsFit
from deltatwin.calibration.physics.measurements import measurements
from deltatwin.calibration.physics.model import PhysicsModel, _projected
from deltatwin.twin.instruments.optics import AXES


def mixture_p90(u: np.ndarray) -> float:
    """x (same unit as ``u``) with mean over the entries of P(|N(0, u)| <= x) = 0.9 (the 90 %
    error over the workspace of errors with standard uncertainties ``u``)."""
    u = np.asarray(u, float)
    u = u[np.isfinite(u)]
    if u.size == 0 or not np.any(u > 0):
        return 0.0
    coverage = lambda x: float(np.mean(2 * stats.norm.cdf(x / np.maximum(u, 1e-300)) - 1)) - 0.9
    return float(optimize.brentq(coverage, 0.0, 10 * u.max(), xtol=1e-6 * u.max()))


def _figures(u: np.ndarray, read: np.ndarray) -> dict:
    """{axis: p90 nm, 'all': p90 nm} of standard uncertainties u (N,3) m on the read entries."""
    out = {a: mixture_p90(u[read[:, k], k]) * 1e9 for k, a in enumerate(AXES)
           if read[:, k].any()}
    out["all"] = mixture_p90(u[read]) * 1e9
    return out


def parameter_covariance(fit: PhysicsFit) -> np.ndarray:
    """(p, p) covariance (SI) of the fitted parameters: the fit's on its identified directions;
    on the directions the data cannot determine (held at their starting values), the prior's,
    one typical size (fit scale) per scaled unit."""
    meas, S, V = fit.measurements_, fit.model_.scales, fit.identified_directions_
    prior = np.eye(S.size) - V @ V.T                       # unidentified subspace (scaled)
    C = S[:, None] * prior * S[None, :]
    if V.shape[1]:
        Jz = _projected(meas, meas.cal, fit.jacobian_ * S) @ V
        sigma = fit.identifiability_["residual_sigma_nm"] * 1e-9
        SV = S[:, None] * V
        C = C + SV @ np.linalg.pinv(Jz.T @ Jz) @ SV.T * sigma ** 2
    return C


def _shifted(fit: PhysicsFit, df: pd.DataFrame, meta: dict, column: str, step: float,
             model: PhysicsModel | None = None) -> np.ndarray:
    """d prediction / d column (N,3) per unit of the column, by a first-order difference."""
    model = model or fit.model_
    base = model.predict_path(measurements(df, meta, model.params))
    moved = df.copy()
    moved[column] = moved[column] + step
    return (model.predict_path(measurements(moved, meta, model.params)) - base) / step


def uncertainty_budget(fit: PhysicsFit, df: pd.DataFrame, meta: dict, reading_u_m: float,
                       T_u_K: float, servo_u_rad: float, pressure_u_Pa: float,
                       per_sensor: bool = False) -> pd.DataFrame:
    """The budget table: one row per source (``kind``: parameters / noise), its standard
    uncertainty's 90 % figure over the workspace per axis and pooled (nm), and its share of the
    combined variance. ``df``/``meta``: the dataset ``fit`` was fitted to. ``per_sensor``: one
    thermometer row per sensor with a lever (``kind`` thermometer) besides their sum."""
    meas = fit.measurements_
    read = meas.group >= 0
    rows = []
    C = parameter_covariance(fit)
    J = fit.jacobian_
    for e in fit.model_.effects:
        cols = np.concatenate([np.arange(f.sl.start, f.sl.stop) for f in fit.model_.free
                               if f.effect == e.name] or [np.zeros(0, int)])
        if cols.size:
            Je = J[:, :, cols]
            var = np.einsum("naj,jk,nak->na", Je, C[np.ix_(cols, cols)], Je)
            rows.append(("parameters", f"{e.name} ({cols.size} parameters)", np.sqrt(var)))
    var_all = np.einsum("naj,jk,nak->na", J, C, J)
    noise = [("noise", "interferometer reading", np.full(read.shape, reading_u_m))]
    sensors = [c for c in df.columns if c.startswith("T_") and c.endswith("_C")]
    lever = {c: _shifted(fit, df, meta, c, 0.01) for c in sensors}
    used = [c for c in sensors if np.nanmax(np.abs(lever[c])) > 0]
    if used:
        u_T = np.sqrt(sum((lever[c] * T_u_K) ** 2 for c in used))
        noise.append(("noise", f"thermometers ({len(used)} with a lever, {T_u_K * 1e3:g} mK each)",
                      u_T))
    by_sensor = [("thermometer", f"{c} ({T_u_K * 1e3:g} mK)", np.abs(lever[c]) * T_u_K)
                 for c in used] if per_sensor else []
    servo = np.sqrt(sum((_shifted(fit, df, meta, f"q{i}_rad", 1e-6) * servo_u_rad) ** 2
                        for i in (1, 2, 3)))
    noise.append(("noise", f"servo settling ({servo_u_rad:g} rad per motor)", servo))
    air = PhysicsModel(list(dict.fromkeys(fit.effects + ["air_refraction"])), fit.model_.params,
                       fit.model_.values())
    base = air.predict_path(meas)
    pts = meas.points
    readings = np.arange(pts.t_s.size) < len(df)     # the zero rows follow the readings
    moved = air.predict_path(dataclasses.replace(meas, points=dataclasses.replace(
        pts, pressure_Pa=pts.pressure_Pa + pressure_u_Pa * readings)))
    noise.append(("noise", f"{'barometer' if 'p_Pa' in df else 'unrecorded pressure'} "
                  f"({pressure_u_Pa:g} Pa)", np.abs(moved - base)))
    combined = np.sqrt(var_all + sum(u ** 2 for _, _, u in noise))
    table = []
    total_var = float(np.nanmean(np.where(read, combined ** 2, np.nan)))
    for kind, name, u in rows + noise + by_sensor + [("combined", "all parameters (correlated) and noise",
                                          combined)]:
        f = _figures(np.where(read, u, np.nan), read)
        share = float(np.nanmean(np.where(read, u ** 2, np.nan))) / total_var
        table.append({"kind": kind, "source": name, **{f"{k}_p90_nm": v for k, v in f.items()},
                      "variance_share": share})
    return pd.DataFrame(table)
