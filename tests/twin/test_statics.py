"""Statics: compliance against finite differences of the exact potential energy; loop closure in
MuJoCo's own kinematics; the seed's force magnitudes; the structure-of-arrays assembly against
the previous (array-of-matrices) implementation, kept below as the reference."""
import mujoco
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import deltatwin.models.batched
from deltatwin.models.geometry import build_geometry
from deltatwin.models.kinematics import (
    Pose,
    elbow_points,
    flexure_rest_directions,
    forward,
    home_rod_directions,
    rotate_about_axis,
)
from deltatwin.models.mjcf import build_model, loop_closure, pose_model
from deltatwin.models.params import load_params
from deltatwin.twin.statics import GRAVITY_M_S2, Statics


@pytest.fixture(scope="module")
def statics():
    p = load_params()
    return Statics(p, build_geometry(p))


def _angle_vec(a, b):
    c = np.cross(a, b)
    s = np.linalg.norm(c)
    return c * (np.arctan2(s, a @ b) / s) if s > 0 else c


def _angle_vecs(a, b):
    """_angle_vec over leading axes (..., 3)."""
    c = np.cross(a, b)
    s = np.linalg.norm(c, axis=-1, keepdims=True)
    return c * np.arctan2(s, np.sum(a * b, axis=-1, keepdims=True)) / np.where(s > 0, s, 1.0)


def exact_energy(S, q, pose, y):
    """Potential energy (J) of the configuration y, with exact (finite) rotations and rod lengths;
    written independently of the displacement method in deltatwin.twin.statics."""
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


@pytest.mark.parametrize("q", [[0.065, 0.065, -0.065], [-0.065, 0.065, 0.0]])
def test_preload_deflection_matches_exact_equilibrium(statics, q):
    """The flexures' preload alone (no load, no gravity) at stroke corners: the linear solve's
    deflection equals the minimum of the exact energy (bend angles, finite rotations) to 0.1 nm
    (measured 0.05 nm; with sin(beta) as the strain it was 1.2 nm off)."""
    q = np.array([q])
    pose = forward(statics.geom, q)
    lin = statics.solve(q, gravity=False)
    U = lambda y: exact_energy(statics, q, pose, y)
    y = lin.y[0].copy()
    H = fd_hessian(U, y, 1e-5)
    for _ in range(3):
        h = 1e-7
        grad = np.array([(U(y + h * e) - U(y - h * e)) / (2 * h) for e in np.eye(18)])
        y -= np.linalg.solve(H, grad)
    assert np.linalg.norm(y[:3]) > 1e-6                 # micrometres of preload deflection
    assert np.abs(lin.deflection[0, :3] - y[:3]).max() < 1e-10


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


# -- reference: the previous implementation (per-pose 10x10 matrices built from the strain maps) --
def _skew(v):
    S = np.zeros(v.shape + (3,))
    S[..., 0, 1], S[..., 0, 2] = -v[..., 2], v[..., 1]
    S[..., 1, 0], S[..., 1, 2] = v[..., 2], -v[..., 0]
    S[..., 2, 0], S[..., 2, 1] = -v[..., 1], v[..., 0]
    return S


def reference_chain_system(S, q, pose):
    """Per-chain stiffness (N,3,10,10) and preload force (N,3,10), strain maps written out."""
    g, k = S.geom, S.k
    n_pose = q.shape[0]
    theta = g.theta(q)
    A = elbow_points(g, theta)
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
    axes = np.stack([u, u, e_n, a_dir], axis=2)
    V = g.B[None] + (1.0 - S.params.prbm_gamma) * (E - g.B[None])
    centres = np.stack([g.B[None].repeat(n_pose, 0), V, V, V], axis=2)
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
    axial = np.sum(nn * D, axis=-2)
    w_rod = np.swapaxes(np.cross(n[..., None, :], np.swapaxes(D, -1, -2)), -1, -2) / L[..., None, None]
    Me_n = np.sum(nn * Me, axis=-2)
    B_elbow = w_rod - (Me - nn * Me_n[..., None, :])
    B_plat = w_rod.copy()
    B_plat[..., 3:6] -= np.eye(3) - nn * n[..., None, :]
    tors = -Me_n
    tors[..., 3:6] += n
    rest_e, rest_p = flexure_rest_directions(g, q, pose, S.home_dirs)
    e0_el, e0_pl = _angle_vecs(rest_e, n), _angle_vecs(rest_p, n)
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


def reference_solve(S, q, wrench, gravity):
    """Generalised displacements (N,18) and platform compliance (N,6,6), dense linear algebra."""
    pose = forward(S.geom, q)
    K, f0 = reference_chain_system(S, q, pose)
    Kpp, Kpi, Kii = K[..., :6, :6], K[..., :6, 6:], K[..., 6:, 6:]
    Kii_inv = np.linalg.inv(Kii)
    T = Kpi @ Kii_inv
    K_plat = np.sum(Kpp - T @ np.swapaxes(Kpi, -1, -2), axis=1)
    f_plat = np.sum(f0[..., :6] - (T @ f0[..., 6:, None])[..., 0], axis=1)
    f = np.broadcast_to(wrench, (q.shape[0], 6)).copy()
    if gravity:
        f[:, 2] -= S.params.platform_mass_kg * GRAVITY_M_S2
    yp = np.linalg.solve(K_plat, (f + f_plat)[..., None])[..., 0]
    rhs = f0[..., 6:] - (np.swapaxes(Kpi, -1, -2) @ yp[:, None, :, None])[..., 0]
    yi = (Kii_inv @ rhs[..., None])[..., 0]
    y = np.concatenate([yp, yi[..., 0], yi[..., 1:].reshape(-1, 9)], axis=1)
    return y, np.linalg.inv(K_plat)


def flawed_statics(rng):
    """A robot with joint, length, encoder and axis errors, so that no symmetry hides a term."""
    p = load_params()
    p = p.replace(d_rod_length_m=rng.normal(0, 20e-6, (3, 2)), d_arm_length_m=rng.normal(0, 20e-6, 3),
                  d_base_joint_m=rng.normal(0, 50e-6, (3, 3)),
                  d_elbow_joint_m=rng.normal(0, 50e-6, (3, 2, 3)),
                  d_platform_joint_m=rng.normal(0, 50e-6, (3, 2, 3)),
                  encoder_offset_rad=rng.normal(0, 2e-3, 3),
                  actuator_axis_tilt_rad=rng.normal(0, 2e-3, (3, 2)))
    return Statics(p, build_geometry(p))


def _rel_err(a, b, axes):
    """Worst per-pose difference relative to the pose's largest reference magnitude."""
    return np.max(np.abs(a - b).max(axis=axes) / np.abs(b).max(axis=axes))


@pytest.mark.parametrize("robot", ["nominal", "flawed"])
def test_assembly_equals_previous_implementation(statics, robot):
    """Chain stiffness, preload, solution and compliance on random poses equal the reference
    (previous, matrix-based) implementation to rounding: the closed-form assembly is exact."""
    rng = np.random.default_rng(11)
    S = statics if robot == "nominal" else flawed_statics(rng)
    q = rng.uniform(*S.geom.stroke, size=(2500, 3))        # more than one chunk
    q[0] = 0.0                                             # home: flexures straight, no preload
    pose = forward(S.geom, q)
    K, f0 = S._chain_system(q[:300], Pose(pose.p[:300], pose.R[:300]))
    K_ref, f0_ref = reference_chain_system(S, q[:300], Pose(pose.p[:300], pose.R[:300]))
    assert K.shape == (10, 10, 3, 300) and f0.shape == (10, 3, 300)
    assert _rel_err(np.moveaxis(K, (2, 3), (1, 0)), K_ref, (-1, -2)) < 1e-12
    assert _rel_err(np.moveaxis(f0, (1, 2), (1, 0))[1:], f0_ref[1:], -1) < 1e-10
    assert np.abs(f0[..., 0]).max() < 1e-12 * np.abs(f0_ref).max()
    wrench = np.array([0.3, -0.8, 1.8, 0.01, -0.02, 0.005])
    res = S.solve(q, wrench=wrench, gravity=True)
    y_ref, C_ref = reference_solve(S, q, wrench, gravity=True)
    assert _rel_err(res.y, y_ref, 1) < 1e-9
    assert _rel_err(res.deflection[:, :3], y_ref[:, :3], 1) < 1e-9
    assert _rel_err(S.compliance(q[:300]), C_ref[:300], (1, 2)) < 1e-9


def test_non_finite_pose_is_reported_with_its_index(statics):
    """A caller-supplied kinematic pose with NaN gives an error naming the pose, not NaN output."""
    q = np.zeros((2000, 3))
    pose = forward(statics.geom, q)
    pose.p[1500, 2] = np.nan                               # in the second chunk
    with pytest.raises(ValueError, match="pose 1500 .*1 pose"):
        statics.solve(q, pose=pose)


def test_result_does_not_depend_on_the_thread_count(statics, monkeypatch):
    """Chunks are solved on threads, each writing its own rows: identical bits for 1 or 2."""
    q = np.random.default_rng(5).uniform(*statics.geom.stroke, size=(2500, 3))
    pose = forward(statics.geom, q)
    monkeypatch.setattr(deltatwin.models.batched, "THREADS", 1)
    one = statics.solve(q, pose=pose).y
    monkeypatch.setattr(deltatwin.models.batched, "THREADS", 2)
    assert np.array_equal(statics.solve(q, pose=pose).y, one)


def test_batched_geometry_is_refused_clearly(statics):
    geom = build_geometry(statics.params, temperatures={"rods": np.full((4, 3, 2), 21.0)})
    with pytest.raises(ValueError, match="batched"):
        Statics(statics.params, geom)
