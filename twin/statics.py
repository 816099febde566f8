"""Statics at nanometre level: platform deflection under a wrench and gravity.

Compliant elements (all linear-elastic, from geometry and material, see models/stiffness.py):
  * drive train between encoder and arm: torsion about the actuator axis (the servo's integral
    action holds the encoder itself exactly at steady state);
  * arm bending and torsion: pseudo-rigid-body model (Howell), three rotational springs at the
    characteristic pivot (in-plane bending, out-of-plane bending, torsion);
  * each rod: axial stretch (rod body + two notch necks in series);
  * each rod-end flexure hinge: bending (two axes) at the elbow and at the platform, and the two
    hinges' torsion in series about the rod axis.
The flexures are straight at the home pose (q = 0); elsewhere they are bent and push back, so the
platform deflects a little even without load (pose-dependent elastic preload).

The displacement method (small deformations about the exact kinematic pose): generalised
coordinates y = [dp (3), dr (3), dtheta (3), phi (3x3)], strains e = e0 + B y, energy
1/2 e^T k e, equilibrium K y = f_ext - B^T k e0 with K = B^T k B.  Condensing the internal
coordinates gives the platform's 6x6 compliance.  Second-order geometric terms are of order
(deflection / rod length) ~ 1e-5 of the deflection, i.e. picometres (checked in the tests
against finite differences of the exact potential energy).  Units: m, rad, N, N*m.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from models.geometry import Geometry
from models.params import RobotParams
from models.stiffness import Stiffness, element_stiffness

from .kinematics import (Pose, elbow_points, flexure_rest_directions, forward,
                         home_rod_directions, rotate_about_axis)

GRAVITY_M_S2 = 9.80665
N_COORD = 18  # dp(3) dr(3) dtheta(3) phi(3 chains x 3)
_CHUNK = 8192


@dataclass(frozen=True)
class StaticResult:
    """Static equilibrium of a batch of poses."""
    pose: Pose              # deflected platform pose
    kinematic_pose: Pose    # rigid-body pose for the same motor coordinates
    y: np.ndarray           # (N,18) generalised displacements (see module doc)

    @property
    def deflection(self) -> np.ndarray:
        """(N,6): platform translation (m) and small rotation (rad) from the kinematic pose."""
        return self.y[:, :6]


def _skew(v: np.ndarray) -> np.ndarray:
    S = np.zeros(v.shape + (3,))
    S[..., 0, 1], S[..., 0, 2] = -v[..., 2], v[..., 1]
    S[..., 1, 0], S[..., 1, 2] = v[..., 2], -v[..., 0]
    S[..., 2, 0], S[..., 2, 1] = -v[..., 1], v[..., 0]
    return S


class Statics:
    """Static model of one robot (parameters -> geometry, stiffness, home rod directions)."""

    def __init__(self, params: RobotParams, geom: Geometry):
        self.params, self.geom = params, geom
        self.k: Stiffness = element_stiffness(params, geom)
        self.home_dirs = home_rod_directions(geom)

    # -- assembly -----------------------------------------------------------------------------
    def _chain_system(self, q: np.ndarray, pose: Pose):
        """Per-chain stiffness (N,3,10,10) and preload force (N,3,10) at kinematic poses.

        Local coordinates of chain i: [dp (3), dr (3), dtheta_i, phi_i (3)]."""
        g, k = self.geom, self.k
        n_pose = q.shape[0]
        theta = g.theta(q)
        A = elbow_points(g, theta)                                       # (N,3,2,3)
        w = np.einsum("nab,ijb->nija", pose.R, g.P0)
        dvec = pose.p[:, None, None, :] + w - A
        L = np.linalg.norm(dvec, axis=-1)
        n = dvec / L[..., None]
        u = np.broadcast_to(g.axis[None], (n_pose, 3, 3))
        E = g.B[None] + rotate_about_axis(u, theta, np.broadcast_to(g.elbow_vec, (n_pose, 3, 3)))
        a_dir = E - g.B[None]
        a_dir /= np.linalg.norm(a_dir, axis=-1, keepdims=True)
        e_n = np.cross(a_dir, u)
        e_n /= np.linalg.norm(e_n, axis=-1, keepdims=True)
        # rotation axes of the chain's internal coordinates: drive, PRBM in-plane, out-of-plane, torsion
        axes = np.stack([u, u, e_n, a_dir], axis=2)                      # (N,3,4,3)
        V = g.B[None] + (1.0 - self.params.prbm_gamma) * (E - g.B[None])
        centres = np.stack([g.B[None].repeat(n_pose, 0), V, V, V], axis=2)  # (N,3,4,3)

        # displacement maps of platform hinge (MP), elbow hinge (MA), elbow rotation (Me): (N,3,2,3,10)
        shape = (n_pose, 3, 2, 3, 10)
        MP = np.zeros(shape)
        MP[..., :3] = np.eye(3)
        MP[..., 3:6] = -_skew(w)
        MA = np.zeros(shape)
        MA[..., 6:] = np.swapaxes(np.cross(axes[:, :, None, :, :],
                                           A[:, :, :, None, :] - centres[:, :, None, :, :]), -1, -2)
        Me = np.zeros(shape)
        Me[..., 6:] = np.swapaxes(axes, -1, -2)[:, :, None]
        D = MP - MA
        nn = n[..., None]
        axial = np.sum(nn * D, axis=-2)                                  # (N,3,2,10)
        w_rod = np.swapaxes(np.cross(n[..., None, :], np.swapaxes(D, -1, -2)), -1, -2) / L[..., None, None]
        Me_n = np.sum(nn * Me, axis=-2)                                  # n . M_e
        B_elbow = w_rod - (Me - nn * Me_n[..., None, :])                 # bending at the elbow hinge
        B_plat = w_rod.copy()                                            # bending at the platform hinge
        B_plat[..., 3:6] -= np.eye(3) - nn * n[..., None, :]
        tors = -Me_n
        tors[..., 3:6] += n                                              # relative twist about the rod

        # initial (preload) bending strains: rest direction x actual direction
        rest_e, rest_p = flexure_rest_directions(g, q, pose, self.home_dirs)
        e0_el, e0_pl = np.cross(rest_e, n), np.cross(rest_p, n)

        rows = np.concatenate([
            np.sqrt(k.rod_axial)[None, :, :, None, None] * axial[..., None, :],
            np.sqrt(k.hinge_bending) * B_elbow,
            np.sqrt(k.hinge_bending) * B_plat,
            np.sqrt(0.5 * k.hinge_torsion) * tors[..., None, :],
        ], axis=-2).reshape(n_pose, 3, -1, 10)
        K = np.swapaxes(rows, -1, -2) @ rows
        K[..., np.arange(6, 10), np.arange(6, 10)] += np.concatenate([[k.drive], k.arm])
        f0 = -k.hinge_bending * (np.einsum("nijab,nija->nib", B_elbow, e0_el)
                                 + np.einsum("nijab,nija->nib", B_plat, e0_pl))
        return K, f0

    @staticmethod
    def _condense(K, f0):
        """Condense the chains' internal coordinates: platform stiffness (N,6,6), force (N,6),
        and the map back to internal coordinates."""
        Kpp, Kpi, Kii = K[..., :6, :6], K[..., :6, 6:], K[..., 6:, 6:]
        Kii_inv = np.linalg.inv(Kii)
        T = Kpi @ Kii_inv                                                # (N,3,6,4)
        K_plat = np.sum(Kpp - T @ np.swapaxes(Kpi, -1, -2), axis=1)
        f_plat = np.sum(f0[..., :6] - (T @ f0[..., 6:, None])[..., 0], axis=1)
        return K_plat, f_plat, Kii_inv

    # -- public API ---------------------------------------------------------------------------
    def solve(self, q, wrench=None, gravity: bool = True, pose: Pose | None = None) -> StaticResult:
        """Static pose for motor coordinates q (N,3) under ``wrench`` (N,6) or (6,):
        force (N) at the platform frame origin and moment (N*m), world frame."""
        q = np.atleast_2d(np.asarray(q, dtype=np.float64))
        kin = pose if pose is not None else forward(self.geom, q)
        f = np.zeros((q.shape[0], 6))
        if wrench is not None:
            f[:] = np.broadcast_to(np.asarray(wrench, dtype=np.float64), (q.shape[0], 6))
        if gravity:
            f[:, 2] -= self.params.platform_mass_kg * GRAVITY_M_S2
        y = np.empty((q.shape[0], N_COORD))
        for s in range(0, q.shape[0], _CHUNK):
            sl = slice(s, s + _CHUNK)
            K, f0 = self._chain_system(q[sl], Pose(kin.p[sl], kin.R[sl]))
            K_plat, f_plat, Kii_inv = self._condense(K, f0)
            yp = np.linalg.solve(K_plat, (f[sl] + f_plat)[..., None])[..., 0]
            rhs = f0[..., 6:] - (np.swapaxes(K[..., :6, 6:], -1, -2) @ yp[:, None, :, None])[..., 0]
            yi = (Kii_inv @ rhs[..., None])[..., 0]                      # (n,3,4)
            y[sl, :6] = yp
            y[sl, 6:9] = yi[..., 0]
            y[sl, 9:] = yi[..., 1:].reshape(-1, 9)
        R = Rotation.from_rotvec(y[:, 3:6]).as_matrix() @ kin.R
        return StaticResult(pose=Pose(kin.p + y[:, :3], R), kinematic_pose=kin, y=y)

    def compliance(self, q) -> np.ndarray:
        """Platform compliance (N,6,6) at motor coordinates q: [m/N, m/(N m); rad/N, rad/(N m)]."""
        q = np.atleast_2d(np.asarray(q, dtype=np.float64))
        K, f0 = self._chain_system(q, forward(self.geom, q))
        return np.linalg.inv(self._condense(K, f0)[0])
