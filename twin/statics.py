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

Strains of rod j of chain i, whose unit direction is n and hinge distance L; chain coordinates
x = [dp, dr, eta], eta = [dtheta_i, phi_i] rotating the arm about the axes a_k = (u, u, e_n, a)
(actuator axis, out-of-plane normal, arm direction) through the centres (B, V, V, V):
  delta = dp + dr x w - sum_k eta_k c_k,   c_k = a_k x (A - centre_k)   rod end displacement
  omega = sum_k eta_k a_k                                                 elbow rotation
  axial stretch n.delta; rod rotation psi = n x delta / L; elbow bending psi - P omega, platform
  bending psi - P dr (P = I - n n^T); torsion n.(dr - omega).
With m = (omega + dr)/2, r = omega - dr and v = delta/L + n x m the same rod energy reads
  1/2 [(k_ax - 2 k_b/L^2) (n.delta)^2 + 2 k_b |v|^2 + k_b/2 |r|^2 + (k_t - k_b)/2 (n.r)^2],
whose Hessian has closed-form blocks; the code assembles those blocks directly.

Implementation: structure of arrays.  Every per-pose quantity is an array whose last axis runs
over the poses of a chunk, with vector component / matrix entry, chain and rod as leading axes,
so each numpy call works on thousands of poses at once; the condensation (4x4 per chain) and the
platform solve (6x6) are Cholesky factorisations written entry by entry over those arrays.
Chunks of CHUNK_POSES poses are solved on the threads of models/batched.py ``map_chunks``
(numpy releases the GIL inside its loops); each chunk writes its own rows, so the result does
not depend on the thread count.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from deltatwin.models import batched
from deltatwin.models.geometry import Geometry
from deltatwin.models.kinematics import Pose, forward, home_rod_directions
from deltatwin.models.params import RobotParams
from deltatwin.models.stiffness import Stiffness, element_stiffness

GRAVITY_M_S2 = 9.80665
N_COORD = 18  # dp(3) dr(3) dtheta(3) phi(3 chains x 3)
CHUNK_POSES = 1024  # poses per assembly chunk (working set stays in the CPU caches)
_DP, _DR, _ETA = slice(0, 3), slice(3, 6), slice(6, 10)   # chain coordinates (see module doc)
# [h]x entries: (row, column, component of h, sign)
_SKEW_ENTRIES = ((0, 1, 2, -1.0), (0, 2, 1, 1.0), (1, 0, 2, 1.0), (1, 2, 0, -1.0),
                 (2, 0, 1, -1.0), (2, 1, 0, 1.0))


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


def deflected_pose(kin: Pose, y: np.ndarray) -> Pose:
    """The kinematic pose displaced by ``y`` (N,6: position m, rotation vector rad): its small
    rotation applied on the kinematic one, component-first (models/batched.py)."""
    R = batched.matmul(batched.rotation_matrices(y[:, 3:6].T), kin.R.transpose(1, 2, 0))
    return Pose(kin.p + y[:, :3], np.ascontiguousarray(R.transpose(2, 0, 1)))


def _bend_vector(rest, actual):
    """Rotation vector (3,...) turning unit vector ``rest`` into unit vector ``actual``: along
    rest x actual, of length the angle between them (rad)."""
    c = batched.cross(rest, actual)
    sin_angle = np.sqrt(batched.dot(c, c))
    safe = np.where(sin_angle > 0.0, sin_angle, 1.0)
    return c * np.where(sin_angle > 0.0, np.arctan2(sin_angle, batched.dot(rest, actual)) / safe,
                        1.0)


def _rod_pairs(a, b):
    """sum over a chain's two rods of the outer products a b^T: (k,3,2,m), (l,3,2,m) -> (k,l,3,m)."""
    return np.einsum("aijm,bijm->abim", a, b)


def _both_rods(x):
    """Sum over the rod axis (second to last) of a chain's two rods."""
    return x[..., 0, :] + x[..., 1, :]


def _rotation_terms(axis: np.ndarray, v: np.ndarray):
    """Rodrigues about fixed unit axes (...,3): rot(v, angle) = fixed + cos(angle) radial +
    sin(angle) tangential; the three terms component-first with a trailing pose axis."""
    fixed = axis * np.sum(axis * v, axis=-1, keepdims=True)
    return tuple(np.moveaxis(t, -1, 0)[..., None] for t in (fixed, v - fixed, np.cross(axis, v)))


class Statics:
    """Static model of one robot (parameters -> geometry, stiffness, home rod directions)."""

    def __init__(self, params: RobotParams, geom: Geometry):
        if geom.batched:
            raise ValueError("Statics needs the geometry of one robot state; a batched (per-point) "
                             "geometry is not supported")
        self.params, self.geom = params, geom
        self.k: Stiffness = element_stiffness(params, geom)
        self.home_dirs = home_rod_directions(geom)
        # pose-independent terms, component-first with a trailing pose axis (see _chain_system)
        g, axis = geom, geom.axis
        unit = lambda v: v / np.linalg.norm(v, axis=-1, keepdims=True)
        self._u = np.moveaxis(axis, -1, 0)[:, :, None, None]                        # (3,3,1,1)
        self._base = np.moveaxis(g.B, -1, 0)[:, :, None, None]
        self._elbow_arm = _rotation_terms(axis[:, None], g.arm_vec)                  # (3,3,2,1)
        # arm direction a and out-of-plane normal e_n = a x u, turning with the arm: (3,3,1,1)
        self._arm_dir = _rotation_terms(axis[:, None], unit(g.elbow_vec)[:, None])
        self._arm_normal = _rotation_terms(axis[:, None], unit(np.cross(g.elbow_vec, axis))[:, None])
        elbow_len = np.linalg.norm(g.elbow_vec, axis=-1)
        self._pivot_lever = ((1.0 - params.prbm_gamma) * elbow_len)[:, None, None]  # |V - B|
        n0, n0_plat = self.home_dirs
        self._rest_elbow = _rotation_terms(axis[:, None], n0)                       # (3,3,2,1)
        self._platform_vecs = np.concatenate([g.P0.reshape(6, 3), n0_plat.reshape(6, 3)])
        k = self.k
        self._k_axial = k.rod_axial[:, :, None]
        self._k_internal = np.concatenate([[k.drive], k.arm])

    # -- assembly -----------------------------------------------------------------------------
    def _chain_system(self, q: np.ndarray, pose: Pose):
        """Chain stiffness (10,10,3,m) and preload force (10,3,m) at m kinematic poses
        (entries first, then chain, then pose).

        Local coordinates of chain i: [dp (3), dr (3), dtheta_i, phi_i (3)]."""
        g, k = self.geom, self.k
        m = q.shape[0]
        qT = q.T[:, None, :]                                                     # (3,1,m)
        cos_t, sin_t = np.cos(qT + g.theta_zero[:, None, None]), np.sin(qT + g.theta_zero[:, None, None])
        fixed, radial, tangential = self._elbow_arm
        A = fixed + radial * cos_t + tangential * sin_t + self._base              # (3,3,2,m)
        fixed, radial, tangential = self._arm_dir
        a_dir = fixed + radial * cos_t + tangential * sin_t                       # (3,3,1,m)
        fixed, radial, tangential = self._arm_normal
        e_n = fixed + radial * cos_t + tangential * sin_t
        pivot = self._base + self._pivot_lever * a_dir                            # V
        # platform hinge vectors w = R P0 and platform-side rest directions R n0_plat: one GEMM
        rotated = (pose.R.reshape(m * 3, 3) @ self._platform_vecs.T).reshape(m, 3, 2, 3, 2)
        w, rest_plat = np.ascontiguousarray(rotated.transpose(2, 1, 3, 4, 0))      # (3,3,2,m)
        d = pose.p.T[:, None, None, :] + w - A
        inv_len = 1.0 / np.sqrt(batched.dot(d, d))                                       # (3,2,m)
        n = d * inv_len

        axes = np.stack([np.broadcast_to(self._u, a_dir.shape), np.broadcast_to(self._u, a_dir.shape),
                         e_n, a_dir], axis=1)                                     # (3,4,3,1,m)
        # lever arms of the elbow hinge about the centres (B, V, V, V): c_k = a_k x lever_k
        arm_A, pivot_A = A - self._base, A - pivot
        c = np.empty((3, 4) + A.shape[1:])                                        # (3,4,3,2,m)
        batched.cross(self._u, arm_A, out=c[:, 0])
        batched.cross(axes[:, 1:], pivot_A[:, None], out=c[:, 1:])
        n_c = batched.dot(n[:, None], c)                                                 # (4,3,2,m)
        # v's eta columns G_k = n x a_k / 2 - c_k / L = (lever_k / L + n / 2) x a_k
        G = np.empty_like(c)
        batched.cross(arm_A * inv_len + 0.5 * n, self._u, out=G[:, 0])
        batched.cross((pivot_A * inv_len + 0.5 * n)[:, None], axes[:, 1:], out=G[:, 1:])
        wn = batched.cross(w, n)  # s1's dr columns
        h = w * inv_len - 0.5 * n                                                 # v's dr columns: -[h]x
        kb = k.hinge_bending
        kv = 2.0 * kb                                                             # weight of |v|^2
        s_ax = self._k_axial - kv * inv_len ** 2                                  # weight of (n.delta)^2
        s_tw = 0.5 * (k.hinge_torsion - kb)                                       # weight of (n.r)^2
        kv_len = kv * inv_len

        # Hessian blocks of the upper triangle, each summed over the chain's two rods, from
        #   (n.delta)^2: rank one per rod, row [n, w x n, -n.c_k], weight s_ax;
        #   |v|^2: rows [I/L, -[h]x, G], weight kv;
        #   |r|^2 and (n.r)^2 with r = [0, -I, axes] the same for both rods: r^T W r at chain level,
        #   W = k_b I + s_tw sum_j n_j n_j^T.
        axes_c = axes[..., 0, :]                                                  # (3,4,3,m)
        W = s_tw * _rod_pairs(n, n)                                               # (3,3,3,m)
        for a in range(3):
            W[a, a] += kb
        WA = np.einsum("abim,bkim->akim", W, axes_c)                              # W axes
        sn, swn = s_ax * n, s_ax * wn
        eye = np.eye(3)[:, :, None, None]
        K = np.empty((10, 10, 3, m))
        K[_DP, _DP] = _rod_pairs(sn, n) + eye * _both_rods(kv_len * inv_len)
        K[_DP, _DR] = _rod_pairs(sn, wn)
        kh = _both_rods(kv_len * h)
        for a, b, comp, sign in _SKEW_ENTRIES:                                    # -kv/L [h]x
            K[a, 3 + b] -= sign * kh[comp]
        K[_DP, _ETA] = _both_rods(kv_len * G) - _rod_pairs(sn, n_c)
        K[_DR, _DR] = (_rod_pairs(swn, wn) - kv * _rod_pairs(h, h)
                         + eye * (kv * _both_rods(batched.dot(h, h))) + W)
        K[_DR, _ETA] = kv * _both_rods(batched.cross(h[:, None], G)) - _rod_pairs(swn, n_c) - WA
        K[_ETA, _ETA] = (_rod_pairs(s_ax * n_c, n_c) + kv * np.einsum("ckijm,clijm->klim", G, G)
                         + np.einsum("akim,alim->klim", axes_c, WA)
                         + np.diag(self._k_internal)[:, :, None, None])
        for lower, upper in ((_DR, _DP), (_ETA, _DP), (_ETA, _DR)):
            K[lower, upper] = K[upper, lower].swapaxes(0, 1)

        # preload: initial bending strains of both hinges, the rotation vector from the rest to
        # the actual direction (the bend angle, not its sine: a flexure's moment is linear in
        # its angle; see models/delta_agietron/README.md)
        fixed, radial, tangential = self._rest_elbow
        rest_elbow = fixed + radial * np.cos(qT) + tangential * np.sin(qT)
        e_elbow, e_plat = _bend_vector(rest_elbow, n), _bend_vector(rest_plat, n)
        sigma = batched.cross(e_elbow + e_plat, n) * inv_len
        f0 = np.empty((10, 3, m))
        f0[_DP] = -kb * _both_rods(sigma)
        f0[_DR] = kb * _both_rods(e_plat - batched.cross(w, sigma))
        f0[_ETA] = kb * (np.einsum("cijm,ckijm->kim", sigma, c)
                         + np.einsum("cim,ckim->kim", _both_rods(e_elbow), axes_c))
        return K, f0

    @staticmethod
    def _condense(K, f0):
        """Condense the chains' internal coordinates: platform stiffness (6,6,m), force (6,m),
        and the map back to internal coordinates (Cholesky factors of K_ii (4,4,3,m) and
        L^-1 [K_ip, f_i] (4,7,3,m))."""
        L = batched.cholesky(K[_ETA, _ETA])
        X = batched.forward_substitute(L, np.concatenate([K[_ETA, :6], f0[_ETA, None]], axis=1))
        S = np.einsum("kaim,kbim->abm", X, X)                                      # (7,7,m)
        K_plat = np.sum(K[:6, :6], axis=2) - S[:6, :6]
        f_plat = np.sum(f0[:6], axis=1) - S[:6, 6]
        return K_plat, f_plat, (L, X)

    def _platform_system(self, q, pose: Pose):
        return self._condense(*self._chain_system(q, pose))

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

        def solve_chunk(sl):
            K_plat, f_plat, (L, X) = self._platform_system(q[sl], Pose(kin.p[sl], kin.R[sl]))
            L_plat = batched.cholesky(K_plat)
            yp = batched.backward_substitute(
                L_plat, batched.forward_substitute(L_plat, f[sl].T + f_plat))
            yi = batched.backward_substitute(L, X[:, 6] - np.einsum("kaim,am->kim", X[:, :6], yp))
            y[sl, :6] = yp.T
            y[sl, 6:9] = yi[0].T
            y[sl, 9:] = yi[1:].T.reshape(-1, 9)                                  # (m, chain, axis)

        batched.map_chunks(solve_chunk, q.shape[0], CHUNK_POSES)
        bad = np.flatnonzero(~np.all(np.isfinite(y), axis=1))
        if bad.size:
            i = int(bad[0])
            raise ValueError(f"statics: no finite equilibrium at pose {i} (q = {q[i].tolist()} rad, "
                             f"kinematic position {kin.p[i].tolist()} m; {bad.size} pose(s)): "
                             "non-finite pose or stiffness not positive definite")
        return StaticResult(pose=deflected_pose(kin, y[:, :6]), kinematic_pose=kin, y=y)

    def compliance(self, q) -> np.ndarray:
        """Platform compliance (N,6,6) at motor coordinates q: [m/N, m/(N m); rad/N, rad/(N m)]."""
        q = np.atleast_2d(np.asarray(q, dtype=np.float64))
        kin = forward(self.geom, q)
        K_plat = batched.map_chunks(
            lambda sl: self._platform_system(q[sl], Pose(kin.p[sl], kin.R[sl]))[0],
            q.shape[0], CHUNK_POSES)
        return np.linalg.inv(np.moveaxis(np.concatenate(K_plat, axis=-1), -1, 0))
