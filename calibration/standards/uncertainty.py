"""Expanded uncertainty (k = 2) of the standards' figures from the instruments' specifications
and the environment, in the spirit of ISO/TR 230-9 ("Estimation of measurement uncertainty for
machine tool tests according to series ISO 230, basic equations": a budget of standard
uncertainties combined in quadrature, expanded with k = 2), and the conformance decision of
ISO 14253-1 (the acceptance zone is the tolerance zone reduced by the expanded uncertainty, the
guard band; a value between T - U and T + U proves neither conformance nor nonconformance).

The budget of one interferometer reading at a distance L from its zero (m):

* resolution: q / sqrt(12) for the reading and again for the zero;
* noise: the reading's standard deviation (the air turbulence of ``noise_floor_m``) over the
  readings averaged, and the zero's (a laboratory's zero is a reading; the twin's simulated
  interferometers zero on the true path, twin/instruments/simulated.py, so its zero has none);
* air refraction: L |dn/dT| u(T_air), L |dn/dp| u(p), L |dn/de| u(e) (the index's sensitivities
  from the Edlén formula of ``twin.instruments.optics.air_index``, by central differences): the
  air's temperature, pressure and water vapour the correction does not know;
* cosine/Abbe: a beam misaligned by theta (at most) reads L (1 - cos theta) short: L theta^2 / 2
  as a rectangular bound (/ sqrt(3)); an Abbe offset d times the tilt's uncertainty;
* dead path: the beam between head and zero position, D, sees the index change the reading does
  not correct: D times the index's uncertainty;
* material temperature: the robot's titanium at a temperature known to u(T) and a CTE known to
  u(alpha), dT away from 20 degC: L sqrt((alpha u(T))^2 + (u(alpha) dT)^2).

How a figure takes it (``expanded``): a position figure (a mean deviation, x̄, E, M, A, AP and
its parts, ETVE, drift) the whole budget at its largest L, the noise over the readings it
averages; a difference at one position (B) only the random part of two means; a repeatability
figure (s, R, RP) the instrument's own repeatability u_rep = sqrt(noise^2 + q^2 / 12) times the
figure's multiplier (R: 4, RP: rp_gaussian's), the part of the figure the instrument may
account for.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace

from deltatwin.twin.instruments.optics import air_index

SOURCES = ("resolution", "noise", "air refraction", "cosine/Abbe", "dead path",
           "material temperature")
K = 2.0


def index_sensitivities(T_C: float = 20.0, p_Pa: float = 101325.0, e_Pa: float = 1000.0):
    """(dn/dT per K, dn/dp per Pa, dn/de per Pa) of air at the given state (Edlén, central
    differences)."""
    def d(f, h):
        return float((f(h) - f(-h)) / (2 * h))
    return (d(lambda h: air_index(T_C + h, p_Pa, e_Pa), 0.01),
            d(lambda h: air_index(T_C, p_Pa + h, e_Pa), 1.0),
            d(lambda h: air_index(T_C, p_Pa, e_Pa + h), 1.0))


@dataclass(frozen=True)
class MeasurementSpec:
    """The measuring chain of one axis (SI; standard uncertainties unless named a bound)."""
    resolution_m: float = 1.24e-9
    noise_m: float = 5e-9
    zero_noise_m: float = 5e-9            # the zero is a reading too (the twin's: exact, 0)
    air_T_u_C: float = 0.01
    pressure_u_Pa: float = 10.0
    vapour_u_Pa: float = 50.0
    misalignment_rad: float = 1e-4        # bound on the beam-to-axis angle
    abbe_offset_m: float = 1e-3
    tilt_u_rad: float = 1e-7
    dead_path_m: float = 0.2
    cte_per_K: float = 8.6e-6             # titanium (the robot's parts)
    cte_u_per_K: float = 0.5e-6
    material_T_u_C: float = 0.01
    material_dT_K: float = 0.5            # departure of the robot from 20 degC

    def budget(self, length_m: float, readings: int = 1) -> dict:
        """Standard uncertainties (m) per source of a deviation at ``length_m`` from the zero,
        the mean of ``readings`` readings."""
        L = abs(float(length_m))
        dT, dp, de = index_sensitivities()
        u_index = math.sqrt((dT * self.air_T_u_C) ** 2 + (dp * self.pressure_u_Pa) ** 2
                            + (de * self.vapour_u_Pa) ** 2)
        return {"resolution": self.resolution_m / math.sqrt(12) * math.sqrt(2),
                "noise": math.hypot(self.noise_m / math.sqrt(readings), self.zero_noise_m),
                "air refraction": L * u_index,
                "cosine/Abbe": math.hypot(L * self.misalignment_rad ** 2 / (2 * math.sqrt(3)),
                                          self.abbe_offset_m * self.tilt_u_rad),
                "dead path": self.dead_path_m * u_index,
                "material temperature": L * math.hypot(self.cte_per_K * self.material_T_u_C,
                                                       self.cte_u_per_K * self.material_dT_K)}

    def to_dict(self) -> dict:
        return asdict(self)


def combine(budget: dict) -> float:
    """Expanded uncertainty U = k sqrt(sum u^2), k = 2 (m)."""
    return K * math.sqrt(sum(u * u for u in budget.values()))


def expanded(spec: MeasurementSpec, kind: str, length_m: float = 0.0, readings: int = 1,
             multiplier: float = 4.0) -> tuple[float, dict]:
    """(U m, the budget of standard uncertainties m) of a figure of ``kind``: "position" (at
    ``length_m`` from the zero, means of ``readings``), "difference" (two means of
    ``readings`` at one position: resolution and noise only) or "repeatability" (the
    instrument's repeatability times ``multiplier``)."""
    b = spec.budget(length_m, readings)
    if kind == "position":
        return combine(b), b
    if kind == "difference":
        rand = {"resolution": b["resolution"],
                "noise": spec.noise_m * math.sqrt(2 / readings)}
        return combine(rand), rand
    if kind == "repeatability":
        rep = {"resolution": multiplier * spec.resolution_m / math.sqrt(12),
               "noise": multiplier * spec.noise_m}
        return combine(rep) / K, rep          # the instrument's share, already a bound
    raise ValueError(f"uncertainty kind {kind!r}: expected position, difference or "
                     "repeatability")


def conformance(value: float, U: float, tolerance: float) -> str:
    """ISO 14253-1 decision for a figure that must not exceed ``tolerance``: "conforms" when
    value <= T - U (inside the acceptance zone), "does not conform" when value > T + U,
    "inconclusive" between (the guard band)."""
    if value <= tolerance - U:
        return "conforms"
    if value > tolerance + U:
        return "does not conform"
    return "inconclusive"


def spec_from_scenario(sc, axis: str) -> MeasurementSpec:
    """The measuring chain of ``axis`` in a scenario's laboratory: its interferometers'
    resolution and noise, its thermometers' for the air and the material, its air's wander
    (the barometer's and hygrometer's noise where it records them), the nominal dead path, the
    autocollimators' noise for the tilt. A source the scenario's world lacks is left out: the
    air where its index does not move (no air_refraction), the material where nothing expands
    (no thermal_expansion), the beam's misalignment where the beams are aligned (no
    beam_misalignment); the twin's interferometers zero on the true path (no zero noise)."""
    s = sc.settings
    names = {e.name for e in sc.effects}
    wander = sc.air_wander()
    u_T = math.hypot(s.T_noise_C, s.T_resolution_C / math.sqrt(12))
    air = "air_refraction" in names
    spec = MeasurementSpec(resolution_m=s.resolution_m, noise_m=s.noise_floor_m,
                           zero_noise_m=0.0, air_T_u_C=u_T if air else 0.0,
                           pressure_u_Pa=wander["pressure_Pa"][0],
                           vapour_u_Pa=wander["vapour_Pa"][0], material_T_u_C=u_T,
                           dead_path_m=sc.dead_path()[axis], tilt_u_rad=s.ac_noise_rad)
    changes = {}
    if "thermal_expansion" not in names:
        changes.update(material_T_u_C=0.0, material_dT_K=0.0)
    if "beam_misalignment" not in names:
        changes.update(misalignment_rad=0.0)
    return replace(spec, **changes)
