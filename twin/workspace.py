"""The reachable workspace: image of the actuator-stroke cube under forward kinematics.

Seen from the top it is a hexagon; from the side, two pyramids on a hexagonal base.  Its volume
is the integral of |det(dp/dq)| over the stroke cube (Gauss-Legendre, exact for this smooth map
to ~1e-9), with the convex hull of the boundary image (trimesh) as a cross-check and for display.
Units: m, m^3, rad.
"""
from __future__ import annotations

import itertools

import numpy as np
import trimesh

from deltatwin.models.geometry import Geometry
from deltatwin.models.kinematics import (
    flexure_rest_directions,
    forward,
    home_rod_directions,
    rod_directions,
)


def position_jacobian(geom: Geometry, q: np.ndarray, h: float = 1e-6) -> np.ndarray:
    """dp/dq (N,3,3) by central differences of the exact forward kinematics."""
    q = np.atleast_2d(q)
    J = np.empty(q.shape + (3,))
    for k in range(3):
        dq = np.zeros(3)
        dq[k] = h
        J[:, :, k] = (forward(geom, q + dq, check=False).p - forward(geom, q - dq, check=False).p) / (2 * h)
    return J


def volume(geom: Geometry, order: int = 8) -> float:
    """Workspace volume (m^3) = integral of |det J| over the stroke cube."""
    x, w = np.polynomial.legendre.leggauss(order)
    lo, hi = geom.stroke
    nodes = (x + 1) / 2 * (hi - lo) + lo
    weights = w * (hi - lo) / 2
    q = np.array(list(itertools.product(nodes, repeat=3)))
    wq = np.prod(np.array(list(itertools.product(weights, repeat=3))), axis=1)
    return float(np.sum(wq * np.abs(np.linalg.det(position_jacobian(geom, q)))))


def boundary_motor_coordinates(geom: Geometry, n: int = 9) -> np.ndarray:
    """Motor coordinates sampling the faces of the stroke cube (M,3)."""
    lo, hi = geom.stroke
    g = np.linspace(lo, hi, n)
    pts = set()
    for fixed in range(3):
        for v in (lo, hi):
            for a, b in itertools.product(g, g):
                q = [a, b]
                q.insert(fixed, v)
                pts.add(tuple(q))
    return np.array(sorted(pts))


def hull(geom: Geometry, n: int = 9, point=None) -> trimesh.Trimesh:
    """Convex hull (m) of the image of the stroke cube's surface: of the platform origin, or of
    ``point`` (3,) given in the platform frame (the mirror cube's centre: where it is measured)."""
    pose = forward(geom, boundary_motor_coordinates(geom, n))
    return trimesh.convex.convex_hull(pose.p if point is None else pose.point(point))


def flexure_angles(geom: Geometry, q: np.ndarray) -> np.ndarray:
    """Bending angle (rad) of every rod-end flexure (N,3,2,2: elbow, platform) relative to home,
    where the flexures are straight."""
    q = np.atleast_2d(q)
    pose = forward(geom, q, check=False)
    n, _ = rod_directions(geom, q, pose)
    rest_e, rest_p = flexure_rest_directions(geom, q, pose, home_rod_directions(geom))
    ang = lambda a, b: np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.sum(a * b, axis=-1))
    return np.stack([ang(rest_e, n), ang(rest_p, n)], axis=-1)
