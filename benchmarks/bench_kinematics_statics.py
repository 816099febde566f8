"""Forward kinematics + statics throughput on a batch of poses (target: >= 50,000 poses/s for
exact 6-DOF forward kinematics and the static deflection under a wrench and gravity per pose).

Prints poses/s for forward kinematics alone, statics alone (given the kinematic poses) and both
(``Statics.solve`` without a pose), each the median and best of REPEATS runs, and the verdict
against the target (on the median).  Accuracy checks on the same batch: worst loop closure of the
kinematics and the worst difference between the batched deflection and pose-by-pose solves.
Run: python benchmarks/bench_kinematics_statics.py [N]   (default N = 28,500)
"""
import os
import sys
import time

import numpy as np

from deltatwin.models.geometry import build_geometry
from deltatwin.models.kinematics import elbow_points, forward
from deltatwin.models.params import load_params
from deltatwin.twin import statics as statics_module
from deltatwin.twin.statics import Statics

TARGET_POSES_PER_S = 50_000
REPEATS = 7

n = int(sys.argv[1]) if len(sys.argv) > 1 else 28_500
params = load_params()
geom = build_geometry(params)
statics = Statics(params, geom)
q = np.random.default_rng(0).uniform(*geom.stroke, size=(n, 3))
wrench = np.array([0.0, 0.0, 2.0, 0.0, 0.0, 0.0])       # the coils' ~2 N, plus gravity
statics.solve(q[:2000], wrench)                         # warm-up


def rate(fun):
    """Median and best poses/s of REPEATS runs of fun(); and fun's last result."""
    times = []
    for _ in range(REPEATS):
        t0 = time.perf_counter()
        out = fun()
        times.append(time.perf_counter() - t0)
    return n / np.median(times), n / np.min(times), out


kin_rate = rate(lambda: forward(geom, q))
pose = kin_rate[2]
statics_rate = rate(lambda: statics.solve(q, wrench, pose=pose))
both_rate = rate(lambda: statics.solve(q, wrench))     # includes forward kinematics
res = both_rate[2]

A = elbow_points(geom, geom.theta(q))
d = pose.p[:, None, None] + np.einsum("nab,ijb->nija", pose.R, geom.P0) - A
closure = np.abs(np.linalg.norm(d, axis=-1) - geom.L).max()
every = max(1, n // 200)
single = np.array([statics.solve(q[i:i + 1], wrench).deflection[0] for i in range(0, n, every)])
diff = np.abs(single - res.deflection[::every]).max()

print(f"poses: {n:,}  repeats: {REPEATS}  statics threads: {statics_module.THREADS}  "
      f"chunk: {statics_module.CHUNK_POSES}  load average: {os.getloadavg()[0]:.2f}")
for name, (median, best, _) in (("forward kinematics", kin_rate), ("statics (given poses)", statics_rate),
                                ("kinematics + statics", both_rate)):
    print(f"{name:>22}: {median:>9,.0f} poses/s median  {best:>9,.0f} best")
verdict = "MET" if both_rate[0] >= TARGET_POSES_PER_S else "NOT MET"
print(f"target >= {TARGET_POSES_PER_S:,} poses/s (kinematics + statics, median): {verdict} "
      f"({both_rate[0] / TARGET_POSES_PER_S:.2f}x)")
print(f"kinematic loop closure max: {closure:.2e} m (tolerance 1e-12 m)")
print(f"batched vs single-pose deflection max difference: {diff:.2e} m "
      f"(largest deflection {np.abs(res.deflection[:, :3]).max():.2e} m)")
