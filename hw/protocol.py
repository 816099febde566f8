"""Line-protocol plumbing shared by every serial driver and emulator.

An instrument's protocol is DECLARED once, as a table of commands (``Protocol``): each
``Command`` has a request template and a reply template (``None`` = no reply) whose ``{fields}``
are typed by ``Field`` objects (pattern, parse, format). Drivers build requests and parse replies
from the table (``LineInstrument.ask``); emulators parse requests and format replies from the
same table, so one declaration serves both ends. A field named in both the request and the reply
is an echo: the driver checks that the reply echoes what was sent (a stale or foreign reply is
rejected, not believed).

``Framing`` wraps a line's payload: ``PLAIN`` for the vendors' protocols, ``CRC16`` (payload
``*XXXX``, CRC-16/CCITT) for the protocols this project defines, so that a dropped or garbled byte
is detected instead of read as a different number.

``SerialLine`` is the byte transport over pyserial (``serial.serial_for_url``: a device path such
as ``/dev/ttyUSB0`` or ``/dev/pts/N``, a symlink to one, or ``socket://host:port``): terminator,
per-exchange timeout -> ``InstrumentTimeout``, XON (0x11) / XOFF (0x13) bytes dropped from
replies, a lost port -> ``PortLost`` and reopened on the next attempt.

Errors (all ``InstrumentError`` from twin/instruments/interface.py):
``ReplyError`` a reply that does not follow the protocol (garbled, truncated, bad checksum, wrong
echo), ``PortLost`` the port vanished or cannot be opened, ``InstrumentRejected`` the instrument
refused the command for a reason that retrying cannot fix (it is never retried).
"""
from __future__ import annotations

import binascii
import logging
import re
import string
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import serial

from deltatwin.twin.instruments.interface import InstrumentError, InstrumentTimeout

log = logging.getLogger(__name__)

XON, XOFF = b"\x11", b"\x13"
TERMINATORS = {"LF": b"\n", "CR": b"\r", "CRLF": b"\r\n"}
# what pyserial lets through when a device goes away (termios.error is no OSError; termios
# exists on POSIX only, and a Windows lab PC must still import the drivers)
try:
    from termios import error as _TermiosError
except ImportError:
    _LINK_ERRORS: tuple = (serial.SerialException, OSError)
else:
    _LINK_ERRORS = (serial.SerialException, OSError, _TermiosError)
_POLL_S = 0.01   # pyserial read timeout: how often a waiting read checks its own deadline


class ReplyError(InstrumentError):
    """A reply that does not follow the protocol: garbled, truncated, bad checksum, wrong echo."""


class PortLost(InstrumentError):
    """The serial port vanished (device unplugged, emulator gone) or cannot be opened."""


class InstrumentRejected(InstrumentError):
    """The instrument refused the command for a reason retrying cannot fix (unknown command,
    bad argument, outside its limits)."""


def terminator_bytes(name: str) -> bytes:
    """``"LF"``, ``"CR"`` or ``"CRLF"`` -> the bytes; anything else is a ValueError."""
    try:
        return TERMINATORS[name]
    except KeyError:
        raise ValueError(f"terminator {name!r} is not one of {sorted(TERMINATORS)}") from None


# --------------------------------------------------------------------------- fields

@dataclass(frozen=True)
class Field:
    """One typed field of a command or reply: regex ``pattern`` (no capturing groups), ``parse``
    text -> value, ``format`` value -> text."""
    pattern: str
    parse: Callable[[str], Any] = str
    format: Callable[[Any], str] = str


# unambiguous (one way to match any text), so a failed match costs linear time, not quadratic
_REAL = r"[+-]?(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][+-]?\d+)?|[+-]?(?:nan|inf)"


def _shortest(v) -> str:
    return repr(float(v))


def real(fmt: str | None = None) -> Field:
    """A real number written with ``fmt`` (default: the shortest text that reads back to the
    same float64, i.e. an exact round trip)."""
    return Field(_REAL, float, _shortest if fmt is None else fmt.format)


def integer(fmt: str = "{:d}") -> Field:
    return Field(r"[+-]?\d+", int, fmt.format)


def text(pattern: str = r"[ -~]*") -> Field:
    """Printable ASCII text matching ``pattern``."""
    return Field(pattern)


def reals(n: int | None = None, fmt: str | None = None, sep: str = " ") -> Field:
    """``n`` real numbers (``None``: one or more) separated by ``sep`` -> tuple of floats."""
    one = f"(?:{_REAL})"
    pattern = one + f"(?:{re.escape(sep)}{one})" + ("*" if n is None else f"{{{n - 1}}}")

    def parse(s: str) -> tuple[float, ...]:
        return tuple(float(v) for v in s.split(sep))

    one_format = _shortest if fmt is None else fmt.format
    return Field(pattern, parse, lambda vs: sep.join(one_format(float(v)) for v in vs))


# --------------------------------------------------------------------------- commands

@dataclass(frozen=True)
class Command:
    """One command: ``request`` and ``reply`` templates (``str.format`` syntax, fields by name
    from ``fields``); ``reply=None`` means the instrument does not answer."""
    request: str
    reply: str | None = None
    fields: dict[str, Field] = field(default_factory=dict)

    def __post_init__(self):
        for template in (self.request, self.reply):
            for name in _field_names(template):
                if name not in self.fields:
                    raise ValueError(f"command {self.request!r}: field {{{name}}} not declared")
        object.__setattr__(self, "_request_re", _compile(self.request, self.fields))
        object.__setattr__(self, "_reply_re", _compile(self.reply, self.fields))

    @property
    def echoed(self) -> tuple[str, ...]:
        """Fields sent in the request and repeated in the reply."""
        return tuple(n for n in _field_names(self.request) if n in _field_names(self.reply))


def _field_names(template: str | None) -> list[str]:
    if template is None:
        return []
    return [name for _, name, _, _ in string.Formatter().parse(template) if name]


def _compile(template: str | None, fields: dict[str, Field]) -> re.Pattern | None:
    if template is None:
        return None
    parts = []
    for literal, name, _, _ in string.Formatter().parse(template):
        parts.append(re.escape(literal))
        if name:
            parts.append(f"(?P<{name}>{fields[name].pattern})")
    return re.compile("".join(parts))


def _render(template: str, fields: dict[str, Field], values: dict[str, Any]) -> str:
    missing = [n for n in _field_names(template) if n not in values]
    if missing:
        raise ValueError(f"{template!r}: missing value(s) for {missing}")
    return template.format(**{n: fields[n].format(values[n]) for n in _field_names(template)})


def _parse(regex: re.Pattern, fields: dict[str, Field], line: str) -> dict[str, Any] | None:
    m = regex.fullmatch(line)
    if m is None:
        return None
    return {n: fields[n].parse(v) for n, v in m.groupdict().items()}


# --------------------------------------------------------------------------- framing

@dataclass(frozen=True)
class Framing:
    """How a payload becomes a line: ``checksum`` appends ``*XXXX`` (CRC-16/CCITT of the payload,
    initial value 0xFFFF, upper-case hex) and checks it on the way in."""
    checksum: bool = False

    def encode(self, payload: str) -> str:
        if not self.checksum:
            return payload
        return f"{payload}*{binascii.crc_hqx(payload.encode('latin-1'), 0xFFFF):04X}"

    def decode(self, line: str) -> str | None:
        """The payload, or None when the checksum is missing or wrong."""
        if not self.checksum:
            return line
        payload, star, crc = line.rpartition("*")
        if not star or not re.fullmatch(r"[0-9A-F]{4}", crc):
            return None
        if binascii.crc_hqx(payload.encode("latin-1"), 0xFFFF) != int(crc, 16):
            return None
        return payload


PLAIN = Framing(checksum=False)
CRC16 = Framing(checksum=True)


@dataclass(frozen=True)
class Protocol:
    """A declared line protocol: ``commands`` by semantic name (drivers and emulators refer to
    commands by these names, never by their text), the framing and the default terminator.
    ``error`` optionally declares an error reply that may come instead of any reply (fields
    ``code`` and ``reason``); codes in ``rejected_codes`` mean "retrying cannot help"."""
    name: str
    commands: dict[str, Command]
    framing: Framing = PLAIN
    terminator: str = "LF"
    error: Command | None = None
    rejected_codes: frozenset = frozenset()

    # driver side
    def request(self, name: str, **values) -> str:
        cmd = self.commands[name]
        return self.framing.encode(_render(cmd.request, cmd.fields, values))

    def parse_reply(self, name: str, line: str, sent: dict[str, Any], instrument: str) -> dict:
        """Parse the reply to command ``name``; raise ``ReplyError`` when it does not follow the
        protocol or does not echo ``sent``, or the error declared by ``error`` when it is one."""
        cmd = self.commands[name]
        payload = self.framing.decode(line)
        if payload is None:
            raise ReplyError(instrument, f"bad checksum in reply to {name!r}: {line!r}")
        if self.error is not None:
            err = _parse(self.error._reply_re, self.error.fields, payload)
            if err is not None:
                raise self.make_error(instrument, err)
        values = _parse(cmd._reply_re, cmd.fields, payload)
        if values is None:
            raise ReplyError(instrument, f"reply to {name!r} does not match "
                                         f"{cmd.reply!r}: {line!r}")
        for n in cmd.echoed:
            if cmd.fields[n].format(values[n]) != cmd.fields[n].format(sent[n]):
                raise ReplyError(instrument, f"reply to {name!r} echoes {n}={values[n]!r}, "
                                             f"sent {sent[n]!r}: {line!r}")
        return values

    def make_error(self, instrument: str, err: dict) -> InstrumentError:
        """An error reply -> ``InstrumentRejected`` if its code is in ``rejected_codes``, else
        ``InstrumentError`` (retried)."""
        code, reason = err.get("code"), err.get("reason", "")
        cls = InstrumentRejected if code in self.rejected_codes else InstrumentError
        return cls(instrument, reason, code)

    # emulator side
    def parse_request(self, line: str) -> tuple[str, dict] | None:
        """(command name, values) of a request line, or None if it is no declared request (or
        its checksum is wrong)."""
        payload = self.framing.decode(line)
        if payload is None:
            return None
        for name, cmd in self.commands.items():
            values = _parse(cmd._request_re, cmd.fields, payload)
            if values is not None:
                return name, values
        return None

    def command_with_header(self, line: str) -> str | None:
        """The command whose request begins with ``line``'s header (the literal text before
        its first field, e.g. ``"CURR "``) although the whole line is no valid request: a known
        command with a malformed argument ("bad argument", not "unknown command")."""
        payload = self.framing.decode(line)
        for name, cmd in self.commands.items():
            head = next(string.Formatter().parse(cmd.request))
            if payload is not None and head[1] and head[0] and payload.startswith(head[0]):
                return name
        return None

    def reply(self, name: str, **values) -> str:
        cmd = self.commands[name]
        return self.framing.encode(_render(cmd.reply, cmd.fields, values))

    def error_reply(self, code, reason: str) -> str:
        return self.framing.encode(_render(self.error.reply, self.error.fields,
                                           {"code": code, "reason": reason}))


# ------------------------------------------------- the generic protocols this project defines

GENERIC_ERRORS = {1: "unknown command", 2: "bad argument", 3: "checksum mismatch",
                  4: "busy", 5: "device fault"}
GENERIC_REJECTED = frozenset({1, 2})


def generic_protocol(name: str, commands: dict[str, Command]) -> Protocol:
    """A protocol in this project's generic convention (docs/hardware.md): CRC-16 framing, LF,
    ``*IDN?`` -> ``IDN <identity>``, any reply may instead be ``ERR <code> <reason>`` with the
    codes of ``GENERIC_ERRORS`` (1 and 2 are rejections, never retried)."""
    identify = Command("*IDN?", "IDN {identity}", {"identity": text()})
    error = Command("ERR", "ERR {code} {reason}", {"code": integer(), "reason": text()})
    return Protocol(name, {"identify": identify, **commands}, framing=CRC16, terminator="LF",
                    error=error, rejected_codes=GENERIC_REJECTED)


# --------------------------------------------------------------------------- transport

class SerialLine:
    """A line-oriented serial link over pyserial. Opens lazily; any OS-level failure closes it
    and raises ``PortLost``, and the next call reopens it (a port that came back works again).

    ``url``: device path or pyserial URL; ``baud``; ``terminator`` bytes; ``timeout_s``: the
    longest wait for one complete reply line."""

    def __init__(self, url: str, *, instrument: str, baud: int = 9600,
                 terminator: bytes = b"\n", timeout_s: float = 1.0, xonxoff: bool = False):
        self.url, self.instrument, self.baud = url, instrument, baud
        self.terminator, self.timeout_s, self.xonxoff = terminator, timeout_s, xonxoff
        self._port: serial.SerialBase | None = None
        self._buffer = bytearray()

    def open(self) -> None:
        if self._port is not None:
            return
        try:
            self._port = serial.serial_for_url(self.url, baudrate=self.baud, timeout=_POLL_S,
                                               write_timeout=self.timeout_s,
                                               xonxoff=self.xonxoff)
        except (*_LINK_ERRORS, ValueError) as exc:
            raise PortLost(self.instrument, f"cannot open {self.url}: {exc}") from exc
        self._buffer.clear()
        log.debug("%s: opened %s", self.instrument, self.url)

    def close(self) -> None:
        port, self._port = self._port, None
        self._buffer.clear()
        if port is not None:
            try:
                port.close()
            except _LINK_ERRORS:
                pass

    def _lost(self, exc: Exception) -> PortLost:
        self.close()
        return PortLost(self.instrument, f"port {self.url} lost: {exc}")

    def write_line(self, line: str) -> None:
        self.open()
        try:
            self._port.write(line.encode("latin-1") + self.terminator)
            self._port.flush()
        except _LINK_ERRORS as exc:
            raise self._lost(exc) from exc

    def read_line(self, timeout_s: float | None = None) -> str:
        """The next complete line (terminator removed, XON/XOFF bytes dropped), decoded as
        latin-1. Raises ``InstrumentTimeout`` (keeping a partial line as the reason) or
        ``PortLost``."""
        self.open()
        deadline = time.monotonic() + (self.timeout_s if timeout_s is None else timeout_s)
        while True:
            end = self._buffer.find(self.terminator)
            if end >= 0:
                raw = bytes(self._buffer[:end])
                del self._buffer[:end + len(self.terminator)]
                return raw.decode("latin-1")
            remaining = deadline - time.monotonic()
            if remaining <= 0 and self._take_waiting():
                continue    # the reply came in time: this process was not scheduled to see it
            if remaining <= 0:
                partial = bytes(self._buffer)
                self._buffer.clear()
                what = f"; partial line {partial!r}" if partial else ""
                raise InstrumentTimeout(self.instrument, f"no complete reply within "
                                        f"{self.timeout_s if timeout_s is None else timeout_s:g} s"
                                        f" on {self.url}{what}")
            try:
                chunk = self._port.read(max(1, self._port.in_waiting))
            except _LINK_ERRORS as exc:
                raise self._lost(exc) from exc
            self._append(chunk)

    def _append(self, chunk: bytes) -> None:
        if chunk:
            if XOFF in chunk or XON in chunk:
                log.debug("%s: dropped XON/XOFF byte(s) in %r", self.instrument, chunk)
                chunk = chunk.replace(XOFF, b"").replace(XON, b"")
            self._buffer += chunk

    def _take_waiting(self) -> bool:
        """Append what already waits in the port (no wait); True if that completes a line. A
        reply that arrived before the deadline but was not read (this process was descheduled
        or paused past the deadline under load) is a reply, not a timeout."""
        try:
            waiting = self._port.in_waiting
            if waiting:
                self._append(self._port.read(waiting))
        except _LINK_ERRORS as exc:
            raise self._lost(exc) from exc
        return self.terminator in self._buffer

    def discard_input(self, quiet_s: float = 0.02) -> bytes:
        """Read and drop whatever arrives until the line has been quiet for ``quiet_s`` (stale
        replies after a fault). Returns what was dropped."""
        self.open()
        dropped = bytearray(self._buffer)
        self._buffer.clear()
        last = time.monotonic()
        try:
            while time.monotonic() - last < quiet_s:
                chunk = self._port.read(max(1, self._port.in_waiting))
                if chunk:
                    dropped += chunk
                    last = time.monotonic()
        except _LINK_ERRORS as exc:
            raise self._lost(exc) from exc
        return bytes(dropped)
