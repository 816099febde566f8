"""The metrology loop's optics: where each beam starts and goes, what it reflects on, and what
interferometers and autocollimators therefore read from the platform's full pose.

An interferometer reads the optical path change of its beam, divided by the air index it assumes:
``(n L - n0 L0) / n_comp``.  Each is a double-pass plane-mirror interferometer: the beam goes to a
cube face, back to the head, through the cube corner there, to the face again and back, out
parallel to the input whatever the face's tilt.  Its reading (optical path / 4, up to a constant
of the head) is ``L = h cos(alpha)``: h the perpendicular distance from the cube corner's vertex
(``Optics.head``, the point the head measures from; the measurement axis runs through it) to the
face plane, alpha the angle between the beam and the face normal; equivalently ``s cos^2(alpha)``
for the distance s along the beam from the vertex to the face.  A tilted face reads short (the
textbook cosine error); Abbe offsets, parasitic rotations and beam misalignment come out of this
geometry, and the dead path (L0, at the zero) multiplies every index change.  The Z beam runs
horizontally to a 45 deg fold mirror and up to the cube's bottom face: it is traced as the fold
mirror's image of the head (a longer path, two more reflections).  Checked against an
independent ray trace with real cube-corner faces (tests/twin/raytrace.py) to 1e-12 m.
Units: m, rad.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from deltatwin.models.layout import FOLD_MIRROR_Z, INSTRUMENT_SITES

AXES = ("x", "y", "z")
# cube face each beam reflects on (outward normal, platform frame) and autocollimator channels
FACE_NORMALS = {"x": np.array([-1.0, 0.0, 0.0]), "y": np.array([0.0, -1.0, 0.0]),
                "z": np.array([0.0, 0.0, -1.0])}
AC_CHANNELS = ("ac1_ry", "ac1_rz", "ac2_rx", "ac2_rz")
# autocollimator channels giving the tilts of each interferometer's mirror face
COSINE_ANGLES = {"x": ("ac1_ry", "ac1_rz"), "y": ("ac2_rx", "ac2_rz"), "z": ("ac2_rx", "ac1_ry")}
FOLD_TURN = np.array([0.0, 0.0, 1.0])   # direction of the Z beam after the fold mirror


@dataclass
class Optics:
    """Per-point optics (each array has a leading axis N). Effects change them in place."""
    head: dict          # axis -> (N,3) the head's cube-corner vertex (the measurement axis'
                        # origin: the beam's two passes lie symmetric about it)
    direction: dict     # axis -> (N,3) unit beam direction leaving the head
    fold: np.ndarray    # (N,3) Z fold mirror centre
    n_air: dict         # axis -> (N,) refractive index along the beam
    n_comp: dict        # axis -> (N,) index the instrument divides by

    @classmethod
    def nominal(cls, cube_home: np.ndarray, n: int, n_nominal: float = 1.0) -> Optics:
        head, direction = {}, {}
        for a in AXES:
            off, d = INSTRUMENT_SITES[f"interferometer_{a}"]
            head[a] = np.tile(cube_home + off, (n, 1))
            direction[a] = np.tile(d / np.linalg.norm(d), (n, 1))
        return cls(head=head, direction=direction, fold=np.tile(cube_home + FOLD_MIRROR_Z, (n, 1)),
                   n_air={a: np.full(n, n_nominal) for a in AXES},
                   n_comp={a: np.full(n, n_nominal) for a in AXES})

    def copy(self) -> Optics:
        """An independent copy of every field (an effect may change the arrays in place)."""
        copied = lambda v: ({a: x.copy() for a, x in v.items()} if isinstance(v, dict)
                            else v.copy())
        return Optics(**{f.name: copied(getattr(self, f.name)) for f in dataclasses.fields(self)})

    def beam(self, axis: str) -> tuple[np.ndarray, np.ndarray]:
        """Effective straight beam (cube-corner vertex, unit direction) reaching the cube, (N,3)
        each: for Z their images in the fold mirror."""
        o, b = self.head[axis], self.direction[axis]
        if axis != "z":
            return o, b / np.linalg.norm(b, axis=-1, keepdims=True)
        # fold mirror plane: normal bisecting the incoming (nominal -y) and outgoing (+z) beams
        incoming = INSTRUMENT_SITES["interferometer_z"][1]
        nm = FOLD_TURN - incoming
        nm = nm / np.linalg.norm(nm)
        reflect = lambda v: v - 2.0 * (v @ nm)[..., None] * nm
        return self.fold + reflect(o - self.fold), reflect(b / np.linalg.norm(b, axis=-1, keepdims=True))


def _double_pass_terms(pose, cube_offset, cube_size: float, axis: str, vertex, direction):
    """h, cos(alpha) and the face's outward normal in the world (3 arrays (N,)) of the double
    pass on the face of ``axis`` (see ``double_pass_reading``)."""
    nf = FACE_NORMALS[axis]
    k = int(np.flatnonzero(nf)[0])                     # the face's normal is +-e_k of the cube
    centre = np.asarray(cube_offset + 0.5 * cube_size * nf)   # (3,) or (N,3): platform frame
    R, p = pose.R, pose.p
    h = cos_alpha = 0.0
    normal = []
    for i in range(3):
        c_i = p[:, i] + R[:, i, 0] * centre[..., 0] + R[:, i, 1] * centre[..., 1] \
            + R[:, i, 2] * centre[..., 2]                       # face centre, world
        nw_i = nf[k] * R[:, i, k]                      # outward normal, towards the head
        h = h + nw_i * (vertex[:, i] - c_i)
        cos_alpha = cos_alpha - nw_i * direction[:, i]
        normal.append(nw_i)
    return h, cos_alpha, normal


def double_pass_reading(pose, cube_offset: np.ndarray, cube_size: float, axis: str, vertex,
                        direction) -> np.ndarray:
    """Geometric reading h cos(alpha) (m, (N,)) of a double-pass plane-mirror interferometer on
    the cube face of ``axis``: h the distance from the cube corner's ``vertex`` (N,3) to the
    face plane, alpha the angle between the unit beam ``direction`` (N,3) and the face normal.
    The head's own constant path is left out (readings count from a zero). Written entry by
    entry over the points (models/batched.py: (N,3) arrays reduced over their last axis pay
    numpy's per-item overhead)."""
    h, cos_alpha, _ = _double_pass_terms(pose, cube_offset, cube_size, axis, vertex, direction)
    return h * cos_alpha


def optical_path(pose, cube_offset, cube_size, optics: Optics, axis: str) -> np.ndarray:
    """Optical path n h cos(alpha) (m) of the interferometer of ``axis`` (a quarter of the
    double pass's round trips)."""
    vertex, b = optics.beam(axis)
    return optics.n_air[axis] * double_pass_reading(pose, cube_offset, cube_size, axis, vertex, b)


def optical_path_pose_gradient(pose, cube_offset, cube_size, optics: Optics,
                               axis: str) -> np.ndarray:
    """(N,6) the derivative of ``optical_path`` with respect to the platform's pose: its
    position and a small rotation w applied on its rotation (R -> exp([w]x) R), at fixed
    optics. With the face's world normal n_w and the vertex v: a move dp changes h by
    -n_w . dp; a rotation turns n_w by w x n_w and the face centre c about p, so h changes by
    w . (n_w x (v - p)) and cos(alpha) = -n_w . b by w . (b x n_w)."""
    v, b = optics.beam(axis)
    h, cos_alpha, nw = _double_pass_terms(pose, cube_offset, cube_size, axis, v, b)
    n = optics.n_air[axis]
    lever = [v[:, i] - pose.p[:, i] for i in range(3)]
    out = np.empty((h.shape[0], 6))
    for i in range(3):
        j, k = (i + 1) % 3, (i + 2) % 3
        out[:, i] = -n * cos_alpha * nw[i]
        out[:, 3 + i] = n * (cos_alpha * (nw[j] * lever[k] - nw[k] * lever[j])
                             + h * (b[:, j] * nw[k] - b[:, k] * nw[j]))
    return out


def nominal_dead_path(cube_size: float) -> dict:
    """Nominal beam path (m) per axis from the head to its cube face at home (via the fold mirror
    for Z): the dead path the real-time cosine correction assumes."""
    h = 0.5 * cube_size
    out = {a: float(np.linalg.norm(INSTRUMENT_SITES[f"interferometer_{a}"][0])) - h for a in "xy"}
    head_z = INSTRUMENT_SITES["interferometer_z"][0]
    out["z"] = float(np.linalg.norm(head_z - FOLD_MIRROR_Z) + np.linalg.norm(FOLD_MIRROR_Z)) - h
    return out


def autocollimator_angles(R: np.ndarray) -> dict[str, np.ndarray]:
    """Tilts (rad) of the cube's -x face (autocollimator 1: ry, rz) and -y face (autocollimator
    2: rx, rz) for platform rotations R (N,3,3)."""
    nx, ny = -R[:, :, 0], -R[:, :, 1]
    return {"ac1_ry": np.arctan2(nx[:, 2], -nx[:, 0]), "ac1_rz": np.arctan2(-nx[:, 1], -nx[:, 0]),
            "ac2_rx": np.arctan2(-ny[:, 2], -ny[:, 1]), "ac2_rz": np.arctan2(ny[:, 0], -ny[:, 1])}


def saturation_vapour_pressure(T_C):
    """Saturation vapour pressure over water (Pa) at T (degC): the CIPM-2007 air-density
    formula's (Davis 1992), as Ciddor's and the NIST air-index calculator use it."""
    T = np.asarray(T_C, dtype=np.float64) + 273.15
    return np.exp(1.2378847e-5 * T ** 2 - 1.9121316e-2 * T + 33.93711047 - 6.3431645e3 / T)


def vapour_pressure(humidity_pct, T_C):
    """Water-vapour partial pressure (Pa) of air at relative humidity (%) and T (degC)."""
    return np.asarray(humidity_pct, dtype=np.float64) / 100.0 * saturation_vapour_pressure(T_C)


def air_index(T_C, p_Pa, vapour_Pa, wavelength_m: float = 632.99e-9):
    """Refractive index of air: Edlén (1966) as revised by Birch & Downs (1993, 1994).
    T in degC, total pressure and water-vapour partial pressure in Pa, vacuum wavelength in m."""
    sigma2 = (1e-6 / wavelength_m) ** 2   # (1/um)^2
    ns = 1e-8 * (8342.54 + 2406147.0 / (130.0 - sigma2) + 15998.0 / (38.9 - sigma2))
    T = np.asarray(T_C, dtype=np.float64)
    p = np.asarray(p_Pa, dtype=np.float64)
    ntp = p * ns / 96095.43 * (1.0 + 1e-8 * (0.601 - 0.00972 * T) * p) / (1.0 + 0.003661 * T)
    return 1.0 + ntp - np.asarray(vapour_Pa) * (3.7345 - 0.0401 * sigma2) * 1e-10


def cosine_factor(angle_a, angle_b):
    """cos^2(alpha) of a face whose normal is tilted from the beam by the two autocollimator
    angles a, b (rad; tan a, tan b the normal's components across the beam over its component
    along it): the reading per unit of distance along the beam."""
    return 1.0 / (1.0 + np.tan(angle_a) ** 2 + np.tan(angle_b) ** 2)


def cosine_correction(reading_m, dead_path_m, factor, factor0=1.0):
    """The real-time cosine correction: from a reading counted since the zero, the distance
    along the beam to the face since the zero, s - s0 (m). The reading is s c - s0 c0
    (c = ``cosine_factor`` of the measured tilts, c0 at the zero, s0 the dead path), so
    s - s0 = (s0 c0 + reading) / c - s0."""
    return (dead_path_m * factor0 + reading_m) / factor - dead_path_m
