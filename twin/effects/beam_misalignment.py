"""Interferometer beams not parallel to the axes and not through the cube centre."""
from __future__ import annotations

import numpy as np

from deltatwin.models import batched
from deltatwin.twin.effects.base import Effect, Parameter


def _tilt(direction, angles):
    """Tilt unit vectors (N,3) by two small angles about the two axes normal to them; the
    tilted vectors and the two axes, (N,3) each (computed component-first, models/batched.py)."""
    b = direction.T
    helper = np.zeros_like(b)
    upright = np.abs(b[2]) < 0.9
    helper[2], helper[0] = upright, ~upright
    e1 = batched.cross(b, helper)
    e1 /= np.sqrt(batched.dot(e1, e1))
    e2 = batched.cross(b, e1)
    d = b + angles[0] * e1 + angles[1] * e2
    return (d / np.sqrt(batched.dot(d, d))).T, e1.T, e2.T


class BeamMisalignment(Effect):
    name = "beam_misalignment"
    summary = ("Each beam tilted by two angles (cosine error of the axis itself) and offset "
               "sideways from the cube centre (Abbe offsets: parasitic rotations then read as "
               "displacement).")
    parameters = (
        Parameter("angle_rad", "rad", ((2e-4, -1e-4), (-1.5e-4, 2e-4), (1e-4, 1.5e-4)),
                  "per axis x, y, z: two tilt angles of the beam", fit_scale=2e-4, fit_start=0.0),
        Parameter("abbe_offset_m", "m", ((0.8e-3, -0.5e-3), (-0.6e-3, 0.7e-3), (0.5e-3, 0.9e-3)),
                  "per axis x, y, z: two sideways offsets of the beam from the cube centre",
                  fit_scale=1e-3, fit_start=0.0),
    )

    def optics(self, points, optics):
        for k, axis in enumerate(("x", "y", "z")):
            d, e1, e2 = _tilt(optics.direction[axis], self.angle_rad[k])
            optics.direction[axis] = d
            optics.head[axis] = (optics.head[axis] + self.abbe_offset_m[k, 0] * e1
                                 + self.abbe_offset_m[k, 1] * e2)
