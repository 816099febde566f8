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

from deltatwin.models import batched
from deltatwin.models.layout import MAGNET_HALF_M, magnet_positions
from deltatwin.twin.effects.base import Effect, Parameter

MU0 = 4e-7 * np.pi


def dipole_force_torque(m1, r1, m2, r2):
    """Force (N) and torque (N*m, about r2) on dipole m2 at r2 from dipole m1 at r1 (A*m^2, m).
    Component-first arrays (3, ...) broadcasting over the trailing axes (models/batched.py)."""
    r = r2 - r1
    d2 = batched.dot(r, r)
    d = np.sqrt(d2)
    u = r / d
    m1u = batched.dot(m1, u)
    m2u = batched.dot(m2, u)
    m1m2 = batched.dot(m1, m2)
    F = 3 * MU0 / (4 * np.pi * d2 * d2) * (m2 * m1u + m1 * m2u + u * m1m2 - 5 * u * m1u * m2u)
    B = MU0 / (4 * np.pi * d2 * d) * (3 * u * m1u - m1)
    return F, batched.cross(m2, B)


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
        w = np.zeros((pose.p.shape[0], 6))
        # a coil without current has no moment and exerts nothing: only the rows with a current
        # are computed (a thermal campaign's are all zero)
        rows = np.flatnonzero(np.any(points.currents_A != 0, axis=1))
        if rows.size == 0:
            return w
        every = rows.size == w.shape[0]
        p, R_all, I_all = ((pose.p, pose.R, points.currents_A) if every else
                           (pose.p[rows], pose.R[rows], points.currents_A[rows]))
        coils = self.coil_dipoles(params, points.home_p).T[:, None, :, None]   # (3,1,3 coils,1)
        magnets = magnet_positions(params).T[:, :, None]                       # (3,3 magnets,1)
        out = w if every else np.empty((rows.size, 6))

        def chunk(sl):      # chunks of points: the nine pairs' arrays stay in the CPU caches
            R = R_all[sl].transpose(1, 2, 0)                                   # (3,3,m)
            # magnets (axis 1) component-first: lever from the platform origin, centre (3,3,m)
            arm = batched.matvec(R[:, :, None], magnets)
            mag = p[sl].T[:, None] + arm
            m_mag = (-self.magnet_moment_Am2 * R[:, 2])[:, None, None]        # down, with platform
            currents = I_all[sl].T
            m_coil = np.zeros((3, 1) + currents.shape)                         # (3,1,3 coils,m)
            m_coil[2, 0] = self.coil_moment_per_A * currents
            # every coil (axis 2) on every magnet (axis 1)
            F, tau = dipole_force_torque(m_coil, coils, m_mag, mag[:, :, None])
            F_mag = F[:, :, 0] + F[:, :, 1] + F[:, :, 2]                       # (3,3 magnets,m)
            out[sl, :3] = (F_mag[:, 0] + F_mag[:, 1] + F_mag[:, 2]).T
            moment = batched.cross(arm, F_mag) + tau.sum(axis=2)
            out[sl, 3:] = (moment[:, 0] + moment[:, 1] + moment[:, 2]).T

        batched.map_chunks(chunk, rows.size)
        if not every:
            w[rows] = out
        return w
