"""Keithley 2700 + multiplexer emulator: SCPI set-up state, error queue (10 entries, like the
instrument), 4-wire PT100 scans answered from the backing ``ThermometerScanner``.

A channel with no sensor behind it, or one listed in ``open_channels`` (an open PT100 lead),
reads ``+9.9E37`` (overflow). Errors go to the queue (``SYST:ERR?``): an unknown command
``-113,"Undefined header"``; a channel that is not on the cards ``-222,"Parameter data out of
range"``; ``READ?`` before the 4-wire PT100 scan is set up
``-221,"Settings conflict"`` and no reply; a backing failure or an injected ``error_code``
(default -230, "Data corrupt or stale") -> queued, and a query gets no reply.
"""
from __future__ import annotations

from collections import deque

from deltatwin.hw.emulators.base import LineEmulator
from deltatwin.hw.keithley2700 import PROTOCOL, format_reading
from deltatwin.twin.instruments.interface import InstrumentError

QUEUE_SIZE = 10
REQUIRED_SETUP = ("function", "transducer", "rtd_type", "scan_list", "continuous_off",
                  "trigger_immediate", "scan_trigger_immediate")


class Keithley2700Emulator(LineEmulator):
    protocol = PROTOCOL
    default_error_code = -230

    def __init__(self, backing, link, channels: dict[int, str], card_channels: int = 40, **kw):
        super().__init__(backing, link, **kw)
        self.channels = dict(channels)       # channel -> backing sensor name
        self.card_channels = card_channels   # channels per multiplexer card (slots 1 and 2)
        self.open_channels: set[int] = set()
        self.errors: deque[tuple[int, str]] = deque(maxlen=QUEUE_SIZE)
        self.state: dict[str, object] = {}
        self.readings_taken = 0
        self._t0 = backing.instruments.clock.now()

    def _queue(self, code: int, reason: str) -> None:
        self.errors.append((code, reason))

    def handle(self, command: str, values: dict) -> str | None:
        p = self.protocol
        if command == "identify":
            return p.reply("identify", model="2700", serial="4022795", firmware="B09  /A02")
        if command == "clear":
            self.errors.clear()
            return None
        if command == "error":
            code, reason = self.errors.popleft() if self.errors else (0, "No error")
            return p.reply("error", code=code, reason=reason)
        if command == "read":
            return self._read()
        bad = [c for c in values.get("channels", ()) if not (c // 100 in (1, 2)
                                                              and 1 <= c % 100 <= self.card_channels)]
        if bad:
            self._queue(-222, "Parameter data out of range")
            return None
        if p.commands[command].reply is None:      # a set-up command: remember its argument
            self.state[command] = next(iter(values.values()), True)
            return None
        raise AssertionError(f"unhandled command {command}")

    def _read(self) -> str | None:
        scan_list = self.state.get("scan_list")
        configured = all(k in self.state for k in REQUIRED_SETUP) and all(
            self.state[k] == scan_list for k in ("function", "transducer", "rtd_type"))
        if not configured or self.state.get("scan_list_select") != "INT":
            self._queue(-221, "Settings conflict")
            return None
        scan = self.backing.call(self.backing.instruments.thermometers.scan)
        secs = scan.t_s - self._t0
        elements = []
        for chan in scan_list:
            sensor = self.channels.get(chan)
            value = (float("inf") if sensor is None or chan in self.open_channels
                     else scan.temperatures_C[sensor])
            self.readings_taken += 1
            elements.append(format_reading(value, secs, self.readings_taken, chan))
        return self.protocol.reply("read", readings=elements)

    def unknown(self, line: str) -> str | None:
        self._queue(-113, "Undefined header")
        return None

    def fail(self, error: InstrumentError, request) -> str | None:
        code = error.code if isinstance(error.code, int) else -240
        self._queue(code, error.reason if isinstance(error.code, int) else
                    f"Hardware error: {error.reason}")
        return None
