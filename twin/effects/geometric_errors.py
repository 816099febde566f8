"""Manufacturing and assembly errors of the robot's geometry: explicit deviations (what a fit
identifies) plus, in the twin, a seeded random draw once per robot."""
from __future__ import annotations

from deltatwin.twin.effects.base import Effect, Parameter


class GeometricErrors(Effect):
    name = "geometric_errors"
    summary = ("Every rod and arm length, base/elbow/platform joint position, encoder zero and "
               "actuator axis direction deviates from nominal: the explicit errors below plus, in "
               "the twin, a seeded random draw (std below), added to the deviations already in "
               "the robot parameters.")
    parameters = (
        Parameter("rod_length_error_m", "m", ((0.0, 0.0),) * 3, "each rod's length error",
                  fit_scale=3e-6),
        Parameter("arm_length_error_m", "m", (0.0,) * 3, "each arm's length error", fit_scale=10e-6),
        Parameter("base_joint_error_m", "m", ((0.0,) * 3,) * 3,
                  "each actuator axis point's position error (x, y, z)", fit_scale=10e-6),
        Parameter("elbow_joint_error_m", "m", (((0.0,) * 3,) * 2,) * 3,
                  "each elbow hinge's position error (chain, rod, xyz)", fit_scale=10e-6),
        Parameter("platform_joint_error_m", "m", (((0.0,) * 3,) * 2,) * 3,
                  "each platform hinge's position error (chain, rod, xyz)", fit_scale=10e-6),
        Parameter("encoder_offset_rad", "rad", (0.0,) * 3, "each encoder's zero error",
                  fit_scale=50e-6),
        Parameter("axis_tilt_rad", "rad", ((0.0, 0.0),) * 3,
                  "each actuator axis' tilt towards radial and vertical", fit_scale=100e-6),
        Parameter("rod_length_std_m", "m", 3e-6, "std of each rod's length error", 0.0),
        Parameter("arm_length_std_m", "m", 10e-6, "std of each arm's length error", 0.0),
        Parameter("joint_position_std_m", "m", 10e-6,
                  "std of each coordinate of every base, elbow and platform joint", 0.0),
        Parameter("encoder_offset_std_rad", "rad", 50e-6, "std of each encoder's zero error", 0.0),
        Parameter("axis_tilt_std_rad", "rad", 100e-6, "std of each actuator axis tilt", 0.0),
    )

    def robot(self, params, rng):
        # explicit errors, then (twin only) the random draw, in a fixed order of streams
        draw = ((lambda shape: 0.0) if rng is None else rng.standard_normal)
        return params.replace(
            d_rod_length_m=params.d_rod_length_m + self.rod_length_error_m
            + self.rod_length_std_m * draw((3, 2)),
            d_arm_length_m=params.d_arm_length_m + self.arm_length_error_m
            + self.arm_length_std_m * draw(3),
            d_base_joint_m=params.d_base_joint_m + self.base_joint_error_m
            + self.joint_position_std_m * draw((3, 3)),
            d_elbow_joint_m=params.d_elbow_joint_m + self.elbow_joint_error_m
            + self.joint_position_std_m * draw((3, 2, 3)),
            d_platform_joint_m=params.d_platform_joint_m + self.platform_joint_error_m
            + self.joint_position_std_m * draw((3, 2, 3)),
            encoder_offset_rad=params.encoder_offset_rad + self.encoder_offset_rad
            + self.encoder_offset_std_rad * draw(3),
            actuator_axis_tilt_rad=params.actuator_axis_tilt_rad + self.axis_tilt_rad
            + self.axis_tilt_std_rad * draw((3, 2)),
        )
