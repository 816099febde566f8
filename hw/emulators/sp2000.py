"""SP-2000 emulator for the protocol defined in hw/sp2000.py, answered from the backing
``Interferometers`` (nm at 0.001 nm)."""
from __future__ import annotations

from hw.emulators.generic import GenericEmulator
from hw.sp2000 import NM, PROTOCOL


class SP2000Emulator(GenericEmulator):
    protocol = PROTOCOL
    identity = "SIOS SP-2000,emulated,deltatwin"

    def serve(self, command: str, values: dict) -> str | None:
        ifm = self.backing.instruments.interferometers
        if command == "axes":
            return self.protocol.reply("axes", axes=tuple(ifm.axes))
        if command == "zero":
            self.backing.call(ifm.zero)
            return self.protocol.reply("zero")
        r = self.backing.call(ifm.read)
        values = {a: (r.displacement_m[a] / NM, r.std_m[a] / NM) for a in ifm.axes}
        return self.protocol.reply("read", n_samples=r.n_samples, window_s=r.window_s,
                                   values=values)
