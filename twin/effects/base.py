"""What a physical effect is: a name, documented parameters with units and defaults, and the
stages of the twin it changes.

The twin evaluates a campaign in stages (twin/world.py): the robot's parameters, the thermal
network's inputs, the part temperatures that scale the geometry, the wrench on the platform,
the instruments' optics. An effect overrides the hooks of the stages it changes and nothing
else; an effect that is off is simply absent, and every stage then keeps its ideal value
(parts at the reference temperature, no load, beams on their nominal lines, vacuum-like air
index constant). Adding an effect = one module in twin/effects/ + one line in LIBRARY, or a
researcher's own file / package (twin/effects/__init__.py, docs/effects.md).

The same effect is also a term of a physics model fitted to measurements (calibration/physics/):
there the stages that act on the robot (``robot``, ``part_temperatures``, ``wrench``, ``optics``)
and the sensors' reading of the parts (``sensed_parts``) are evaluated on conditions taken from
the data (sensor temperatures, motor coordinates, coil
currents) with ``rng=None`` (nothing random), and the parameters declared with a ``fit_scale``
are the ones a fit adjusts, starting from ``fit_start`` (the effect's "not yet known" value, e.g.
zero misalignment) or the default. Effects that only act through the thermal network
(``environment``, ``heat_sources``) have no model form: in measurements their consequences
arrive through the temperature sensors.
"""
from __future__ import annotations

import difflib
from dataclasses import dataclass
from typing import ClassVar, NamedTuple

import numpy as np

# no effect parameter of this robot exceeds this in its SI unit (elastic moduli ~1e11 Pa, times
# ~1e9 s): a bigger value is a typing or unit mistake, and would overflow the models
MAX_ABS_SI = 1e15


def _numbers_only(raw) -> bool:
    """Whether ``raw`` is a number or (nested) sequence of numbers; text and booleans are not."""
    if isinstance(raw, (list, tuple)):
        return all(_numbers_only(x) for x in raw)
    if isinstance(raw, np.ndarray):
        return raw.dtype.kind in "iuf"
    return isinstance(raw, (int, float, np.integer, np.floating)) and not isinstance(raw, bool)


class EffectError(ValueError):
    """An unknown effect or a bad effect parameter."""


class WrenchDerivatives(NamedTuple):
    """An effect's exact wrench derivatives (``Effect.wrench_derivatives``), N and N*m per unit
    of what they are taken in. ``parameters``: by free parameter name, (N,6) + the parameter's
    shape (a parameter not named is differenced); ``pose``: (N,6,9) in the kinematic pose's
    position (m), a rotation vector applied on its rotation (rad, world frame: R -> exp(w) R)
    and the robot's home (m), or None (differenced)."""
    parameters: dict
    pose: np.ndarray | None


@dataclass(frozen=True)
class Parameter:
    name: str
    unit: str
    default: float | tuple
    doc: str
    minimum: float | None = None   # inclusive bound checked on every element
    fit_scale: float | None = None  # typical size (unit as above) when a fit adjusts it
    fit_start: float | tuple | None = None  # a fit's starting value (default: ``default``)
    # the prediction is linear in it, a coefficient of a measured temperature (an expansion
    # coefficient): its Jacobian column is made of the thermometers' readings, so a fit
    # corrects its estimate for their noise (calibration/physics/thermometers.py)
    per_kelvin: bool = False
    # the prior's width: one standard deviation of where a laboratory's value may lie about the
    # default (unit as above), where the physics spreads wider than ``fit_scale`` (a part of a
    # material the library cannot know); a fit holding the parameter at its prior counts this
    # as its uncertainty there (calibration/physics/fit.py, the consider covariance)
    prior_tolerance: float | None = None

    @property
    def shape(self) -> tuple:
        return np.shape(self.default)

    @property
    def tolerance(self) -> float | None:
        """The prior's width (``prior_tolerance``, else the ``fit_scale``)."""
        return self.fit_scale if self.prior_tolerance is None else self.prior_tolerance


def shift_reading(optics, axis: str, d_m: np.ndarray) -> None:
    """In an ``optics`` hook: add ``d_m`` (N,) m to what the interferometer of ``axis`` reads
    (its head moves back along its beam, lengthening the path it counts): the simplest way to
    write a term found in the residual of a reading."""
    optics.head[axis] = optics.head[axis] - np.asarray(d_m, dtype=np.float64)[:, None] \
        * optics.direction[axis]


MODEL_STAGES = ("robot", "sensed_parts", "part_temperatures", "motor_angles", "wrench", "optics")


class Effect:
    """Base class of the physical effects. Subclasses declare ``name``, ``summary`` and
    ``parameters`` and override the hooks they need (see twin/world.py for the stages)."""
    name: ClassVar[str]
    summary: ClassVar[str]
    parameters: ClassVar[tuple[Parameter, ...]] = ()
    # its model form reads part or air temperatures (in measurements: the data's sensors)
    reads_temperatures: ClassVar[bool] = False

    def __init__(self, where: str = "effect", check_minimum: bool = True, **values):
        known = {p.name: p for p in self.parameters}
        for key in values:
            if key not in known:
                close = difflib.get_close_matches(key, known, n=1)
                hint = f" (did you mean {close[0]!r}?)" if close else ""
                raise EffectError(f"{where}: unknown parameter {key!r} of effect {self.name!r}"
                                  f"{hint}; parameters: {sorted(known)}")
        self.values = {}
        for p in self.parameters:
            raw = values.get(p.name, p.default)
            try:
                if not _numbers_only(raw):      # np.asarray would read "2e-5" or true as numbers
                    raise TypeError
                v = np.asarray(raw, dtype=np.float64)
            except (TypeError, ValueError):
                raise EffectError(f"{where}.{p.name}: expected a number ({p.unit}), got {raw!r}") from None
            if v.shape != p.shape:
                raise EffectError(f"{where}.{p.name}: expected shape {p.shape} ({p.unit}), "
                                  f"got {v.shape}")
            if not np.all(np.isfinite(v)):
                raise EffectError(f"{where}.{p.name}: not a finite number: {raw!r}")
            if np.any(np.abs(v) > MAX_ABS_SI):
                raise EffectError(f"{where}.{p.name} = {raw!r} {p.unit}: |value| above {MAX_ABS_SI:g}"
                                  " is no physical value of this robot in SI units")
            if check_minimum and p.minimum is not None and np.any(v < p.minimum):
                raise EffectError(f"{where}.{p.name} = {raw!r} {p.unit}: must be >= {p.minimum}")
            self.values[p.name] = float(v) if v.ndim == 0 else v
        for k, v in self.values.items():
            setattr(self, k, v)

    @classmethod
    def model_stages(cls) -> tuple[str, ...]:
        """The stages this effect changes that a model fitted to measurements can evaluate."""
        return tuple(h for h in MODEL_STAGES if getattr(cls, h) is not getattr(Effect, h))

    @classmethod
    def free_parameters(cls) -> tuple[Parameter, ...]:
        """The parameters a physics fit adjusts."""
        return tuple(p for p in cls.parameters if p.fit_scale is not None)

    # -- stage hooks (twin/world.py calls them in this order) ---------------------------------
    def robot(self, params, rng):
        """Robot parameters (RobotParams) -> changed parameters (geometric errors); ``rng`` is
        None in a model fitted to measurements (no random draw)."""
        return params

    def environment(self, env, rng) -> None:
        """Change the laboratory's environment on the thermal grid in place (twin.thermal.Inputs:
        room air, support temperatures, pressure); campaign-independent."""

    def heat_sources(self, t_grid, schedule, params) -> dict:
        """Heat powers (W) by network node on the grid times, from what the campaign did
        (``schedule``: moves and coil currents, twin/world.py)."""
        return {}

    def motor_settling(self, rng, n: int) -> np.ndarray | None:
        """Motor angle errors (n,3) rad where the position controller settles after each of n
        settling events (a move, a change of the load), drawn from ``rng``; the encoders still
        read the commanded angles. None: the motors sit at their commanded angles."""
        return None

    def thermometers(self, sensors: tuple) -> tuple:
        """The thermal network's sensors (twin.thermal.Sensor: how each is coupled to its part
        and to the air; ideal without an effect) -> changed sensors."""
        return sensors

    def sensed_parts(self, points) -> dict | None:
        """Model side only: the temperature (degC) of the part under each sensor, by sensor
        name, from the sensors' smoothed readings and rates (``points.sensor_readings``), or
        None (the part is taken at its sensor's reading)."""
        return None

    def part_temperatures(self, points) -> dict | None:
        """Per-point part temperatures (degC) that scale the geometry, or None."""
        return None

    def motor_angles(self, points) -> np.ndarray | None:
        """(N,3) rad by which each motor's true angle differs from what its encoder reads at
        the points (``points.q``; an encoder's periodic or scale error, a backlash that follows
        ``points.move_direction``), or None. Deterministic: the same in the twin and a model."""
        return None

    def wrench(self, points) -> np.ndarray | None:
        """Wrench (N,6) on the platform (N at the platform origin, N*m), world frame."""
        return None

    def wrench_derivatives(self, points) -> WrenchDerivatives | None:
        """Model side, optional: the wrench's exact derivatives at the current values and
        ``points.pose`` (``WrenchDerivatives``), or None: the physics model then differences
        ``wrench`` (a Richardson stencil per parameter, with halvings where it is nonlinear,
        and central differences in the pose). Written with a test against central
        differences of ``wrench``."""
        return None

    def optics(self, points, optics) -> None:
        """Change the instruments' optics in place (beam origins/directions, air index)."""

    def outside_range(self) -> list[str]:
        """Parameters below their physical minimum (a fitted value can be; a scenario's not)."""
        return [p.name for p in self.parameters
                if p.minimum is not None and np.any(np.asarray(self.values[p.name]) < p.minimum)]

    def describe(self) -> dict:
        return {"name": self.name, "summary": self.summary,
                "parameters": {p.name: {"unit": p.unit, "default": p.default, "doc": p.doc,
                                        "value": np.asarray(self.values[p.name]).tolist()}
                               for p in self.parameters}}
