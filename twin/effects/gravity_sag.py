"""The platform's weight through the robot's compliance."""
from __future__ import annotations

import numpy as np

from deltatwin.twin.effects.base import Effect, Parameter
from deltatwin.twin.statics import GRAVITY_M_S2


class GravitySag(Effect):
    name = "gravity_sag"
    summary = ("The weight of the platform (with cube and magnets) acts at its centre of mass; the "
               "statics turn it into a pose-dependent sag (tens of nm).")
    parameters = (
        Parameter("load_factor", "-", 1.0,
                  "the weight (platform mass x g) relative to the robot file's platform mass", 0.0,
                  fit_scale=0.1),
    )

    def wrench(self, points):
        w = np.zeros((points.t_s.shape[0], 6))
        w[:, 2] = -self.load_factor * points.params.platform_mass_kg * GRAVITY_M_S2
        return w
