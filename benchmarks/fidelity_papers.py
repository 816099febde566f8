"""Twin vs the seeds' observable magnitudes (docs/twin.md table): room range over the thermal
campaign, 2 A displacement at a fixed pose and its repeatability (interface path, 20 on/off
cycles), the std of each force-campaign point's 4 readings.
Run: python benchmarks/fidelity_papers.py"""
import numpy as np

from deltatwin.twin.instruments.simulated import SimulatedLab
from deltatwin.twin.scenario import Scenario

sc = Scenario.load("paper-thermal")
twin, _ = sc.build(None)
t = twin.t_grid
room = twin.env.room_C[(t >= 0) & (t <= 3 * 86400)]
print(f"room over 3 days: {room.min():.2f} .. {room.max():.2f} degC (seed 21-25)")

sc = Scenario.load("paper-force")
twin, plan = sc.build(0.2)
lab = SimulatedLab(twin, sc.settings)
inst = lab.instrument_set()
q = np.array([0.03, 0.03, 0.03])
inst.robot.move_to(np.zeros(3))
inst.interferometers.zero()
inst.robot.move_to(q)
diffs = []
for _cycle in range(20):
    r = {}
    for I in (0.0, 2.0):
        inst.coils.set_currents(np.full(3, I))
        inst.clock.sleep(sc.settings.wait_s)
        vals = [inst.interferometers.read().displacement_m for _ in range(4)]
        r[I] = np.array([[v[a] for a in "xyz"] for v in vals]).mean(axis=0)
    diffs.append(r[2.0] - r[0.0])
diffs = np.array(diffs) * 1e9
truth = twin.truth(twin.points([lab.t] * 2, np.tile(q, (2, 1)), np.array([[0, 0, 0], [2, 2, 2.0]])))
print("fixed pose q =", q.tolist(), "rad; wrench at 2 A:", np.round(truth.wrench[1] - truth.wrench[0], 3))
print("2 A displacement X/Y/Z (mean of 20 cycles): " + " / ".join(f"{v:.0f}" for v in np.abs(diffs.mean(0)))
      + " nm (seed 291 / 700 / 168)")
rep = 1.645 * diffs.std(axis=0, ddof=1)
print("repeatability (90 %, 1.645 sigma): " + " / ".join(f"±{v:.0f}" for v in rep)
      + " nm (seed ±46 / 36 / 61)")

df, _ = sc.simulate()
worst = max(df[f"{a}_repeat_std_nm"].max() for a in "xyz")
print(f"force campaign ({len(df)} points): std of a point's {sc.campaign['readings']} readings, "
      f"max over points and axes: {worst:.1f} nm (seed: never above 20 nm)")
