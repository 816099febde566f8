"""Meshes that MuJoCo's primitive geoms cannot show, built with trimesh (units: m)."""
from __future__ import annotations

import numpy as np
import trimesh


def notch_hinge(neck_diameter: float, notch_radius: float, outer_diameter: float,
                sections: int = 24) -> trimesh.Trimesh:
    """Rotationally symmetric circular-notch flexure hinge along z, centred at the origin."""
    half = np.sqrt(notch_radius ** 2 - (notch_radius - (outer_diameter - neck_diameter) / 2) ** 2)
    z = np.linspace(-half, half, 17)
    r = neck_diameter / 2 + notch_radius - np.sqrt(notch_radius ** 2 - z ** 2)
    profile = np.column_stack([np.r_[0.0, r, 0.0], np.r_[z[0], z, z[-1]]])
    return trimesh.creation.revolve(profile, sections=sections)


def platform_plate(hinge_points: np.ndarray, thickness: float) -> trimesh.Trimesh:
    """Platform plate: convex hull of its hinge points (x, y), from z = -thickness to 0."""
    xy = hinge_points[..., :2].reshape(-1, 2)
    pts = np.vstack([np.column_stack([xy, np.zeros(len(xy))]),
                     np.column_stack([xy, np.full(len(xy), -thickness)])])
    return trimesh.convex.convex_hull(pts)
