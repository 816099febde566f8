"""Joule heating of the force simulator's coils (they had to go into an insulated box)."""
from __future__ import annotations

from deltatwin.twin.effects.base import Effect, Parameter


class CoilHeating(Effect):
    name = "coil_heating"
    summary = "Each coil dissipates R I^2 into its winding, in an insulated box on the table."
    parameters = (
        Parameter("resistance_Ohm", "Ohm", 6.5,
                  "winding resistance (800 turns of 0.5 mm copper, ~75 m)", 0.0),
    )

    def heat_sources(self, t_grid, schedule, params):
        I = schedule.currents(t_grid)
        return {f"coil{i + 1}": self.resistance_Ohm * I[:, i] ** 2 for i in range(3)}
