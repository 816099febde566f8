"""Benchmark: planning a campaign (issue 20). Prints each figure beside the target it is held to.

1. A sweep of 4 magnitudes x 50 seeds = 200 cases (quiet/beam-misalignment, the Abbe offsets
   scaled; fit: the known geometry; diagnose) on a local pool of 1 worker, on a pool of 2
   workers killed (SIGKILL) a third of the way and resumed, and on a Dask cluster of real
   `dask scheduler` / `dask worker` processes on 127.0.0.1 (2 worker processes, 1 thread each):
   identical records (every column but the wall time), nothing finished recomputed, cases/s.
   The magnitudes are chosen by the prediction (those nearest 20, 50, 80 % power on a grid) plus
   0, so the Monte Carlo check falls where power is neither 0 nor 1.
2. Predicted (linearised) vs Monte Carlo detection power at each magnitude: within +-0.1.
3. Pose selection on quiet/magnetic-force at the paper's full grids (1080 calibration points
   at 5 forces, 625 validation): D- and I-optimal subsets of 1/3 of the points vs the full grid
   (target: validation error within 10 %) and a random third.
4. The uncertainty budget of the force paper's campaign (paper-force at scale 0.3) fitted with
   geometric errors, magnetic force, thermal expansion and loop drift.

    python benchmarks/bench_design.py                 # all (~20 min on 2 idle cores)
    python benchmarks/bench_design.py --cases 40 --pose-scale 0.3     # a quick look
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pandas as pd

from deltatwin.calibration.design.budget import uncertainty_budget
from deltatwin.calibration.design.poses import selection_study
from deltatwin.calibration.design.power import (
    monte_carlo_power,
    power_figure,
    power_table,
    predicted_power_curve,
)
from deltatwin.calibration.design.sweep import (
    SweepSpec,
    deterministic_columns,
    finished,
    read_records,
    run_sweep,
)
from deltatwin.calibration.physics.fit import PhysicsFit
from deltatwin.twin.scenario import Scenario

SPEC = """
[sweep]
name = "bench-beam-misalignment"
seed = 2020
replicates = {replicates}

[[study]]
scenario = "quiet/beam-misalignment"
effect = "beam_misalignment"
parameter = "abbe_offset_m"
magnitudes = {magnitudes}

[designs.tenth]
scale = {scale}
"""


def _spec(folder: Path, replicates: int, magnitudes, scale: float) -> Path:
    p = folder / "spec.toml"
    p.write_text(SPEC.format(replicates=replicates, magnitudes=json.dumps(magnitudes),
                             scale=scale))
    return p


def _choose_magnitudes(folder: Path, scale: float, rng) -> tuple[list, pd.DataFrame]:
    grid = [round(x, 4) for x in np.geomspace(0.02, 0.6, 24)]
    spec = SweepSpec.load(_spec(folder, 1, grid, scale))
    curve = predicted_power_curve(spec.cases[:1], grid, rng, n_draws=1000)
    picks = sorted({float(curve.magnitude[np.argmin(np.abs(curve.power - p))])
                    for p in (0.2, 0.5, 0.8)})
    return [0.0] + picks, curve


def _killed_and_resumed(spec: Path, out: Path, n_cases: int) -> dict:
    cmd = [sys.executable, "-m", "deltatwin", "sweep", str(spec), "-o", str(out), "--workers",
           "2", "-q", "--json"]
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, start_new_session=True, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    while len(finished(out)) < n_cases // 3 and proc.poll() is None:
        time.sleep(0.05)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    first = time.perf_counter() - t0
    before = {p: p.stat().st_mtime_ns for p in out.glob("*/*/case-*.parquet")}
    r = subprocess.run(cmd[:-2] + ["--resume", "--json"], capture_output=True, text=True,
                       check=True)
    s = json.loads(r.stdout)
    untouched = all(p.stat().st_mtime_ns == m for p, m in before.items())
    return {"killed_after": len(before), "skipped_on_resume": s["skipped"], "ran": s["ran"],
            "finished_untouched": untouched,
            "cases_per_s": n_cases / (first + s["wall_s"])}


def _dask_cluster(folder: Path):
    sched_file = folder / "scheduler.json"
    dask = str(Path(sys.executable).parent / "dask")     # the environment's, activated or not
    procs = [subprocess.Popen([dask, "scheduler", "--host", "127.0.0.1", "--port", "0",
                               "--no-dashboard", "--scheduler-file", str(sched_file)],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)]
    while not sched_file.exists():
        time.sleep(0.1)
    procs.append(subprocess.Popen([dask, "worker", "--nworkers", "2", "--nthreads", "1",
                                   "--no-dashboard", "--scheduler-file", str(sched_file)],
                                  stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
    address = json.loads(sched_file.read_text())["address"]
    from distributed import Client

    with Client(address) as c:
        c.wait_for_workers(2, timeout=120)
    return address, procs


def sweeps(folder: Path, n_cases: int, scale: float, rng, reuse: bool):
    """The three runs; with ``reuse``, a run whose folder already holds every case is not
    repeated (its throughput was printed by the earlier run)."""
    if reuse and (folder / "spec.toml").exists():
        spec = folder / "spec.toml"
        s = SweepSpec.load(spec)
        mags = sorted({c.magnitude for c in s.cases})
    else:
        mags, _ = _choose_magnitudes(folder, scale, rng)
        spec = _spec(folder, n_cases // len(mags), mags, scale)
        s = SweepSpec.load(spec)
    print(f"sweep: {len(s.cases)} cases, magnitudes {mags} (chosen by the prediction), "
          f"scale {scale}")
    complete = lambda name: reuse and len(finished(folder / name)) == len(s.cases)
    if complete("pool1"):
        print("  pool, 1 worker: records reused from an earlier run")
        one = None
    else:
        one = run_sweep(s, folder / "pool1", workers=1)
        print(f"  pool, 1 worker: {one['cases_per_s']:.3f} cases/s ({one['wall_s']:.0f} s)")
    if complete("pool2"):
        print("  pool, 2 workers killed and resumed: records reused from an earlier run")
        kr = None
    else:
        kr = _killed_and_resumed(spec, folder / "pool2", len(s.cases))
        print(f"  pool, 2 workers, killed after {kr['killed_after']} records and resumed: "
              f"{kr['skipped_on_resume']} skipped, {kr['ran']} run, finished files untouched: "
              f"{kr['finished_untouched']}; {kr['cases_per_s']:.3f} cases/s including the "
              "restart")
    address, procs = _dask_cluster(folder)
    try:
        dk = run_sweep(s, folder / "dask", scheduler=address, resume=reuse)
    finally:
        for p in reversed(procs):
            p.terminate()
            p.wait(timeout=60)
    print(f"  dask (scheduler + 2 worker processes on 127.0.0.1): {dk['cases_per_s']:.3f} "
          f"cases/s ({dk['wall_s']:.0f} s, {dk['ran']} cases run)")
    recs = {k: read_records(folder / k) for k in ("pool1", "pool2", "dask")}
    cols = deterministic_columns(recs["pool1"])
    same = all(recs["pool1"][cols].equals(recs[k][cols]) for k in ("pool2", "dask"))
    print(f"  target: identical records on pool (1 and 2 workers) and Dask -> "
          f"{'MET' if same else 'NOT MET'} ({len(recs['pool1'])} records, {len(cols)} columns "
          "compared)")
    if kr:
        resumed = kr["finished_untouched"] and kr["skipped_on_resume"] == kr["killed_after"]
        print(f"  target: resume without recomputing -> {'MET' if resumed else 'NOT MET'}")
    if one:
        print(f"  throughput, 2 Dask workers / 1 pool worker: "
              f"{dk['cases_per_s'] / one['cases_per_s']:.2f}x")
    return recs["pool1"], s, mags


def power(records, spec: SweepSpec, mags, folder: Path, rng, campaigns: int) -> None:
    # the design's prediction: averaged over the campaigns of its first replicates' seeds
    cases = [c for c in spec.cases if c.magnitude == 0][:campaigns]
    pred = predicted_power_curve(cases, mags, rng, n_draws=4000)
    t = power_table(pred, monte_carlo_power(records))
    pd.set_option("display.width", 160)
    print("\ndetection power (beam_misalignment, Abbe offsets x magnitude):")
    print(f"  prediction averaged over {len(cases)} simulated campaigns (power_sd: its spread)")
    print(t[["magnitude", "cases", "predicted", "power_sd", "mc_significant", "mc_se",
             "mc_named", "difference", "noncentrality"]].to_string(index=False,
                                                                    float_format="%.3f"))
    worst = float(np.max(np.abs(t.difference)))
    print(f"  target: |predicted - Monte Carlo| <= 0.1 at every magnitude -> largest "
          f"{worst:.3f}: {'MET' if worst <= 0.1 else 'NOT MET'}")
    fig = power_figure(t, "quiet/beam-misalignment: detection power")
    fig.savefig(folder / "power.png", dpi=120)
    t.to_csv(folder / "power.csv", index=False)
    print(f"  table and plot: {folder / 'power.csv'}, {folder / 'power.png'}")


def poses(scale: float, rng) -> None:
    sc = Scenario.load("quiet/magnetic-force")
    df, meta = sc.simulate(scale)
    n_cal = int((df["split"] == "cal").sum())
    t0 = time.perf_counter()
    r = selection_study(df, meta, ["geometric_errors", "magnetic_force"], n_cal // 3,
                        sc.settings.noise_floor_m, rng)
    print(f"\npose selection (quiet/magnetic-force, scale {scale}: {r['n_candidates']} "
          f"calibration candidates, {r['n_selected']} chosen, {r['n_validation']} validation "
          f"points; noise floor {meta['truth']['noise_floor_nm']} nm; "
          f"{time.perf_counter() - t0:.0f} s):")
    full = r["all"]["val_err90_nm"]
    for k in ("all", "D_optimal", "I_optimal", "random"):
        e = r[k]
        print(f"  {k:<10} {e['cal_points']:5d} points: val err90 {e['val_err90_nm']:6.2f} nm "
              f"({e['val_err90_nm'] / full:5.3f} x full), mean prediction variance "
              f"{e['mean_prediction_variance']:.3f} sigma^2, {e['identified_directions']} "
              f"directions identified, forces {e['forces_N']}")
    for k in ("D_optimal", "I_optimal"):
        ratio = r[k]["val_err90_nm"] / full
        print(f"  target: {k} within 10 % of the full grid with 1/3 of the points -> "
              f"{ratio:.3f}: {'MET' if ratio <= 1.10 else 'NOT MET'}")


def budget(scale: float) -> None:
    """The force paper's campaign fitted with four effects: its uncertainty budget beside the
    validation error the same fit reaches."""
    sc = Scenario.load("paper-force")
    df, meta = sc.simulate(scale)
    fit = PhysicsFit(["geometric_errors", "magnetic_force", "thermal_expansion", "loop_drift"],
                     noise_nm=sc.settings.noise_floor_m * 1e9).fit(df, meta)
    servo = next(e for e in sc.effects if e.name == "servo_settling").values["angle_std_rad"]
    b = uncertainty_budget(fit, df, meta, sc.settings.noise_floor_m, sc.settings.T_noise_C,
                           float(servo), 200.0)
    print(f"\nuncertainty budget (paper-force, scale {scale}, {len(df)} points; servo "
          f"{servo:g} rad, pressure 200 Pa, thermometers {sc.settings.T_noise_C * 1e3:g} mK):")
    print(b.to_string(index=False, float_format="%.2f"))
    print(f"  combined {b.all_p90_nm.iloc[-1]:.1f} nm beside the fit's validation error "
          f"{fit.val_['all']['err_p90']:.1f} nm (90 %)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", type=int, default=200)
    ap.add_argument("--sweep-scale", type=float, default=0.1)
    ap.add_argument("--pose-scale", type=float, default=1.0)
    ap.add_argument("--campaigns", type=int, default=5,
                    help="simulated campaigns the power prediction averages over")
    ap.add_argument("--out", default=None, help="folder for the records, table and plot")
    ap.add_argument("--reuse", action="store_true",
                    help="reuse the spec and the complete sweeps in --out (an earlier run)")
    ap.add_argument("--skip-poses", action="store_true", help="stop after the power table")
    ap.add_argument("--budget-only", action="store_true",
                    help="only the uncertainty budget of the force paper's campaign")
    ap.add_argument("--budget-scale", type=float, default=0.3)
    args = ap.parse_args()
    rng = np.random.default_rng(20)
    folder = Path(args.out or tempfile.mkdtemp(prefix="bench-design-"))
    folder.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    if args.budget_only:
        budget(args.budget_scale)
        return
    records, spec, mags = sweeps(folder, args.cases, args.sweep_scale, rng, args.reuse)
    power(records, spec, mags, folder, rng, args.campaigns)
    if args.skip_poses:
        return
    poses(args.pose_scale, rng)
    budget(args.budget_scale)
    print(f"\ntotal {time.perf_counter() - t0:.0f} s; results in {folder}")


if __name__ == "__main__":
    main()
