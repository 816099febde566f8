"""An emulated laboratory: one emulator per instrument of an ``InstrumentSet``, each on its own
pseudo-terminal (or TCP port), and the ports file that reaches them.

    with EmulatedLab(instruments, directory) as lab:
        write_ports("ports.toml", lab.ports())
        lab.emulators["robot"].inject("no_reply")       # fault injection, per instrument

Layout: a clock port (the backing clock, so drivers follow simulated time), the robot
controller, one SP-2000 for every interferometer axis, one LDS1000 per pair of autocollimator
channels (in the backing's channel order: axes 1, 2), the Keithley 2700 with the thermometers on
channels 101, 102, ..., 140, 201, ... (backing sensor order) and, when the backing has coils, the coil supply.
"""
from __future__ import annotations

import tempfile
from pathlib import Path

from deltatwin.hw.emulators.base import BackingLab, PtyLink, TcpLink
from deltatwin.hw.emulators.clock import ClockEmulator
from deltatwin.hw.emulators.coil_supply import CoilSupplyEmulator
from deltatwin.hw.emulators.keithley2700 import Keithley2700Emulator
from deltatwin.hw.emulators.lds1000 import AngleSource, LDS1000Emulator
from deltatwin.hw.emulators.robot_controller import RobotControllerEmulator
from deltatwin.hw.emulators.sp2000 import SP2000Emulator
from deltatwin.hw.ports import DEFAULTS, LabPorts, Port
from deltatwin.hw.retry import RetryPolicy
from deltatwin.twin.instruments.interface import InstrumentSet


class EmulatedLab:
    """``link``: "pty" (symlinks in ``directory``) or "tcp"; ``realtime`` paces the backing
    clock by the wall clock; ``timeout_s`` per reply line goes to the ports file; ``ac_unit``
    is the LDS1000s' display unit (``sec``: arcsec to 0.01, which holds the twin's 0.02 arcsec
    steps exactly; ``µrad`` to 0.1); ``world``: what the backing simulates (scenario,
    scenario_sha256, seed, scale), answered on the clock port (``WORLD?``) so that a campaign
    checks it runs against the same scenario and seed; ``ac_max_step_arcsec`` goes to the ports
    file (the autocollimator drivers' continuity check)."""

    def __init__(self, instruments: InstrumentSet, directory: str | Path | None = None, *,
                 link: str = "pty", realtime: bool = False, timeout_s: float | None = None,
                 retry: RetryPolicy = RetryPolicy(), name: str = "emulated laboratory",
                 ac_unit: str = "sec", world: dict | None = None,
                 ac_max_step_arcsec: float | None = None):
        if link not in ("pty", "tcp"):
            raise ValueError(f"link must be 'pty' or 'tcp', got {link!r}")
        sensors = tuple(instruments.thermometers.sensors)
        if len(sensors) > 80:
            raise ValueError(f"{len(sensors)} thermometers: two 40-channel cards hold 80")
        self._tmp = None
        if directory is None and link == "pty":
            self._tmp = tempfile.TemporaryDirectory(prefix="deltatwin-emu-")
            directory = self._tmp.name
        self.directory = Path(directory) if directory is not None else None
        if self.directory is not None:
            self.directory.mkdir(parents=True, exist_ok=True)
        self.backing = BackingLab(instruments, realtime=realtime)
        self.link_kind, self.timeout_s, self.retry, self.name = link, timeout_s, retry, name
        self.ac_max_step_arcsec = ac_max_step_arcsec

        def make_link(port_name):
            return PtyLink(self.directory, port_name) if link == "pty" else TcpLink()

        b = self.backing
        self.emulators = {
            "clock": ClockEmulator(b, make_link("clock"), name="clock", world=world),
            "robot": RobotControllerEmulator(b, make_link("robot"), name="robot"),
            "interferometers": SP2000Emulator(b, make_link("interferometers"),
                                              name="interferometers"),
        }
        channels = tuple(instruments.autocollimators.channels)
        source = AngleSource(b)
        self.autocollimator_axes = []
        for k in range(0, len(channels), 2):
            axes = {i + 1: ch for i, ch in enumerate(channels[k:k + 2])}
            name = f"autocollimator{k // 2 + 1}"
            self.emulators[name] = LDS1000Emulator(b, make_link(name), axes, source,
                                                   unit=ac_unit, name=name)
            self.autocollimator_axes.append((name, axes))
        self.thermometer_channels = {100 * (1 + i // 40) + 1 + i % 40: s
                                     for i, s in enumerate(sensors)}
        self.emulators["thermometers"] = Keithley2700Emulator(
            b, make_link("thermometers"), self.thermometer_channels, name="thermometers")
        if instruments.coils is not None:
            self.emulators["coils"] = CoilSupplyEmulator(b, make_link("coils"), name="coils")

    def _port(self, name: str, kind: str) -> Port:
        baud, _, timeout_s = DEFAULTS[kind]
        emu = self.emulators[name]
        return Port(emu.url, baud, emu.terminator_name,
                    timeout_s if self.timeout_s is None else self.timeout_s)

    def ports(self) -> LabPorts:
        """The ports file content that reaches these emulators."""
        ins = self.backing.instruments
        return LabPorts(
            lab=self.name,
            clock=self._port("clock", "clock"),
            robot=self._port("robot", "robot"),
            interferometers=self._port("interferometers", "interferometers"),
            interferometer_axes=tuple(ins.interferometers.axes),
            autocollimators=tuple((self._port(name, "autocollimators"), axes)
                                  for name, axes in self.autocollimator_axes),
            thermometers=self._port("thermometers", "thermometers"),
            thermometer_channels=self.thermometer_channels,
            coils=self._port("coils", "coils") if "coils" in self.emulators else None,
            n_coils=ins.coils.n_coils if ins.coils is not None else 3,
            retry=self.retry,
            autocollimator_max_step_arcsec=(self.ac_max_step_arcsec,)
            * len(self.autocollimator_axes))

    def devices(self) -> dict[str, tuple[str, str]]:
        """name -> (URL for the ports file, device behind it)."""
        return {n: (e.url, e.link.device) for n, e in self.emulators.items()}

    def start(self) -> EmulatedLab:
        for e in self.emulators.values():
            e.start()
        return self

    def stop(self) -> None:
        for e in self.emulators.values():
            e.stop()
        if self._tmp is not None:
            self._tmp.cleanup()

    def __enter__(self) -> EmulatedLab:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()
