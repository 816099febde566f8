"""Kinematics against an independent closed form (Williams' three-sphere method) and by hand."""
import numpy as np
import pytest

from deltatwin.models.geometry import build_geometry
from deltatwin.models.kinematics import KinematicsError, forward, inverse
from deltatwin.models.params import load_params


@pytest.fixture(scope="module")
def geom():
    return build_geometry(load_params())


def williams_fk(geom, q):
    """R. L. Williams II (2015), revolute-input Delta FK: intersection of three spheres solved by
    eliminating x and y linearly, then a quadratic in z (written independently of models.kinematics)."""
    theta = q + geom.theta_zero
    out = []
    for th in theta:
        c = []
        for i in range(3):
            u = geom.axis[i]
            a = geom.elbow_vec[i]
            arm = a * np.cos(th[i]) + np.cross(u, a) * np.sin(th[i])   # u is perpendicular to a
            c.append(geom.B[i] + arm - geom.P0[i].mean(axis=0))
        c = np.array(c)
        L = geom.L.mean()
        # |p - c_i|^2 = L^2; subtract pairs -> two linear equations in x, y given z
        M = 2 * np.array([c[1, :2] - c[0, :2], c[2, :2] - c[0, :2]])
        kz = -2 * np.array([c[1, 2] - c[0, 2], c[2, 2] - c[0, 2]])
        k0 = np.array([c[1] @ c[1] - c[0] @ c[0], c[2] @ c[2] - c[0] @ c[0]])
        Minv = np.linalg.inv(M)
        xy0, xy1 = Minv @ k0, Minv @ kz            # x, y = xy0 + xy1 z
        d0 = xy0 - c[0, :2]
        qa = xy1 @ xy1 + 1
        qb = 2 * (d0 @ xy1) - 2 * c[0, 2]
        qc = d0 @ d0 + c[0, 2] ** 2 - L ** 2
        z = (-qb - np.sqrt(qb ** 2 - 4 * qa * qc)) / (2 * qa)   # the lower solution
        out.append(np.r_[xy0 + xy1 * z, z])
    return np.array(out)


def test_ideal_forward_matches_williams_closed_form(geom):
    q = np.random.default_rng(1).uniform(*geom.stroke, size=(200, 3))
    pose = forward(geom, q)
    assert np.abs(pose.p - williams_fk(geom, q)).max() < 1e-12
    assert np.abs(pose.rotvec).max() < 1e-13   # ideal geometry: a pure translation


def test_inverse_round_trip_and_closed_form_angles(geom):
    q = np.random.default_rng(2).uniform(*geom.stroke, size=(200, 3))
    pose = forward(geom, q)
    q_back, R = inverse(geom, pose.p)
    assert np.abs(q_back - q).max() < 1e-13
    # Williams' IK per chain: E cos(t) + F sin(t) = G
    p = pose.p[:5]
    for n in range(5):
        for i in range(3):
            a, u = geom.elbow_vec[i], geom.axis[i]
            v = p[n] + geom.P0[i].mean(axis=0) - geom.B[i]
            E, F = v @ a, v @ np.cross(u, a)
            G = 0.5 * (a @ a + v @ v - geom.L[i].mean() ** 2)
            t = np.arctan2(F, E) + np.array([1, -1]) * np.arccos(G / np.hypot(E, F))
            assert np.min(np.abs(t - geom.theta_zero[i] - q_back[n, i])) < 1e-12


def test_rod_length_error_rotation_matches_linearised_hand_derivation():
    """One rod 1 um long: the platform pose change is J^-1 dL, where each rod's row of J is
    (n, w x n) (rod direction n, platform hinge lever w): first-order, by hand."""
    params = load_params()
    ideal = build_geometry(params)
    dL = np.zeros((3, 2))
    dL[0, 0] = 1e-6
    bad = build_geometry(params.replace(d_rod_length_m=dL))
    q = np.array([[0.02, -0.03, 0.01]])
    p0 = forward(ideal, q)
    p1 = forward(bad, q)
    from deltatwin.models.kinematics import elbow_points
    A = elbow_points(ideal, ideal.theta(q))[0]
    w = np.einsum("ab,ijb->ija", p0.R[0], ideal.P0)
    n = p0.p[0] + w - A
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    J = np.concatenate([n, np.cross(w, n)], axis=-1).reshape(6, 6)
    expected = np.linalg.solve(J, dL.ravel())
    rot = p1.rotvec[0]
    assert np.linalg.norm(rot) > 1e-6   # a 1 um rod error tilts the platform by ~ 10 urad
    # second-order terms are ~ (1e-5)^2 relative: agreement to 1e-4 of the effect
    assert np.linalg.norm(rot - expected[3:]) < 1e-4 * np.linalg.norm(expected[3:])
    dp = p1.p[0] - p0.p[0]
    assert np.linalg.norm(dp - expected[:3]) < 1e-4 * np.linalg.norm(expected[:3])


def test_bad_input_is_named(geom):
    with pytest.raises(KinematicsError, match="pose 1"):
        forward(geom, [[0, 0, 0], [0.5, 0, 0]])
    with pytest.raises(KinematicsError, match="pose 0.*unreachable|pose 0"):
        inverse(geom, [[0.0, 0.0, -0.5]])
    with pytest.raises(KinematicsError, match="outside the actuator stroke"):
        inverse(geom, [[0.0, 0.0, forward(geom, np.zeros((1, 3))).p[0, 2] + 0.02]])
    with pytest.raises(KinematicsError, match="not finite"):
        inverse(geom, [[np.nan, 0.0, -0.1]])


def test_batched_geometry_equals_one_robot_per_point():
    """Per-point part temperatures (a batched geometry) give exactly the pose of a robot built
    at each point's temperatures; IK inverts it."""
    params = load_params()
    rng = np.random.default_rng(7)
    q = rng.uniform(-0.05, 0.05, (6, 3))
    temps = {"base": rng.uniform(18, 26, 6), "arms": rng.uniform(18, 26, (6, 3)),
             "rods": rng.uniform(18, 26, (6, 3, 2)), "platform": rng.uniform(18, 26, 6)}
    batched = forward(build_geometry(params, temps), q)
    for k in range(6):
        one = params.replace(T_base_C=float(temps["base"][k]), T_arms_C=temps["arms"][k],
                             T_rods_C=temps["rods"][k], T_platform_C=float(temps["platform"][k]))
        pose = forward(build_geometry(one), q[k:k + 1])
        assert np.abs(batched.p[k] - pose.p[0]).max() < 1e-15
        assert np.abs(batched.R[k] - pose.R[0]).max() < 1e-15
    q_back, _ = inverse(build_geometry(params, temps), batched.p)
    assert np.abs(q_back - q).max() < 1e-12
    # a 5 K warmer rod set moves the platform by micrometres: the temperatures are really used
    assert np.abs(batched.p - forward(build_geometry(params), q).p).max() > 1e-6
