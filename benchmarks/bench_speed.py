"""Speed of the loop a researcher feels, in one run, each figure beside its target:

0. the loop at full scale: ``fit`` of paper-thermal (28,492 rows) with the seven model effects
   below and the laboratory's known frame arm (docs/twin.md), against 5 s, and ``diagnose`` of
   the fitted model as ``deltatwin diagnose`` runs it (the fitted values kept when converged on
   the data: one Jacobian, then the candidates), against 3 s; beside them their floors: the fit's
   a Gauss-Newton of 3 steps at 3 evaluations each (9 evaluations), the diagnosis' one Jacobian;
   then ``deltatwin diagnose`` of the model ``deltatwin fit`` wrote, as a whole process (its
   wall time against the 3 s; the CPU time counts its second process, models.batched);
1. one physics-model evaluation (``PhysicsModel.predict_path``) at full scale: paper-thermal,
   28,492 rows, the seven model effects (geometric_errors thermal_expansion gravity_sag
   magnetic_force loop_drift air_refraction beam_misalignment), against 0.07 s;
2. how ``simulate``, ``fit`` and ``diagnose`` (of the fitted model) scale with the rows: the
   exponent of time ~ rows^k from three campaign sizes (least squares on the logarithms); near
   1 is linear, a rise shows a regression.  On quiet/thermal-and-loop with its true model
   (geometric_errors thermal_expansion loop_drift, 70 parameters), a fit that converges at
   every size (the seven effects on a reduced paper-thermal stop at the fit's iteration limit:
   a fit property, not a speed one);
3. how ``fit`` scales with the free parameters: three effect sets on one campaign size;
4. two commands side by side: ``deltatwin fit`` and ``deltatwin calibrate`` each run alone,
   then two copies at once, with the threads set once at start (deltatwin/threads.py, as the
   command line does) and, for comparison, with the libraries' defaults (BLAS on every core);
   the slowdown is the pair's time over the lone run's, minus one (target <= 15 %), in CPU time
   per process (user + system of each child, os.wait4: what the pair costs each other through
   the shared caches and memory, whatever else loads the machine) and in wall time;
5. ``deltatwin demo`` as a whole process (imports, simulate, the floor's and the ladder's fits,
   the diagnoses, the report and the recording), its CPU time against 6 s.

Wall times are medians of the repeats (``time.perf_counter``); CPU times (``process_time``)
beside them, and the load average before each part, because the machine is shared: a wall
time far above its CPU time says other processes took the cores.  With one thread (the
default, docs/performance.md) the CPU time is what the wall time is on an idle machine, so
the exponents are fitted to it.  Run:

    python benchmarks/bench_speed.py            # full: ~5-10 min on this 2-core machine
    python benchmarks/bench_speed.py --quick    # smaller campaigns, one repeat (~2 min)
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

SEVEN = ("geometric_errors", "thermal_expansion", "gravity_sag", "magnetic_force", "loop_drift",
         "air_refraction", "beam_misalignment")
SCALING_SCENARIO = "quiet/thermal-and-loop"
SCALING_EFFECTS = ("geometric_errors", "thermal_expansion", "loop_drift")
EVALUATION_TARGET_S = 0.07
FIT_TARGET_S, DIAGNOSE_TARGET_S, DEMO_TARGET_S = 5.0, 3.0, 6.0
# paper-thermal's robot hangs from an arm of its frame: a known constant of the laboratory
FRAME_ARM = {"loop_drift": {"frame_arm_m": [-0.6, 0.0]}}
SIDE_BY_SIDE_TARGET = 0.15
# a child process as `deltatwin` runs it, the threads set once at start
CLI_WITH_THREADS = ("import sys; from deltatwin.threads import set_threads; set_threads(); "
                    "from deltatwin.cli import main; sys.exit(main(sys.argv[1:]))")
CLI_DEFAULTS = "import sys; from deltatwin.cli import main; sys.exit(main(sys.argv[1:]))"


def load() -> str:
    return f"load average {os.getloadavg()[0]:.1f}" if hasattr(os, "getloadavg") else ""


def children_cpu() -> float:
    """CPU time (user + system, s) of this process' finished children: a diagnosis' attribution
    runs in one (models.batched.in_background), and its time is the diagnosis' too."""
    import resource
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def timed(fun, repeats: int):
    """(median wall s, median CPU s of this process and the children it waited for, last
    result) of ``repeats`` calls."""
    wall, cpu, out = [], [], None
    for _ in range(repeats):
        c0, t0 = time.process_time() + children_cpu(), time.perf_counter()
        out = fun()
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() + children_cpu() - c0)
    return float(np.median(wall)), float(np.median(cpu)), out


def exponent(sizes, seconds) -> float:
    """k of seconds ~ sizes^k, least squares on the logarithms."""
    return float(np.polyfit(np.log(sizes), np.log(seconds), 1)[0])


def full_loop(df, meta, repeats: int) -> None:
    from deltatwin.calibration.diagnosis.diagnose import diagnose
    from deltatwin.calibration.physics.fit import PhysicsFit
    from deltatwin.calibration.physics.measurements import measurements
    from deltatwin.calibration.physics.model import PhysicsModel

    print(f"0. the loop at full scale ({len(df):,} rows, {', '.join(SEVEN)})   [{load()}]")
    w_fit, c_fit, fit = timed(lambda: PhysicsFit(list(SEVEN), start=FRAME_ARM).fit(df, meta),
                              repeats)

    def diagnose_fitted():
        kept = PhysicsFit(list(SEVEN), start=fit.model_.values()).fit(
            df, meta, keep_converged_start=True, start_directions=fit.identified_directions_,
            fitted_on=fit.data_sha256_)         # as `deltatwin diagnose` does from the file
        c0 = time.process_time() + children_cpu()
        return kept, diagnose(kept), time.process_time() + children_cpu() - c0
    w_diag, c_diag, (kept, diagnosis, c_diagnosis) = timed(diagnose_fitted, repeats)
    model = PhysicsModel(SEVEN, values=fit.model_.values())
    meas = measurements(df, meta, model.params)
    _, c_eval, _ = timed(lambda: model.predict_path(meas, fit.theta_), 3)
    _, c_jac, _ = timed(lambda: model.jacobian(meas, fit.theta_), 1)
    for name, wall, cpu, floor, target, note in (
            ("fit", w_fit, c_fit, 9 * c_eval, FIT_TARGET_S,
             f"{fit.status_[:40]}, {fit.n_jacobians_} Jacobians, {fit.n_evaluations_} model "
             "evaluations in all"),
            ("diagnose", w_diag, c_diag, c_jac, DIAGNOSE_TARGET_S,
             f"model {kept.solver_message_[:40]}; the diagnosis itself {c_diagnosis:.2f} s "
             f"CPU; missing {diagnosis['missing_effect']}")):
        print(f"   {name:<8} {wall:6.2f} s wall, CPU {cpu:6.2f} s, target <= {target} s: ratio "
              f"{cpu / target:4.2f} (CPU) {'MET' if cpu <= target else 'NOT MET'}; floor "
              f"{floor:5.2f} s CPU, ratio {cpu / floor:5.1f}  ({note})")
    print(f"   one Jacobian {c_jac:.2f} s CPU ({c_jac / c_eval:.0f} evaluations' worth, "
          f"{model.n_free} parameters), one evaluation {c_eval:.3f} s CPU")


def cli_diagnose(data: Path, repeats: int) -> None:
    """``deltatwin diagnose`` of the model ``deltatwin fit`` wrote, as a researcher runs it
    (whole process: imports, reading, the kept model's Jacobian, the diagnosis; the attribution,
    and the candidates' Jacobians, in second processes where there are two cores), against the
    3 s target in wall time."""
    model = data.with_name("seven-effects.toml")
    known = ",".join(str(x) for x in FRAME_ARM["loop_drift"]["frame_arm_m"])
    _run_children([["fit", str(data), "--effects", ",".join(SEVEN), "--set",
                    f"loop_drift.frame_arm_m={known}", "-o", str(model), "-q"]], True)
    runs = [_run_children([["diagnose", str(data), "--model", str(model), "--json", "-q"]], True)
            for _ in range(repeats)]
    wall, cpu = np.median(runs, axis=0)
    print(f"   deltatwin diagnose (whole process, {data.name}): {wall:.2f} s wall, target <= "
          f"{DIAGNOSE_TARGET_S} s: ratio {wall / DIAGNOSE_TARGET_S:.2f} "
          f"{'MET' if wall <= DIAGNOSE_TARGET_S else 'NOT MET'}; CPU {cpu:.2f} s with its "
          f"second process   [{load()}]")


def evaluation(df, meta, repeats: int) -> None:
    from deltatwin.calibration.physics.measurements import measurements
    from deltatwin.calibration.physics.model import PhysicsModel
    from deltatwin.models.params import load_params

    params = load_params(None)
    meas = measurements(df, meta, params)
    model = PhysicsModel(SEVEN, params)
    theta = model.theta() + np.random.default_rng(0).normal(size=model.n_free) * model.scales
    model.predict_path(meas, theta)                                  # warm-up: statics, caches
    wall, cpu, _ = timed(lambda: model.predict_path(meas, theta), max(repeats, 5))
    print(f"1. one model evaluation, {meas.n:,} rows, {model.n_free} parameters: "
          f"{wall:.3f} s wall (CPU {cpu:.3f} s), target <= {EVALUATION_TARGET_S} s: "
          f"ratio {wall / EVALUATION_TARGET_S:.2f}, "
          f"{'MET' if wall <= EVALUATION_TARGET_S else 'NOT MET'}   [{load()}]")


def scaling_with_rows(scales, repeats: int) -> None:
    from deltatwin.calibration.diagnosis.diagnose import diagnose
    from deltatwin.calibration.physics.fit import PhysicsFit
    from deltatwin.twin.scenario import Scenario

    sc = Scenario.load(SCALING_SCENARIO)
    rows, cpu = [], {"simulate": [], "fit": [], "diagnose": []}
    print(f"2. scaling with rows ({SCALING_SCENARIO}, fit and diagnose with "
          f"{', '.join(SCALING_EFFECTS)}): seconds wall / CPU   [{load()}]")
    print(f"   {'rows':>7} {'simulate':>13} {'fit':>13} {'diagnose':>13}")
    for s in scales:
        w_sim, c_sim, (df, meta) = timed(lambda s=s: sc.simulate(s), repeats)
        w_fit, c_fit, fit = timed(lambda df=df, meta=meta: PhysicsFit(list(SCALING_EFFECTS)).fit(
            df, meta), repeats)
        w_diag, c_diag, _ = timed(lambda fit=fit: diagnose(fit), repeats)
        rows.append(len(df))
        for name, c in (("simulate", c_sim), ("fit", c_fit), ("diagnose", c_diag)):
            cpu[name].append(c)
        print(f"   {len(df):7d} {w_sim:6.2f} /{c_sim:6.2f} {w_fit:6.2f} /{c_fit:6.2f} "
              f"{w_diag:6.2f} /{c_diag:6.2f}")
    print("   exponent (CPU time ~ rows^k): "
          + ", ".join(f"{name} {exponent(rows, c):.2f}" for name, c in cpu.items()))


def scaling_with_parameters(scale: float, repeats: int) -> None:
    from deltatwin.calibration.physics.fit import PhysicsFit
    from deltatwin.calibration.physics.model import PhysicsModel
    from deltatwin.twin.scenario import Scenario

    df, meta = Scenario.load(SCALING_SCENARIO).simulate(scale)
    sets = [("thermal_expansion", "loop_drift"),
            ("thermal_expansion", "loop_drift", "beam_misalignment", "air_refraction"),
            SCALING_EFFECTS + ("beam_misalignment", "air_refraction")]
    sizes, seconds = [], []
    print(f"3. fit scaling with parameters ({SCALING_SCENARIO}, {len(df):,} rows): seconds "
          f"wall / CPU   [{load()}]")
    for effects in sets:
        wall, cpu, _ = timed(lambda e=effects: PhysicsFit(list(e)).fit(df, meta), repeats)
        sizes.append(PhysicsModel(list(effects)).n_free)
        seconds.append(cpu)
        print(f"   {sizes[-1]:4d} parameters: {wall:6.2f} / {cpu:6.2f}  ({', '.join(effects)})")
    print(f"   exponent (CPU time ~ parameters^k): {exponent(sizes, seconds):.2f}")


def demo(repeats: int) -> None:
    """``deltatwin demo`` as a researcher runs it (whole process: imports, simulate, fits,
    diagnoses, report and recording), CPU time of the child."""
    with tempfile.TemporaryDirectory() as tmp:
        runs = [_run_children([["demo", "--out", tmp, "--json", "-q"]], True)
                for _ in range(repeats)]
    wall, cpu = np.median(runs, axis=0)
    print(f"5. deltatwin demo (whole process): CPU {cpu:.2f} s (wall {wall:.2f} s), target <= "
          f"{DEMO_TARGET_S} s: ratio {cpu / DEMO_TARGET_S:.2f} (CPU) "
          f"{'MET' if cpu <= DEMO_TARGET_S else 'NOT MET'}   [{load()}]")


def _run_children(argv_list, threads_set: bool) -> tuple[float, float]:
    """Wall time (s) of running the commands in ``argv_list`` at once, and the median CPU time
    (user + system, s) of one of them."""
    code = CLI_WITH_THREADS if threads_set else CLI_DEFAULTS
    env = {k: v for k, v in os.environ.items()
           if k not in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")}
    t0 = time.perf_counter()
    procs = [subprocess.Popen([sys.executable, "-c", code, *argv], stdout=subprocess.DEVNULL,
                              stderr=subprocess.DEVNULL, env=env) for argv in argv_list]
    cpu, codes = [], []
    for p in procs:
        _, status, usage = os.wait4(p.pid, 0)
        codes.append(os.waitstatus_to_exitcode(status))
        cpu.append(usage.ru_utime + usage.ru_stime)
    if any(codes):
        raise RuntimeError(f"a child command failed (exit codes {codes}): {argv_list[0]}")
    return time.perf_counter() - t0, float(np.median(cpu))


def side_by_side(data: Path, repeats: int) -> None:
    commands = {"fit": ["fit", str(data), "--effects", "thermal_expansion,loop_drift", "-q"],
                "calibrate": ["calibrate", "--features", "thermal", str(data), "-q"]}
    print(f"4. two commands side by side (each alone, then two at once), {data.name}   "
          f"[{load()}]")
    for threads_set, label in ((True, "threads set once (1)"), (False, "library defaults")):
        for name, argv in commands.items():
            alone, pair = [], []
            for _ in range(repeats):              # alternate, so that drift hits both alike
                alone.append(_run_children([argv], threads_set))
                pair.append(_run_children([argv, argv], threads_set))
            (wall1, cpu1), (wall2, cpu2) = (np.median(x, axis=0) for x in (alone, pair))
            slow, slow_wall = float(cpu2 / cpu1 - 1.0), float(wall2 / wall1 - 1.0)
            verdict = ("MET" if slow <= SIDE_BY_SIDE_TARGET else "NOT MET") if threads_set else ""
            print(f"   {label:<21} {name:<9} alone CPU {cpu1:6.2f} s (wall {wall1:6.2f}), two "
                  f"at once CPU {cpu2:6.2f} s each (wall {wall2:6.2f}): slowdown CPU "
                  f"{100 * slow:5.1f} % (wall {100 * slow_wall:5.1f} %), target <= "
                  f"{100 * SIDE_BY_SIDE_TARGET:.0f} % {verdict}   [{load()}]")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="smaller campaigns, one repeat")
    ap.add_argument("--skip-side-by-side", action="store_true")
    ap.add_argument("--skip-full-loop", action="store_true")
    ap.add_argument("--only-side-by-side", action="store_true",
                    help="part 4 alone (on paper-thermal at --quick's or full scale)")
    args = ap.parse_args(argv)

    from deltatwin.threads import set_threads
    from deltatwin.twin.dataset import write_dataset
    from deltatwin.twin.scenario import Scenario

    set_threads()                                    # as the command line does
    repeats = 1 if args.quick else 3
    scales = (0.1, 0.2, 0.4) if args.quick else (0.25, 0.5, 1.0)
    df, meta = Scenario.load("paper-thermal").simulate(0.25 if args.quick else 1.0)
    with tempfile.TemporaryDirectory() as tmp:
        data = Path(tmp) / "paper-thermal.parquet"
        write_dataset(df, meta, data)
        if not args.only_side_by_side:
            if not args.skip_full_loop:
                full_loop(df, meta, 1)
                cli_diagnose(data, repeats)
            evaluation(df, meta, repeats)
            scaling_with_rows(scales, repeats)
            scaling_with_parameters(scales[0], repeats)
            demo(repeats)
        if not args.skip_side_by_side:
            side_by_side(data, 2 if args.quick else 3)
    return 0


if __name__ == "__main__":
    sys.exit(main())
