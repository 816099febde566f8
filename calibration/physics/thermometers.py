"""The thermometers' noise in the variables of a physics fit.

A parameter that multiplies a temperature (an expansion coefficient, a loop's drift per kelvin)
has a Jacobian column made of the thermometers' readings, and their noise is in it: the column
seems to hold information it does not (a 0.6 m frame arm's expansion column gains 47 nm beyond
the others from 3 mK thermometers, 1.7 nm without them, where the fit's threshold is 17 nm),
and least squares attenuates the coefficient towards zero (errors in the variables). Both are
estimated here by drawing the noise afresh, as the laboratory's instruments state it, and
taking the change it makes to the model's prediction and Jacobian; the fit
(calibration/physics/fit.py) chooses its determined directions on the information beyond the
thermometers' and corrects its score by their share (Fuller 1987; Nakamura 1990, the corrected
score).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import linalg

from deltatwin.calibration.errors import FitError
from deltatwin.calibration.physics.measurements import (
    TEMPERATURE_WINDOW_S,
    Measurements,
    data_sha256,
    thermometer_draw,
    with_sensor_streams,
)
from deltatwin.calibration.physics.model import PhysicsModel, projected
from deltatwin.calibration.streams import causal_weights
from deltatwin.twin.noise import quantised_u

# draws of the thermometers' noise that estimate what it alone gives the fit
THERMOMETER_DRAWS = 4
# the correction is made in the directions where the thermometers' noise is less than this
# share of the information: there it amplifies the estimate's noise by at most
# 1 / (1 - share) = 2 (a method-of-moments correction has no finite moments where the share
# nears 1)
MAX_NOISE_SHARE = 0.5
# estimates kept in the process (oldest dropped first), each (p, p) and (p,): a few kB; the
# key holds the data's fingerprint
KEPT = 32
_KEPT: dict = {}


def thermometer_u_K(meta: dict | None) -> float:
    """The thermometers' standard uncertainty per scan (K): noise and resolution from the
    data's instrument specifications (``meta["instruments"]``: ``T_noise_C``,
    ``T_resolution_C``), else the papers' PT100 scanner's (the twin's defaults)."""
    from deltatwin.twin.instruments.simulated import InstrumentSettings

    spec = (meta or {}).get("instruments") or {}
    default = InstrumentSettings()
    noise = spec.get("T_noise_C", default.T_noise_C)
    step = spec.get("T_resolution_C", default.T_resolution_C)
    for name, v in (("T_noise_C", noise), ("T_resolution_C", step)):
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0 <= v < 1:
            raise FitError(f"metadata 'instruments' {name!r} = {v!r}: expected kelvin, 0 to 1")
    return quantised_u(float(noise), float(step))


@dataclass(frozen=True)
class ThermometerNoise:
    """What the thermometers' noise puts into a fit, in the scaled calibration residual
    (``projected``, m) and its Jacobian (m per fit scale), N the change of the Jacobian and dA
    that of the prediction when every reading gets a fresh draw of the noise:
    ``information`` (p, p) E[N^T N] (m^2 per scale^2) and ``score`` (p,) E[N^T dA] (m^2 per
    scale), the latter at the parameters ``t_ref`` (p,, fit scales)."""

    information: np.ndarray
    score: np.ndarray
    t_ref: np.ndarray
    per_kelvin: np.ndarray         # (p,) bool: the coefficients of temperatures (Parameter)

    @classmethod
    def none(cls, p: int) -> ThermometerNoise:
        return cls(np.zeros((p, p)), np.zeros(p), np.zeros(p), np.zeros(p, bool))

    def __bool__(self) -> bool:
        return bool(np.any(self.information))

    def restricted(self, V: np.ndarray, Jz: np.ndarray,
                   max_share: float = MAX_NOISE_SHARE) -> ThermometerNoise:
        """The share of this noise a fit corrects for: that of the coefficients of
        temperatures (``per_kelvin``: the prediction is linear in them, so the score's noise
        share is linear in them too; a parameter that changes the temperatures themselves, a
        sensor's contact, is not corrected), in the directions ``V`` (p, k) where it is less
        than ``max_share`` of the information Jz^T Jz (``Jz`` (n, k) the scaled calibration
        Jacobian in them, m per fit scale): the generalised eigenvectors X of
        (V^T C V) x = mu (Jz^T Jz) x (X^T Jz^T Jz X = 1) with mu < max_share, their share
        G X X^T G (V^T C V) and G X X^T V^T score (G = Jz^T Jz) mapped back by V."""
        if not self or not V.shape[1]:
            return self
        lin = self.per_kelvin
        C = np.where(lin[:, None] & lin[None, :], self.information, 0.0)
        G = Jz.T @ Jz
        mu, X = linalg.eigh(V.T @ C @ V, G)
        kept = X[:, mu < max_share]
        share = G @ kept @ kept.T                                      # (k, k) projector
        return ThermometerNoise(V @ share @ (V.T @ C @ V) @ V.T,
                                V @ share @ (V.T @ np.where(lin, self.score, 0.0)),
                                self.t_ref, lin)

    def terms(self, V: np.ndarray, t: np.ndarray, unit: float = 1.0):
        """(C_z, g) in the directions ``V`` (p, k) at the parameters ``t`` (p,, fit scales),
        in m^2 times ``unit`` squared: the thermometers' share of the information, V^T C V,
        and of the score, V^T (score + C (t - t_ref)) (the score is linear in the parameters
        that multiply temperatures, which is what the noise changes). None without noise."""
        if not self or not V.shape[1]:
            return None
        g = self.score + self.information @ (t - self.t_ref)
        return V.T @ self.information @ V * unit ** 2, V.T @ g * unit ** 2


def thermometer_noise(model: PhysicsModel, meas: Measurements, meta: dict | None,
                      theta: np.ndarray, seed: int, at: tuple | None = None) -> ThermometerNoise:
    """The ThermometerNoise of ``model`` on ``meas`` at the parameters ``theta`` (``at``: the
    model's (prediction, Jacobian) there, if at hand), from THERMOMETER_DRAWS draws seeded
    ``seed`` of noise of the size ``thermometer_u_K`` gives; none for a model that reads no
    temperature. The columns and the prediction's change hold the temperatures times a
    geometry that the parameters move by parts per million, so one estimate serves every
    start of the same effects on the same data: kept for the process, keyed by the data's
    fingerprint, the parameters, ``theta`` and ``seed``."""
    p = model.n_free
    columns = np.zeros(p, bool)
    for f in model.free:
        columns[f.sl] = next(e for e in model.effects if e.name == f.effect).reads_temperatures
    u = thermometer_u_K(meta)
    if not columns.any() or u <= 0 or not meas.sensors:
        return ThermometerNoise.none(p)
    fingerprint = data_sha256(meas)
    key = (fingerprint, tuple(model.labels), theta.tobytes(), u, int(seed), repr(model.params))
    if fingerprint is not None and key in _KEPT:
        return _KEPT[key]
    A, J = at if at is not None else model.jacobian(meas, theta, columns)
    base = np.where(columns, J, 0.0)
    rng = np.random.default_rng(seed)
    information, score = np.zeros((p, p)), np.zeros(p)
    for _ in range(THERMOMETER_DRAWS):
        noisy = thermometer_draw(meas, meta, model.params, rng, u)
        A_noisy, J_noisy = model.jacobian(noisy, theta, columns)
        N = projected(meas, meas.cal, J_noisy - base, scale=model.scales)
        information += N.T @ N / THERMOMETER_DRAWS
        score += N.T @ projected(meas, meas.cal, A_noisy - A) / THERMOMETER_DRAWS
    per_kelvin = np.zeros(p, bool)
    for f in model.free:
        cls = type(next(e for e in model.effects if e.name == f.effect))
        per_kelvin[f.sl] = next(q for q in cls.parameters if q.name == f.name).per_kelvin
    for a in (information, score, per_kelvin):
        a.flags.writeable = False           # kept and shared: never changed in place
    out = ThermometerNoise(information, score, theta / model.scales, per_kelvin)
    if fingerprint is not None:
        while len(_KEPT) >= KEPT:
            _KEPT.pop(next(iter(_KEPT)))
        _KEPT[key] = out
    return out


# the steps of the temperature levels (K) and rates (K/s) that measure the prediction's lever
# on them: the prediction is linear in both to parts per million (an expansion coefficient
# times a temperature), so the size only has to stand well above the float64 rounding
LEVEL_STEP_K, RATE_STEP_K_S = 0.01, 1e-5


def thermometer_covariance(model: PhysicsModel, meas: Measurements, meta: dict | None,
                           theta: np.ndarray, response: np.ndarray) -> np.ndarray:
    """(k, k) the covariance the thermometers' noise gives a fit's coordinates in its
    identified directions, propagated exactly to first order (GUM, law of propagation): each
    sensor's reading noise (``thermometer_u_K``, independent between scans; rows that read the
    same scan share it) passes linearly through the causal smoothing into the temperature
    levels and rates (``causal_weights``), from them through the model's lever on each row's
    reading (``LEVEL_STEP_K``, ``RATE_STEP_K_S``) into the calibration residual, and from it
    into the coordinates through the fit's estimating equations (``response`` (N,3,k),
    model.py ``reading_response``). A noise that moves the
    readings slowly enters the parameters and hardly the residual: what the residual's sandwich
    cannot see. Zeros without temperature-reading effects or sensors."""
    k = response.shape[2]
    u = thermometer_u_K(meta)
    reads = any(e.reads_temperatures for e in model.effects)
    if not k or not reads or u <= 0 or not meas.sensors:
        return np.zeros((k, k))
    order, scan = _scans(meas)
    level_map, rate_map = causal_weights(meas.points.t_s[:meas.n][order],
                                         TEMPERATURE_WINDOW_S, degree=1)
    base = model.predict_path(meas, theta)
    streams = meas.points.sensor_readings
    cov = np.zeros((k, k))
    for s, (part, level, rate) in streams.items():
        to_raw = np.zeros((meas.n, k))
        for which, (step, smoothing) in enumerate(((LEVEL_STEP_K, level_map),
                                                   (RATE_STEP_K_S, rate_map))):
            moved = [level, rate]
            moved[which] = moved[which] + step * (np.arange(level.size) < meas.n)
            lever = (model.predict_path(with_sensor_streams(
                meas, {**streams, s: (part, *moved)}), theta) - base) / step      # (N,3)
            weights = np.einsum("na,nak->nk", np.nan_to_num(lever), response)
            to_raw[order] += smoothing.T @ weights[order]
        per_scan = np.zeros((scan.max() + 1, k))
        np.add.at(per_scan, scan, to_raw)
        cov += per_scan.T @ per_scan
    return u ** 2 * cov


def _scans(meas: Measurements) -> tuple[np.ndarray, np.ndarray]:
    """(order, scan): the rows in time order (N,), and each row's scan index (N,): rows that
    follow each other in time with every sensor's reading the same read one scan (a scanner
    slower than the points), whose noise they share."""
    order = np.argsort(meas.points.t_s[:meas.n], kind="stable")
    T = meas.df[[f"T_{s}_C" for s in meas.sensors]].to_numpy(dtype=np.float64)[order]
    new = np.concatenate([[True], np.any(T[1:] != T[:-1], axis=1)])
    scan = np.empty(meas.n, dtype=np.int64)
    scan[order] = np.cumsum(new) - 1
    return order, scan
