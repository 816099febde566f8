"""Campaign clocks for the hardware side.

``WallClock``: a laboratory's time (monotonic wall clock since the clock was made).
``SerialClock``: the emulated laboratory's clock port (hw/emulators/clock.py), so that a campaign
through the emulators follows the twin's simulated time and runs as fast as the serial exchanges
allow. A real laboratory has no such port (its ports file has no ``[clock]`` section).

Clock protocol (generic convention, docs/hardware.md):

    *IDN?        -> IDN deltatwin emulated clock
    TIME?        -> TIME <t_s>       campaign time (s, every digit)
    SLEEP <s>    -> SLEEP OK         after <s> seconds of campaign time have passed
"""
from __future__ import annotations

import json
import time

from deltatwin.hw.driver import LineInstrument
from deltatwin.hw.protocol import Command, generic_protocol, real, text
from deltatwin.twin.instruments.interface import DEFAULT_TIMEOUT_S, Clock

PROTOCOL = generic_protocol("deltatwin emulated clock", {
    "now": Command("TIME?", "TIME {t_s}", {"t_s": real()}),
    "sleep": Command("SLEEP {s}", "SLEEP OK", {"s": real()}),
    # the emulated laboratory's world: its scenario, scenario_sha256, seed and scale as one JSON
    # object ({} when it does not say), so a campaign refuses to run against another scenario
    "world": Command("WORLD?", "WORLD {world}", {"world": text(r"\{[ -~]*\}")}),
})
IDENTITY_PREFIX = "deltatwin emulated clock"


class WallClock(Clock):
    """Seconds since the campaign started: ``start_s`` at creation, then the monotonic wall
    clock. A resumed campaign passes the campaign time it has reached (last journaled point +
    the wall time since it was journaled), so its timeline continues."""

    def __init__(self, start_s: float = 0.0):
        self._t0 = time.monotonic() - start_s

    def now(self) -> float:
        return time.monotonic() - self._t0

    def sleep(self, seconds: float) -> None:
        if seconds > 0:
            time.sleep(seconds)


class SerialClock(LineInstrument, Clock):
    protocol = PROTOCOL
    identity_prefix = IDENTITY_PREFIX

    def __init__(self, line, *, name="clock", **kw):
        super().__init__(line, name=name, **kw)

    def now(self) -> float:
        return self.operation("now", lambda: self.ask("now")["t_s"], DEFAULT_TIMEOUT_S)

    def world(self) -> dict:
        """What the emulated laboratory simulates (scenario, scenario_sha256, seed, scale), or
        {} when it does not say."""
        return self.operation("world", lambda: json.loads(self.ask("world")["world"]),
                              DEFAULT_TIMEOUT_S)

    def sleep(self, seconds: float) -> None:
        """Wait ``seconds`` of campaign time (a lost reply makes the retry wait again)."""
        if seconds <= 0:
            return
        wait = seconds + self.line.timeout_s   # covers an emulator paced in real time
        self.operation("sleep", lambda: self.ask("sleep", timeout_s=wait, s=seconds),
                       DEFAULT_TIMEOUT_S + seconds)
