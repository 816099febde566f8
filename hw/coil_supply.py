"""The force simulator's coil current supply (``CoilSupply``): a generic line protocol
(docs/hardware.md). One command sets every coil, so the coils change together.

CRC-16 framing, LF; any reply may instead be ``ERR <code> <reason>``.

    *IDN?             -> IDN deltatwin coil supply,<serial>,<firmware>
    CURR i1 i2 i3     -> CURR OK          set each coil's current (A); ERR 4 if still settling
    SETTLED?          -> SETTLED 0|1      1 once the currents have settled; ERR 5 <reason>
                                          (once) if setting them failed
    CURR?             -> CURR i1 i2 i3    measured currents (A, 1 µA resolution)
"""
from __future__ import annotations

import time

import numpy as np

from deltatwin.hw.driver import LineInstrument
from deltatwin.hw.protocol import Command, ReplyError, generic_protocol, integer, reals
from deltatwin.twin.instruments.interface import DEFAULT_TIMEOUT_S, CoilSupply, InstrumentTimeout

PROTOCOL = generic_protocol("deltatwin coil supply", {
    "set": Command("CURR {currents}", "CURR OK", {"currents": reals()}),
    "settled": Command("SETTLED?", "SETTLED {state}", {"state": integer()}),
    "read": Command("CURR?", "CURR {currents}", {"currents": reals(None, "{:.6f}")}),
})
IDENTITY_PREFIX = "deltatwin coil supply"
POLL_S = 0.002


class CoilSupplyDriver(LineInstrument, CoilSupply):
    protocol = PROTOCOL
    identity_prefix = IDENTITY_PREFIX

    def __init__(self, line, *, n_coils: int = 3, name="coils", **kw):
        super().__init__(line, name=name, **kw)
        self.n_coils = n_coils

    def _set_once(self, currents: np.ndarray, deadline: float) -> None:
        self.ask("set", currents=currents)
        while not self.ask("settled")["state"]:
            if time.monotonic() > deadline:
                raise InstrumentTimeout(self.name, f"currents {currents.tolist()} A not settled "
                                                   f"before the deadline")
            time.sleep(POLL_S)

    def set_currents(self, currents_A: np.ndarray, timeout_s: float = DEFAULT_TIMEOUT_S) -> None:
        currents = np.asarray(currents_A, dtype=np.float64).reshape(-1)
        if currents.shape != (self.n_coils,):
            raise ValueError(f"{self.name}: {self.n_coils} currents expected, got {currents.shape}")
        deadline = time.monotonic() + timeout_s
        self.operation("set_currents", lambda: self._set_once(currents, deadline), timeout_s)

    def _read_once(self) -> np.ndarray:
        currents = self.ask("read")["currents"]
        if len(currents) != self.n_coils:
            raise ReplyError(self.name, f"CURR? gave {len(currents)} currents, expected "
                                        f"{self.n_coils}")
        return np.array(currents, dtype=np.float64)

    def read_currents(self, timeout_s: float = DEFAULT_TIMEOUT_S) -> np.ndarray:
        return self.operation("read_currents", self._read_once, timeout_s)
