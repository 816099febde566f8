"""Benchmark: planning a campaign. Prints each figure beside the target it is held to.

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

from deltatwin.calibration.design.budget import (
    budget_monte_carlo,
    uncertainty_budget,
    without_random_errors,
)
from deltatwin.calibration.design.poses import (
    fraction_study,
    fraction_summary,
    load_level_study,
    order_study,
    selection_study,
)
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


def _dask_cluster(folder: Path, n_workers: int = 2):
    sched_file = folder / "scheduler.json"
    sched_file.unlink(missing_ok=True)
    dask = str(Path(sys.executable).parent / "dask")     # the environment's, activated or not
    procs = [subprocess.Popen([dask, "scheduler", "--host", "127.0.0.1", "--port", "0",
                               "--no-dashboard", "--scheduler-file", str(sched_file)],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)]
    while not sched_file.exists():
        time.sleep(0.1)
    procs.append(subprocess.Popen([dask, "worker", "--nworkers", str(n_workers), "--nthreads",
                                   "1", "--no-dashboard", "--scheduler-file", str(sched_file)],
                                  stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
    address = json.loads(sched_file.read_text())["address"]
    from distributed import Client

    with Client(address) as c:
        c.wait_for_workers(n_workers, timeout=120)
    return address, procs


def _timing(r: dict) -> str:
    return (f"{r['cases_per_s']:.3f} cases/s ({r['wall_s']:.0f} s wall), "
            f"{r['cpu_s_per_case']:.2f} CPU s per case, load average "
            f"{r['load_average_start']:.1f} -> {r['load_average_end']:.1f}")


def _stop(procs) -> None:
    for p in reversed(procs):
        p.terminate()
        p.wait(timeout=60)


def scaling(folder: Path, mags, scale: float, n_cases: int) -> None:
    """Throughput with 1 and 2 workers, local pool and Dask, on ``n_cases`` of the sweep's
    cases (fewer replicates of the same magnitudes): cases/s (wall), the CPU seconds a case
    took in its worker, and the machine's load average beside each (the cores are shared)."""
    (folder / "scaling").mkdir(parents=True, exist_ok=True)
    spec = SweepSpec.load(_spec(folder / "scaling", max(n_cases // len(mags), 1), mags, scale))
    print(f"\nthroughput: {len(spec.cases)} cases per run; {os.cpu_count()} cores; 1 thread "
          "per case (BLAS and chunk pool)")
    rows = []
    for backend, workers in (("pool", 1), ("pool", 2), ("dask", 1), ("dask", 2)):
        out = folder / "scaling" / f"{backend}{workers}"
        if backend == "pool":
            r = run_sweep(spec, out, workers=workers)
        else:
            address, procs = _dask_cluster(folder / "scaling", workers)
            try:
                r = run_sweep(spec, out, scheduler=address)
            finally:
                _stop(procs)
        rows.append((backend, workers, r))
        print(f"  {backend} {workers} worker{'s' if workers > 1 else ' '}: {_timing(r)}")
    for backend in ("pool", "dask"):
        one, two = (r for b, w, r in rows if b == backend)
        print(f"  {backend}: 2 workers / 1 worker = {two['cases_per_s'] / one['cases_per_s']:.2f}x "
              f"cases/s; CPU per case {two['cpu_s_per_case'] / one['cpu_s_per_case']:.2f}x "
              "(near 1: the workers do not oversubscribe the cores)")


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
        print(f"  pool, 1 worker: {_timing(one)}")
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
        _stop(procs)
    print(f"  dask (scheduler + 2 worker processes on 127.0.0.1), {dk['ran']} cases run: "
          f"{_timing(dk)}")
    recs = {k: read_records(folder / k) for k in ("pool1", "pool2", "dask")}
    cols = deterministic_columns(recs["pool1"])
    same = all(recs["pool1"][cols].equals(recs[k][cols]) for k in ("pool2", "dask"))
    print(f"  target: identical records on pool (1 and 2 workers) and Dask -> "
          f"{'MET' if same else 'NOT MET'} ({len(recs['pool1'])} records, {len(cols)} columns "
          "compared)")
    if kr:
        resumed = kr["finished_untouched"] and kr["skipped_on_resume"] == kr["killed_after"]
        print(f"  target: resume without recomputing -> {'MET' if resumed else 'NOT MET'}")
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


FORCE_MODEL = ["geometric_errors", "magnetic_force"]
BUDGET_MODEL = ["geometric_errors", "magnetic_force", "thermal_expansion", "loop_drift"]


def poses(scale: float, rng, n_random: int, folder: Path) -> None:
    """Pose selection on the force paper's grids: the 1/3 target (D, I, one random third), then
    1/3, 1/10, 1/20 of the points D-optimal against ``n_random`` random subsets each, then which
    two of the five load levels."""
    sc = Scenario.load("quiet/magnetic-force")
    df, meta = sc.simulate(scale)
    n_cal = int((df["split"] == "cal").sum())
    sigma = sc.settings.noise_floor_m
    t0, c0 = time.perf_counter(), time.process_time()
    r = selection_study(df, meta, FORCE_MODEL, n_cal // 3, sigma, rng)
    print(f"\npose selection (quiet/magnetic-force, scale {scale}: {r['n_candidates']} "
          f"calibration candidates, {r['n_selected']} chosen, {r['n_validation']} validation "
          f"points; noise floor {meta['truth']['noise_floor_nm']} nm; "
          f"{time.process_time() - c0:.0f} CPU s, {time.perf_counter() - t0:.0f} s wall):")
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

    # the same campaign read without the interferometers' noise: the fitted models' error
    # against it is the estimation error a selection changes (the reading noise is common)
    clean = without_random_errors(sc).simulate(scale)[0]
    c0 = time.process_time()
    study = fraction_study(df, meta, FORCE_MODEL, [1 / 3, 1 / 10, 1 / 20], sigma, rng, n_random,
                           clean=clean)
    study.to_csv(folder / "fractions.csv", index=False)
    truth_full = float(study.truth_err90_nm.iloc[0])
    print(f"\nfractions of the calibration points, D- and I-optimal vs {n_random} random subsets "
          f"each ({time.process_time() - c0:.0f} CPU s; every fit in {folder / 'fractions.csv'})")
    for error, what in (("val_err90_nm", f"validation error (full grid {full:.2f} nm)"),
                        ("truth_err90_nm", "error against the noise-free validation readings "
                                           f"(full grid {truth_full:.2f} nm)")):
        summary = fraction_summary(study, error)
        print(f"  {what}:")
        print(summary.drop(columns=["random_draws"]).to_string(index=False,
                                                               float_format="%.3f"))
        for _, row in summary.iterrows():
            print(f"  1/{1 / row.fraction:.0f} {row.selection}: {row.x_full:.3f} x full; random "
                  f"median {row.random_median_x_full:.3f} x full; better than "
                  f"{row.random_worse_share:.0%} of the random subsets "
                  f"({row.random_failed} could not be fitted)")

    c0 = time.process_time()
    levels = load_level_study(df, meta, FORCE_MODEL, 2, sigma, clean=clean)
    print(f"\nload levels: every pair of the five forces (all {n_cal // 5} calibration "
          f"positions at each), ranked by the D criterion; validated on all 5 levels "
          f"({time.process_time() - c0:.0f} CPU s):")
    print(levels.drop(columns=["status"]).to_string(index=False, float_format="%.3f"))
    pairs = levels[levels.levels_N.map(len) == 2]
    best, worst = pairs.iloc[0], pairs.iloc[-1]
    print(f"  D-best pair {best.levels_N}: {best.truth_err90_nm:.2f} nm against the truth "
          f"({best.val_err90_nm:.2f} validation); D-worst pair {worst.levels_N}: "
          f"{worst.truth_err90_nm:.2f} nm ({worst.val_err90_nm:.2f}); Spearman rank correlation "
          f"of log det with -error against the truth over the pairs: "
          f"{pairs.log_det.rank().corr(-pairs.truth_err90_nm.rank()):.2f}")


def order(scale: float, seeds) -> None:
    """Order and interleaving of the force paper's campaign (paper-force: thermal drifts and
    the loop's expansion in the data), with and without the loop drift in the model."""
    sc = Scenario.load("paper-force")
    c0 = time.process_time()
    t = order_study("paper-force", {"without loop_drift": BUDGET_MODEL[:3],
                                    "with loop_drift": BUDGET_MODEL},
                    scale, seeds, sc.settings.noise_floor_m)
    print(f"\norder: the papers' (calibration grid, then validation grid) vs interleaved, "
          f"paper-force at scale {scale}, seeds {list(seeds)} ({time.process_time() - c0:.0f} "
          "CPU s):")
    print(t.to_string(index=False, float_format="%.3f"))
    g = t.groupby(["model", "order"]).agg(val_err90_median_nm=("val_err90_nm", "median"),
                                          truth_err90_median_nm=("truth_err90_nm", "median"),
                                          prediction_variance=(
                                              "validation_prediction_variance", "median"))
    print(g.to_string(float_format="%.3f"))
    for model, m in t.groupby("model"):
        for error in ("val_err90_nm", "truth_err90_nm"):
            p = m[m.order == "papers"].set_index("seed")[error]
            i = m[m.order == "interleaved"].set_index("seed")[error]
            print(f"  {model}, {error}: interleaved better on {int((i < p).sum())} of {len(p)} "
                  f"seeds; median papers / interleaved {np.median(p / i):.2f}")


def budget(scale: float, rng) -> None:
    """The force paper's campaign fitted with four effects: its uncertainty budget beside the
    validation error the same fit reaches."""
    sc = Scenario.load("paper-force")
    df, meta = sc.simulate(scale)
    fit = PhysicsFit(BUDGET_MODEL, noise_nm=sc.settings.noise_floor_m * 1e9).fit(df, meta)
    servo = next(e for e in sc.effects if e.name == "servo_settling").values["angle_std_rad"]
    readings = sc.campaign["readings"]
    b = uncertainty_budget(fit, df, meta, sc.settings.noise_floor_m / np.sqrt(readings),
                           sc.settings.T_noise_C, float(servo), sc.air_wander(), rng)
    print(f"\nuncertainty budget (paper-force, scale {scale}, {len(df)} points; reading "
          f"{sc.settings.noise_floor_m * 1e9:g} nm / sqrt({readings}) readings; servo "
          f"{servo:g} rad, the scenario's air, thermometers {sc.settings.T_noise_C * 1e3:g} mK):")
    print(b.to_string(index=False, float_format="%.2f"))
    print(f"  combined {b.all_p90_nm.iloc[-1]:.1f} nm beside the fit's validation error "
          f"{fit.val_['all']['err_p90']:.1f} nm (90 %)")


def budget_mc(scale: float, campaigns: int) -> None:
    """The budget's Monte Carlo check: ``campaigns`` simulated campaigns of one robot."""
    c0, t0 = time.process_time(), time.perf_counter()
    t = budget_monte_carlo("paper-force", BUDGET_MODEL, campaigns, scale, 2020,
                           progress=lambda i, n: print(f"  campaign {i}/{n}", file=sys.stderr))
    print(f"\nbudget vs Monte Carlo (paper-force at scale {scale}, {campaigns} campaigns of one "
          f"robot; {time.process_time() - c0:.0f} CPU s in this process, "
          f"{time.perf_counter() - t0:.0f} s wall):")
    print(t.to_string(index=False, float_format="%.3f"))
    print(f"  target: every line's budget inside the Monte Carlo 95 % interval -> "
          f"{int(t.agrees.sum())} of {len(t)} lines"
          f" ({', '.join(t.source[~t.agrees]) or 'all agree'} outside)")


STAGES = ("sweep", "scaling", "poses", "order", "budget", "budget-mc")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--stages", nargs="+", choices=STAGES, default=list(STAGES),
                    help="what to run (default: all); 'sweep' includes the power table")
    ap.add_argument("--cases", type=int, default=200)
    ap.add_argument("--sweep-scale", type=float, default=0.1)
    ap.add_argument("--scaling-cases", type=int, default=24,
                    help="cases per throughput run (4 runs: pool and Dask, 1 and 2 workers)")
    ap.add_argument("--pose-scale", type=float, default=1.0)
    ap.add_argument("--random-subsets", type=int, default=8,
                    help="random subsets per fraction the D-optimal one is compared with")
    ap.add_argument("--order-scale", type=float, default=0.3)
    ap.add_argument("--order-seeds", type=int, default=4)
    ap.add_argument("--campaigns", type=int, default=5,
                    help="simulated campaigns the power prediction averages over")
    ap.add_argument("--out", default=None, help="folder for the records, table and plot")
    ap.add_argument("--reuse", action="store_true",
                    help="reuse the spec and the complete sweeps in --out (an earlier run)")
    ap.add_argument("--budget-scale", type=float, default=0.3)
    ap.add_argument("--budget-mc-scale", type=float, default=0.1)
    ap.add_argument("--budget-campaigns", type=int, default=20)
    args = ap.parse_args()
    rng = np.random.default_rng(20)
    folder = Path(args.out or tempfile.mkdtemp(prefix="bench-design-"))
    folder.mkdir(parents=True, exist_ok=True)
    t0, c0 = time.perf_counter(), time.process_time()
    print(f"load average at start {os.getloadavg()[0]:.1f} ({os.cpu_count()} cores)")
    if "sweep" in args.stages or "scaling" in args.stages:
        if "sweep" in args.stages:
            records, spec, mags = sweeps(folder, args.cases, args.sweep_scale, rng, args.reuse)
            power(records, spec, mags, folder, rng, args.campaigns)
        else:
            mags, _ = _choose_magnitudes(folder, args.sweep_scale, rng)
        if "scaling" in args.stages:
            scaling(folder, mags, args.sweep_scale, args.scaling_cases)
    if "poses" in args.stages:
        poses(args.pose_scale, rng, args.random_subsets, folder)
    if "order" in args.stages:
        order(args.order_scale, range(1, args.order_seeds + 1))
    if "budget" in args.stages:
        budget(args.budget_scale, rng)
    if "budget-mc" in args.stages:
        budget_mc(args.budget_mc_scale, args.budget_campaigns)
    print(f"\ntotal {time.perf_counter() - t0:.0f} s wall, {time.process_time() - c0:.0f} CPU s "
          f"in this process; load average at the end {os.getloadavg()[0]:.1f}; results in "
          f"{folder}")


if __name__ == "__main__":
    main()
