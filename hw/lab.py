"""A laboratory's instruments over serial: the ports file -> an ``InstrumentSet`` of drivers.

This is what ``deltatwin campaign --instruments serial --ports FILE`` uses::

    from deltatwin.hw.lab import open_lab
    instruments = open_lab("ports.toml")      # or a LabPorts
    ...                                       # the campaign talks to the interface only
    instruments.close()
"""
from __future__ import annotations

import os
from dataclasses import dataclass

from deltatwin.hw.clock import SerialClock, WallClock
from deltatwin.hw.coil_supply import CoilSupplyDriver
from deltatwin.hw.keithley2700 import Keithley2700Scanner
from deltatwin.hw.lds1000 import ARCSEC_RAD, LDS1000, NewportAutocollimators
from deltatwin.hw.ports import LabPorts, Port, load_ports
from deltatwin.hw.protocol import SerialLine, terminator_bytes
from deltatwin.hw.robot_controller import RobotController
from deltatwin.hw.sp2000 import SP2000Interferometers
from deltatwin.twin.instruments.interface import DEFAULT_TIMEOUT_S, InstrumentSet


def serial_line(port: Port, instrument: str) -> SerialLine:
    return SerialLine(port.url, instrument=instrument, baud=port.baud,
                      terminator=terminator_bytes(port.terminator), timeout_s=port.timeout_s,
                      xonxoff=port.xonxoff)


@dataclass
class SerialInstrumentSet(InstrumentSet):
    """An ``InstrumentSet`` whose ``close`` also closes a serial clock."""

    def close(self) -> None:
        super().close()
        close = getattr(self.clock, "close", None)
        if close is not None:
            close()

    def connect(self, timeout_s: float = DEFAULT_TIMEOUT_S) -> None:
        """Identify and set up every instrument now (instead of at its first use), so that a
        wrong port or a missing instrument is reported before a campaign starts."""
        drivers = [self.clock, self.robot, self.interferometers, self.thermometers, self.coils,
                   *getattr(self.autocollimators, "controllers", [])]
        for d in drivers:
            if hasattr(d, "operation"):
                d.operation("connect", lambda: None, timeout_s)


def open_lab(ports: LabPorts | str | os.PathLike,
             wall_clock_start_s: float = 0.0) -> SerialInstrumentSet:
    """Drivers for every instrument of the ports file (ports open at first use). Without a
    ``[clock]`` port the campaign time is the wall clock, starting at ``wall_clock_start_s``."""
    if not isinstance(ports, LabPorts):
        ports = load_ports(ports)
    kw = {"retry_policy": ports.retry}
    clock = (WallClock(wall_clock_start_s) if ports.clock is None
             else SerialClock(serial_line(ports.clock, "clock"), **kw))
    steps = ports.autocollimator_max_step_arcsec or (None,) * len(ports.autocollimators)
    controllers = [LDS1000(serial_line(port, f"autocollimator{k + 1}"), axes,
                           name=f"autocollimator{k + 1}",
                           max_step_rad=None if step is None else step * ARCSEC_RAD, **kw)
                   for k, ((port, axes), step) in enumerate(zip(ports.autocollimators, steps))]
    coils = (None if ports.coils is None else
             CoilSupplyDriver(serial_line(ports.coils, "coils"), n_coils=ports.n_coils, **kw))
    return SerialInstrumentSet(
        clock=clock,
        robot=RobotController(serial_line(ports.robot, "robot"), **kw),
        interferometers=SP2000Interferometers(serial_line(ports.interferometers,
                                                          "interferometers"),
                                              ports.interferometer_axes, clock, **kw),
        autocollimators=NewportAutocollimators(controllers, clock),
        thermometers=Keithley2700Scanner(serial_line(ports.thermometers, "thermometers"),
                                         ports.thermometer_channels, clock, **kw),
        coils=coils,
        extra={"lab": ports.lab})
