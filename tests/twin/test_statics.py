"""Statics: compliance against finite differences of the exact potential energy; loop closure in
MuJoCo's own kinematics; the seed's force magnitudes."""
import mujoco
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from models.geometry import build_geometry
from models.mjcf import build_model, loop_closure, pose_model
from models.params import load_params
from twin.kinematics import forward, home_rod_directions, rotate_about_axis
from twin.statics import Statics


@pytest.fixture(scope="module")
def statics():
    p = load_params()
    return Statics(p, build_geometry(p))


def _angle_vec(a, b):
    c = np.cross(a, b)
    s = np.linalg.norm(c)
    return c * (np.arctan2(s, a @ b) / s) if s > 0 else c


def exact_energy(S, q, pose, y):
    """Potential energy (J) of the configuration y, with exact (finite) rotations and rod lengths;
    written independently of the displacement method in twin.statics."""
    g, k = S.geom, S.k
    n0, n0_plat = home_rod_directions(g)
    dth, phi = y[6:9], y[9:].reshape(3, 3)
    p = pose.p[0] + y[:3]
    R = Rotation.from_rotvec(y[3:6]).as_matrix() @ pose.R[0]
    U = 0.5 * k.drive * dth @ dth + 0.5 * np.sum(k.arm * phi ** 2)
    for i in range(3):
        u = g.axis[i]
        th = g.theta(q)[0, i] + dth[i]
        E = g.B[i] + rotate_about_axis(u, th, g.elbow_vec[i])
        a_dir = (E - g.B[i]) / np.linalg.norm(E - g.B[i])
        e_n = np.cross(a_dir, u)
        e_n /= np.linalg.norm(e_n)
        V = g.B[i] + (1 - S.params.prbm_gamma) * (E - g.B[i])
        flex = Rotation.from_rotvec(phi[i, 0] * u + phi[i, 1] * e_n + phi[i, 2] * a_dir)
        elbow_rot = (flex * Rotation.from_rotvec(dth[i] * u)).as_rotvec()
        for j in range(2):
            A = V + flex.apply(g.B[i] + rotate_about_axis(u, th, g.arm_vec[i, j]) - V)
            d = p + R @ g.P0[i, j] - A
            ell = np.linalg.norm(d)
            n = d / ell
            rest_e = flex.apply(rotate_about_axis(u, th - g.theta_zero[i], n0[i, j]))
            rest_p = R @ n0_plat[i, j]
            b_e, b_p = _angle_vec(rest_e, n), _angle_vec(rest_p, n)
            twist = n @ (y[3:6] - elbow_rot)
            U += 0.5 * k.rod_axial[i, j] * (ell - g.L[i, j]) ** 2
            U += 0.5 * k.hinge_bending * (b_e @ b_e + b_p @ b_p) + 0.25 * k.hinge_torsion * twist ** 2
    return U


def fd_hessian(fun, y0, h=1e-6):
    n = y0.size
    H = np.empty((n, n))
    for a in range(n):
        for b in range(a, n):
            ea, eb = np.eye(n)[a] * h, np.eye(n)[b] * h
            H[a, b] = H[b, a] = (fun(y0 + ea + eb) - fun(y0 + ea - eb) - fun(y0 - ea + eb)
                                 + fun(y0 - ea - eb)) / (4 * h * h)
    return H


@pytest.mark.parametrize("q", [[0.0, 0.0, 0.0], [0.05, -0.04, 0.02]])
def test_compliance_matches_finite_differences_of_exact_energy(statics, q):
    q = np.array([q])
    pose = forward(statics.geom, q)
    res = statics.solve(q, gravity=False)            # the flexures' own preload equilibrium
    H = fd_hessian(lambda y: exact_energy(statics, q, pose, y), res.y[0])
    C_fd = np.linalg.inv(H)[:6, :6]
    C = statics.compliance(q)[0]
    # translational block within 1 % (element by element, relative to the largest term)
    assert np.abs(C[:3, :3] - C_fd[:3, :3]).max() < 0.01 * np.abs(C_fd[:3, :3]).max()
    assert np.abs(C[3:, 3:] - C_fd[3:, 3:]).max() < 0.01 * np.abs(C_fd[3:, 3:]).max()


def test_deflection_under_2N_matches_exact_equilibrium(statics):
    q = np.array([[0.03, 0.01, -0.04]])
    pose = forward(statics.geom, q)
    W = np.array([0.3, 0.8, 1.8, 0.0, 0.0, 0.0])
    lin = statics.solve(q, wrench=W, gravity=False)
    U = lambda y: exact_energy(statics, q, pose, y) - W @ y[:6]
    y = lin.y[0].copy()
    H = fd_hessian(U, y)
    for _ in range(3):     # Newton on the exact energy, gradient by central differences
        h = 1e-7
        grad = np.array([(U(y + h * e) - U(y - h * e)) / (2 * h) for e in np.eye(18)])
        y -= np.linalg.solve(H, grad)
    d_exact = y[:3]
    d_lin = lin.deflection[0, :3]
    assert np.linalg.norm(d_lin - d_exact) < 0.01 * np.linalg.norm(d_exact)


def test_static_pose_closes_loops_in_mujoco(statics):
    """The solved static configuration, put into MuJoCo's own kinematic tree, closes every loop
    to < 1e-12 m, and MuJoCo's rod slides equal the statics' rod stretch."""
    params = statics.params
    _, m = build_model(params)
    d = mujoco.MjData(m)
    rng = np.random.default_rng(3)
    for q in rng.uniform(*statics.geom.stroke, size=(5, 3)):
        kin = forward(statics.geom, q[None])
        stretch = pose_model(m, d, q, kin.p[0], kin.R[0])
        assert stretch < 1e-12 and loop_closure(m, d) < 1e-12     # rigid kinematics
        res = statics.solve(q[None], wrench=[0.0, 0.0, 2.0, 0.0, 0.0, 0.0])
        y = res.y[0]
        pose_model(m, d, q + y[6:9], res.pose.p[0], res.pose.R[0], arm_flex=y[9:].reshape(3, 3))
        assert loop_closure(m, d) < 1e-12


def test_coil_like_load_gives_the_seed_order_of_magnitude(statics):
    """~2 N upward through the platform (the coils' repulsion) at the workspace centre gives
    hundreds of nm, within 2x of the seed's 168 nm in Z; lateral compliance is 2-3x the
    vertical, as the seed's larger X/Y displacements suggest."""
    res = statics.solve(np.zeros((1, 3)), wrench=[0.0, 0.0, 2.0, 0.0, 0.0, 0.0], gravity=False)
    ref = statics.solve(np.zeros((1, 3)), gravity=False)
    dz_nm = (res.pose.p[0, 2] - ref.pose.p[0, 2]) * 1e9
    assert 168 / 2 < dz_nm < 168 * 2
    C = statics.compliance(np.zeros((1, 3)))[0]
    assert 1.5 < C[0, 0] / C[2, 2] < 4


def test_gravity_sags_the_platform_downwards(statics):
    res = statics.solve(np.zeros((1, 3)), gravity=True)
    ref = statics.solve(np.zeros((1, 3)), gravity=False)
    sag = res.pose.p[0] - ref.pose.p[0]
    expected = statics.compliance(np.zeros((1, 3)))[0][:3, 2] * (-statics.params.platform_mass_kg * 9.80665)
    assert np.allclose(sag, expected, rtol=1e-9, atol=1e-15)
    assert sag[2] < -50e-9
