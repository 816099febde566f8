"""The library of physical effects: each a plug-in with a name, documented parameters (units,
defaults) and the stages of the twin it changes (see base.py). A scenario switches them on by
name; ``deltatwin effects`` lists them."""
from __future__ import annotations

import difflib

from deltatwin.twin.effects.air_refraction import AirRefraction
from deltatwin.twin.effects.base import Effect, EffectError, Parameter
from deltatwin.twin.effects.beam_misalignment import BeamMisalignment
from deltatwin.twin.effects.coil_heating import CoilHeating
from deltatwin.twin.effects.geometric_errors import GeometricErrors
from deltatwin.twin.effects.gravity_sag import GravitySag
from deltatwin.twin.effects.loop_drift import LoopDrift
from deltatwin.twin.effects.magnetic_force import MagneticForce
from deltatwin.twin.effects.motor_heating import MotorHeating
from deltatwin.twin.effects.peltier_supports import PeltierSupports
from deltatwin.twin.effects.room_climate import RoomClimate
from deltatwin.twin.effects.sensor_contact import SensorContact
from deltatwin.twin.effects.servo_settling import ServoSettling
from deltatwin.twin.effects.thermal_expansion import ThermalExpansion

LIBRARY: dict[str, type[Effect]] = {cls.name: cls for cls in (
    GeometricErrors, ThermalExpansion, GravitySag, MagneticForce, LoopDrift, AirRefraction,
    BeamMisalignment, SensorContact, ServoSettling, RoomClimate, PeltierSupports, MotorHeating, CoilHeating)}


def make_effect(name: str, values: dict | None = None, where: str = "effects",
                check_minimum: bool = True) -> Effect:
    """The effect ``name`` with parameter ``values`` (validated; a fitted model's values may be
    below a parameter's physical minimum with ``check_minimum=False``); errors name ``where``."""
    if name not in LIBRARY:
        close = difflib.get_close_matches(name, LIBRARY, n=1)
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        raise EffectError(f"{where}: unknown effect {name!r}{hint}; known: {sorted(LIBRARY)}")
    return LIBRARY[name](where=f"{where}.{name}", check_minimum=check_minimum, **(values or {}))


__all__ = ["LIBRARY", "Effect", "EffectError", "Parameter", "make_effect"]
