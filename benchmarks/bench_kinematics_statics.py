"""Forward kinematics + statics throughput on a batch of poses (target: >= 50,000 poses/s).

Prints poses/s and the accuracy check made on the same batch: worst loop closure of the
kinematics, and the worst difference between the batched static deflection and a pose-by-pose
solve of the same poses.   Run: python benchmarks/bench_kinematics_statics.py [N]
"""
import sys
import time

import numpy as np

from models.geometry import build_geometry
from models.params import load_params
from twin.kinematics import elbow_points, forward
from twin.statics import Statics

n = int(sys.argv[1]) if len(sys.argv) > 1 else 50_000
params = load_params()
geom = build_geometry(params)
statics = Statics(params, geom)
q = np.random.default_rng(0).uniform(*geom.stroke, size=(n, 3))
wrench = np.array([0.0, 0.0, 2.0, 0.0, 0.0, 0.0])
statics.solve(q[:100], wrench)                       # warm-up
t0 = time.perf_counter()
res = statics.solve(q, wrench)                       # includes forward kinematics
dt = time.perf_counter() - t0
pose = res.kinematic_pose
A = elbow_points(geom, geom.theta(q))
d = pose.p[:, None, None] + np.einsum("nab,ijb->nija", pose.R, geom.P0) - A
closure = np.abs(np.linalg.norm(d, axis=-1) - geom.L).max()
single = np.array([statics.solve(q[i:i + 1], wrench).deflection[0] for i in range(0, n, max(1, n // 200))])
diff = np.abs(single - res.deflection[::max(1, n // 200)]).max()
print(f"poses: {n}  time: {dt:.3f} s  throughput: {n / dt:,.0f} poses/s (target 50,000)")
print(f"kinematic loop closure max: {closure:.2e} m (tolerance 1e-12 m)")
print(f"batched vs single-pose deflection max difference: {diff:.2e} m")
