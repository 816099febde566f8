"""Clock emulator (hw/clock.py's protocol): the backing ``InstrumentSet``'s clock on a port,
so that drivers follow the twin's simulated time."""
from __future__ import annotations

from deltatwin.hw.clock import PROTOCOL
from deltatwin.hw.emulators.generic import GenericEmulator


class ClockEmulator(GenericEmulator):
    protocol = PROTOCOL
    identity = "deltatwin emulated clock"

    def serve(self, command: str, values: dict) -> str | None:
        clock = self.backing.instruments.clock
        if command == "now":
            return self.protocol.reply("now", t_s=self.backing.call(clock.now))
        self.backing.call(clock.sleep, values["s"])
        return self.protocol.reply("sleep")
