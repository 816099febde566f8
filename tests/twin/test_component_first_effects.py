"""Effects written component-first (models/batched.py): the same numbers as their previous
(N,3)-layout formulas, kept here as the reference, the dipole force checked against the
gradient of the dipole energy, and the magnetic wrench's exact derivatives against central
differences."""
from types import SimpleNamespace

import numpy as np
from scipy.spatial.transform import Rotation

from deltatwin.models.geometry import build_geometry
from deltatwin.models.kinematics import Pose, forward
from deltatwin.models.mjcf import magnet_positions
from deltatwin.models.params import load_params
from deltatwin.twin.effects.beam_misalignment import _tilt
from deltatwin.twin.effects.magnetic_force import (
    MU0,
    MagneticForce,
    dipole_force_torque,
    dipole_force_torque_gradient,
)


def reference_dipole(m1, r1, m2, r2):
    """(..., 3)-layout dipole force and torque before the rewrite (commit dac728b)."""
    r = r2 - r1
    d = np.linalg.norm(r, axis=-1, keepdims=True)
    u = r / d
    m1u = np.sum(m1 * u, -1, keepdims=True)
    m2u = np.sum(m2 * u, -1, keepdims=True)
    m1m2 = np.sum(m1 * m2, -1, keepdims=True)
    F = 3 * MU0 / (4 * np.pi * d ** 4) * (m2 * m1u + m1 * m2u + u * m1m2 - 5 * u * m1u * m2u)
    B = MU0 / (4 * np.pi * d ** 3) * (3 * u * m1u - m1)
    return F, np.cross(m2, B)


def reference_wrench(effect, points):
    pose, params = points.pose, points.params
    coils = effect.coil_dipoles(params, points.home_p)
    mag = pose.p[:, None, :] + (pose.R[:, None] @ magnet_positions(params)[None, :, :, None])[..., 0]
    m_mag = np.broadcast_to((-effect.magnet_moment_Am2 * pose.R[:, :, 2])[:, None, None, :],
                            mag.shape[:2] + (3, 3))
    m_coil = np.zeros(points.currents_A.shape + (3,))
    m_coil[..., 2] = effect.coil_moment_per_A * points.currents_A
    F, tau = reference_dipole(m_coil[:, None, :, :], coils[None, None, :, :], m_mag,
                              mag[:, :, None, :])
    F_mag = F.sum(axis=2)
    w = np.zeros((pose.p.shape[0], 6))
    w[:, :3] = F_mag.sum(axis=1)
    w[:, 3:] = (np.cross(mag - pose.p[:, None, :], F_mag) + tau.sum(axis=2)).sum(axis=1)
    return w


def test_magnetic_wrench_equals_the_previous_formulas():
    params = load_params()
    geom = build_geometry(params)
    rng = np.random.default_rng(8)
    q = rng.uniform(*geom.stroke, size=(3000, 3))
    points = SimpleNamespace(pose=forward(geom, q), params=params,
                             home_p=forward(geom, np.zeros((1, 3))).p[0],
                             currents_A=rng.uniform(-1.0, 1.0, (3000, 3)))
    effect = MagneticForce(coil_offset_m=rng.normal(size=(3, 3)) * 1e-3)
    new, ref = effect.wrench(points), reference_wrench(effect, points)
    for part in (slice(0, 3), slice(3, 6)):
        assert np.abs(new[:, part] - ref[:, part]).max() <= 1e-15 * np.abs(ref[:, part]).max()


def _magnet_points(n: int, rng):
    params = load_params()
    geom = build_geometry(params)
    currents = rng.uniform(-1.0, 1.0, (n, 3))
    currents[::7] = 0.0                              # rows without current: no force
    return SimpleNamespace(pose=forward(geom, rng.uniform(*geom.stroke, size=(n, 3))),
                           params=params, home_p=forward(geom, np.zeros((1, 3))).p[0],
                           currents_A=currents)


def test_dipole_gradient_matches_central_differences():
    """d F / d r2 and d tau / d r2 at fixed moments, by central differences of the formulas."""
    rng = np.random.default_rng(12)
    m1, r1, m2 = rng.normal(size=(3, 5)), rng.normal(size=(3, 5)) * 1e-3, rng.normal(size=(3, 5))
    r2 = r1 + np.array([0.004, -0.003, 0.012])[:, None] + rng.normal(size=(3, 5)) * 2e-3
    dF, dtau = dipole_force_torque_gradient(m1, r1, m2, r2)
    h = 1e-8
    for j in range(3):
        step = np.zeros((3, 1))
        step[j] = h
        (F_plus, tau_plus), (F_minus, tau_minus) = (dipole_force_torque(m1, r1, m2, r2 + s)
                                                    for s in (step, -step))
        for exact, plus, minus in ((dF, F_plus, F_minus), (dtau, tau_plus, tau_minus)):
            reference = (plus - minus) / (2 * h)
            assert np.abs(exact[:, j] - reference).max() < 1e-6 * np.abs(reference).max()


def test_magnetic_wrench_derivatives_match_central_differences():
    """``MagneticForce.wrench_derivatives`` (what a physics model's load columns and pose
    sensitivity use) against central differences of ``wrench``: in every parameter (the coil
    offsets one by one), the platform's position, a rotation applied on its rotation and the
    home; force and moment each to 1e-8 of their largest; zero on the rows without current."""
    rng = np.random.default_rng(11)
    points = _magnet_points(2000, rng)
    effect = MagneticForce(coil_offset_m=rng.normal(size=(3, 3)) * 1e-3)
    exact = effect.wrench_derivatives(points)
    assert {p.name for p in MagneticForce.free_parameters()} <= set(exact.parameters)

    def agrees(column, sides, h, what):
        reference = (sides[0] - sides[1]) / (2 * h)
        for part in (slice(0, 3), slice(3, 6)):
            size = np.abs(reference[:, part]).max()
            assert size > 0, what
            assert np.abs(column[:, part] - reference[:, part]).max() < 1e-8 * size, what
        assert not np.any(column[::7]), what

    steps = {"magnet_moment_Am2": 1e-3, "coil_moment_per_A": 1e-4, "core_depth_m": 1e-7,
             "coil_offset_m": 1e-7}
    for name, h in steps.items():
        value = np.asarray(effect.values[name], float)
        for idx in np.ndindex(value.shape):
            sides = []
            for sign in (1.0, -1.0):
                moved = value.copy()
                moved[idx] += sign * h
                setattr(effect, name, moved if value.shape else float(moved))
                sides.append(effect.wrench(points))
            setattr(effect, name, value if value.shape else float(value))
            agrees(exact.parameters[name][(slice(None), slice(None)) + idx], sides, h,
                   (name, idx))
    pose, home, h = points.pose, points.home_p, 1e-7
    for d in range(9):
        sides = []
        for sign in (1.0, -1.0):
            step = np.zeros(3)
            step[d % 3] = sign * h
            points.pose, points.home_p = (
                (Pose(pose.p + step, pose.R), home) if d < 3 else
                (Pose(pose.p, Rotation.from_rotvec(step).as_matrix() @ pose.R), home) if d < 6
                else (pose, home + step))
            sides.append(effect.wrench(points))
        points.pose, points.home_p = pose, home
        agrees(exact.pose[:, :, d], sides, h, ("pose", d))


def test_dipole_force_is_minus_the_energy_gradient():
    """F = -grad U with U = -m2 . B1(r2), by central differences (independent of the formula)."""
    rng = np.random.default_rng(9)
    m1, r1, m2 = rng.normal(size=3), np.zeros(3), rng.normal(size=3)
    r2 = np.array([0.004, -0.003, 0.012])

    def energy(r):
        d = np.linalg.norm(r - r1)
        u = (r - r1) / d
        return -m2 @ (MU0 / (4 * np.pi * d ** 3) * (3 * u * (m1 @ u) - m1))

    h = 1e-7
    grad = np.array([(energy(r2 + h * e) - energy(r2 - h * e)) / (2 * h) for e in np.eye(3)])
    F, _ = dipole_force_torque(m1[:, None], r1[:, None], m2[:, None], r2[:, None])
    assert np.abs(F[:, 0] + grad).max() < 1e-6 * np.abs(grad).max()


def test_beam_tilt_equals_the_previous_formulas():
    rng = np.random.default_rng(10)
    direction = rng.normal(size=(500, 3))
    direction[:250, 2] *= 10.0                          # both helper branches
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    angles = np.array([2e-4, -1e-4])
    helper = np.where(np.abs(direction[:, 2:3]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
    e1 = np.cross(direction, helper)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(direction, e1)
    d = direction + angles[0] * e1 + angles[1] * e2
    reference = (d / np.linalg.norm(d, axis=1, keepdims=True), e1, e2)
    for new, ref in zip(_tilt(direction, angles), reference):
        assert np.abs(new - ref).max() <= 4e-16


def test_points_unique_q_is_computed_once_per_q_array():
    from deltatwin.twin.world import Points
    q = np.array([[0.0, 0.1, 0.0], [0.2, 0.0, 0.0], [0.0, 0.1, 0.0]])
    pts = Points(t_s=np.zeros(3), q=q, currents_A=np.zeros((3, 3)), node_T={},
                 room_C=np.zeros(3), pressure_Pa=np.zeros(3), support_C={},
                 params=load_params(), home_p=np.zeros(3))
    qu, inv = pts.unique_q()
    assert np.array_equal(qu[inv], q) and qu.shape == (2, 3)
    assert pts.unique_q()[0] is qu                      # cached
    pts.q = q[:2].copy()                                # a new q array: recomputed
    qu2, inv2 = pts.unique_q()
    assert np.array_equal(qu2[inv2], q[:2])
