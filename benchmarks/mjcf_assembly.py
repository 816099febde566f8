"""The MuJoCo model's assembly and dynamics (models/delta_agietron/README.md figures): closest
approach of every part pair over a workspace sample (mj_geomDistance), how far each beam's hit
point stays from its cube face's edge (mj_ray), and 10 s of mj_step of the exported file
holding a pose against the exact static solve.
Run: python benchmarks/mjcf_assembly.py"""
import itertools
import tempfile
import time
from pathlib import Path

import mujoco
import numpy as np

from deltatwin.models.geometry import build_geometry
from deltatwin.models.kinematics import forward
from deltatwin.models.mjcf import (
    build_model,
    build_spec,
    is_room_body,
    loop_closure,
    pose_model,
    to_xml_full_precision,
)
from deltatwin.models.params import load_params
from deltatwin.twin import workspace
from deltatwin.twin.statics import Statics

params = load_params()
geom = build_geometry(params)
_, model = build_model(params)
data = mujoco.MjData(model)
lo, hi = geom.stroke
q = np.vstack([workspace.boundary_motor_coordinates(geom, 9),
               np.array(list(itertools.product(np.linspace(lo, hi, 5), repeat=3)))])
pose = forward(geom, q)
names = [model.geom(g).name for g in range(model.ngeom)]
body, parent = model.geom_bodyid, model.body_parentid
pairs = [(a, b) for a, b in itertools.combinations(range(model.ngeom), 2)
         if body[a] != body[b] and parent[body[a]] != body[b] and parent[body[b]] != body[a]
         and "table" not in (names[a], names[b])]


def moving(g):
    """True for a geom on a moving part of the robot (not the world, base, coils, instruments)."""
    return body[g] != 0 and not is_room_body(model.body(body[g]).name) and names[g] != "base_plate"


closest = {}
for k in range(len(q)):
    pose_model(model, data, q[k], pose.p[k], pose.R[k])
    for a, b in pairs:
        if moving(a) or moving(b):
            closest[(a, b)] = min(closest.get((a, b), np.inf),
                                  mujoco.mj_geomDistance(model, data, a, b, 0.05, None))
print(f"{len(q)} poses (stroke-cube faces 9x9 + 5x5x5 grid); closest pairs (mm):")
for (a, b), dist in sorted(closest.items(), key=lambda item: item[1])[:14]:
    print(f"  {names[a]:>24s} - {names[b]:<24s} {dist * 1e3:8.3f}")

cube = pose.point(geom.cube_offset) - forward(geom, np.zeros((1, 3))).point(geom.cube_offset)
half = params.mirror_cube_size_m / 2
margin = lambda lateral, vertical: (half - max(np.abs(cube[:, lateral]).max(),
                                                np.abs(cube[:, vertical]).max())) * 1e3
print("beam hit point's margin to the face edge (mm), axis ray, over the poses: "
      f"X/AC1 faces {margin(1, 2):.2f}, Y/AC2 faces {margin(0, 2):.2f}, Z face {margin(0, 1):.2f}")

with tempfile.TemporaryDirectory() as tmp:
    path = Path(tmp) / "robot.xml"
    path.write_text(to_xml_full_precision(build_spec(params)))
    m = mujoco.MjModel.from_xml_path(str(path))
d = mujoco.MjData(m)
site = m.site("mirror_cube_centre").id
statics = Statics(params, geom)
for q_hold in (np.zeros(3), np.array([0.03, -0.02, 0.01]), np.array([0.065, 0.065, -0.065])):
    mujoco.mj_resetData(m, d)
    d.ctrl[:] = q_hold
    t0, steps = time.perf_counter(), int(round(10.0 / m.opt.timestep))
    for _ in range(steps):
        mujoco.mj_step(m, d)
    wall = time.perf_counter() - t0
    exact = statics.solve(q_hold[None]).pose.point(geom.cube_offset)[0]
    rigid = forward(geom, q_hold[None]).point(geom.cube_offset)[0]
    print(f"q = {q_hold.tolist()} rad, 10 s at dt {m.opt.timestep:g} s ({wall:.1f} s wall): finite "
          f"{bool(np.isfinite(d.qacc).all())}, max |qvel| {np.abs(d.qvel).max():.1e}; cube - exact "
          f"static solve {np.round((d.site_xpos[site] - exact) * 1e6, 2).tolist()} um "
          f"(exact - rigid {np.round((exact - rigid) * 1e9, 0).tolist()} nm); "
          f"loop violation {loop_closure(m, d) * 1e6:.1f} um")
