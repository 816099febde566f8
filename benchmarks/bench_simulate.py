"""Full-scale paper-thermal campaign (all instruments and temperatures) on the twin: points/s
and wall time against the issue's target (<= 15 s)."""
import time

from deltatwin.twin.scenario import Scenario

TARGET_S = 15.0

sc = Scenario.load("paper-thermal")
t0 = time.perf_counter()
df, _ = sc.simulate()
dt = time.perf_counter() - t0
print(f"paper-thermal full scale: {len(df)} points in {dt:.2f} s = {len(df) / dt:,.0f} points/s; "
      f"target <= {TARGET_S:.0f} s: {'MET' if dt <= TARGET_S else 'NOT MET'}")
