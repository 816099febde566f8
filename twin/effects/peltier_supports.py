"""Peltier-stabilised interferometer supports: steady heads, but a warmer table."""
from __future__ import annotations

from deltatwin.twin.effects.base import Effect, Parameter
from deltatwin.twin.effects.room_climate import ornstein_uhlenbeck
from deltatwin.twin.thermal import SUPPORTS


class PeltierSupports(Effect):
    name = "peltier_supports"
    summary = ("The three interferometer supports are held at their set point by PID-controlled "
               "Peltier elements (±stability); they conduct heat into the table and warm the "
               "air by the beams (the table ends 1-2 K above the room).")
    parameters = (
        Parameter("setpoint_C", "degC", 25.0, "support temperature"),
        Parameter("stability_C", "K", 0.01, "std of the controlled temperature", 0.0),
    )

    def environment(self, env, rng):
        for s in SUPPORTS:
            env.supports_C[s] = self.setpoint_C + ornstein_uhlenbeck(
                rng, env.t_grid, self.stability_C, 600.0, step_s=10.0)
