"""Clock emulator (hw/clock.py's protocol): the backing ``InstrumentSet``'s clock on a port,
so that drivers follow the twin's simulated time."""
from __future__ import annotations

import json
import math

from deltatwin.hw.clock import PROTOCOL
from deltatwin.hw.emulators.generic import GenericEmulator


class ClockEmulator(GenericEmulator):
    protocol = PROTOCOL
    identity = "deltatwin emulated clock"

    def __init__(self, *args, world: dict | None = None, **kw):
        super().__init__(*args, **kw)
        self.world = dict(world or {})     # what the backing simulates (WORLD?)

    def serve(self, command: str, values: dict) -> str | None:
        clock = self.backing.instruments.clock
        if command == "now":
            return self.protocol.reply("now", t_s=self.backing.call(clock.now))
        if command == "world":
            return self.protocol.reply("world", world=json.dumps(self.world, sort_keys=True))
        s = values["s"]
        if not (math.isfinite(s) and s >= 0):
            return self.bad_argument(f"sleep must be a finite number of seconds >= 0, got {s!r}")
        try:
            self.backing.call(clock.sleep, s)
        except ValueError as exc:      # e.g. past the end of a simulated world
            return self.bad_argument(str(exc))
        return self.protocol.reply("sleep")
