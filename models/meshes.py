"""Meshes that MuJoCo's primitive geoms cannot show, built with trimesh (units: m)."""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    import trimesh


def platform_plate(hinge_points: np.ndarray, thickness: float) -> trimesh.Trimesh:
    """Platform plate: convex hull of its hinge points (x, y), from z = -thickness to 0."""
    import trimesh  # trimesh loads scipy.optimize: only when a MuJoCo model is built
    xy = hinge_points[..., :2].reshape(-1, 2)
    pts = np.vstack([np.column_stack([xy, np.zeros(len(xy))]),
                     np.column_stack([xy, np.full(len(xy), -thickness)])])
    return trimesh.convex.convex_hull(pts)
