"""A small deterministic InstrumentSet (the "toy lab") that backs the emulators in these tests,
and fixtures that run it behind real pseudo-terminals with the serial drivers in front.

The toy lab is not a mock of anything serial: the drivers talk pyserial to real ptys, and the
emulators translate what they hear into calls on this InstrumentSet. Its readings are simple
functions of its state plus seeded noise, so the same sequence of interface calls on two toy
labs with the same seed gives the same readings."""
from __future__ import annotations

import numpy as np
import pytest

from deltatwin.hw.emulators.lab import EmulatedLab
from deltatwin.hw.lab import open_lab
from deltatwin.hw.retry import RetryPolicy
from deltatwin.twin.instruments.interface import (
    AngleReading,
    Autocollimators,
    Clock,
    CoilSupply,
    InstrumentError,
    InstrumentSet,
    InterferometerReading,
    Interferometers,
    Robot,
    TemperatureScan,
    ThermometerScanner,
)

STROKE_RAD = 0.2
ARCSEC = np.pi / 648000.0


class ToyClock(Clock):
    def __init__(self):
        self.t = 0.0

    def now(self):
        return self.t

    def sleep(self, seconds):
        self.t += max(0.0, seconds)


class ToyRobot(Robot):
    def __init__(self, clock):
        self.clock, self.q, self.moves = clock, np.zeros(3), 0

    def move_to(self, q_rad, timeout_s=30.0):
        q = np.asarray(q_rad, dtype=float)
        if np.any(np.abs(q) > STROKE_RAD):
            raise InstrumentError(self.name, f"target {q.tolist()} outside the stroke", "stroke")
        self.clock.sleep(0.5)
        self.q = q.copy()
        self.moves += 1

    def read_encoders(self, timeout_s=30.0):
        return self.q + np.array([1e-7, -2e-7, 3e-7])


class ToyInterferometers(Interferometers):
    axes = ("x", "y")

    def __init__(self, clock, robot, rng):
        self.clock, self.robot, self.rng = clock, robot, rng
        self.offset = np.zeros(2)
        self.reads = 0

    def _position(self):
        return 0.05 * np.array([self.robot.q[0] - self.robot.q[1], self.robot.q[2]])

    def zero(self, timeout_s=30.0):
        self.offset = self._position()

    def read(self, timeout_s=30.0):
        self.clock.sleep(0.2)
        self.reads += 1
        d = self._position() - self.offset + self.rng.normal(0.0, 3e-9, 2)
        s = 5e-9 + self.rng.uniform(0.0, 1e-9, 2)
        return InterferometerReading(self.clock.now(), dict(zip(self.axes, d)),
                                     dict(zip(self.axes, s)), 4096, 0.2)


class ToyAutocollimators(Autocollimators):
    channels = ("ac1_ry", "ac1_rz", "ac2_rx", "ac2_rz")
    RANGE = 400 * ARCSEC

    def __init__(self, clock, robot, rng):
        self.clock, self.robot, self.rng = clock, robot, rng
        self.reads = 0

    def read(self, timeout_s=30.0):
        self.reads += 1
        q = self.robot.q
        raw = 1e-2 * np.array([q[0], q[1], q[2], q[0] + q[1]]) + self.rng.normal(0, 1e-7, 4)
        inside = np.abs(raw) <= self.RANGE
        angles = np.where(inside, raw, np.nan)
        return AngleReading(self.clock.now(), dict(zip(self.channels, angles)),
                            dict(zip(self.channels, inside.tolist())))


class ToyThermometers(ThermometerScanner):
    sensors = ("air_x", "air_y", "base", "arm1")

    def __init__(self, clock, rng):
        self.clock, self.rng = clock, rng
        self.scans = 0

    def scan(self, timeout_s=30.0):
        self.scans += 1
        t = self.clock.now()
        temps = 20.0 + 1e-3 * t + np.array([0.1, 0.2, 0.3, 0.4]) + self.rng.normal(0, 1e-3, 4)
        return TemperatureScan(t, dict(zip(self.sensors, temps)))


class ToyCoils(CoilSupply):
    def __init__(self, clock):
        self.clock, self.currents = clock, np.zeros(3)

    def set_currents(self, currents_A, timeout_s=30.0):
        self.clock.sleep(0.1)
        self.currents = np.asarray(currents_A, dtype=float).copy()

    def read_currents(self, timeout_s=30.0):
        return self.currents + np.array([1e-6, 2e-6, -1e-6])


def toy_lab(seed: int = 7) -> InstrumentSet:
    rng = np.random.default_rng(seed)
    clock = ToyClock()
    robot = ToyRobot(clock)
    return InstrumentSet(clock=clock, robot=robot,
                         interferometers=ToyInterferometers(clock, robot, rng),
                         autocollimators=ToyAutocollimators(clock, robot, rng),
                         thermometers=ToyThermometers(clock, rng), coils=ToyCoils(clock))


FAST_RETRY = RetryPolicy(attempts=4, first_delay_s=0.01, factor=2.0, max_delay_s=0.2)
LINE_TIMEOUT_S = 0.25


@pytest.fixture
def emulated(tmp_path):
    """(toy lab, running EmulatedLab on ptys) -- short timeouts, fast retries."""
    backing = toy_lab()
    with EmulatedLab(backing, tmp_path / "ports", timeout_s=LINE_TIMEOUT_S,
                     retry=FAST_RETRY) as lab:
        yield backing, lab


@pytest.fixture
def drivers(emulated):
    """The serial InstrumentSet (drivers) talking to the emulated lab."""
    _, lab = emulated
    instruments = open_lab(lab.ports())
    yield instruments
    instruments.close()
