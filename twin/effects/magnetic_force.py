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
from deltatwin.twin.effects.base import Effect, Parameter, WrenchDerivatives

MU0 = 4e-7 * np.pi


def _separation(m1, r1, m2, r2):
    """The dipoles' separation r = r2 - r1: |r|^2, |r|, the unit vector u, m1 . u, m2 . u and
    m1 . m2 (component-first arrays)."""
    r = r2 - r1
    d2 = batched.dot(r, r)
    d = np.sqrt(d2)
    u = r / d
    return d2, d, u, batched.dot(m1, u), batched.dot(m2, u), batched.dot(m1, m2)


def dipole_force_torque(m1, r1, m2, r2):
    """Force (N) and torque (N*m, about r2) on dipole m2 at r2 from dipole m1 at r1 (A*m^2, m).
    Component-first arrays (3, ...) broadcasting over the trailing axes (models/batched.py)."""
    d2, d, u, m1u, m2u, m1m2 = _separation(m1, r1, m2, r2)
    F = 3 * MU0 / (4 * np.pi * d2 * d2) * (m2 * m1u + m1 * m2u + u * m1m2 - 5 * u * m1u * m2u)
    B = MU0 / (4 * np.pi * d2 * d) * (3 * u * m1u - m1)
    return F, batched.cross(m2, B)


def dipole_force_torque_gradient(m1, r1, m2, r2):
    """Derivatives of ``dipole_force_torque``'s force (N/m) and torque (N*m/m) in the position
    r2 of dipole m2 at fixed moments, (3 components, 3 coordinates, ...): [i, j] = d F_i / d r2_j
    (minus the derivative in r1). With u = r / d, a1 = m1 . u, a2 = m2 . u, c = m1 . m2:
    d F / d r_j = 3 mu0 / (4 pi d^5) [m2 m1_j + m1 m2_j + (c - 5 a1 a2) e_j
    - 5 u (m1_j a2 + m2_j a1) - 5 u_j (m2 a1 + m1 a2 + u c) + 35 u u_j a1 a2], and the torque's
    m2 x d B / d r_j with d B / d r_j = 3 mu0 / (4 pi d^4) [u m1_j + m1 u_j + a1 e_j - 5 a1 u u_j]."""
    d2, d, u, a1, a2, c = _separation(m1, r1, m2, r2)
    k_B = 3 * MU0 / (4 * np.pi * d2 * d2)
    k_F = k_B / d
    shape = np.broadcast_shapes(u.shape, m1.shape, m2.shape)
    dF, dtau = np.empty((3,) + shape), np.empty((3,) + shape)
    pair = m2 * a1 + m1 * a2 + u * c                    # the vector u_j multiplies
    for j in range(3):
        g = (m2 * m1[j] + m1 * m2[j] - 5 * u * (m1[j] * a2 + m2[j] * a1) - 5 * u[j] * pair
             + 35 * u * (u[j] * a1 * a2))
        g[j] += c - 5 * a1 * a2
        dF[:, j] = k_F * g
        dB = u * m1[j] + m1 * u[j] - 5 * u * (u[j] * a1)
        dB[j] += a1
        batched.cross(m2, k_B * dB, out=dtau[:, j])
    return dF, dtau


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

    def _over_rows_with_current(self, points, width: tuple, pairs) -> np.ndarray:
        """(N,) + ``width`` zeros, with ``pairs(sl, p, R, currents, coils, magnets)`` written into
        the rows that carry a current, in chunks of them (the nine pairs' arrays stay in the CPU
        caches): a coil without current has no moment and exerts nothing (a thermal campaign's
        rows are all zero)."""
        pose, params = points.pose, points.params
        w = np.zeros((pose.p.shape[0],) + width)
        rows = np.flatnonzero(np.any(points.currents_A != 0, axis=1))
        if rows.size == 0:
            return w
        every = rows.size == w.shape[0]
        p, R, currents = ((pose.p, pose.R, points.currents_A) if every else
                          (pose.p[rows], pose.R[rows], points.currents_A[rows]))
        coils = self.coil_dipoles(params, points.home_p).T[:, None, :, None]   # (3,1,3 coils,1)
        magnets = magnet_positions(params).T[:, :, None]                       # (3,3 magnets,1)
        out = w if every else np.empty((rows.size,) + width)
        batched.map_chunks(lambda sl: pairs(out[sl], p[sl], R[sl].transpose(1, 2, 0),
                                            currents[sl].T, coils, magnets), rows.size)
        if not every:
            w[rows] = out
        return w

    @staticmethod
    def _dipoles(R, currents, magnets, magnet_moment, coil_moment_per_A):
        """The magnets' levers from the platform origin and centres (3,3 magnets,m), their moments
        (3,1,1,m: down, with the platform) and the coils' (3,1,3 coils,m: up, per current)."""
        arm = batched.matvec(R[:, :, None], magnets)
        m_mag = (-magnet_moment * R[:, 2])[:, None, None]
        m_coil = np.zeros((3, 1) + currents.shape)
        m_coil[2, 0] = coil_moment_per_A * currents
        return arm, m_mag, m_coil

    def wrench(self, points):
        def pairs(out, p, R, currents, coils, magnets):
            arm, m_mag, m_coil = self._dipoles(R, currents, magnets, self.magnet_moment_Am2,
                                               self.coil_moment_per_A)
            mag = p.T[:, None] + arm
            # every coil (axis 2) on every magnet (axis 1)
            F, tau = dipole_force_torque(m_coil, coils, m_mag, mag[:, :, None])
            F_mag = F[:, :, 0] + F[:, :, 1] + F[:, :, 2]                       # (3,3 magnets,m)
            out[:, :3] = (F_mag[:, 0] + F_mag[:, 1] + F_mag[:, 2]).T
            moment = batched.cross(arm, F_mag) + tau.sum(axis=2)
            out[:, 3:] = (moment[:, 0] + moment[:, 1] + moment[:, 2]).T

        return self._over_rows_with_current(points, (6,), pairs)

    def wrench_derivatives(self, points):
        """Exact: the wrench is bilinear in the two moments (the magnets' and the coils' per
        ampere); a coil's position moves the pairs it belongs to by minus their separation's
        change (``dipole_force_torque_gradient``), the core depth lowers every coil. In the
        pose: a move of the platform moves every magnet (minus every coil's move), the home
        moves every coil; a rotation w (R -> exp(w) R) turns the magnets' levers and moments
        (w x arm, w x m), and the moment's lever with them."""
        def pairs(out, p, R, currents, coils, magnets):
            arm, m_mag, m_coil = self._dipoles(R, currents, magnets, 1.0, 1.0)  # unit moments
            mag = (p.T[:, None] + arm)[:, :, None]
            F, tau = dipole_force_torque(m_coil, coils, m_mag, mag)
            dF, dtau = dipole_force_torque_gradient(m_coil, coils, m_mag, mag)
            lever = arm[:, :, None]                                   # (3,3 magnets,1,m)

            def wrench_of(force, torque, lever_change=None):
                """Sums over the magnets (axis 1) of the pairs' force and moment, (6, coils, m)."""
                moment = batched.cross(lever, force) + torque
                if lever_change is not None:
                    moment += batched.cross(lever_change, F)
                return np.concatenate([force.sum(axis=1), moment.sum(axis=1)])

            # the unit moments' wrench
            out[:, :, 0] = wrench_of(F, tau).sum(axis=1).T
            # each coil's position (minus the magnets'), per coordinate j: (6, coils, m)
            by_coil = [-wrench_of(dF[:, j], dtau[:, j]) for j in range(3)]
            for j in range(3):
                out[:, :, 1 + 3 * np.arange(3) + j] = by_coil[j].transpose(2, 0, 1)
                out[:, :, 10 + j] = -by_coil[j].sum(axis=1).T           # the platform's move
            for k in range(3):                                           # a rotation about e_k
                e = np.zeros((3, 1, 1, 1))
                e[k] = 1.0
                turned = batched.cross(e, lever)                         # w x arm
                F_k, tau_k = dipole_force_torque(m_coil, coils, batched.cross(e, m_mag), mag)
                for j in range(3):
                    F_k += dF[:, j] * turned[j]
                    tau_k += dtau[:, j] * turned[j]
                out[:, :, 13 + k] = wrench_of(F_k, tau_k, turned).sum(axis=1).T

        unit = self._over_rows_with_current(points, (6, 16), pairs)
        moments = self.magnet_moment_Am2 * self.coil_moment_per_A
        by_coil = moments * unit[:, :, 1:10].reshape(-1, 6, 3, 3)          # (N,6,coil,coordinate)
        move = moments * unit[:, :, 10:13]
        return WrenchDerivatives(
            {"magnet_moment_Am2": self.coil_moment_per_A * unit[:, :, 0],
             "coil_moment_per_A": self.magnet_moment_Am2 * unit[:, :, 0],
             "core_depth_m": -by_coil[:, :, :, 2].sum(axis=2),
             "coil_offset_m": by_coil},
            np.concatenate([move, moments * unit[:, :, 13:16], -move], axis=2))
