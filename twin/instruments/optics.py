"""The metrology loop's optics: where each beam starts and goes, what it reflects on, and what
interferometers and autocollimators therefore read from the platform's full pose.

An interferometer reads the optical path change along its beam to a face of the Zerodur cube,
divided by the air index it assumes: ``(n s - n0 s0) / n_comp``.  ``s`` is the exact distance
along the beam to the (moving, tilting) mirror plane, so Abbe offsets, the cosine error of
parasitic rotations (the double pass's return path on a tilted face) and beam misalignment come out of the geometry,
and the dead path (s0, the distance at the zero) multiplies every index change.  The Z beam
runs horizontally to a 45 deg fold mirror and up to the cube's bottom face: it is traced as
the fold mirror's image of the head (a longer path, two reflections).  Units: m, rad.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from deltatwin.models.mjcf import FOLD_MIRROR_Z, INSTRUMENT_SITES

AXES = ("x", "y", "z")
# cube face each beam reflects on (outward normal, platform frame) and autocollimator channels
FACE_NORMALS = {"x": np.array([-1.0, 0.0, 0.0]), "y": np.array([0.0, -1.0, 0.0]),
                "z": np.array([0.0, 0.0, -1.0])}
AC_CHANNELS = ("ac1_ry", "ac1_rz", "ac2_rx", "ac2_rz")
FOLD_TURN = np.array([0.0, 0.0, 1.0])   # direction of the Z beam after the fold mirror


@dataclass
class Optics:
    """Per-point optics (each array has a leading axis N). Effects change them in place."""
    head: dict          # axis -> (N,3) beam origin at the interferometer head
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

    def beam(self, axis: str) -> tuple[np.ndarray, np.ndarray]:
        """Effective straight beam (origin, unit direction) reaching the cube, (N,3) each."""
        o, b = self.head[axis], self.direction[axis]
        if axis != "z":
            return o, b / np.linalg.norm(b, axis=-1, keepdims=True)
        # fold mirror plane: normal bisecting the incoming (nominal -y) and outgoing (+z) beams
        incoming = INSTRUMENT_SITES["interferometer_z"][1]
        nm = FOLD_TURN - incoming
        nm = nm / np.linalg.norm(nm)
        reflect = lambda v: v - 2.0 * (v @ nm)[..., None] * nm
        return self.fold + reflect(o - self.fold), reflect(b / np.linalg.norm(b, axis=-1, keepdims=True))


def face_distance(pose, cube_offset: np.ndarray, cube_size: float, axis: str, origin, direction):
    """Distance (N,) along the beam from ``origin`` to the plane of the cube face of ``axis``."""
    nf = FACE_NORMALS[axis]
    centre_local = np.broadcast_to(cube_offset + 0.5 * cube_size * nf, pose.p.shape)
    c = pose.p + np.einsum("nab,nb->na", pose.R, centre_local)
    nw = pose.R @ nf
    return np.sum(nw * (c - origin), axis=-1) / np.sum(nw * direction, axis=-1)


def return_factor(cos_incidence):
    """Plane-mirror (double-pass) geometry: the beam goes out a distance s, comes back along the
    mirror's reflection to the head's plane, s / cos(2 theta); the reading is half the round
    trip, s (1 + 1/cos 2theta) / 2 ~ s (1 + theta^2): the cosine error of a tilted mirror."""
    return 0.5 * (1.0 + 1.0 / (2.0 * cos_incidence ** 2 - 1.0))


def optical_path(pose, cube_offset, cube_size, optics: Optics, axis: str) -> np.ndarray:
    """Optical path n*s (m) of the beam of ``axis`` (half the round trip)."""
    o, b = optics.beam(axis)
    s = face_distance(pose, cube_offset, cube_size, axis, o, b)
    cos_incidence = np.abs(np.sum((pose.R @ FACE_NORMALS[axis]) * b, axis=-1))
    return optics.n_air[axis] * s * return_factor(cos_incidence)


def autocollimator_angles(R: np.ndarray) -> dict[str, np.ndarray]:
    """Tilts (rad) of the cube's -x face (autocollimator 1: ry, rz) and -y face (autocollimator
    2: rx, rz) for platform rotations R (N,3,3)."""
    nx, ny = -R[:, :, 0], -R[:, :, 1]
    return {"ac1_ry": np.arctan2(nx[:, 2], -nx[:, 0]), "ac1_rz": np.arctan2(-nx[:, 1], -nx[:, 0]),
            "ac2_rx": np.arctan2(-ny[:, 2], -ny[:, 1]), "ac2_rz": np.arctan2(ny[:, 0], -ny[:, 1])}


def air_index(T_C, p_Pa, vapour_Pa, wavelength_m: float = 632.99e-9):
    """Refractive index of air: Edlén (1966) as revised by Birch & Downs (1993, 1994).
    T in degC, total pressure and water-vapour partial pressure in Pa, vacuum wavelength in m."""
    sigma2 = (1e-6 / wavelength_m) ** 2   # (1/um)^2
    ns = 1e-8 * (8342.54 + 2406147.0 / (130.0 - sigma2) + 15998.0 / (38.9 - sigma2))
    T = np.asarray(T_C, dtype=np.float64)
    p = np.asarray(p_Pa, dtype=np.float64)
    ntp = p * ns / 96095.43 * (1.0 + 1e-8 * (0.601 - 0.00972 * T) * p) / (1.0 + 0.003661 * T)
    return 1.0 + ntp - np.asarray(vapour_Pa) * (3.7345 - 0.0401 * sigma2) * 1e-10


def cosine_correction(reading_m, dead_path_m, angle_a, angle_b, angle_a0=0.0, angle_b0=0.0):
    """The seed's real-time cosine correction: the path to the mirror (dead path + reading)
    divided by the double-pass factor of the measured face tilts (cos theta = cos a cos b),
    relative to the zero's tilts."""
    f = return_factor(np.cos(angle_a) * np.cos(angle_b))
    f0 = return_factor(np.cos(angle_a0) * np.cos(angle_b0))
    return (dead_path_m + reading_m) / f - dead_path_m / f0
