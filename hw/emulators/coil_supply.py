"""Coil supply emulator: ``CURR i1 i2 i3`` starts the backing ``CoilSupply.set_currents`` in
the background, ``SETTLED?`` reports 0 while it runs, ``CURR?`` reads the backing currents."""
from __future__ import annotations

import numpy as np

from deltatwin.hw.coil_supply import PROTOCOL
from deltatwin.hw.emulators.base import BackgroundAction
from deltatwin.hw.emulators.generic import GenericEmulator


class CoilSupplyEmulator(GenericEmulator):
    protocol = PROTOCOL
    identity = "deltatwin coil supply,emulated,1.0"

    def __init__(self, *args, **kw):
        super().__init__(*args, **kw)
        self.ramp = BackgroundAction()

    def serve(self, command: str, values: dict) -> str | None:
        coils = self.backing.instruments.coils
        if command == "set":
            if self.ramp.busy:
                return self.protocol.error_reply(4, "busy: settling")
            currents = np.array(values["currents"])
            if currents.shape != (coils.n_coils,):
                return self.bad_argument(f"{coils.n_coils} currents expected, got "
                                         f"{currents.size}")
            if not np.all(np.isfinite(currents)):
                return self.bad_argument(f"currents must be finite numbers (A), got "
                                         f"{currents.tolist()}")
            self.ramp.start(self.backing.call, coils.set_currents, currents)
            return self.protocol.reply("set")
        if command == "settled":
            return self.protocol.reply("settled", state=int(self.ramp.done()))
        return self.protocol.reply("read", currents=self.backing.call(coils.read_currents))
