"""Emulators of the protocols in this project's generic convention (robot controller, coil
supply, SP-2000 as defined in hw/sp2000.py, clock): errors are replies ``ERR <code> <reason>``;
an unknown or checksum-failing request gets ``ERR 1``/``ERR 3``; a backing failure ``ERR 5``."""
from __future__ import annotations

from deltatwin.hw.emulators.base import LineEmulator
from deltatwin.hw.protocol import GENERIC_ERRORS
from deltatwin.twin.instruments.interface import InstrumentError


class GenericEmulator(LineEmulator):
    default_error_code = 5
    identity = ""

    def handle(self, command: str, values: dict) -> str | None:
        if command == "identify":
            return self.protocol.reply("identify", identity=self.identity)
        return self.serve(command, values)

    def serve(self, command: str, values: dict) -> str | None:
        raise NotImplementedError

    def unknown(self, line: str) -> str | None:
        payload = self.protocol.framing.decode(line)
        if payload is None:
            return self.protocol.error_reply(3, GENERIC_ERRORS[3])
        shown = "".join(c if " " <= c <= "~" else "?" for c in payload[:40])
        command = self.protocol.command_with_header(line)
        if command is not None:
            return self.protocol.error_reply(2, f"{GENERIC_ERRORS[2]}: {shown}")
        return self.protocol.error_reply(1, f"{GENERIC_ERRORS[1]}: {shown}")

    def overlong(self) -> str | None:
        return self.protocol.error_reply(2, f"{GENERIC_ERRORS[2]}: request longer than "
                                            f"{self.max_line} characters")

    def bad_argument(self, reason: str) -> str:
        return self.protocol.error_reply(2, f"{GENERIC_ERRORS[2]}: {reason}")

    def fail(self, error: InstrumentError, request) -> str | None:
        code = error.code if isinstance(error.code, int) and error.code in GENERIC_ERRORS else 5
        reason = error.reason if error.code in (None, code) else f"{error.reason} [{error.code}]"
        return self.protocol.error_reply(code, reason)
