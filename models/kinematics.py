"""Exact kinematics of the Delta robot with general geometry (errors and thermal expansion).

Each rod is a distance constraint between its elbow hinge and its platform hinge, so the six
rods fix the platform's full 6-DOF pose: with ideal parallelograms the platform only translates,
while unequal rods or misplaced hinges tilt it (the parasitic rotations that autocollimators see).

* ``forward(geom, q)``: motor coordinates (N,3) -> ``Pose`` (position (N,3), rotation (N,3,3)).
* ``inverse(geom, p)``: platform position (N,3) -> motor coordinates (N,3) (and the rotation).

Both are batched Newton iterations on the six rod equations with analytic Jacobians, started
from the ideal closed form; every pose is checked to close its loops to ``CLOSURE_TOL_M``.
Units: m, rad.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial.transform import Rotation

from deltatwin.models import batched
from deltatwin.models.geometry import Geometry

CLOSURE_TOL_M = 1e-12
_MAX_ITER = 30
_REFACTOR_STEP = 1e-6   # m or rad: Newton above, chord below (see forward)


class KinematicsError(ValueError):
    """A pose that is unreachable or outside the actuator strokes."""


@dataclass(frozen=True)
class Pose:
    """Platform pose: position of the platform frame origin (m) and its rotation matrix."""
    p: np.ndarray  # (N,3)
    R: np.ndarray  # (N,3,3)

    @property
    def rotvec(self) -> np.ndarray:
        """Rotation vector (rad), (N,3): the small parasitic rotations."""
        return Rotation.from_matrix(self.R).as_rotvec()

    def point(self, local: np.ndarray) -> np.ndarray:
        """World position (N,3) of a point given in the platform frame (3,)."""
        return self.p + self.R @ np.asarray(local, dtype=np.float64)


def rotate_about_axis(axis: np.ndarray, angle: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rodrigues: rotate vectors ``v`` (...,3) about unit ``axis`` (...,3) by ``angle`` (...)."""
    c, s = np.cos(angle)[..., None], np.sin(angle)[..., None]
    return v * c + np.cross(axis, v) * s + axis * np.sum(axis * v, axis=-1, keepdims=True) * (1.0 - c)


def _per_point(geom: Geometry) -> Geometry:
    """The geometry with a leading per-point axis on every joint array (length 1 when the
    geometry is one robot state), so that one code path serves both."""
    if geom.batched:
        return geom
    return replace(geom, B=geom.B[None], axis=geom.axis[None], arm_vec=geom.arm_vec[None],
                   elbow_vec=geom.elbow_vec[None], P0=geom.P0[None], L=geom.L[None],
                   theta_zero=geom.theta_zero[None], cube_offset=geom.cube_offset[None])


def _platform_vectors(P0: np.ndarray, R: np.ndarray) -> np.ndarray:
    """Platform hinge vectors R P0 in the world (N,3,2,3); P0 is (1|N,3,2,3)."""
    return (R[:, None, None] @ P0[..., None])[..., 0]


def elbow_points(geom: Geometry, theta: np.ndarray) -> np.ndarray:
    """Elbow hinge positions (N,3,2,3) for arm angles ``theta`` (N,3)."""
    g = _per_point(geom)
    ax = np.broadcast_to(g.axis[:, :, None, :], theta.shape[:1] + (3, 2, 3))
    ang = np.broadcast_to(theta[:, :, None], theta.shape[:1] + (3, 2))
    return g.B[:, :, None, :] + rotate_about_axis(ax, ang, g.arm_vec)


def check_stroke(geom: Geometry, q: np.ndarray, what: str = "motor coordinates") -> None:
    lo, hi = geom.stroke
    bad = np.flatnonzero(np.any((q < lo - 1e-12) | (q > hi + 1e-12) | ~np.isfinite(q), axis=1))
    if bad.size:
        i = int(bad[0])
        raise KinematicsError(f"{what} at pose {i} = {q[i].tolist()} rad are outside the actuator "
                              f"stroke [{lo}, {hi}] rad ({bad.size} pose(s) out of stroke)")


def _residual_and_jacobian(geom, A, p, R):
    """Rod equations f = |P - A|^2 - L^2 (N,6) and their derivatives.

    Returns f, d = P - A (N,3,2,3), w = R P0 (N,3,2,3)."""
    g = _per_point(geom)
    w = _platform_vectors(g.P0, R)
    d = p[:, None, None, :] + w - A
    f = np.sum(d * d, axis=-1) - g.L ** 2
    return f.reshape(-1, 6), d, w


def _newton(update, n: int, what: str):
    """Run ``update()`` (returns max step per pose) until every pose has converged."""
    for _ in range(_MAX_ITER):
        step = update()
        if np.all(step < 1e-14):
            return
    bad = np.flatnonzero(~(step < 1e-14))
    raise KinematicsError(f"{what} did not converge at pose {int(bad[0])} ({bad.size} pose(s))")


def _check_closure(geom, A, p, R, what):
    _, d, _ = _residual_and_jacobian(geom, A, p, R)
    err = np.abs(np.linalg.norm(d, axis=-1) - _per_point(geom).L).reshape(-1, 6).max(axis=1)
    bad = np.flatnonzero(~(err < CLOSURE_TOL_M))
    if bad.size:
        raise KinematicsError(f"{what}: loop closure {err[bad[0]]:.3e} m at pose {int(bad[0])} "
                              f"exceeds {CLOSURE_TOL_M} m")
    return err


def _component_first(geom: Geometry):
    """The joint arrays component-first with a trailing point axis (length 1 for one robot
    state, N for a per-point geometry): B, axis (3,3,1,1|N), arm_vec, P0 (3,3,2,1|N),
    L (3,2,1|N), theta_zero (3,1|N)."""
    g = _per_point(geom)
    # an array broadcast over the points (stride 0: the same for all) keeps one point
    one = lambda v: v[:1] if v.strides[0] == 0 else v
    chain_vec = lambda v: np.ascontiguousarray(one(v).transpose(2, 1, 0))[:, :, None]
    rod_vec = lambda v: np.ascontiguousarray(one(v).transpose(3, 1, 2, 0))
    return (chain_vec(g.B), chain_vec(g.axis), rod_vec(g.arm_vec), rod_vec(g.P0),
            np.ascontiguousarray(one(g.L).transpose(1, 2, 0)),
            np.ascontiguousarray(one(g.theta_zero).T))


def _trilaterate_low(c: np.ndarray, r: np.ndarray, first_pose: int = 0) -> np.ndarray:
    """Lower intersection point (3,N) of three spheres, centres c (3,3 spheres,N) and radii
    r (3,N), component-first (poses numbered from ``first_pose`` in errors)."""
    d21, d31 = c[:, 1] - c[:, 0], c[:, 2] - c[:, 0]
    d = np.sqrt(batched.dot(d21, d21))
    ex = d21 / d
    i = batched.dot(ex, d31)
    ey = d31 - i * ex
    j = np.sqrt(batched.dot(ey, ey))
    ey /= j
    ez = batched.cross(ex, ey)
    x = (r[0] ** 2 - r[1] ** 2 + d ** 2) / (2 * d)
    y = (r[0] ** 2 - r[2] ** 2 + i ** 2 + j ** 2) / (2 * j) - i * x / j
    z2 = r[0] ** 2 - x ** 2 - y ** 2
    bad = np.flatnonzero(~(z2 >= 0))
    if bad.size:
        raise KinematicsError(f"pose {first_pose + int(bad[0])}: the rods cannot reach the "
                              f"platform (three-sphere intersection is empty; {bad.size} pose(s))")
    base = c[:, 0] + x * ex + y * ey
    zz = np.sqrt(z2) * ez
    return np.where(zz[2] > 0, base - zz, base + zz)


def forward(geom: Geometry, q, check: bool = True) -> Pose:
    """Forward kinematics: motor coordinates q (N,3) rad -> platform Pose (exact, 6-DOF).

    Written component-first (models/batched.py): every array carries the points on its last
    axis, and the Newton steps solve their 6x6 systems by Cholesky of the normal equations, entry
    by entry over the points (the same root as a direct solve: the steps only steer the
    iteration to where every rod equation holds; the loop closure is checked on the result).
    Points go in chunks of ``batched.CHUNK_POINTS``, so that a chunk's arrays stay in the CPU
    caches."""
    q = np.atleast_2d(np.asarray(q, dtype=np.float64))
    if check:
        check_stroke(geom, q)
    n = q.shape[0]
    joints = _component_first(geom)
    p, R = np.empty((n, 3)), np.empty((n, 3, 3))

    def solve_chunk(sl):
        on_chunk = lambda x: x[..., sl] if x.shape[-1] == n else x      # per-point or one robot
        p_chunk, R_chunk = _forward_newton(q[sl], *map(on_chunk, joints), first_pose=sl.start)
        p[sl], R[sl] = p_chunk.T, R_chunk.transpose(2, 0, 1)

    batched.map_chunks(solve_chunk, n)
    return Pose(p=p, R=R)


def _forward_newton(q, B, axis, arm_vec, P0, L, theta_zero, first_pose: int):
    """Newton on the six rod equations for the poses of one chunk (component-first joint
    arrays, see ``_component_first``): position (3,m) and rotation (3,3,m)."""
    m = q.shape[0]
    theta = (q.T + theta_zero)[:, None]                                   # (3 chains,1,m)
    cos_t, sin_t = np.cos(theta), np.sin(theta)
    A = (B + arm_vec * cos_t + batched.cross(axis, arm_vec) * sin_t
         + axis * batched.dot(axis, arm_vec) * (1.0 - cos_t))             # elbows (3,3,2,m)
    # start: ideal closed form with each parallelogram replaced by its centre line
    centres = 0.5 * (A[:, :, 0] + A[:, :, 1]) - 0.5 * (P0[:, :, 0] + P0[:, :, 1])
    p = _trilaterate_low(centres, np.broadcast_to(0.5 * (L[:, 0] + L[:, 1]), (3, m)), first_pose)
    R = np.zeros((3, 3, m))
    R[0, 0] = R[1, 1] = R[2, 2] = 1.0
    L2 = L * L
    # Newton while the steps are large, then chord: the rows d f / d(position, rotation) / 2 =
    # (d, w x d) per rod are factored again only while a step moved a pose by more than
    # _REFACTOR_STEP (~1e-5 m from the centre-line start with geometric errors); once within it
    # they change by < 1e-4 of themselves and each further step gains four digits for a
    # residual, a product and two substitutions
    moved = np.inf
    for _ in range(_MAX_ITER):
        w = batched.matvec(R[:, :, None, None], P0)                      # platform hinges R P0
        d = p[:, None, None] + w - A
        half_f = 0.5 * (batched.dot(d, d) - L2)                          # rod equations / 2
        if np.max(moved) > _REFACTOR_STEP:
            rows = np.concatenate([d, batched.cross(w, d)]).reshape(6, 6, m)
            factor = batched.normal_factor(rows)
        step = batched.least_squares_step(factor, rows, half_f.reshape(6, m))
        p = p + step[:3]
        R = batched.matmul(batched.rotation_matrices(step[3:]), R)
        moved = np.abs(step).max(axis=0)
        if np.all(moved < 1e-14):
            break
    else:
        bad = np.flatnonzero(~(moved < 1e-14))
        raise KinematicsError(f"forward kinematics did not converge at pose "
                              f"{first_pose + int(bad[0])} ({bad.size} pose(s) of its chunk)")
    d = p[:, None, None] + batched.matvec(R[:, :, None, None], P0) - A
    err = np.abs(np.sqrt(batched.dot(d, d)) - L).reshape(6, m).max(axis=0)
    bad = np.flatnonzero(~(err < CLOSURE_TOL_M))
    if bad.size:
        raise KinematicsError(f"forward kinematics: loop closure {err[bad[0]]:.3e} m at pose "
                              f"{first_pose + int(bad[0])} exceeds {CLOSURE_TOL_M} m")
    return p, R


def rod_residuals(geom: Geometry, q, pose: Pose) -> np.ndarray:
    """The six rod equations |P - A|^2 - L^2 (N,6), m^2, of ``pose`` under ``geom`` at motor
    coordinates q (N,3): zero at the pose ``forward`` returns."""
    q = np.atleast_2d(np.asarray(q, dtype=np.float64))
    return _residual_and_jacobian(geom, elbow_points(geom, geom.theta(q)), pose.p, pose.R)[0]


def rod_vectors(geom: Geometry, q, pose: Pose) -> tuple[np.ndarray, np.ndarray]:
    """At ``pose``: each rod's vector from its elbow hinge to its platform hinge, P - A, and
    the platform hinge's vector R P0, (N,3,2,3) each (m). The rod equations' derivative with
    respect to the platform hinge is 2 (P - A), to the elbow hinge -2 (P - A)."""
    q = np.atleast_2d(np.asarray(q, dtype=np.float64))
    _, d, w = _residual_and_jacobian(geom, elbow_points(geom, geom.theta(q)), pose.p, pose.R)
    return d, w


def pose_derivative(geom: Geometry, q, pose: Pose, d_residuals: np.ndarray) -> np.ndarray:
    """Exact derivative of the forward kinematics' pose with respect to parameters, from the rod
    equations' partial derivatives at the fixed pose ``d_residuals`` (N,6,k): the implicit
    function theorem, d pose = -(d f / d pose)^-1 d f / d parameter. Returns (N,6,k): position
    (m) then rotation vector (rad, the rotation applied on the left of ``pose.R``) per unit of
    each parameter. For a few outputs of many parameters, ``pose_adjoint`` solves one
    right-hand side per output instead."""
    return -np.linalg.solve(_pose_jacobian(geom, q, pose), d_residuals)


def _pose_jacobian(geom: Geometry, q, pose: Pose, rods: tuple | None = None) -> np.ndarray:
    """The rod equations' derivative (N,6,6) in the pose (position, rotation vector);
    ``rods``: ``rod_vectors`` at the pose when the caller has them."""
    q = np.atleast_2d(np.asarray(q, dtype=np.float64))
    d, w = rod_vectors(geom, q, pose) if rods is None else rods
    return np.concatenate([2 * d, 2 * np.cross(w, d)], axis=-1).reshape(q.shape[0], 6, 6)


def pose_adjoint(geom: Geometry, q, pose: Pose, through: np.ndarray,
                 rods: tuple | None = None) -> np.ndarray:
    """(N,a,6) ``through`` (N,a,6) times the inverse of the rod equations' derivative in the
    pose: minus its product with the rod equations' partial derivatives in parameters (N,6,k)
    is the ``a`` outputs' derivative in them (``pose_derivative``), for any k at the cost of
    ``a`` right-hand sides. ``rods``: ``rod_vectors`` at the pose when the caller has them."""
    J = _pose_jacobian(geom, q, pose, rods)
    return np.linalg.solve(J.transpose(0, 2, 1), through.transpose(0, 2, 1)).transpose(0, 2, 1)


def _ideal_chain_angles(geom: Geometry, p: np.ndarray) -> np.ndarray:
    """Closed-form arm angles (N,3) for each chain's centre line, platform not rotated."""
    g = _per_point(geom)
    a, u = g.elbow_vec, g.axis                                   # (1|N,3,3)
    v = p[:, None, :] + g.P0.mean(axis=2) - g.B                  # B -> platform hinge centre
    L = g.L.mean(axis=2)
    ua, uv = np.sum(u * a, -1), np.sum(u * v, -1)
    E = np.sum(v * a, -1) - ua * uv
    F = np.sum(v * np.cross(u, a), -1)
    G = 0.5 * (np.sum(a * a, -1) + np.sum(v * v, -1) - L ** 2) - ua * uv
    h = np.hypot(E, F)
    cos_arg = G / h
    bad = np.flatnonzero(np.any(~(np.abs(cos_arg) <= 1.0), axis=1))
    if bad.size:
        raise KinematicsError(f"position at pose {int(bad[0])} = {p[bad[0]].tolist()} m is "
                              f"unreachable by the arms ({bad.size} pose(s))")
    base = np.arctan2(F, E)
    alpha = np.arccos(cos_arg)
    cand = np.stack([base + alpha, base - alpha])
    home = g.theta_zero[None]
    cand = (cand - home + np.pi) % (2 * np.pi) - np.pi + home   # nearest branch to home
    pick = np.argmin(np.abs(cand - home), axis=0)
    return np.take_along_axis(cand, pick[None], 0)[0]


def inverse(geom: Geometry, p, check: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Inverse kinematics: platform position p (N,3) m -> (q (N,3) rad, R (N,3,3)).

    The platform rotation is whatever the rods impose at that position (identity if ideal)."""
    p = np.atleast_2d(np.asarray(p, dtype=np.float64))
    if not np.all(np.isfinite(p)):
        i = int(np.flatnonzero(~np.all(np.isfinite(p), axis=1))[0])
        raise KinematicsError(f"position at pose {i} is not finite: {p[i].tolist()}")
    n = p.shape[0]
    theta = _ideal_chain_angles(geom, p)
    R = np.broadcast_to(np.eye(3), (n, 3, 3)).copy()
    rel = None

    def update():
        nonlocal theta, R, rel
        A = elbow_points(geom, theta)
        f, d, w = _residual_and_jacobian(geom, A, p, R)
        g = _per_point(geom)
        dA = np.cross(g.axis[:, :, None, :], A - g.B[:, :, None, :])
        J = np.zeros((n, 3, 2, 6))
        for i in range(3):
            J[:, i, :, i] = -2 * np.sum(d[:, i] * dA[:, i], axis=-1)
        J[..., 3:] = 2 * np.cross(w, d)
        step = np.linalg.solve(J.reshape(n, 6, 6), -f[..., None])[..., 0]
        theta = theta + step[:, :3]
        R = Rotation.from_rotvec(step[:, 3:]).as_matrix() @ R
        return np.abs(step).max(axis=1) * np.array(1.0)

    _newton(update, n, "inverse kinematics")
    _check_closure(geom, elbow_points(geom, theta), p, R, "inverse kinematics")
    q = theta - geom.theta_zero
    if check:
        check_stroke(geom, q, "motor coordinates for the requested position")
    return q, R


def rod_directions(geom: Geometry, q: np.ndarray, pose: Pose) -> tuple[np.ndarray, np.ndarray]:
    """Unit rod directions elbow -> platform (N,3,2,3) and hinge-to-hinge distances (N,3,2)."""
    A = elbow_points(geom, geom.theta(q))
    d = pose.p[:, None, None, :] + _platform_vectors(_per_point(geom).P0, pose.R) - A
    L = np.linalg.norm(d, axis=-1)
    return d / L[..., None], L


def home_rod_directions(geom: Geometry) -> tuple[np.ndarray, np.ndarray]:
    """Rod directions at the home pose (q = 0), where the flexures are straight:
    in the world (= arm frame at q = 0) and in the platform frame, each (3,2,3)."""
    home = forward(geom, np.zeros((1, 3)), check=False)
    n0, _ = rod_directions(geom, np.zeros((1, 3)), home)
    return n0[0], np.einsum("ba,ijb->ija", home.R[0], n0[0])


def flexure_rest_directions(geom: Geometry, q: np.ndarray, pose: Pose, home_dirs) -> tuple:
    """Directions (N,3,2,3) a rod would have if its elbow / platform flexure were unbent."""
    n0, n0_plat = home_dirs
    shape = q.shape[:1] + (3, 2, 3)
    rest_e = rotate_about_axis(np.broadcast_to(geom.axis[None, :, None, :], shape),
                               np.broadcast_to(q[:, :, None], shape[:-1]),
                               np.broadcast_to(n0[None], shape))
    rest_p = np.einsum("nab,ijb->nija", pose.R, n0_plat)
    return rest_e, rest_p
