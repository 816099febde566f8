"""The twin's interferometer reading against an independent ray trace (tests/twin/raytrace.py:
real beam-splitter diagonal, three real cube-corner faces, the Z fold mirror as a mirror), and the
real-time cosine correction against the trace's distance along the beam."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from deltatwin.models.kinematics import Pose
from deltatwin.models.mjcf import FOLD_MIRROR_Z, INSTRUMENT_SITES
from deltatwin.twin.campaign import COSINE_ANGLES
from deltatwin.twin.instruments.optics import (
    AXES,
    FACE_NORMALS,
    Optics,
    autocollimator_angles,
    cosine_correction,
    cosine_factor,
    nominal_dead_path,
    optical_path,
    optical_path_pose_gradient,
)

from .raytrace import Mirror, make_head, trace_reading

CUBE_SIZE = 0.025
# the fold mirror as the frame holds it: 45 deg, turning the horizontal Z beam (-y) up (+z)
FOLD = Mirror(FOLD_MIRROR_Z, np.array([0.0, 1.0, 1.0]) / np.sqrt(2.0), 0.02)
ACROSS = {"x": np.array([0.0, 0.4, 1.0]), "y": np.array([1.0, 0.0, 0.3]),
          "z": np.array([1.0, 0.0, 0.2])}


def _face(pose_p, pose_R, axis) -> Mirror:
    nf = FACE_NORMALS[axis]
    return Mirror(pose_p + pose_R @ (0.5 * CUBE_SIZE * nf), pose_R @ nf, 0.5 * CUBE_SIZE)


def _twin_path(p, R, axis, vertex, direction) -> float:
    optics = Optics.nominal(np.zeros(3), 1)
    optics.head[axis] = vertex[None]
    optics.direction[axis] = direction[None]
    return float(optical_path(Pose(p[None], R[None]), np.zeros(3), CUBE_SIZE, optics, axis)[0])


def _trace(p, R, axis, vertex, direction, entry_offset_m):
    head = make_head(vertex, direction, entry_offset_m, ACROSS[axis])
    np.testing.assert_allclose(head.effective_vertex(), vertex, atol=1e-16)
    return trace_reading(head, _face(p, R, axis), (FOLD,) if axis == "z" else ())


def _poses(rng, n, max_shift_m=1e-3, max_angle_rad=2e-3):
    p = rng.uniform(-max_shift_m, max_shift_m, (n, 3))
    R = Rotation.from_rotvec(rng.uniform(-max_angle_rad, max_angle_rad, (n, 3))).as_matrix()
    return p, R


# head geometries: nominal; beam tilted (two angles) with the head offset sideways (Abbe offset)
HEADS = {"nominal": (np.zeros(3), np.zeros(2)),
         "tilted-offset": (np.array([0.8e-3, -0.6e-3, 0.5e-3]), np.array([2e-4, -1.5e-4]))}


def _head(axis, offset, tilt):
    site, d = INSTRUMENT_SITES[f"interferometer_{axis}"]
    d = d / np.linalg.norm(d)
    e1 = np.cross(d, [0.0, 0.0, 1.0] if abs(d[2]) < 0.9 else [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(d, e1)
    b = d + tilt[0] * e1 + tilt[1] * e2
    return site + offset - (offset @ d) * d, b / np.linalg.norm(b)


@pytest.mark.parametrize("axis", AXES)
@pytest.mark.parametrize("head", HEADS)
def test_reading_equals_ray_trace_on_moved_and_tilted_cube(axis, head):
    """Readings counted from a zero pose: the twin's n h cos(alpha) (n = 1) and the trace's
    optical path / 4 agree to 1e-12 m for cube poses up to 1 mm and 2 mrad, entry points 2-5 mm
    off the measurement axis, X, Y and Z (through the fold mirror)."""
    rng = np.random.default_rng(14)
    vertex, b = _head(axis, *HEADS[head])
    p, R = _poses(rng, 12)
    p0, R0 = np.zeros(3), np.eye(3)
    twin0 = _twin_path(p0, R0, axis, vertex, b)
    worst = 0.0
    for entry in (0.002, -0.005):
        trace0, out = _trace(p0, R0, axis, vertex, b, entry)
        np.testing.assert_allclose(out, -b, atol=1e-14)        # leaves parallel to the input
        for k in range(len(p)):
            trace, out = _trace(p[k], R[k], axis, vertex, b, entry)
            np.testing.assert_allclose(out, -b, atol=1e-14)
            twin = _twin_path(p[k], R[k], axis, vertex, b)
            worst = max(worst, abs((twin - twin0) - (trace - trace0)))
    print(f"{axis} {head}: twin - trace, worst {worst:.2e} m")
    assert worst < 1e-12, worst


def test_tilted_mirror_reads_short():
    """The issue's case on X (dead path 87.5 mm): a face tilted 1 mrad about the point where the
    measurement axis meets it reads -87.5 nm (s cos^2 - s); moved by d along its own normal it
    reads d cos(theta). Both from the trace and from the twin."""
    vertex, b = _head("x", *HEADS["nominal"])
    s0 = nominal_dead_path(CUBE_SIZE)["x"]
    assert s0 == pytest.approx(0.0875, abs=1e-15)
    theta = 1e-3
    R = Rotation.from_rotvec([0.0, theta, 0.0]).as_matrix()
    hit = np.array([-0.5 * CUBE_SIZE, 0.0, 0.0])
    p_tilt = hit - R @ hit                  # rotation about the hit point
    normal = R @ FACE_NORMALS["x"]
    d = 1e-6
    for reading in (lambda p, R_: _twin_path(p, R_, "x", vertex, b),
                    lambda p, R_: _trace(p, R_, "x", vertex, b, 0.003)[0]):
        zero = reading(np.zeros(3), np.eye(3))
        tilted = reading(p_tilt, R)
        assert (tilted - zero) * 1e9 == pytest.approx(-s0 * np.sin(theta) ** 2 * 1e9, abs=1e-6)
        assert (tilted - zero) * 1e9 == pytest.approx(-87.5, abs=0.01)
        # moved by d away from the head along its own normal
        moved = reading(p_tilt - d * normal, R)
        assert (moved - tilted) / d == pytest.approx(np.cos(theta), abs=1e-9)
        assert (moved - tilted) / d < 1.0 - 4e-7        # short: 0.9999995 d


def _distance_along_axis(p, R, axis, vertex, b) -> float:
    """The trace's side: where the measurement axis (the line through the vertex image along the
    beam, unfolded by hand through the fold mirror for Z) meets the face plane."""
    face = _face(p, R, axis)
    x, d, s = vertex, b, 0.0
    if axis == "z":
        t, x = FOLD.hit(x, d)
        s, d = t, FOLD.reflect(d)
    t = ((face.point - x) @ face.normal) / (d @ face.normal)
    return s + t


@pytest.mark.parametrize("axis", AXES)
def test_cosine_correction_recovers_the_distance_along_the_beam(axis):
    """The correction applied to the trace's reading, with the autocollimator angles of the tilted
    cube (exact, no noise) and the zero's dead path, gives the distance along the beam to the face
    since the zero: exactly for X and Y (each corrected by its own face's two tilts); for Z the
    two angles come from the side faces (ac2_rx, ac1_ry), which differ from the bottom face's own
    tilts at third order (0.9 pm at 2 mrad). A dead path off by e leaves e (c0 / c - 1): 2 um off at
    2 mrad ~ 1e-11 m."""
    rng = np.random.default_rng(5)
    vertex, b = _head(axis, *HEADS["nominal"])
    p, R = _poses(rng, 10)
    p0 = np.array([2e-6, -1e-6, 3e-6])
    R0 = Rotation.from_rotvec([50e-6, -30e-6, 20e-6]).as_matrix()   # the zero is tilted too
    s0 = nominal_dead_path(CUBE_SIZE)[axis]
    zero, _ = _trace(p0, R0, axis, vertex, b, 0.003)
    ang0 = autocollimator_angles(R0[None])
    c0 = cosine_factor(*(ang0[c][0] for c in COSINE_ANGLES[axis]))
    assert _distance_along_axis(np.zeros(3), np.eye(3), axis, vertex, b) == pytest.approx(s0, abs=1e-15)
    s0 = _distance_along_axis(p0, R0, axis, vertex, b)      # the zero's actual dead path
    raw_err, worst = 0.0, 0.0
    for k in range(len(p)):
        reading = _trace(p[k], R[k], axis, vertex, b, 0.003)[0] - zero
        ang = autocollimator_angles(R[k][None])
        c = cosine_factor(*(ang[c_][0] for c_ in COSINE_ANGLES[axis]))
        truth = (_distance_along_axis(p[k], R[k], axis, vertex, b)
                 - _distance_along_axis(p0, R0, axis, vertex, b))
        raw_err = max(raw_err, abs(reading - truth))
        worst = max(worst, abs(cosine_correction(reading, s0, c, c0) - truth))
    assert raw_err > 5e-9                             # the cosine error: nanometres
    print(f"{axis}: cosine error before correction {raw_err:.3e} m, after {worst:.3e} m")
    assert worst < (1e-14 if axis != "z" else 2e-12), worst


@pytest.mark.parametrize("axis", AXES)
def test_optical_path_pose_gradient_equals_central_differences(axis):
    """The analytic derivative of the optical path in the cube's position and a rotation applied
    on its rotation, against central differences (1e-6 m and rad: truncation ~1e-12, round-off
    ~5e-17 m / 1e-6 of a path derivative of order one), for tilted and offset beams through the
    air index."""
    rng = np.random.default_rng(13)
    p, R = _poses(rng, 30)
    offset, tilt = HEADS["tilted-offset"]
    vertex, direction = _head(axis, offset, tilt)
    optics = Optics.nominal(np.zeros(3), 30)
    optics.head[axis] = np.tile(vertex, (30, 1))
    optics.direction[axis] = np.tile(direction, (30, 1))
    optics.n_air[axis] = 1.0 + rng.uniform(2.6e-4, 2.8e-4, 30)
    cube_offset = np.array([0.001, -0.002, 0.03])
    gradient = optical_path_pose_gradient(Pose(p, R), cube_offset, CUBE_SIZE, optics, axis)
    h = 1e-6
    for k in range(6):
        sides = []
        for sign in (1.0, -1.0):
            step = np.zeros(3)
            step[k % 3] = sign * h
            moved = (Pose(p + step, R) if k < 3 else
                     Pose(p, Rotation.from_rotvec(step).as_matrix() @ R))
            sides.append(optical_path(moved, cube_offset, CUBE_SIZE, optics, axis))
        central = (sides[0] - sides[1]) / (2 * h)
        assert np.abs(gradient[:, k] - central).max() < 1e-9 * max(np.abs(central).max(), 1.0)
