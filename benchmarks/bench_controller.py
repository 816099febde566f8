"""Benchmark: the latency of one inverse evaluation of the physics model a controller loads:
the portable C evaluator (calibration/physics/controller_evaluator.c, built
here with the system C compiler, -O2) against the numpy reference evaluator, one point at a
time as a controller's loop asks, against a loop budget of 100 us.

For each scenario: simulate its campaign (``--scale``, default the scenario's reduced scale),
fit the physics model (the scenario's effects that have a model form, the laboratory's known
constants given, as benchmarks/bench_compensation.py does), export it (JSON + the C block),
then on calibration rows of its first session, targets = the fitted model's readings:

* agreement: C - numpy evaluator (forward readings, m; inverse q, rad), and the fitted model
  at the C inverse's q against the target (m);
* CPU time per point (time.process_time, one thread): the inverse from home, and the next point
  of a path (the target 1 um further on each axis) warm-started from the previous decision's
  q and pose: numpy; C through the ctypes binding (controller_c.CSession, the Python
  wrapper's and ctypes' call overhead included); and C alone, timed in C by
  benchmarks/controller_latency.c (clock(), the same points, repeated) - what a controller
  spends.

    python benchmarks/bench_controller.py
    python benchmarks/bench_controller.py --scale 0.05 --points 200

Every figure printed is measured here; nothing is compared with stored numbers.
"""
from __future__ import annotations

import argparse
import shutil
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

from deltatwin.calibration.physics import controller_c
from deltatwin.calibration.physics import controller_evaluator as ce
from deltatwin.calibration.physics.export import evaluator_conditions, write_controller_model
from deltatwin.calibration.physics.fit import PhysicsFit
from deltatwin.calibration.physics.inverse import with_motor_coordinates
from deltatwin.calibration.physics.measurements import measurements
from deltatwin.calibration.physics.model import model_effects
from deltatwin.twin.scenario import Scenario

DRIVER = Path(__file__).with_name("controller_latency.c")
BUDGET_US = 100.0
STEP_M = 1e-6           # the next point of a path: 1 um on, every axis


def _fitted(sc, scale):
    df, meta = sc.simulate(scale)
    effects = [e.name for e in sc.effects if e.name in model_effects()]
    known = {e.name: {p.name: e.values[p.name] for p in e.parameters if p.fit_scale is None}
             for e in sc.effects if e.name in effects}
    t0 = time.process_time()
    fit = PhysicsFit(effects, start=known).fit(df, meta)
    print(f"  {len(df)} rows at scale {scale:g}; physics model fitted ({', '.join(effects)}) "
          f"in {time.process_time() - t0:.0f} s CPU")
    return fit.model_, df, meta


def _per_point_us(f, k: int) -> float:
    t0 = time.process_time()
    for i in range(k):
        f(i)
    return (time.process_time() - t0) / k * 1e6


def _compile_driver(d: Path) -> Path:
    exe = d / "controller_latency"
    cc = shutil.which("cc") or shutil.which("gcc")
    subprocess.run([cc, "-std=c99", "-O2", "-I", str(controller_c.SOURCE.parent), "-o", str(exe),
                    str(DRIVER), str(controller_c.SOURCE), "-lm"], check=True)
    return exe


def _in_c(driver, block, zero, target, cond, d: Path, repeat: int) -> dict:
    """The inverse timed by the C driver on the same points (one thread, clock())."""
    def flat(c, i):
        return [*(float(c[k][i]) for k in ce.CONDITIONS), float(c["pressure_Pa"][i]),
                *np.asarray(c["currents_A"][i], float)]
    rows = [flat(zero, 0)] + [[*target[i], *flat(cond, i)] for i in range(target.shape[0])]
    points = d / "points.bin"
    np.concatenate([np.asarray(r, dtype="<f8") for r in rows]).tofile(points)
    out = subprocess.run([str(driver), str(block), str(points), str(repeat)], check=True,
                         capture_output=True, text=True).stdout.split()
    return {"cold": float(out[1]), "warm": float(out[2]), "cold_steps": float(out[3]),
            "warm_steps": float(out[4]), "not_converged": int(out[5])}


def _scenario(name, scale, n_points, library, driver, d: Path) -> list[bool]:
    sc = Scenario.load(name)
    print(f"{name}:")
    model, df, meta = _fitted(sc, scale or sc.reduced_scale)
    path = write_controller_model(model, d / f"{name}.json", meta["sensors"])
    exported = ce.load(path)
    meas = measurements(df, meta, model.params)
    meas.cos_scale[:] = 1.0                 # the controller's readings: no cosine correction
    meas.cos_offset[:] = 0.0
    rows = np.flatnonzero(meas.zero_row == meas.zero_row[0])         # the first session
    rows = rows[np.linspace(0, rows.size - 1, min(n_points, rows.size)).astype(int)]
    target = model.predict_path(meas)[rows]
    cond, zero = evaluator_conditions(model, meas, rows)
    session = ce.Session(exported, zero)
    c_session = controller_c.CSession(library, controller_c.block_path(path), zero)
    one = [{k: v[i:i + 1] for k, v in cond.items()} for i in range(rows.size)]
    c_cond = [c_session.conditions({k: v[i] for k, v in cond.items()}) for i in range(rows.size)]
    k = rows.size
    with threadpool_limits(1):
        numpy_cold = [session.inverse(target[i], one[i]) for i in range(min(k, 50))]
        c_cold, c_poses = [], []
        for i in range(k):
            c_poses.append(c_session.new_pose())
            c_cold.append(c_session.inverse(target[i], c_cond[i], pose=c_poses[i]))
        kn = min(k, 50)             # numpy: ~1-2 ms a point
        us = {
            "numpy_cold": _per_point_us(lambda i: session.inverse(target[i], one[i]), kn),
            "numpy_warm": _per_point_us(lambda i: session.inverse(
                target[i] + STEP_M, one[i], q0=numpy_cold[i]["q"], pose0=numpy_cold[i]["pose"]),
                kn),
            "c_cold": _per_point_us(lambda i: c_session.inverse(target[i], c_cond[i]), k),
            # a fresh copy of the previous decision's pose each call (included in the time)
            "c_warm": _per_point_us(lambda i: c_session.inverse(
                target[i] + STEP_M, c_cond[i], q0=c_cold[i]["q"],
                pose=c_session.new_pose(c_poses[i])), k),
        }
    alone = _in_c(driver, controller_c.block_path(path), zero, target, cond, d, 20)
    c_warm = [c_session.inverse(target[i] + STEP_M, c_cond[i], q0=c_cold[i]["q"],
                                pose=c_session.new_pose(c_poses[i]))
              for i in range(k)]
    q_c = np.array([r["q"] for r in c_cold])
    forward = max(np.abs(c_session.forward(meas.points.q[r], c_cond[i])
                         - session.forward(meas.points.q[r], one[i])[0]).max()
                  for i, r in enumerate(rows[:kn]))
    dq = max(np.abs(q_c[i] - numpy_cold[i]["q"][0]).max() for i in range(kn))
    back = np.abs(model.predict_path(with_motor_coordinates(meas, rows, q_c))[rows]
                  - target).max()
    print(f"  controller file: statics degree {exported['statics']['degree']}, C block "
          f"{controller_c.block_path(path).stat().st_size / 1e3:.0f} kB")
    print(f"  C - numpy evaluator on {kn} rows: forward {forward:.1e} m, inverse q {dq:.1e} rad; "
          f"the fitted model at the C inverse's q - target on {k} rows: {back:.1e} m; "
          f"C statuses {sorted({r['status'] for r in c_cold})}")
    its = lambda rs: np.mean([r["iterations"] for r in rs])
    verdicts = []
    for kind, cold_it, warm_it in (("numpy", its(numpy_cold), None),
                                   ("C", its(c_cold), its(c_warm))):
        cold, warm = us[f"{kind.lower()}_cold"], us[f"{kind.lower()}_warm"]
        ok = warm <= BUDGET_US
        verdicts.append(ok)
        print(f"  {kind:>5} inverse, CPU per point (one thread): from home {cold:8.1f} us "
              f"({cold_it:.1f} steps); the next point of a path, warm-started {warm:8.1f} us"
              + (f" ({warm_it:.1f} steps)" if warm_it is not None else "")
              + f"   budget {BUDGET_US:g} us: {'met' if ok else 'NOT met'}")
    ok = alone["warm"] <= BUDGET_US
    verdicts.append(ok)
    print(f"  C alone (timed in C, {k} points x 20): from home {alone['cold']:8.1f} us "
          f"({alone['cold_steps']:.1f} steps); warm-started {alone['warm']:8.1f} us "
          f"({alone['warm_steps']:.1f} steps); {alone['not_converged']} solves not converged"
          f"   budget {BUDGET_US:g} us: {'met' if ok else 'NOT met'}")
    print(f"  C alone is {us['numpy_warm'] / alone['warm']:.0f}x faster than numpy "
          f"warm-started, {us['numpy_cold'] / alone['cold']:.0f}x from home")
    return verdicts[1:]             # the targets are the C evaluator's


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scale", type=float, default=None,
                    help="campaign scale (default: each scenario's reduced scale)")
    ap.add_argument("--points", type=int, default=500, help="calibration rows timed (C)")
    ap.add_argument("--scenarios", default="paper-thermal,paper-force")
    args = ap.parse_args(argv)
    t0 = time.process_time()
    verdicts = []
    with tempfile.TemporaryDirectory() as tmp:
        library = controller_c.compile_library(tmp)
        driver = _compile_driver(Path(tmp))
        print(f"C evaluator compiled: {library.name} and {driver.name} "
              f"({controller_c.SOURCE.name}, -std=c99 -O2)")
        for name in args.scenarios.split(","):
            d = Path(tmp) / name
            d.mkdir()
            verdicts += _scenario(name, args.scale, args.points, library, driver, d)
    print(f"targets met (C through ctypes and alone, warm-started, <= {BUDGET_US:g} us): "
          f"{sum(verdicts)} of "
          f"{len(verdicts)}; {time.process_time() - t0:.0f} s CPU in all")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
