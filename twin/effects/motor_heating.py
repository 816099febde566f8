"""The actuators' motors heat the base and the arms, more while they move."""
from __future__ import annotations

from deltatwin.twin.effects.base import Effect, Parameter


class MotorHeating(Effect):
    name = "motor_heating"
    summary = ("Each motor dissipates a holding power (it carries its arm) and more while it "
               "moves, in proportion to its share of the move; heat flows to the base and arm.")
    parameters = (
        Parameter("hold_power_W", "W", 0.5, "per motor, at rest", 0.0),
        Parameter("move_power_W", "W", 4.0, "per motor, while moving at full speed", 0.0),
    )

    def heat_sources(self, t_grid, schedule, params):
        speed = schedule.speed_fraction(t_grid)                 # (n,3) in [0, 1]
        return {f"motor{i + 1}": self.hold_power_W + self.move_power_W * speed[:, i]
                for i in range(3)}
