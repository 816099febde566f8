"""The component-first forward kinematics and batched algebra (models/batched.py) against the
previous implementation, kept here as the reference: per-point (N,3)-layout Newton with a
direct 6x6 solve and scipy rotations."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from deltatwin.models import batched
from deltatwin.models.geometry import build_geometry
from deltatwin.models.kinematics import (
    KinematicsError,
    Pose,
    _per_point,
    _residual_and_jacobian,
    elbow_points,
    forward,
    pose_adjoint,
    pose_derivative,
)
from deltatwin.models.params import load_params
from deltatwin.twin.effects import make_effect


def reference_forward(geom, q):
    """The forward kinematics before the component-first rewrite (commit dac728b)."""
    n = q.shape[0]
    A = elbow_points(geom, geom.theta(q))
    g = _per_point(geom)
    c = A.mean(axis=2) - g.P0.mean(axis=2)
    r = np.broadcast_to(g.L.mean(axis=2), (n, 3))
    d21, d31 = c[:, 1] - c[:, 0], c[:, 2] - c[:, 0]
    d = np.linalg.norm(d21, axis=1)
    ex = d21 / d[:, None]
    i = np.sum(ex * d31, axis=1)
    ey = d31 - i[:, None] * ex
    j = np.linalg.norm(ey, axis=1)
    ey /= j[:, None]
    ez = np.cross(ex, ey)
    x = (r[:, 0] ** 2 - r[:, 1] ** 2 + d ** 2) / (2 * d)
    y = (r[:, 0] ** 2 - r[:, 2] ** 2 + i ** 2 + j ** 2) / (2 * j) - i * x / j
    base = c[:, 0] + x[:, None] * ex + y[:, None] * ey
    zz = np.sqrt(r[:, 0] ** 2 - x ** 2 - y ** 2)[:, None] * ez
    p = np.where((zz[:, 2] > 0)[:, None], base - zz, base + zz)
    R = np.broadcast_to(np.eye(3), (n, 3, 3)).copy()
    for _ in range(30):
        f, d, w = _residual_and_jacobian(geom, A, p, R)
        J = np.concatenate([2 * d, 2 * np.cross(w, d)], axis=-1).reshape(n, 6, 6)
        step = np.linalg.solve(J, -f[..., None])[..., 0]
        p = p + step[:, :3]
        R = Rotation.from_rotvec(step[:, 3:]).as_matrix() @ R
        if np.all(np.abs(step).max(axis=1) < 1e-14):
            return Pose(p, R)
    raise AssertionError("reference did not converge")


def geometries():
    params = load_params()
    with_errors = make_effect("geometric_errors", {}).robot(params, np.random.default_rng(3))
    rng = np.random.default_rng(4)
    n = 5000
    temps = {"base": 20 + rng.uniform(0, 5, n), "arms": 20 + rng.uniform(0, 5, (n, 3)),
             "rods": 20 + rng.uniform(0, 5, (n, 3, 2)), "platform": 20 + rng.uniform(0, 5, n)}
    return {"ideal": build_geometry(params), "errors": build_geometry(with_errors),
            "errors, per-point temperatures": build_geometry(with_errors, temps)}


@pytest.mark.parametrize("name", ["ideal", "errors", "errors, per-point temperatures"])
def test_forward_equals_the_previous_implementation(name):
    """Same pose to the float64 floor of the rod equations: positions to 1e-15 relative; the
    rotation, which a 1e-17 m^2 rounding of |d|^2 - L^2 moves by ~1e-15 rad across the 30 mm
    platform lever, to 4e-15.  5,000 points: several chunks, the last one partial."""
    geom = geometries()[name]
    q = np.random.default_rng(5).uniform(*geom.stroke, size=(5000, 3))
    new, ref = forward(geom, q), reference_forward(geom, q)
    assert np.abs(new.p - ref.p).max() <= 1e-15 * np.abs(ref.p).max()
    assert np.abs(new.R - ref.R).max() <= 4e-15
    assert np.abs(ref.rotvec).max() > 1e-6 or name == "ideal"     # rotations are exercised


def test_forward_names_the_pose_that_fails_in_a_later_chunk():
    geom = build_geometry(load_params())
    q = np.zeros((batched.CHUNK_POINTS + 10, 3))
    per_point = build_geometry(load_params(), {"rods": np.full((q.shape[0], 3, 2), 20.0)})
    bad = batched.CHUNK_POINTS + 7
    L = per_point.L.copy()
    L[bad] *= 0.1                                      # rods far too short to reach
    short = type(per_point)(**{**per_point.__dict__, "L": L})
    assert forward(geom, q).p.shape == (q.shape[0], 3)
    with pytest.raises(KinematicsError, match=f"pose {bad}"):
        forward(short, q, check=False)


def test_rotation_matrices_match_scipy_on_both_branches():
    rng = np.random.default_rng(6)
    w = np.concatenate([rng.normal(size=(50, 3)) * 1e-6, rng.normal(size=(50, 3)) * 1e-3,
                        rng.normal(size=(50, 3))])
    assert np.abs(batched.rotation_matrices(w.T).transpose(2, 0, 1)
                  - Rotation.from_rotvec(w).as_matrix()).max() < 4e-16


def test_least_squares_step_solves_square_systems():
    rng = np.random.default_rng(7)
    G, f = rng.normal(size=(6, 6, 100)), rng.normal(size=(6, 100))
    x = batched.least_squares_step(batched.normal_factor(G), G, f)
    direct = np.linalg.solve(G.transpose(2, 1, 0), -f.T[..., None])[..., 0]
    assert np.abs(x.T - direct).max() < 1e-9 * np.abs(direct).max()


def test_left_jacobian_carries_a_rotation_vector_change_onto_the_rotation():
    """exp([w + dw]x) = exp([J dw]x) exp([w]x) to first order: J dw against a central difference
    of the rotations (step 1e-6 rad: truncation ~1e-12, round-off ~1e-10 of J), on both
    branches (micro-radian deflections, large rotations)."""
    rng = np.random.default_rng(11)
    w = np.concatenate([rng.normal(size=(20, 3)) * 1e-6, rng.normal(size=(20, 3))])
    J = batched.left_jacobian(w.T).transpose(2, 0, 1)
    h = 1e-6
    for k in range(3):
        dw = np.zeros(3)
        dw[k] = h
        R0 = Rotation.from_rotvec(w).as_matrix()
        turn = (Rotation.from_rotvec(w + dw).as_matrix() - Rotation.from_rotvec(w - dw)
                .as_matrix()) @ R0.transpose(0, 2, 1) / (2 * h)      # [J dw]x per unit dw
        axial = np.stack([turn[:, 2, 1], turn[:, 0, 2], turn[:, 1, 0]], axis=1)
        assert np.abs(axial - J[:, :, k]).max() < 1e-9


def test_pose_adjoint_through_outputs_equals_the_direct_product():
    """The adjoint (a right-hand side per output) gives what the pose derivative (one per
    parameter) times the outputs' derivative in the pose gives."""
    params = load_params(None)
    geom = build_geometry(params)
    rng = np.random.default_rng(12)
    q = rng.uniform(*geom.stroke, size=(40, 3))
    pose = forward(geom, q)
    d_residuals = rng.normal(size=(40, 6, 9)) * 1e-3
    through = rng.normal(size=(40, 3, 6))
    direct = np.einsum("nad,ndk->nak", through, pose_derivative(geom, q, pose, d_residuals))
    adjoint = -(pose_adjoint(geom, q, pose, through) @ d_residuals)
    assert np.abs(adjoint - direct).max() < 1e-12 * np.abs(direct).max()
