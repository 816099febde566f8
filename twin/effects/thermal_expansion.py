"""Each robot part expands with its own temperature (its material's CTE)."""
from __future__ import annotations

import numpy as np

from deltatwin.twin.effects.base import Effect, Parameter

PARTS = ("base", "arms", "rods", "platform")


class ThermalExpansion(Effect):
    name = "thermal_expansion"
    reads_temperatures = True
    summary = ("Base, each arm, each rod pair and the platform take their node temperature from "
               "the thermal network and scale their joint geometry by 1 + CTE (T - T_ref); the "
               "kinematics are solved exactly with the per-point geometry.")
    parameters = (
        Parameter("cte_factor", "-", (1.0,) * 4,
                  "CTE of base, arms, rods, platform relative to their material's", 0.0,
                  fit_scale=0.05, per_kelvin=True),
    )

    def part_temperatures(self, points):
        T = points.node_T
        n = points.t_s.shape[0]
        T_ref = points.params.reference_temperature_C
        rods = np.stack([T["rod1"], T["rod2"], T["rod3"]], axis=1)
        parts = {"base": T["base"], "arms": np.stack([T["arm1"], T["arm2"], T["arm3"]], axis=1),
                 "rods": np.broadcast_to(rods[:, :, None], (n, 3, 2)), "platform": T["platform"]}
        # a CTE factor f scales the expansion: the same as a temperature rise scaled by f
        return {part: T_ref + f * (parts[part] - T_ref) for part, f in zip(PARTS, self.cte_factor)}
