"""Reference evaluator of a physics model exported for a controller (``deltatwin-physics-
controller`` JSON, written by calibration/physics/export.py; docs/compensation.md describes it).

Standalone on purpose: numpy and the standard library only, nothing from deltatwin, so that a
controller's author can read (and port) every step, and a test can compare it with the fitted
model it was exported from. Runnable as a script: ``python controller_evaluator.py MODEL.json``
prints the model's summary.

What the model computes: the reading each interferometer (x, y, z) counts from its session's
zero, at motor coordinates q and the conditions at that moment, and its inverse (the motor
coordinates at which the readings equal a target). Every array carries the points on its first
axis; the evaluation is vectorised over them. Units: m, rad, degC, Pa, A, N.

The steps (the same as the fitted model's, calibration/physics/model.py):

1. geometry at the points: every joint array of a part (base, each arm, each rod, platform) is
   its value at the reference temperature times 1 + CTE (T_part - T_ref);
2. kinematic pose: the six rod equations |p + R P0_ij - A_ij(q)|^2 = L_ij^2 solved by Newton
   for the platform position p and rotation R;
3. load: the wrench on the platform (its weight, the coil-magnet dipole forces at the kinematic
   pose) through the compliance at q, on top of the preload deflection at q (both Chebyshev
   series in q, fitted to the twin's statics), moves and turns the platform;
4. optics: each beam's head and direction (nominal, then the effects' changes in the model's
   order: the loop's thermal drift, the beams' tilts and Abbe offsets, the air index) and the
   double-pass plane-mirror reading n h cos(alpha) of the cube face;
5. counted from the session's zero (home, coils off, the zero's conditions) and divided by the
   index the instrument assumes.

The inverse solves the six rod equations and the three readings together for (q, p, R) by
Newton, with their analytic derivatives (the readings' through the rigid platform; the load's
and the optics' small dependence on the pose left out of the Jacobian, so the iteration
converges linearly with a rate ~1e-4 and the residual is always evaluated in full), warm-started
from a previous solution when given.
"""
from __future__ import annotations

import json
import sys

import numpy as np

FORMAT = "deltatwin-physics-controller"
FORMAT_VERSION = 1
AXES = ("x", "y", "z")
FACE_NORMALS = np.array([[-1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])
MU0 = 4e-7 * np.pi
CONDITIONS = ("base", "arm1", "arm2", "arm3", "rod1", "rod2", "rod3", "platform", "table",
              "frame", "air_x", "air_y", "air_z", "comp_x", "comp_y", "comp_z", "room", "support")
KINEMATICS_TOL_M = 1e-14     # Newton step at which a pose has converged
CLOSURE_TOL_M = 1e-12        # largest |rod length - L| accepted
MAX_ITER = 50


class ControllerModelError(ValueError):
    """A controller model file or its inputs are not what this evaluator reads."""


def _cross(a, b):
    """Cross product over the last axis (np.cross's argument handling costs more than the
    product on one point)."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1)


def load(path) -> dict:
    """The model file as arrays (``np.asarray`` of every list), checked for its format."""
    try:
        with open(path, encoding="utf-8") as f:
            doc = json.load(f)
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ControllerModelError(f"{path}: not a JSON file ({exc})") from exc
    except OSError as exc:
        raise ControllerModelError(f"{path}: cannot be read ({exc.strerror})") from exc
    if not isinstance(doc, dict):
        doc = {"format": None}
    if doc.get("format") != FORMAT or doc.get("format_version") != FORMAT_VERSION:
        raise ControllerModelError(f"{path}: format {doc.get('format')!r} version "
                                   f"{doc.get('format_version')!r}; this evaluator reads "
                                   f"{FORMAT!r} version {FORMAT_VERSION}")
    return _arrays(doc)


def _arrays(v):
    if isinstance(v, dict):
        return {k: _arrays(x) for k, x in v.items()}
    if isinstance(v, list) and v and all(isinstance(x, (int, float, list)) for x in v):
        return np.asarray(v, dtype=np.float64)
    return v


# -- conditions -------------------------------------------------------------------------------

def conditions(model: dict, values: dict, n: int) -> dict:
    """The conditions of n points as arrays (n,): temperatures (degC) under the names of
    ``CONDITIONS``, ``pressure_Pa``, ``currents_A`` (n, 3). Missing temperatures are at the
    reference, pressure at 101325 Pa, currents 0."""
    T_ref = float(model["thermal"]["reference_C"])
    out = {}
    for k in CONDITIONS:
        v = values.get(k, T_ref)
        out[k] = np.broadcast_to(np.asarray(v, dtype=np.float64), (n,))
    out["pressure_Pa"] = np.broadcast_to(np.asarray(values.get("pressure_Pa", 101325.0), float),
                                         (n,))
    out["currents_A"] = np.broadcast_to(np.asarray(values.get("currents_A", 0.0), float), (n, 3))
    for k, v in out.items():
        if not np.all(np.isfinite(v)):
            raise ControllerModelError(f"condition {k!r} is not finite")
    return out


# -- 1. geometry --------------------------------------------------------------------------------

def geometry(model: dict, c: dict) -> dict:
    """Joint arrays at the points' part temperatures (a leading axis n on each)."""
    g, th = model["geometry"], model["thermal"]
    T_ref, cte = float(th["reference_C"]), th["cte_per_K"]
    n = c["base"].shape[0]
    s_base = 1.0 + float(cte["base"]) * (c["base"] - T_ref)
    arms = np.stack([c["arm1"], c["arm2"], c["arm3"]], axis=1)
    rods = np.stack([c["rod1"], c["rod2"], c["rod3"]], axis=1)
    s_arm = 1.0 + float(cte["arms"]) * (arms - T_ref)                        # (n,3)
    s_rod = 1.0 + float(cte["rods"]) * (rods - T_ref)                        # (n,3)
    s_plat = 1.0 + float(cte["platform"]) * (c["platform"] - T_ref)
    return {"B": s_base[:, None, None] * g["B_m"],
            "axis": np.broadcast_to(g["axis"], (n, 3, 3)),
            "arm_vec": s_arm[:, :, None, None] * g["arm_vec_m"],
            "P0": s_plat[:, None, None, None] * g["P0_m"],
            "L": s_rod[:, :, None] * g["L_m"],
            "theta_zero": g["theta_zero_rad"],
            "cube_offset": s_plat[:, None] * g["cube_offset_m"]}


def rotation(w: np.ndarray) -> np.ndarray:
    """Rotation matrices (n,3,3) of rotation vectors w (n,3) rad (Rodrigues)."""
    t2 = np.sum(w * w, axis=1)
    small = t2 < 1e-8
    t = np.sqrt(np.where(small, 1.0, t2))
    a = np.where(small, 1.0 - t2 / 6.0 + t2 * t2 / 120.0, np.sin(t) / t)
    b = np.where(small, 0.5 - t2 / 24.0 + t2 * t2 / 720.0, 2.0 * (np.sin(0.5 * t) / t) ** 2)
    K = np.zeros((w.shape[0], 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -w[:, 2], w[:, 1], -w[:, 0]
    K[:, 1, 0], K[:, 2, 0], K[:, 2, 1] = w[:, 2], -w[:, 1], w[:, 0]
    return np.eye(3) + a[:, None, None] * K + b[:, None, None] * (K @ K)


def elbows(g: dict, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Elbow hinges A (n,3,2,3) at motor coordinates q (n,3) and dA/dq_i (n,3,2,3)."""
    theta = (q + g["theta_zero"])[:, :, None, None]
    ax = g["axis"][:, :, None, :]
    v = g["arm_vec"]
    cos_t, sin_t = np.cos(theta), np.sin(theta)
    axv = _cross(ax, v)
    along = ax * np.sum(ax * v, axis=-1, keepdims=True)
    rotated = v * cos_t + axv * sin_t + along * (1.0 - cos_t)
    return g["B"][:, :, None, :] + rotated, _cross(ax, rotated)


# -- 2. kinematic pose --------------------------------------------------------------------------

def _rod_system(g, A, p, R):
    """Rod equations f (n,6) and their derivatives in (p, rotation) (n,6,6)."""
    w = np.einsum("nab,nijb->nija", R, g["P0"])
    d = p[:, None, None, :] + w - A
    f = (np.sum(d * d, axis=-1) - g["L"] ** 2).reshape(-1, 6)
    J = 2.0 * np.concatenate([d, _cross(w, d)], axis=-1).reshape(-1, 6, 6)
    return f, J, d


def start_pose(g: dict, A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Closed-form start: each parallelogram replaced by its centre line, the lower
    intersection of three spheres; R = identity."""
    c = 0.5 * (A[:, :, 0] + A[:, :, 1]) - 0.5 * (g["P0"][:, :, 0] + g["P0"][:, :, 1])
    r = 0.5 * (g["L"][:, :, 0] + g["L"][:, :, 1])
    ex = c[:, 1] - c[:, 0]
    d = np.linalg.norm(ex, axis=1)
    ex = ex / d[:, None]
    d31 = c[:, 2] - c[:, 0]
    i = np.sum(ex * d31, axis=1)
    ey = d31 - i[:, None] * ex
    j = np.linalg.norm(ey, axis=1)
    ey = ey / j[:, None]
    ez = _cross(ex, ey)
    x = (r[:, 0] ** 2 - r[:, 1] ** 2 + d ** 2) / (2 * d)
    y = (r[:, 0] ** 2 - r[:, 2] ** 2 + i ** 2 + j ** 2) / (2 * j) - i * x / j
    z2 = r[:, 0] ** 2 - x ** 2 - y ** 2
    if not np.all(z2 >= 0):
        raise ControllerModelError("the rods cannot reach the platform at these motor "
                                   "coordinates (three-sphere intersection empty)")
    base = c[:, 0] + x[:, None] * ex + y[:, None] * ey
    zz = np.sqrt(z2)[:, None] * ez
    p = np.where(zz[:, 2:3] > 0, base - zz, base + zz)
    return p, np.broadcast_to(np.eye(3), (p.shape[0], 3, 3)).copy()


def kinematic_pose(g: dict, q: np.ndarray, pose=None) -> tuple[np.ndarray, np.ndarray]:
    """Platform position (n,3) and rotation (n,3,3) at motor coordinates q (n,3): Newton on the
    six rod equations from ``pose`` (a previous (p, R)) or the closed-form start; the loop
    closure is checked."""
    A, _ = elbows(g, q)
    p, R = start_pose(g, A) if pose is None else (pose[0].copy(), pose[1].copy())
    for _ in range(MAX_ITER):
        f, J, _ = _rod_system(g, A, p, R)
        step = np.linalg.solve(J, -f[..., None])[..., 0]
        p = p + step[:, :3]
        R = rotation(step[:, 3:]) @ R
        if np.all(np.abs(step) < KINEMATICS_TOL_M):
            break
    _check_closure(g, A, p, R)
    return p, R


def _check_closure(g, A, p, R):
    _, _, d = _rod_system(g, A, p, R)
    err = np.abs(np.linalg.norm(d, axis=-1) - g["L"]).reshape(-1, 6).max(axis=1)
    if not np.all(err < CLOSURE_TOL_M):
        i = int(np.flatnonzero(~(err < CLOSURE_TOL_M))[0])
        raise ControllerModelError(f"kinematics did not close at point {i}: {err[i]:.3g} m")


# -- 3. load ------------------------------------------------------------------------------------

def chebyshev3(coef: np.ndarray, lo: float, hi: float, q: np.ndarray) -> np.ndarray:
    """A tensor Chebyshev series (d+1, d+1, d+1, ...) on [lo, hi]^3 at q (n,3): (n, ...)."""
    x = (2.0 * q - (lo + hi)) / (hi - lo)
    deg = coef.shape[0] - 1
    T = np.empty((deg + 1,) + x.shape)
    T[0] = 1.0
    if deg:
        T[1] = x
    for k in range(2, deg + 1):
        T[k] = 2.0 * x * T[k - 1] - T[k - 2]
    # sum_ijk T_i(x1) T_j(x2) T_k(x3) c_ijk: the (n, (d+1)^3) basis times the coefficients
    m = deg + 1
    basis = (T[:, None, None, :, 0] * T[None, :, None, :, 1] * T[None, None, :, :, 2])
    out = basis.reshape(m ** 3, -1).T @ coef.reshape(m ** 3, -1)
    return out.reshape(x.shape[:1] + coef.shape[3:])


def wrench(model: dict, c: dict, p: np.ndarray, R: np.ndarray) -> np.ndarray:
    """Wrench (n,6) on the platform (N at its origin, N m), world frame."""
    load = model["load"]
    n = p.shape[0]
    w = np.zeros((n, 6))
    if load.get("gravity_N") is not None:
        w[:, :3] += load["gravity_N"]
    mag = load.get("magnetic")
    if mag is not None:
        arm = np.einsum("nab,kb->nka", R, mag["magnets_platform_m"])        # (n,3 magnets,3)
        r2 = p[:, None, :] + arm
        m2 = -float(mag["magnet_moment_Am2"]) * R[:, :, 2]                   # (n,3)
        # every coil (axis 2) on every magnet (axis 1): (n, 3 magnets, 3 coils, 3)
        m1 = np.zeros((n, 1, 3, 3))
        m1[..., 2] = float(mag["coil_moment_per_A"]) * c["currents_A"][:, None, :]
        r = r2[:, :, None, :] - mag["coils_m"][None, None]
        d2 = np.sum(r * r, axis=-1, keepdims=True)
        d = np.sqrt(d2)
        u = r / d
        m2 = m2[:, None, None, :]
        m1u = np.sum(m1 * u, axis=-1, keepdims=True)
        m2u = np.sum(m2 * u, axis=-1, keepdims=True)
        m1m2 = np.sum(m1 * m2, axis=-1, keepdims=True)
        F_tot = (3 * MU0 / (4 * np.pi * d2 * d2) * (m2 * m1u + m1 * m2u + u * m1m2
                                                    - 5 * u * m1u * m2u)).sum(axis=2)
        B = MU0 / (4 * np.pi * d2 * d) * (3 * u * m1u - m1)
        tau_tot = _cross(np.broadcast_to(m2, B.shape), B).sum(axis=2)
        w[:, :3] += F_tot.sum(axis=1)
        w[:, 3:] += (_cross(arm, F_tot) + tau_tot).sum(axis=1)
    return w


def deflected(model: dict, c: dict, q: np.ndarray, p: np.ndarray, R: np.ndarray):
    """The platform's pose under its load: preload deflection + compliance x wrench."""
    st = model["statics"]
    lo, hi = (float(v) for v in st["q_range_rad"])
    loaded = model["load"].get("gravity_N") is not None or model["load"].get("magnetic") is not None
    if not loaded:
        y = chebyshev3(st["preload_coef"], lo, hi, q)
    else:       # preload and compliance in one series (42 values per node)
        m = st["preload_coef"].shape[0]
        both = chebyshev3(np.concatenate([st["preload_coef"], st["compliance_coef"].reshape(
            (m, m, m, 36))], axis=-1), lo, hi, q)
        y = both[:, :6] + np.einsum("nij,nj->ni", both[:, 6:].reshape(-1, 6, 6),
                                    wrench(model, c, p, R))
    return p + y[:, :3], rotation(y[:, 3:]) @ R


# -- 4. optics ----------------------------------------------------------------------------------

def air_index(T_C, p_Pa, vapour_Pa, wavelength_m):
    """Refractive index of air: Edlen (1966) as revised by Birch & Downs (1993, 1994)."""
    sigma2 = (1e-6 / wavelength_m) ** 2
    ns = 1e-8 * (8342.54 + 2406147.0 / (130.0 - sigma2) + 15998.0 / (38.9 - sigma2))
    ntp = p_Pa * ns / 96095.43 * (1.0 + 1e-8 * (0.601 - 0.00972 * T_C) * p_Pa) \
        / (1.0 + 0.003661 * T_C)
    return 1.0 + ntp - vapour_Pa * (3.7345 - 0.0401 * sigma2) * 1e-10


def _tilt(d, angles):
    """A beam direction (n,3) tilted by two small angles about the axes across it (the
    twin's beam_misalignment): (new direction, the two unit vectors across it)."""
    upright = (np.abs(d[:, 2]) < 0.9)[:, None]
    e1 = _cross(d, np.where(upright, [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]))
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = _cross(d, e1)
    out = d + angles[0] * e1 + angles[1] * e2
    return out / np.linalg.norm(out, axis=1, keepdims=True), e1, e2


def _loop_drift(step: dict, c: dict, pos: np.ndarray, support_C: np.ndarray) -> np.ndarray:
    """Displacement (n,3) of an optical element at ``pos`` (n,3) standing on a support at
    ``support_C``: the table expands in its plane about the robot's axis, the frame lifts the
    robot's base and (hanging from an arm) moves it sideways, the support lifts the element."""
    dT_table, dT_frame = c["table"] - step["reference_C"], c["frame"] - step["reference_C"]
    height = step["frame_height_m"] + pos[:, 2]
    base_shift = ((step["table_cte_per_K"] * dT_table
                   - step["frame_cte_per_K"] * dT_frame)[:, None] * step["frame_arm_m"])
    d = np.zeros_like(pos)
    d[:, :2] = step["table_cte_per_K"] * dT_table[:, None] * pos[:, :2] - base_shift
    d[:, 2] = (step["support_cte_per_K"] * (support_C - step["reference_C"]) * height
               - step["frame_cte_per_K"] * dT_frame * step["frame_height_m"])
    return d


def optics(model: dict, c: dict) -> dict:
    """Heads (n,3), directions (n,3), fold mirror (n,3), air index and the instrument's index
    (n,) per axis at the conditions, after the model's optics steps in order."""
    o = model["optics"]
    n = c["base"].shape[0]
    head = {a: np.tile(o["heads_m"][a], (n, 1)) for a in AXES}
    direction = {a: np.tile(o["directions"][a], (n, 1)) for a in AXES}
    fold = np.tile(o["fold_m"], (n, 1))
    n_air = {a: np.ones(n) for a in AXES}
    n_comp = {a: np.ones(n) for a in AXES}
    for step in o["steps"]:
        kind = step["kind"]
        if kind == "loop_drift":
            for a in AXES:      # every support stands on the table (its sensors' level)
                head[a] = head[a] + _loop_drift(step, c, head[a], c["support"])
            fold = fold + _loop_drift(step, c, fold, c["table"])
        elif kind == "beam_misalignment":
            for k, a in enumerate(AXES):
                direction[a], e1, e2 = _tilt(direction[a], step["angle_rad"][k])
                head[a] = (head[a] + step["abbe_offset_m"][k][0] * e1
                           + step["abbe_offset_m"][k][1] * e2)
        elif kind == "air_refraction":
            f, lam, vap = step["beam_room_fraction"], step["wavelength_m"], step["vapour_pressure_Pa"]
            for k, a in enumerate(AXES):
                T_beam = (1.0 - f) * c[f"air_{a}"] + f * c["room"]
                n_air[a] = air_index(T_beam, c["pressure_Pa"], vap, lam)
                n_comp[a] = air_index(c[f"comp_{a}"] + step["compensation_offset_C"][k],
                                      step["assumed_pressure_Pa"], vap, lam)
        else:
            raise ControllerModelError(f"optics step {kind!r} is not one this evaluator knows")
    return {"head": head, "direction": direction, "fold": fold, "n_air": n_air,
            "n_comp": n_comp}


def _beam(model, opt, k):
    """Effective straight beam (vertex, unit direction) reaching the cube face of axis k: for
    Z their images in the fold mirror."""
    a = AXES[k]
    v, b = opt["head"][a], opt["direction"][a]
    b = b / np.linalg.norm(b, axis=1, keepdims=True)
    if a != "z":
        return v, b
    nm = model["optics"]["fold_normal"]
    reflect = lambda x: x - 2.0 * (x @ nm)[:, None] * nm
    return opt["fold"] + reflect(v - opt["fold"]), reflect(b)


def optical_paths(model, opt, g, p, R) -> np.ndarray:
    """Optical paths n h cos(alpha) (n,3) m of the three double-pass interferometers."""
    size = float(model["geometry"]["cube_size_m"])
    out = np.empty((p.shape[0], 3))
    for k, a in enumerate(AXES):
        vertex, b = _beam(model, opt, k)
        nf = FACE_NORMALS[k]
        centre = p + np.einsum("nab,nb->na", R, g["cube_offset"] + 0.5 * size * nf)
        nw = R @ nf
        h = np.sum(nw * (vertex - centre), axis=1)
        out[:, k] = opt["n_air"][a] * h * (-np.sum(nw * b, axis=1))
    return out


def _path_derivative(model, opt, p, R) -> np.ndarray:
    """d optical path / d (p, rotation) (n,3,6) of the rigid platform (cos alpha held)."""
    J = np.empty((p.shape[0], 3, 6))
    for k, a in enumerate(AXES):
        vertex, b = _beam(model, opt, k)
        nw = R @ FACE_NORMALS[k]
        scale = (opt["n_air"][a] * -np.sum(nw * b, axis=1))[:, None]
        J[:, k, :3] = -scale * nw
        J[:, k, 3:] = scale * _cross(nw, vertex - p)
    return J


# -- 5. readings --------------------------------------------------------------------------------

class Session:
    """One session's zero: its conditions (home, coils off) give the optical paths the
    readings count from."""

    def __init__(self, model: dict, zero_conditions: dict):
        self.model = model
        c = conditions(model, {**zero_conditions, "currents_A": 0.0}, 1)
        self.paths_zero, _ = _paths(model, c, np.zeros((1, 3)))

    def forward(self, q, cond: dict, pose=None) -> np.ndarray:
        """Readings (n,3) m at motor coordinates q (n,3) rad in the conditions ``cond``."""
        q = np.atleast_2d(np.asarray(q, dtype=np.float64))
        c = conditions(self.model, cond, q.shape[0])
        paths, opt = _paths(self.model, c, q, pose)
        return self._counted(paths, opt)

    def _counted(self, paths, opt):
        return np.stack([(paths[:, k] - self.paths_zero[0, k]) / opt["n_comp"][a]
                         for k, a in enumerate(AXES)], axis=1)

    def inverse(self, target_m, cond: dict, q0=None, pose0=None, tol_m: float = 1e-12,
                max_iter: int = 20) -> dict:
        """Motor coordinates (n,3) at which the readings equal ``target_m`` (n,3) m in the
        conditions ``cond``: Newton on (q, p, R) with the rod equations and the readings, from
        ``q0`` (default home) and ``pose0`` (a previous solution's (p, R); default the
        closed-form start at q0). Returns q, status (converged / out_of_stroke / not_converged /
        not_finite),
        residual_m (max over the axes, the readings re-evaluated in full at q), iterations, and
        the pose (a warm start for the next call)."""
        model = self.model
        target = np.atleast_2d(np.asarray(target_m, dtype=np.float64))
        n = target.shape[0]
        c = conditions(model, cond, n)
        g = geometry(model, c)
        opt = optics(model, c)
        lo, hi = (float(v) for v in model["geometry"]["stroke_rad"])
        q = np.zeros((n, 3)) if q0 is None else np.array(np.broadcast_to(q0, (n, 3)), float)
        A, dA = elbows(g, q)
        p, R = start_pose(g, A) if pose0 is None else (pose0[0].copy(), pose0[1].copy())
        resid = np.full(n, np.inf)
        steps = 0
        for _ in range(max_iter + 1):       # the last pass evaluates the last step only
            A, dA = elbows(g, q)
            f, Jpose, d = _rod_system(g, A, p, R)
            pd, Rd = deflected(model, c, q, p, R)
            r = self._counted(optical_paths(model, opt, g, pd, Rd), opt) - target
            resid = np.max(np.abs(r), axis=1)
            # |d|^2 - L^2 = 2 L (|d| - L): the rods closed to 1e-13 m
            kin_ok = np.max(np.abs(f) / (2.0 * g["L"].reshape(-1, 6)), axis=1) < 1e-13
            if np.all((resid <= tol_m) & kin_ok) or steps == max_iter:
                break
            # rows: 6 rod equations, 3 readings; columns: q (3), p (3), rotation (3)
            M = np.zeros((n, 9, 9))
            M[:, :6, 3:] = Jpose
            dq = -2.0 * np.einsum("nija,nija->nij", d, dA)                  # (n,3,2)
            for i in range(3):
                M[:, 2 * i:2 * i + 2, i] = dq[:, i]
            ncomp = np.stack([opt["n_comp"][a] for a in AXES], axis=1)
            M[:, 6:, 3:] = _path_derivative(model, opt, pd, Rd) / ncomp[:, :, None]
            step = np.linalg.solve(M, -np.concatenate([f, r], axis=1)[..., None])[..., 0]
            q = q + step[:, :3]
            p = p + step[:, 3:6]
            R = rotation(step[:, 6:]) @ R
            steps += 1
        status = np.where((resid <= tol_m) & kin_ok, "converged", "not_converged").astype(object)
        status[np.any((q < lo - 1e-12) | (q > hi + 1e-12), axis=1)] = "out_of_stroke"
        status[~(np.all(np.isfinite(q), axis=1) & np.isfinite(resid))] = "not_finite"
        return {"q": q, "status": status.astype(str), "residual_m": resid, "iterations": steps,
                "pose": (p, R)}


def _paths(model, c, q, pose=None):
    g = geometry(model, c)
    p, R = kinematic_pose(g, q, pose)
    pd, Rd = deflected(model, c, q, p, R)
    opt = optics(model, c)
    return optical_paths(model, opt, g, pd, Rd), opt


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) != 1:
        print("usage: python controller_evaluator.py MODEL.json", file=sys.stderr)
        return 2
    try:
        model = load(argv[0])
    except ControllerModelError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"{FORMAT} v{FORMAT_VERSION}: effects {model['source']['effects']}; stroke "
          f"{model['geometry']['stroke_rad'].tolist()} rad; optics steps "
          f"{[s['kind'] for s in model['optics']['steps']]}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
