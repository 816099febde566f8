"""ISO 230-3 environmental temperature variation error (ETVE) test, and the drift's relation
to the room's temperature.

As the standard describes the test (ISO 230-3:2020, "Test code for machine tools - Part 3:
Determination of thermal effects", clause 5; its public summary in the AFNOR catalogue,
boutique.afnor.org, ISO 230-3:2020: the ETVE test, the drift test procedure of ISO/TR 16015,
A.4.2): the machine stands at rest at one position while the relative displacement between
tool and workpiece side is recorded in each sensitive direction, together with the
environment's temperature, over a period long enough to show the environment's cycle (a
day, say). The figures:

* ETVE per direction: the largest range of the displacement over the test,
  max_t d(t) - min_t d(t);
* the drift over the test: d(end) - d(start);
* the environment's temperature range over the test, max T - min T, per sensor;
* the relation to the temperature (not defined by the standard; what a robot maker asks): the
  least-squares slope b of d = a + b T_ref over the test (m/K, reported in nm/K) with its
  standard error from the residuals, and the residuals' rms (what the straight line leaves:
  the lag of the structure behind the room shows as a loop).

Units: m, s, degC (K for differences); the summary prints nm, h and nm/K.
"""
from __future__ import annotations

import json
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class DirectionFigures:
    """One direction's figures (m, m/K)."""
    axis: str
    etve: float
    drift: float
    slope_m_per_K: float
    slope_std_m_per_K: float
    residual_rms: float

    def figures(self) -> dict:
        return {"ETVE_nm": self.etve * 1e9, "drift_nm": self.drift * 1e9,
                "slope_nm_per_K": self.slope_m_per_K * 1e9,
                "slope_std_nm_per_K": self.slope_std_m_per_K * 1e9,
                "residual_rms_nm": self.residual_rms * 1e9}


@dataclass(frozen=True)
class EtveResult:
    """The ETVE test's figures: per direction, the temperature ranges, the duration."""
    duration_s: float
    n: int
    reference_sensor: str
    temperature_range_K: dict
    directions: tuple[DirectionFigures, ...]

    def to_json(self) -> str:
        doc = {"standard": "ISO 230-3 ETVE", "duration_h": self.duration_s / 3600.0,
               "n": self.n, "reference_sensor": self.reference_sensor,
               "temperature_range_K": self.temperature_range_K,
               "directions": {d.axis: d.figures() for d in self.directions}}
        return json.dumps(doc, allow_nan=False)

    def summary(self) -> str:
        ref = self.temperature_range_K[self.reference_sensor]
        lines = [f"ISO 230-3 ETVE over {self.duration_s / 3600.0:.2f} h ({self.n} readings); "
                 f"{self.reference_sensor} range {ref * 1e3:.1f} mK",
                 f"{'axis':>5} {'ETVE nm':>10} {'drift nm':>10} {'nm/K':>10} {'+-':>8} "
                 f"{'resid. rms nm':>14}"]
        for d in self.directions:
            f = d.figures()
            lines.append(f"{d.axis:>5} {f['ETVE_nm']:10.1f} {f['drift_nm']:10.1f} "
                         f"{f['slope_nm_per_K']:10.1f} {f['slope_std_nm_per_K']:8.1f} "
                         f"{f['residual_rms_nm']:14.1f}")
        return "\n".join(lines)


def temperature_slope(d_m, T_C) -> tuple[float, float, float]:
    """(slope m/K, its standard error, residual rms m) of the straight line d = a + b T."""
    d = np.asarray(d_m, dtype=np.float64)
    T = np.asarray(T_C, dtype=np.float64)
    X = np.column_stack([np.ones_like(T), T - T.mean()])
    coef, *_ = np.linalg.lstsq(X, d, rcond=None)
    res = d - X @ coef
    dof = max(d.size - 2, 1)
    sxx = float(np.sum((T - T.mean()) ** 2))
    se = float(np.sqrt(np.sum(res ** 2) / dof / sxx)) if sxx > 0 else float("inf")
    return float(coef[1]), se, float(np.sqrt(np.mean(res ** 2)))


def evaluate(t_s, displacement_m: dict, temperatures_C: dict, reference: str) -> EtveResult:
    """ETVE figures from readings at rest: ``t_s`` (n,), ``displacement_m`` {axis: (n,)} (m),
    ``temperatures_C`` {sensor: (n,)}; ``reference`` the sensor the slope is taken against
    (the room's air by the robot, say)."""
    t = np.asarray(t_s, dtype=np.float64)
    if t.ndim != 1 or t.size < 3 or np.any(np.diff(t) <= 0):
        raise ValueError("ISO 230-3: at least 3 readings at increasing times are needed")
    if reference not in temperatures_C:
        raise ValueError(f"ISO 230-3: reference sensor {reference!r} not among "
                         f"{sorted(temperatures_C)}")
    temps = {}
    for name, T in temperatures_C.items():
        T = np.asarray(T, dtype=np.float64)
        if T.shape != t.shape or not np.all(np.isfinite(T)):
            raise ValueError(f"ISO 230-3: temperatures of {name!r} must be {t.size} finite values")
        temps[name] = T
    dirs = []
    for axis, d in displacement_m.items():
        d = np.asarray(d, dtype=np.float64)
        if d.shape != t.shape or not np.all(np.isfinite(d)):
            raise ValueError(f"ISO 230-3: displacements along {axis} must be {t.size} finite "
                             "values")
        slope, se, rms = temperature_slope(d, temps[reference])
        dirs.append(DirectionFigures(axis, float(np.ptp(d)), float(d[-1] - d[0]), slope, se, rms))
    return EtveResult(float(t[-1] - t[0]), t.size, reference,
                      {k: float(np.ptp(v)) for k, v in temps.items()}, tuple(dirs))
