"""The papers' contactless force simulator: three coils below the platform repel three magnets.

Each magnet (15x15x3 mm NdFeB, magnetised through its thickness) is a point dipole moving with
the platform, pointing down; each coil with its ferrite core is a point dipole fixed on the
table, pointing up, of moment proportional to its current: like poles face each other, so the
force is repulsive and grows fast as the gap closes (~1/r^4), i.e. stronger low in the
workspace. Force and torque of every coil on every magnet (the exact dipole-dipole formulas,
so lateral offsets give lateral forces) are summed into a wrench about the platform origin.
"""
from __future__ import annotations

import numpy as np

from deltatwin.models.mjcf import MAGNET_HALF_M, magnet_positions
from deltatwin.twin.effects.base import Effect, Parameter

MU0 = 4e-7 * np.pi


def dipole_force_torque(m1, r1, m2, r2):
    """Force (N) and torque (N*m, about r2) on dipole m2 at r2 from dipole m1 at r1 (A*m^2, m).
    Arrays broadcast over leading axes (..., 3)."""
    r = r2 - r1
    d = np.linalg.norm(r, axis=-1, keepdims=True)
    u = r / d
    m1u = np.sum(m1 * u, -1, keepdims=True)
    m2u = np.sum(m2 * u, -1, keepdims=True)
    m1m2 = np.sum(m1 * m2, -1, keepdims=True)
    F = 3 * MU0 / (4 * np.pi * d ** 4) * (m2 * m1u + m1 * m2u + u * m1m2 - 5 * u * m1u * m2u)
    B = MU0 / (4 * np.pi * d ** 3) * (3 * u * m1u - m1)
    return F, np.cross(m2, B)


class MagneticForce(Effect):
    name = "magnetic_force"
    summary = ("Coil-magnet repulsion from the coil currents (dipole model): force and moment on "
               "each magnet from current, gap and lateral offset, summed into the platform wrench.")
    parameters = (
        Parameter("magnet_moment_Am2", "A*m^2", 0.64,
                  "magnet dipole moment (Br V / mu0: 1.2 T, 15x15x3 mm)", 0.0),
        Parameter("coil_moment_per_A", "A*m^2/A", 0.16,
                  "coil + ferrite core dipole moment per ampere (800 turns)", 0.0, fit_scale=0.02),
        Parameter("core_depth_m", "m", 0.008, "coil dipole centre below the coil face", 0.0),
        Parameter("coil_offset_m", "m", ((-0.0025, -0.006, 0.0),) * 3,
                  "each coil's position error from under its magnet at home (world x, y, z)",
                  fit_scale=1e-3, fit_start=0.0),
    )

    def __init__(self, where="effect", **values):
        super().__init__(where, **values)
        self._coils = None

    def coil_dipoles(self, params, home_pose_p):
        """Coil dipole centres (3,3), world frame: under each magnet at the home pose, across the
        nominal gap, plus the coil offsets."""
        mag = home_pose_p + magnet_positions(params)
        face = mag - np.array([0.0, 0.0, MAGNET_HALF_M[2] + params.coil_gap_m])
        return face - np.array([0.0, 0.0, self.core_depth_m]) + self.coil_offset_m

    def wrench(self, points):
        pose, params = points.pose, points.params
        coils = self.coil_dipoles(params, points.home_p)                       # (3,3)
        mag = pose.p[:, None, :] + (pose.R[:, None] @ magnet_positions(params)[None, :, :, None])[..., 0]
        m_mag = -self.magnet_moment_Am2 * pose.R[:, :, 2]                       # down, with platform
        m_mag = np.broadcast_to(m_mag[:, None, None, :], mag.shape[:2] + (3, 3))
        m_coil = np.zeros(points.currents_A.shape + (3,))
        m_coil[..., 2] = self.coil_moment_per_A * points.currents_A             # (N,3 coils,3)
        # every coil (axis 2) on every magnet (axis 1)
        F, tau = dipole_force_torque(m_coil[:, None, :, :], coils[None, None, :, :],
                                     m_mag, mag[:, :, None, :])
        F_mag = F.sum(axis=2)                                                   # (N,3 magnets,3)
        arm = mag - pose.p[:, None, :]
        w = np.zeros((pose.p.shape[0], 6))
        w[:, :3] = F_mag.sum(axis=1)
        w[:, 3:] = (np.cross(arm, F_mag) + tau.sum(axis=2)).sum(axis=1)
        return w
