"""The common instrument interface: what a campaign may ask of the laboratory.

A campaign (twin/campaign.py) talks only to an ``InstrumentSet``. Two families implement it:
the twin's simulated instruments (twin/instruments/simulated.py), whose shared clock is
simulated, and the serial drivers in hw/, which talk to real instruments (or to the twin-backed
emulators) over pyserial. Every call blocks until it has an answer or its timeout expires.
Failures are exceptions that carry the instrument's name and its own reason (error code and
text when the instrument gives one), never silent NaNs; a reading outside an instrument's range
is reported as such in the reading, not clipped.

Units: SI (m, rad, s, degC for temperatures, A, Pa); relative humidity in % (its instruments'
own unit). Interferometer readings are relative to the instrument's zero.
"""
from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, field

import numpy as np

DEFAULT_TIMEOUT_S = 30.0


class InstrumentError(RuntimeError):
    """An instrument failed to do what was asked. ``reason`` is the instrument's own words."""

    def __init__(self, instrument: str, reason: str, code: str | int | None = None):
        self.instrument, self.reason, self.code = instrument, reason, code
        tag = f" [{code}]" if code is not None else ""
        super().__init__(f"{instrument}: {reason}{tag}")


class InstrumentTimeout(InstrumentError):
    """No (complete) answer within the timeout."""


@dataclass(frozen=True)
class InterferometerReading:
    """One accepted-or-not reading of every interferometer axis, taken in one window.

    ``displacement_m[axis]`` is the filtered mean over the window, ``std_m[axis]`` the standard
    deviation of the window's samples (the acceptance statistic)."""
    t_s: float
    displacement_m: dict[str, float]
    std_m: dict[str, float]
    n_samples: int
    window_s: float


@dataclass(frozen=True)
class AngleReading:
    """Autocollimator angles (rad) by channel, e.g. ``ac1_ry``; ``in_range[ch]`` is False when
    the instrument reported the angle outside its measuring range (the value is then NaN)."""
    t_s: float
    angles_rad: dict[str, float]
    in_range: dict[str, bool]


@dataclass(frozen=True)
class TemperatureScan:
    """Temperatures (degC) by sensor name, from the scan completed at ``t_s``."""
    t_s: float
    temperatures_C: dict[str, float]


@dataclass(frozen=True)
class PressureReading:
    """Barometric pressure (Pa, absolute) of the laboratory air, from the barometer's latest
    completed measurement at ``t_s``."""
    t_s: float
    pressure_Pa: float


@dataclass(frozen=True)
class HumidityReading:
    """Relative humidity (%, over water) of the air by the beams, from the hygrometer's latest
    completed measurement at ``t_s``."""
    t_s: float
    humidity_pct: float


class Clock(ABC):
    """Campaign time (s). Simulated instruments share a simulated clock; hardware uses the
    wall clock."""

    @abstractmethod
    def now(self) -> float: ...

    @abstractmethod
    def sleep(self, seconds: float) -> None: ...


class Robot(ABC):
    name = "robot"

    @abstractmethod
    def move_to(self, q_rad: np.ndarray, timeout_s: float = DEFAULT_TIMEOUT_S) -> None:
        """Move to motor coordinates q (3,) rad and block until the controller reports
        in-position. Raises InstrumentError (e.g. outside the stroke) or InstrumentTimeout."""

    @abstractmethod
    def read_encoders(self, timeout_s: float = DEFAULT_TIMEOUT_S) -> np.ndarray:
        """Motor coordinates (3,) rad as the encoders read them."""


class Interferometers(ABC):
    name = "interferometers"
    axes: tuple[str, ...] = ()   # e.g. ("x", "y") or ("x", "y", "z")

    @abstractmethod
    def zero(self, timeout_s: float = DEFAULT_TIMEOUT_S) -> None:
        """Set every axis' reading to zero at the present position."""

    @abstractmethod
    def read(self, timeout_s: float = DEFAULT_TIMEOUT_S) -> InterferometerReading:
        """Take one reading window of every axis (blocks for the window)."""


class Autocollimators(ABC):
    name = "autocollimators"
    channels: tuple[str, ...] = ()  # e.g. ("ac1_ry", "ac1_rz", "ac2_rx", "ac2_rz")

    @abstractmethod
    def read(self, timeout_s: float = DEFAULT_TIMEOUT_S) -> AngleReading: ...


class ThermometerScanner(ABC):
    name = "thermometers"
    sensors: tuple[str, ...] = ()  # sensor names, in channel order

    @abstractmethod
    def scan(self, timeout_s: float = DEFAULT_TIMEOUT_S) -> TemperatureScan:
        """The latest complete scan of every channel."""


class CoilSupply(ABC):
    name = "coils"
    n_coils = 3

    @abstractmethod
    def set_currents(self, currents_A: np.ndarray, timeout_s: float = DEFAULT_TIMEOUT_S) -> None:
        """Set each coil's current (A); blocks until the supply has settled."""

    @abstractmethod
    def read_currents(self, timeout_s: float = DEFAULT_TIMEOUT_S) -> np.ndarray:
        """Measured coil currents (A), (n_coils,)."""


class Barometer(ABC):
    """What an interferometer's air compensation needs beyond the air temperature: the
    pressure (a lab without one, as in the papers, leaves its wander unrecorded)."""
    name = "barometer"

    @abstractmethod
    def read(self, timeout_s: float = DEFAULT_TIMEOUT_S) -> PressureReading: ...


class Hygrometer(ABC):
    name = "hygrometer"

    @abstractmethod
    def read(self, timeout_s: float = DEFAULT_TIMEOUT_S) -> HumidityReading: ...


@dataclass
class InstrumentSet:
    """Everything a campaign talks to. ``coils`` is None where no force simulator is fitted,
    ``barometer`` and ``hygrometer`` where the laboratory records no pressure or humidity."""
    clock: Clock
    robot: Robot
    interferometers: Interferometers
    autocollimators: Autocollimators
    thermometers: ThermometerScanner
    coils: CoilSupply | None = None
    extra: dict = field(default_factory=dict)
    barometer: Barometer | None = None
    hygrometer: Hygrometer | None = None

    def close(self) -> None:
        for inst in (self.robot, self.interferometers, self.autocollimators,
                     self.thermometers, self.coils, self.barometer, self.hygrometer):
            close = getattr(inst, "close", None)
            if close is not None:
                close()
