"""The position controllers settle each motor within a few encoder increments of its target,
differently each time."""
from __future__ import annotations

from deltatwin.twin.effects.base import Effect, Parameter


class ServoSettling(Effect):
    name = "servo_settling"
    summary = ("After every move and every change of the load (the coil currents) each motor's "
               "controller settles at a random angle about its target (std ``angle_std_rad``, "
               "below the encoders' resolution: the encoders read the target). The platform "
               "therefore sits a few tens of nm from where it sat the last time it was at the "
               "same position under the same load: the non-repeatability of the second paper's "
               "2 A test. No model form (random per settling).")
    parameters = (
        Parameter("angle_std_rad", "rad", 1e-7, "std of a motor's settled angle about its "
                  "target, per settling", 0.0),
    )

    def motor_settling(self, rng, n):
        return self.angle_std_rad * rng.standard_normal((n, 3))
