"""SP-2000 emulator for the protocol defined in hw/sp2000.py, answered from the backing
``Interferometers`` (nm at 0.001 nm).

Besides the line faults of every emulator (hw/emulators/base.py) it injects ``turbulence``: an
air turbulence burst over the beams, seen as a reading window whose sample standard deviation
is ``TURBULENCE_FACTOR`` times the backing's on every axis (``inject("turbulence", count,
after=...)``, applied to ``READ?`` requests). The reply is well formed: rejecting the window is
the campaign's acceptance rule (std limit), which reads again."""
from __future__ import annotations

from deltatwin.hw.emulators.generic import GenericEmulator
from deltatwin.hw.sp2000 import NM, PROTOCOL

TURBULENCE_FACTOR = 10.0


class SP2000Emulator(GenericEmulator):
    protocol = PROTOCOL
    identity = "SIOS SP-2000,emulated,deltatwin"
    instrument_faults = ("turbulence",)

    def instrument_fault_applies(self, kind: str, command: str | None) -> bool:
        return command == "read"

    def serve(self, command: str, values: dict) -> str | None:
        ifm = self.backing.instruments.interferometers
        if command == "axes":
            return self.protocol.reply("axes", axes=tuple(ifm.axes))
        if command == "zero":
            self.backing.call(ifm.zero)
            return self.protocol.reply("zero")
        r = self.backing.call(ifm.read)
        factor = TURBULENCE_FACTOR if self.active_fault is not None else 1.0
        values = {a: (r.displacement_m[a] / NM, factor * r.std_m[a] / NM) for a in ifm.axes}
        return self.protocol.reply("read", n_samples=r.n_samples, window_s=r.window_s,
                                   values=values)
