"""Robot controller emulator: ``MOVE`` starts the backing ``Robot.move_to`` in the background,
``INPOS?`` reports 0 while it runs, then 1 (or the move's error, once), ``ENC?`` reads the
backing encoders."""
from __future__ import annotations

import numpy as np

from deltatwin.hw.emulators.base import BackgroundAction
from deltatwin.hw.emulators.generic import GenericEmulator
from deltatwin.hw.robot_controller import PROTOCOL


class RobotControllerEmulator(GenericEmulator):
    protocol = PROTOCOL
    identity = "deltatwin robot controller,emulated,1.0"

    def __init__(self, *args, **kw):
        super().__init__(*args, **kw)
        self.motion = BackgroundAction()

    def serve(self, command: str, values: dict) -> str | None:
        robot = self.backing.instruments.robot
        if command == "move":
            if self.motion.busy:
                return self.protocol.error_reply(4, "busy: moving")
            q = np.array(values["q"])
            if not np.all(np.isfinite(q)):
                return self.bad_argument(f"target must be finite numbers (rad), got {q.tolist()}")
            self.motion.start(self.backing.call, robot.move_to, q)
            return self.protocol.reply("move")
        if command == "in_position":
            return self.protocol.reply("in_position", state=int(self.motion.done()))
        return self.protocol.reply("encoders", q=self.backing.call(robot.read_encoders))
