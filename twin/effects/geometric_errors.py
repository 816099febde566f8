"""Manufacturing and assembly errors of the robot's geometry, drawn once per robot."""
from __future__ import annotations

import numpy as np

from .base import Effect, Parameter


class GeometricErrors(Effect):
    name = "geometric_errors"
    summary = ("Every rod and arm length, base/elbow/platform joint position, encoder zero and "
               "actuator axis direction deviates from nominal by a seeded random draw (std below), "
               "added to the deviations already in the robot parameters.")
    parameters = (
        Parameter("rod_length_std_m", "m", 3e-6, "std of each rod's length error", 0.0),
        Parameter("arm_length_std_m", "m", 10e-6, "std of each arm's length error", 0.0),
        Parameter("joint_position_std_m", "m", 10e-6,
                  "std of each coordinate of every base, elbow and platform joint", 0.0),
        Parameter("encoder_offset_std_rad", "rad", 50e-6, "std of each encoder's zero error", 0.0),
        Parameter("axis_tilt_std_rad", "rad", 100e-6, "std of each actuator axis tilt", 0.0),
    )

    def robot(self, params, rng):
        n = rng.standard_normal
        return params.replace(
            d_rod_length_m=params.d_rod_length_m + self.rod_length_std_m * n((3, 2)),
            d_arm_length_m=params.d_arm_length_m + self.arm_length_std_m * n(3),
            d_base_joint_m=params.d_base_joint_m + self.joint_position_std_m * n((3, 3)),
            d_elbow_joint_m=params.d_elbow_joint_m + self.joint_position_std_m * n((3, 2, 3)),
            d_platform_joint_m=params.d_platform_joint_m + self.joint_position_std_m * n((3, 2, 3)),
            encoder_offset_rad=params.encoder_offset_rad + self.encoder_offset_std_rad * n(3),
            actuator_axis_tilt_rad=params.actuator_axis_tilt_rad + self.axis_tilt_std_rad * n((3, 2)),
        )
