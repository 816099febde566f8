"""Newport LDS1000 emulator: one controller, two axes, answered from the backing
``Autocollimators``. The controllers of one laboratory share an ``AngleSource`` so that a driver
reading every axis of every controller once causes exactly one backing ``read()``.

An angle outside the measuring range (backing ``in_range`` False) is answered as the range limit
with error ``O``. Commands before ``MR`` set error ``D`` (not allowed); an unknown command sets
``A``; a backing failure or an injected ``error_code`` (default ``S``) answers ``nTP`` with the
previous value and sets the code (the driver reads ``TE`` after every reading).
"""
from __future__ import annotations

import math

from deltatwin.hw.emulators.base import LineEmulator
from deltatwin.hw.lds1000 import ERROR_CODES, PROTOCOL, RANGE_RAD, UNIT_RAD, format_value
from deltatwin.twin.instruments.interface import InstrumentError


class AngleSource:
    """Backing angles shared by the controllers: a channel asked for a second time takes a new
    backing reading (so one pass over every channel = one reading)."""

    def __init__(self, backing):
        self.backing = backing
        self._reading = None
        self._served: set[str] = set()

    def angle(self, channel: str) -> tuple[float, bool]:
        if self._reading is None or channel in self._served:
            self._reading = self.backing.call(self.backing.instruments.autocollimators.read)
            self._served = set()
        self._served.add(channel)
        return self._reading.angles_rad[channel], self._reading.in_range[channel]


class LDS1000Emulator(LineEmulator):
    protocol = PROTOCOL
    default_error_code = "S"

    def __init__(self, backing, link, axes: dict[int, str], source: AngleSource,
                 unit: str = "µrad", **kw):
        super().__init__(backing, link, **kw)
        if unit not in UNIT_RAD:
            raise ValueError(f"unit {unit!r} not one of {list(UNIT_RAD)}")
        self.axes, self.source, self.unit = dict(axes), source, unit
        self.remote = False
        self.last_error = "@"
        self._last_value = {a: format_value(0.0, unit) for a in self.axes}

    def _format(self, angle_rad: float) -> str:
        return format_value(angle_rad / UNIT_RAD[self.unit], self.unit)

    def handle(self, command: str, values: dict) -> str | None:
        p = self.protocol
        if command == "remote":
            self.remote = True
            return None
        if command == "version":
            return p.reply("version", version="LDS1000 Controller Version 3.10")
        if command == "error_code":
            code, self.last_error = self.last_error, "@"
            return p.reply("error_code", code=code)
        if command == "error_text":
            code, self.last_error = self.last_error, "@"
            return p.reply("error_text", code=code, reason=ERROR_CODES[code].upper())
        axis = values["axis"]
        if axis not in self.axes:
            self.last_error = "B"
            return None
        if command == "units":
            return p.reply("units", axis=axis, mode="RT", a="04512", b="1", unit=self.unit,
                           c="00102", d="00241")
        if not self.remote:
            self.last_error = "D"
            return None
        angle, in_range = self.source.angle(self.axes[axis])
        if not in_range or not math.isfinite(angle):
            limit = RANGE_RAD
            angle = math.copysign(limit, angle if math.isfinite(angle) else 1.0)
            self.last_error = "O"
        value = self._format(angle)
        self._last_value[axis] = value
        return p.reply("position", axis=axis, value=value)

    def unknown(self, line: str) -> str | None:
        self.last_error = "A"
        return None

    def overlong(self) -> str | None:
        self.last_error = "A"        # the manual's input buffer holds 255 characters
        return None

    def fail(self, error: InstrumentError, request) -> str | None:
        self.last_error = error.code if error.code in ERROR_CODES else "S"
        if request is not None and request[0] == "position" and request[1]["axis"] in self.axes:
            axis = request[1]["axis"]
            return self.protocol.reply("position", axis=axis, value=self._last_value[axis])
        return None
