"""The robot's motion controller (``Robot``): a generic line protocol (docs/hardware.md).

CRC-16 framing, LF; any reply may instead be ``ERR <code> <reason>``.

    *IDN?            -> IDN deltatwin robot controller,<serial>,<firmware>
    MOVE q1 q2 q3    -> MOVE OK        start a move to motor coordinates (rad); ERR 4 if moving
    INPOS?           -> INPOS 0|1      1 once the move has ended in position; ERR 5 <reason>
                                       (once) if the move failed
    ENC?             -> ENC q1 q2 q3   encoder readings (rad, 13 significant digits)

Targets are written with every digit (exact float64 round trip).
"""
from __future__ import annotations

import time

import numpy as np

from deltatwin.hw.driver import LineInstrument
from deltatwin.hw.protocol import Command, generic_protocol, integer, reals
from deltatwin.twin.instruments.interface import DEFAULT_TIMEOUT_S, InstrumentTimeout, Robot

PROTOCOL = generic_protocol("deltatwin robot controller", {
    "move": Command("MOVE {q}", "MOVE OK", {"q": reals(3)}),
    "in_position": Command("INPOS?", "INPOS {state}", {"state": integer()}),
    "encoders": Command("ENC?", "ENC {q}", {"q": reals(3, "{:.12e}")}),
})
IDENTITY_PREFIX = "deltatwin robot controller"
POLL_S = 0.002   # in-position polling period (wall clock)


class RobotController(LineInstrument, Robot):
    protocol = PROTOCOL
    identity_prefix = IDENTITY_PREFIX

    def __init__(self, line, *, name="robot", **kw):
        super().__init__(line, name=name, **kw)

    def _move_once(self, q: np.ndarray, deadline: float) -> None:
        self.ask("move", q=q)
        while not self.ask("in_position")["state"]:
            if time.monotonic() > deadline:
                raise InstrumentTimeout(self.name, f"not in position at {q.tolist()} rad "
                                                   f"before the move's deadline")
            time.sleep(POLL_S)

    def move_to(self, q_rad: np.ndarray, timeout_s: float = DEFAULT_TIMEOUT_S) -> None:
        q = np.asarray(q_rad, dtype=np.float64).reshape(3)
        deadline = time.monotonic() + timeout_s
        self.operation("move_to", lambda: self._move_once(q, deadline), timeout_s)

    def read_encoders(self, timeout_s: float = DEFAULT_TIMEOUT_S) -> np.ndarray:
        q = self.operation("read_encoders", lambda: self.ask("encoders")["q"], timeout_s)
        return np.array(q, dtype=np.float64)
