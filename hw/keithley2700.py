"""Keithley 2700 with a multiplexer card: a 4-wire PT100 scan (``ThermometerScanner``).

SCPI over RS-232 (sequence and reply format: ../shared/reference.md "Instruments",
docs/hardware.md). Set-up on connect: ``*CLS``, ``FORM:ELEM READ,UNIT,TST,RNUM,CHAN`` (the reply
layout, whatever the instrument's last state), ``ROUT:SCAN:LSEL NONE``, ``SENS:FUNC 'TEMP'``,
``SENS:TEMP:TRAN FRTD``, ``SENS:TEMP:FRTD:TYPE PT100`` (on the scan list), ``INIT:CONT OFF``,
``TRIG:SOUR IMM``, ``TRIG:COUN 1``, ``ROUT:SCAN (@list)``, ``SAMP:COUN n``,
``ROUT:SCAN:TSO IMM``, then ``SYST:ERR?`` must answer ``0,"No error"``. Per scan:
``ROUT:SCAN:LSEL INT``, ``READ?``, ``ROUT:SCAN:LSEL NONE``, ``SYST:ERR?``.

A reply element is ``+2.53908043E+01C,+0.346SECS,+00002RDNG#,110INTCHAN``; the driver accepts
only that form (fixed width but for the reading number, at least 5 digits and consecutive within
a reply: a dropped or garbled byte breaks it and is detected), checks that the channels come back
in scan-list order, and drops stray XON/XOFF bytes. An overflow (``+9.9E37``,
an open or unplugged PT100) raises ``InstrumentError`` with code ``"overflow"`` naming the
channel(s) and sensor(s): an overflowed channel carries no temperature, and the interface
reports failures as errors, never as silent NaNs.
"""
from __future__ import annotations

import re

from deltatwin.hw.driver import LineInstrument
from deltatwin.hw.protocol import (
    Command,
    Field,
    InstrumentRejected,
    Protocol,
    ReplyError,
    integer,
    text,
)
from deltatwin.twin.instruments.interface import (
    DEFAULT_TIMEOUT_S,
    Clock,
    InstrumentError,
    TemperatureScan,
    ThermometerScanner,
)

OVERFLOW = 9.9e37


def _format_channels(channels) -> str:
    channels = list(channels)
    if channels == list(range(channels[0], channels[0] + len(channels))) and len(channels) > 1:
        return f"{channels[0]}:{channels[-1]}"
    return ",".join(str(c) for c in channels)


def _parse_channels(s: str) -> tuple[int, ...]:
    out = []
    for part in s.split(","):
        lo, _, hi = part.partition(":")
        out.extend(range(int(lo), int(hi or lo) + 1))
    return tuple(out)


CHANNELS = Field(r"\d{3}(?::\d{3})?(?:,\d{3}(?::\d{3})?)*", _parse_channels, _format_channels)

# The reply layout the driver sets with FORM:ELEM (so it does not depend on the instrument's
# last state). The reading number has no fixed width (the manual's figure: ``+236RDNG``): at
# least 5 digits as instruments write it (``+00002RDNG#``), more past 99,999 (``+100043RDNG#``);
# the driver checks instead that the numbers of one reply are consecutive.
ELEMENTS = ("READING", "UNITS", "TSTAMP", "RNUMBER", "CHANNEL")
_VALUE = r"(?:[+-]\d\.\d{8}E[+-]\d{2}|\+9\.9E\+?37)"
_ELEMENT = _VALUE + r"C,[+-]\d+\.\d{3}SECS,[+-]\d{5,}RDNG#,\d{3}INTCHAN"
_ELEMENT_GROUPS = re.compile(r"(?P<value>[^C,]+)C,(?P<secs>[^S]+)SECS,(?P<rdng>[^R]+)RDNG#,"
                             r"(?P<chan>\d{3})INTCHAN")


def _parse_readings(s: str) -> list[tuple[int, float, int]]:
    """``(channel, value degC, reading number)`` per element, in reply order."""
    return [(int(m["chan"]), float(m["value"]), int(m["rdng"]))
            for m in _ELEMENT_GROUPS.finditer(s)]


def format_element(elements, value_C: float, secs: float, number: int, channel: int) -> str:
    """One reading as the 2700 writes it with FORM:ELEM ``elements`` (long forms, upper case;
    overflow for a non-finite value)."""
    units = "UNITS" in elements
    parts = {"READING": (f"{value_C:+.8E}" if abs(value_C) < OVERFLOW else "+9.9E37")
                        + ("C" if units else ""),
             "TSTAMP": f"{secs:+.3f}" + ("SECS" if units else ""),
             "RNUMBER": f"{number:+06d}" + ("RDNG#" if units else ""),
             "CHANNEL": f"{channel:03d}" + ("INTCHAN" if units else "")}
    return ",".join(parts[e] for e in elements if e in parts)


def format_reading(value_C: float, secs: float, number: int, channel: int) -> str:
    """One reading in the driver's layout (``ELEMENTS``)."""
    return format_element(ELEMENTS, value_C, secs, number, channel)


READINGS = Field(f"{_ELEMENT}(?:,{_ELEMENT})*", _parse_readings, lambda elements: ",".join(elements))

PROTOCOL = Protocol(
    "Keithley 2700",
    {
        "identify": Command("*IDN?", "KEITHLEY INSTRUMENTS INC.,MODEL {model},{serial},{firmware}",
                            {"model": text(r"\w+"), "serial": text(r"[^,]*"),
                             "firmware": text(r"[^,]*")}),
        "clear": Command("*CLS"),
        "scan_list_select": Command("ROUT:SCAN:LSEL {mode}", None, {"mode": text("NONE|INT")}),
        "function": Command("SENS:FUNC 'TEMP',(@{channels})", None, {"channels": CHANNELS}),
        "transducer": Command("SENS:TEMP:TRAN FRTD,(@{channels})", None, {"channels": CHANNELS}),
        "rtd_type": Command("SENS:TEMP:FRTD:TYPE PT100,(@{channels})", None,
                            {"channels": CHANNELS}),
        "continuous_off": Command("INIT:CONT OFF"),
        "trigger_immediate": Command("TRIG:SOUR IMM"),
        "trigger_count": Command("TRIG:COUN {n}", None, {"n": integer()}),
        "scan_list": Command("ROUT:SCAN (@{channels})", None, {"channels": CHANNELS}),
        "sample_count": Command("SAMP:COUN {n}", None, {"n": integer()}),
        "scan_trigger_immediate": Command("ROUT:SCAN:TSO IMM"),
        "format_elements": Command("FORM:ELEM READ,UNIT,TST,RNUM,CHAN"),
        "read": Command("READ?", "{readings}", {"readings": READINGS}),
        "error": Command("SYST:ERR?", '{code},"{reason}"',
                         {"code": integer(), "reason": text(r'[^"]*')}),
    },
    terminator="LF",
    # SCPI command errors (-1xx) and bad parameter values: our request was wrong, never retried
    rejected_codes=frozenset(range(-199, -99)) | {-222, -224},
)


class Keithley2700Scanner(LineInstrument, ThermometerScanner):
    """``channels``: multiplexer channel (e.g. 101) -> sensor name, from the ports file;
    ``clock`` stamps each scan."""
    protocol = PROTOCOL

    def __init__(self, line, channels: dict[int, str], clock: Clock, *, name="thermometers",
                 **kw):
        super().__init__(line, name=name, **kw)
        if not channels:
            raise ValueError(f"{name}: no thermometer channel configured")
        self.channels = dict(sorted(channels.items()))
        self.sensors = tuple(self.channels.values())
        self.clock = clock

    def connect(self) -> None:
        ident = self.ask("identify")
        if ident["model"] != "2700":
            raise InstrumentRejected(self.name, f"{self.line.url} answers *IDN? as model "
                                                f"{ident['model']}, not a Keithley 2700")
        chans = tuple(self.channels)
        self.ask("clear")
        self.ask("format_elements")
        self.ask("scan_list_select", mode="NONE")
        self.ask("function", channels=chans)
        self.ask("transducer", channels=chans)
        self.ask("rtd_type", channels=chans)
        self.ask("continuous_off")
        self.ask("trigger_immediate")
        self.ask("trigger_count", n=1)
        self.ask("scan_list", channels=chans)
        self.ask("sample_count", n=len(chans))
        self.ask("scan_trigger_immediate")
        self._raise_pending("set-up")

    def pending_error(self) -> InstrumentError | None:
        err = self.ask("error")
        if err["code"] == 0:
            return None
        return self.protocol.make_error(self.name, err)

    def _raise_pending(self, when: str) -> None:
        err = self.pending_error()
        if err is not None:
            raise type(err)(self.name, f"{when}: {err.reason}", err.code)

    def _scan_once(self) -> TemperatureScan:
        self.ask("scan_list_select", mode="INT")
        readings = self.ask("read")["readings"]
        self.ask("scan_list_select", mode="NONE")
        self._raise_pending("scan")
        got = [c for c, _, _ in readings]
        if got != list(self.channels):
            raise ReplyError(self.name, f"scan returned channels {got}, expected "
                                        f"{list(self.channels)}")
        numbers = [n for _, _, n in readings]
        if numbers != list(range(numbers[0], numbers[0] + len(numbers))):
            raise ReplyError(self.name, f"scan returned reading numbers {numbers}, not "
                                        "consecutive (a digit lost?)")
        over = [f"{c} ({self.channels[c]})" for c, v, _ in readings if v >= OVERFLOW]
        if over:
            raise InstrumentError(self.name, f"overflow (+9.9E37) on channel(s) "
                                             f"{', '.join(over)}: open or unplugged PT100?",
                                  "overflow")
        return TemperatureScan(self.clock.now(), {self.channels[c]: v for c, v, _ in readings})

    def scan(self, timeout_s: float = DEFAULT_TIMEOUT_S) -> TemperatureScan:
        return self.operation("scan", self._scan_once, timeout_s)
