"""Measurement-loop drift: the table, the metrology frame and the instrument supports expand,
moving the interferometer heads and the fold mirror relative to the robot's base."""
from __future__ import annotations

import numpy as np

from deltatwin.twin.effects.base import Effect, Parameter


class LoopDrift(Effect):
    name = "loop_drift"
    reads_temperatures = True
    summary = ("The table expands in its plane about the robot's axis, the frame lifts the robot's "
               "base (and, when the robot hangs from an arm of the frame, moves it sideways by "
               "table minus frame expansion over the arm), each support lifts its head; heads and "
               "the Z fold mirror move relative to the base by CTE * dT * length of every leg of "
               "the loop.")
    parameters = (
        Parameter("frame_height_m", "m", 0.35, "table top to the robot's base plane", 0.0),
        Parameter("frame_arm_m", "m", (0.0, 0.0),
                  "horizontal (x, y) position of the frame's column relative to the robot's axis, "
                  "the robot hanging from a horizontal arm of the frame; (0, 0): a symmetric "
                  "portal, no sideways drift"),
        # the table's and the frame's material is the laboratory's: steel by default, and
        # granite (6-8e-6), cast iron (10e-6) and aluminium (23e-6) within two tolerances
        Parameter("table_cte_per_K", "1/K", 11.7e-6, "table (steel)", 0.0, fit_scale=2e-6,
                  per_kelvin=True, prior_tolerance=6e-6),
        Parameter("frame_cte_per_K", "1/K", 11.7e-6, "metrology frame (steel)", 0.0,
                  fit_scale=2e-6, per_kelvin=True, prior_tolerance=6e-6),
        Parameter("support_cte_per_K", "1/K", 23e-6, "instrument supports (aluminium)", 0.0,
                  fit_scale=3e-6, per_kelvin=True),
        Parameter("reference_C", "degC", 20.0, "temperature at which the loop is as drawn"),
    )

    def _drift(self, points, position, support_C):
        """Displacement (N,3) of an element at ``position`` (N,3, base frame) on a support."""
        dT_table = points.node_T["table"] - self.reference_C
        dT_frame = points.node_T["frame"] - self.reference_C
        height = self.frame_height_m + position[:, 2]            # support height above the table
        d = np.zeros_like(position)
        # the column's foot moves with the table, the arm from the column to the robot expands
        # with the frame: the base moves by (table - frame expansion) * arm, the loop the other way
        base_shift = ((self.table_cte_per_K * dT_table - self.frame_cte_per_K * dT_frame)[:, None]
                      * np.asarray(self.frame_arm_m))
        d[:, :2] = self.table_cte_per_K * dT_table[:, None] * position[:, :2] - base_shift
        d[:, 2] = (self.support_cte_per_K * (support_C - self.reference_C) * height
                   - self.frame_cte_per_K * dT_frame * self.frame_height_m)
        return d

    def optics(self, points, optics):
        for axis in optics.head:
            optics.head[axis] = optics.head[axis] + self._drift(points, optics.head[axis],
                                                                points.support_C[axis])
        # the fold mirror stands on a post at table temperature
        optics.fold = optics.fold + self._drift(points, optics.fold, points.node_T["table"])
