"""SIOS SP-2000 plane-mirror interferometers (``Interferometers``) -- a DEFINED protocol.

No public command set of the SP-2000 was found, so this module defines a small line protocol in
the project's generic convention (docs/hardware.md: CRC-16 framing, LF, ``ERR <code> <reason>``)
and keeps it here, alone: a driver for the real instrument replaces this module (and its
emulator, hw/emulators/sp2000.py, which speaks the table below) without touching anything else.

    *IDN?   -> IDN SIOS SP-2000,<serial>,<firmware>
    AXES?   -> AXES x,y            axis names, in reading order
    ZERO    -> ZERO OK             every axis reads 0 at the present position
    READ?   -> READ <n> <window_s> x:<mean_nm>:<std_nm>,y:<mean_nm>:<std_nm>
               one window of n samples per axis: filtered mean and standard deviation (nm,
               written to 0.001 nm; the instrument resolves ~1.24 nm)
"""
from __future__ import annotations

import re

from deltatwin.hw.driver import LineInstrument
from deltatwin.hw.protocol import (
    Command,
    Field,
    InstrumentRejected,
    generic_protocol,
    integer,
    real,
)
from deltatwin.twin.instruments.interface import (
    DEFAULT_TIMEOUT_S,
    Clock,
    InterferometerReading,
    Interferometers,
)

NM = 1e-9
_AXIS_VALUE = r"[a-z]\w*:[+-]?\d+\.\d{3}:\d+\.\d{3}|[a-z]\w*:nan:nan"


def _parse_axes_values(s: str) -> dict[str, tuple[float, float]]:
    out = {}
    for part in s.split(","):
        axis, mean, std = part.split(":")
        out[axis] = (float(mean), float(std))
    return out


def _format_axes_values(values: dict[str, tuple[float, float]]) -> str:
    return ",".join(f"{axis}:{mean:.3f}:{std:.3f}" for axis, (mean, std) in values.items())


AXES_VALUES = Field(f"(?:{_AXIS_VALUE})(?:,(?:{_AXIS_VALUE}))*", _parse_axes_values,
                    _format_axes_values)
AXIS_NAMES = Field(r"[a-z]\w*(?:,[a-z]\w*)*", lambda s: tuple(s.split(",")), ",".join)

PROTOCOL = generic_protocol("SIOS SP-2000 (deltatwin-defined)", {
    "axes": Command("AXES?", "AXES {axes}", {"axes": AXIS_NAMES}),
    "zero": Command("ZERO", "ZERO OK"),
    "read": Command("READ?", "READ {n_samples} {window_s} {values}",
                    {"n_samples": integer(), "window_s": real(), "values": AXES_VALUES}),
})
IDENTITY = re.compile(r"SIOS SP-2000\b.*")


class SP2000Interferometers(LineInstrument, Interferometers):
    """Every interferometer axis of one SP-2000 evaluation unit; ``axes`` (from the ports file)
    must be what the unit reports, in any order."""
    protocol = PROTOCOL

    def __init__(self, line, axes: tuple[str, ...], clock: Clock, *, name="interferometers",
                 **kw):
        super().__init__(line, name=name, **kw)
        self.axes, self.clock = tuple(axes), clock

    def connect(self) -> None:
        identity = self.ask("identify")["identity"]
        if not IDENTITY.fullmatch(identity):
            raise InstrumentRejected(self.name, f"{self.line.url} identifies as {identity!r}, "
                                                f"not an SP-2000")
        reported = self.ask("axes")["axes"]
        if set(reported) != set(self.axes):
            raise InstrumentRejected(self.name, f"unit reports axes {list(reported)}, the ports "
                                                f"file says {list(self.axes)}")

    def zero(self, timeout_s: float = DEFAULT_TIMEOUT_S) -> None:
        self.operation("zero", lambda: self.ask("zero"), timeout_s)

    def _read_once(self) -> InterferometerReading:
        r = self.ask("read")
        values = r["values"]
        if set(values) != set(self.axes):
            raise InstrumentRejected(self.name, f"READ? gave axes {list(values)}, expected "
                                                f"{list(self.axes)}")
        return InterferometerReading(
            self.clock.now(), {a: values[a][0] * NM for a in self.axes},
            {a: values[a][1] * NM for a in self.axes}, r["n_samples"], r["window_s"])

    def read(self, timeout_s: float = DEFAULT_TIMEOUT_S) -> InterferometerReading:
        return self.operation("read", self._read_once, timeout_s)
