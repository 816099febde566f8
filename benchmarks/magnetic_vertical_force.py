"""Where the force simulator pushes the platform down: the net vertical magnetic force at 2 A over
the stroke cube with paper-force's parameters, and the physics behind its sign.

Two antiparallel dipoles (coil up, magnet down) at separation r, angle theta from the vertical,
give a vertical force on the magnet proportional to cos(theta) (5 cos^2(theta) - 3) / r^4 and a
component along r proportional to (3 cos^2(theta) - 1) / r^4: the pair stays repulsive along r
up to 54.7 deg, but its vertical force turns downward beyond arccos(sqrt(3/5)) = 39.2 deg.
Run: python benchmarks/magnetic_vertical_force.py [levels]"""
import sys
from types import SimpleNamespace

import numpy as np

from deltatwin.models.geometry import build_geometry
from deltatwin.models.kinematics import forward
from deltatwin.models.mjcf import magnet_positions
from deltatwin.twin.effects.magnetic_force import dipole_force_torque
from deltatwin.twin.scenario import Scenario

levels = int(sys.argv[1]) if len(sys.argv) > 1 else 21
sc = Scenario.load("paper-force")
params = sc.params
mag_effect = next(e for e in sc.effects if e.name == "magnetic_force")
geom = build_geometry(params)
lo, hi = params.stroke_rad
g = np.linspace(lo, hi, levels)
q = np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1).reshape(-1, 3)
pose = forward(geom, q)
home_p = forward(geom, np.zeros((1, 3))).p[0]
pts = SimpleNamespace(pose=pose, params=params, home_p=home_p, currents_A=np.full((len(q), 3), 2.0))
w = mag_effect.wrench(pts)
Fz = w[:, 2]
down = Fz < 0
coils = mag_effect.coil_dipoles(params, home_p)
mag = pose.p[:, None, :] + (pose.R[:, None] @ magnet_positions(params)[None, :, :, None])[..., 0]
sep = mag[:, :, None, :] - coils[None, None, :, :]              # (N, magnet, coil, 3)
own = sep[:, np.arange(3), np.arange(3)]                        # each magnet over its own coil
theta = np.degrees(np.arctan2(np.linalg.norm(own[..., :2], axis=-1), own[..., 2]))
print(f"paper-force, 2 A in each coil, {levels}^3 stroke grid ({len(q)} poses)")
print(f"net Fz: {Fz.min():+.3f} .. {Fz.max():+.3f} N; downward at {down.mean() * 100:.1f} % "
      f"of the grid")
print(f"angle of each magnet from its own coil's axis: {theta.min():.1f} .. {theta.max():.1f} deg "
      f"(vertical force of a pair reverses beyond 39.2 deg)")
# each magnet and its own coil alone: the force along their separation (repulsive if > 0)
m_mag = -mag_effect.magnet_moment_Am2 * pose.R[:, None, :, 2].repeat(3, axis=1)
m_coil = np.zeros((len(q), 3, 3))
m_coil[..., 2] = mag_effect.coil_moment_per_A * 2.0
F_own, _ = dipole_force_torque(m_coil, coils[None], m_mag, mag)
along = np.einsum("nmc,nmc->nm", F_own, own / np.linalg.norm(own, axis=-1, keepdims=True))
print(f"each magnet vs its own coil, force along their separation: {along.min():+.3f} .. "
      f"{along.max():+.3f} N (repulsive everywhere: {bool(np.all(along > 0))})")
if down.any():
    dz = (pose.p[down, 2] - home_p[2]) * 1e3
    print(f"where Fz < 0: {dz.min():.2f} .. {dz.max():.2f} mm in z from home (stroke grid: "
          f"{(pose.p[:, 2].min() - home_p[2]) * 1e3:.2f} .. {(pose.p[:, 2].max() - home_p[2]) * 1e3:.2f}); "
          "lateral distance from home "
          f"{np.linalg.norm(pose.p[down, :2] - home_p[:2], axis=1).min() * 1e3:.2f}"
          f" .. {np.linalg.norm(pose.p[down, :2] - home_p[:2], axis=1).max() * 1e3:.2f} mm")
    print(f"  largest own-pair angle there: {theta[down].max(axis=1).min():.1f} .. "
          f"{theta[down].max(axis=1).max():.1f} deg")
