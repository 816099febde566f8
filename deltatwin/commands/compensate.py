"""``deltatwin compensate SCENARIO --model MODEL``: command the scenario's robot through a fitted
model and measure what it achieves, as the papers' controller did.

The same robot as the scenario's (its seed: the same geometry errors), at a later time than its
calibration campaign (new temperatures; for a force scenario new, continuous force levels), goes
to N Cartesian targets inside the workspace (nominal-model readings of motor coordinates drawn
in 80 % of the stroke). Each target is visited twice in a row: commanded by the nominal
kinematics (uncompensated), then by the model's inverse fed with the conditions read at that
moment (the temperature scan, the coil currents). The interferometers, zeroed at home at the
session's start, measure what is achieved. Runs through the instrument interface (the twin's
simulated instruments, or the serial drivers on a ports file's laboratory), journaled and
resumable like ``deltatwin campaign``. Reports per axis the achieved error (90th percentile of
|reading - target| and 1.645 sigma), the uncompensated one, and the model's validation figure on
its calibration data (``--data``; a physics model names its own): the model's error at a target
minus its error at the zero, two draws of its validation error (calibration.compensation).
"""
from __future__ import annotations

import hashlib
import sys
import time
from pathlib import Path

from deltatwin.commands.trust import add_trust_option, trust_of

TARGET_STROKE_FRACTION = 0.8   # targets: nominal readings of q drawn in this share of the stroke
# the session zero as the mean of this many home settles (twin.campaign.zero_offset): the zero
# is one more draw of every error a point has, shared by the whole session; 10 makes its
# random part (servo settling, reading noise) 1/sqrt(10) of a point's, adding 5 % to the
# achieved scatter in quadrature, for ~70 s at home, a fraction of the controller's 600 s fill
ZERO_SETTLES = 10
WITHIN = 1.2                   # the target: achieved within 1.2x the validation prediction


def register(sub) -> None:
    p = sub.add_parser("compensate", help="command the robot through a fitted model and measure "
                                          "the accuracy it achieves (journaled, resumable)",
                       description=__doc__.split("\n\n")[1])
    p.add_argument("scenario", help="scenario TOML path or name in scenarios/ (the robot the "
                                    "model was calibrated on)")
    p.add_argument("--model", type=Path, required=True,
                   help="fitted model: physics (TOML of `deltatwin fit -o`) or black-box (JSON "
                        "of `deltatwin calibrate -o`: DGM or direct IGM)")
    p.add_argument("--targets", type=int, default=50, help="number of Cartesian targets")
    p.add_argument("--seed", type=int, default=None,
                   help="seed of the session: its targets, force levels and (sim) its own "
                        "servo settles and reading windows (default: the scenario's); the "
                        "robot is always the scenario's")
    p.add_argument("--zero-settles", type=int, default=ZERO_SETTLES, metavar="N",
                   help="the session zero as the mean of N home settles (move away and back "
                        f"home, read; default {ZERO_SETTLES}); 1: the papers' single zero")
    p.add_argument("--instruments", choices=("sim", "serial"), default="sim",
                   help="sim: the scenario's twin as simulated instruments (default); serial: "
                        "the drivers on the ports file's laboratory")
    p.add_argument("--ports", type=Path, default=None,
                   help="ports file (TOML) for --instruments serial")
    p.add_argument("--data", type=Path, default=None,
                   help="the model's calibration dataset: its validation figures are the "
                        "prediction, its ranges the calibration range (default: the one a "
                        "physics model names)")
    p.add_argument("--after-h", type=float, default=2.0,
                   help="hours after the end of the calibration campaign (sim; default 2)")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--reduced", action="store_true",
                   help="the calibration campaign was the scenario's reduced scale")
    g.add_argument("--scale", type=float, default=None,
                   help="the calibration campaign's scale, 0 < SCALE <= 1 (sets when it ended)")
    p.add_argument("-o", "--output", type=Path, default=None,
                   help="dataset of the compensated campaign (Parquet, or CSV by suffix; "
                        "default SCENARIO-compensated.parquet)")
    p.add_argument("--journal", type=Path, default=None, help="default: OUTPUT.journal")
    p.add_argument("--resume", action="store_true",
                   help="continue the compensated campaign of the existing journal")
    p.add_argument("--view", type=Path, default=None, metavar="RUN.rrd",
                   help="also write a Rerun recording of the achieved error fields "
                        "(uncompensated, then compensated: target minus reading per target)")
    p.add_argument("--controller", type=Path, default=None, metavar="FILE.json",
                   help="also write a physics model as the file a real-time controller loads "
                        "(documented JSON; calibration/physics/controller_evaluator.py, numpy "
                        "only, evaluates and inverts it; beside it FILE.bin, the same model "
                        "for the portable C evaluator; docs/compensation.md)")
    p.add_argument("--json", action="store_true", help="print the report as one JSON line")
    add_trust_option(p)
    p.set_defaults(func=run)


def compensation_plan(sc, rng, n_targets: int, nominal, axes):
    """(plan, modes, targets (2N, 3) m): each target twice in a row, nominal then model; for a
    force scenario a force level drawn uniformly up to the campaign's largest."""
    import numpy as np

    from deltatwin.calibration.compensation import ConditionLog
    from deltatwin.twin.campaign import Plan

    lo, hi = sc.params.stroke_rad
    q = rng.uniform(TARGET_STROKE_FRACTION * lo, TARGET_STROKE_FRACTION * hi, (n_targets, 3))
    log = ConditionLog(())
    log.zero(0.0, [])
    targets = nominal.forward(q, log.frame())
    force = sc.campaign["kind"] == "force"
    if force:
        F = rng.uniform(0.0, max(sc.campaign.get("forces_N", [2.0])), n_targets)
        per_A = float(sc.campaign.get("force_per_A", 1.0))
    else:
        F, per_A = np.zeros(n_targets), 1.0
    rep = np.repeat(np.arange(n_targets), 2)
    n = rep.size
    plan = Plan(sessions=(("compensation", tuple(axes)),), session=np.zeros(n, int),
                pos_id=rep, split=np.full(n, "val"), q=np.zeros((n, 3)),
                currents_A=np.repeat((F / per_A)[rep, None], 3, axis=1), F_N=F[rep],
                readings=int(sc.campaign.get("readings", 1)) if force else 1)
    return plan, ["nominal", "model"] * n_targets, targets[rep], per_A


def compensation_world(sc, scale, after_h: float, plan, seed: int, lab=None):
    """(twin, simulated lab) of the scenario's robot and laboratory, the lab's clock set
    ``after_h`` hours after the end of the calibration campaign at ``scale`` (the twin's horizon
    covers the compensated campaign ``plan`` from there). The session's settles and reading
    windows are its own draws, from its ``seed`` and start time (``twin.world.random_streams``):
    counted from the world's start with the robot's seed, every session's zero would sit on the
    same servo settle as the calibration campaign's. ``lab``: the scenario whose laboratory
    settings run ``plan`` (default ``sc``; e.g. the same with a longer time per point)."""
    from deltatwin.twin.instruments.simulated import SimulatedLab
    from deltatwin.twin.world import Twin

    _, cal_plan = sc.build(scale)
    start_s = sc.horizon_s(cal_plan) + after_h * 3600.0
    lab = sc if lab is None else lab
    twin = Twin(sc.params, sc.effects, sc.sensors, sc.seed, start_s + lab.horizon_s(plan),
                sc.campaign.get("warmup_s", 7200.0), session=(seed, round(start_s * 1e3)))
    simulated = SimulatedLab(twin, lab.settings)
    simulated.t = start_s
    return twin, simulated


def _check_robot(instruments, sc) -> None:
    """An emulated laboratory says on its clock port which world it simulates: refuse another
    scenario or seed (another robot: the model was not calibrated on it). Its scale is not
    compared: a compensated campaign is not the calibration campaign."""
    world = instruments.clock.world() if hasattr(instruments.clock, "world") else {}
    ours = {k: v for k, v in sc.identity(None).items() if k != "scale"}
    differ = [f"{k}: emulator {world.get(k)!r}, here {v!r}" for k, v in ours.items()
              if world and world.get(k) != v]
    if differ:
        raise ValueError("the emulated laboratory simulates another robot (" + "; ".join(differ)
                         + "): start `deltatwin emulate` with this scenario and its seed")


def _ranges(cal_df, records, sensors) -> dict:
    """Conditions of the compensation decisions outside the calibration data's range."""
    import numpy as np

    out = {}
    if cal_df is None:
        return out
    T = np.array([r["T_C"] for r in records], dtype=np.float64)
    for j, s in enumerate(sensors):
        c = f"T_{s}_C"
        if c not in cal_df:
            continue
        lo, hi = float(cal_df[c].min()), float(cal_df[c].max())
        a, b = float(T[:, j].min()), float(T[:, j].max())
        if a < lo or b > hi:
            out[c] = {"calibration": [lo, hi], "compensation": [a, b],
                      "beyond_K": round(max(lo - a, b - hi, 0.0), 4)}
    if "F_N" in cal_df:
        F = np.array([r["force_N"] for r in records])
        lo, hi = float(cal_df["F_N"].min()), float(cal_df["F_N"].max())
        if F.min() < lo or F.max() > hi:
            out["F_N"] = {"calibration": [lo, hi], "compensation": [float(F.min()),
                                                                     float(F.max())]}
    return out


def _axis_record(achieved: dict, uncompensated: dict, predicted: dict | None,
                 band: tuple | None) -> dict:
    """One axis of the report (nm): the achieved and uncompensated figures, the prediction from
    the model's calibration data (``Compensator.predicted``) and, for a physics model with its
    covariance, the achieved error's 95 % band (``PhysicsCompensator.band``) and whether the
    achieved error lies in it."""
    rec = {"achieved_err90_nm": achieved["err_p90"],
           "achieved_1645sigma_nm": achieved["err_1645sigma"],
           "achieved_mean_nm": achieved["mean"],
           "uncompensated_err90_nm": uncompensated.get("err_p90"),
           "uncompensated_1645sigma_nm": uncompensated.get("err_1645sigma"),
           "predicted_err90_nm": None, "predicted_1645sigma_nm": None}
    if predicted and predicted["err_p90"]:
        rec["predicted_err90_nm"] = predicted["err_p90"]
        rec["predicted_1645sigma_nm"] = predicted["err_1645sigma"]
        rec["achieved_over_predicted"] = achieved["err_p90"] / predicted["err_p90"]
        rec[f"within_{WITHIN:g}x"] = bool(rec["achieved_over_predicted"] <= WITHIN)
        # the validation as its fit reports it (a constant fitted per session) and
        # referenced to the calibration session's own zero (calibration.compensation)
        rec["predicted_offset_fitted_err90_nm"] = predicted["fitted_err_p90"]
        rec["predicted_offset_fitted_1645sigma_nm"] = predicted["fitted_err_1645sigma"]
        rec["predicted_zero_referenced_err90_nm"] = predicted.get("zero_err_p90")
        rec["predicted_zero_referenced_1645sigma_nm"] = predicted.get("zero_err_1645sigma")
    if band is not None:
        rec["predicted_band_err90_nm"] = list(band)
        rec["within_band"] = bool(band[0] <= achieved["err_p90"] <= band[1])
    return rec


def run(args) -> int:
    import numpy as np

    from deltatwin.calibration.compensation import (
        LoopController,
        NominalCompensator,
        achieved_figures,
        load_compensator,
    )
    from deltatwin.commands.campaign import EXIT_INSTRUMENT_FAULT, resumed_wall_clock_s
    from deltatwin.commands.output import strict_json
    from deltatwin.files import check_writable
    from deltatwin.twin.campaign import run_campaign
    from deltatwin.twin.dataset import check_dataset_path, read_dataset, write_dataset
    from deltatwin.twin.instruments.interface import InstrumentError
    from deltatwin.twin.instruments.optics import AXES
    from deltatwin.twin.journal import Journal
    from deltatwin.twin.lab_setup import model_overrides
    from deltatwin.twin.scenario import Scenario, check_scale

    if args.targets < 1:
        raise ValueError(f"--targets must be >= 1, got {args.targets}")
    if args.zero_settles < 1:
        raise ValueError(f"--zero-settles must be >= 1, got {args.zero_settles}")
    if args.instruments == "serial" and args.ports is None:
        raise ValueError("--instruments serial needs --ports FILE")
    if args.instruments == "sim" and args.ports is not None:
        raise ValueError("--ports is only for --instruments serial")
    check_scale(args.scale, "--scale")
    if args.output is not None:
        check_dataset_path(args.output, "-o")
    if not args.after_h >= 0:
        raise ValueError(f"--after-h must be >= 0 hours, got {args.after_h}")
    if args.view is not None:
        check_writable(args.view)
    if args.controller is not None:
        check_writable(args.controller)
    from deltatwin.twin.journal import journal_path as journal_file

    t0 = time.perf_counter()
    sc = Scenario.load(args.scenario, trust_effects=trust_of(args))
    comp = load_compensator(args.model, trust_of(args))
    if args.controller is not None:
        if comp.kind != "physics":
            raise ValueError(f"--controller: {args.model} is a {comp.kind} model; its JSON is "
                             "already what a controller loads (docs/calibration.md); "
                             "--controller exports a physics model (TOML)")
        from deltatwin.calibration.physics.export import write_controller_model
        write_controller_model(comp.model, args.controller, comp.sensors, args.model)
    nominal = NominalCompensator(sc.params)
    data = args.data or (Path(comp.calibration_data) if comp.calibration_data else None)
    if data is not None and not data.exists():
        if args.data is not None:
            raise FileNotFoundError(f"--data {data}: no such dataset")
        data = None
    cal_df, cal_meta = read_dataset(data) if data is not None else (None, None)
    if comp.kind == "physics" and cal_meta is not None:
        # the model commands with the constants it was fitted with: said where they are not
        # the calibration data's setup
        for line in model_overrides(comp.model.effects, {}, cal_meta, str(data)):
            print(f"{args.model}: {line}", file=sys.stderr)
    output = args.output or Path(f"{sc.name}-compensated.parquet")
    journal_path = journal_file(output, args.journal, args.resume)
    if args.instruments == "serial":
        from deltatwin.hw.ports import load_ports
        ports = load_ports(args.ports)

    seed = sc.seed if args.seed is None else args.seed
    rng = np.random.default_rng(seed)
    axes = AXES
    plan, modes, targets, per_A = compensation_plan(sc, rng, args.targets, nominal, axes)
    scale = sc.reduced_scale if args.reduced else args.scale
    model_sha = hashlib.sha256(args.model.read_bytes()).hexdigest()
    header = {"command": "compensate", "scenario": sc.name,
              "scenario_sha256": hashlib.sha256(sc.text.encode()).hexdigest(),
              "robot_seed": sc.seed, "seed": seed, "targets": args.targets,
              "model_sha256": model_sha, "after_h": args.after_h,
              "zero_settles": args.zero_settles,
              "calibration_scale": 1.0 if scale is None else float(scale),
              "instruments": args.instruments, "points": len(plan)}
    controller = LoopController({"nominal": nominal, "model": comp}, modes, targets, (), per_A,
                                scan_period_s=sc.settings.scan_period_s)
    if args.instruments == "sim":
        twin, lab = compensation_world(sc, scale, args.after_h, plan, seed)
        instruments = lab.instrument_set()
        described = {"kind": "sim", "world": "the scenario's twin (simulated instruments)",
                     "start_s": lab.t}
    else:
        from deltatwin.hw.lab import open_lab
        instruments = open_lab(ports, wall_clock_start_s=resumed_wall_clock_s(journal_path))
        described = {"kind": "serial", "ports_file": str(args.ports), "lab": ports.lab}
    try:
        if args.instruments == "serial":
            # before the journal exists: a wrong port or another robot's emulator is reported
            # and leaves nothing behind that blocks a rerun
            try:
                instruments.connect()
                _check_robot(instruments, sc)
            except InstrumentError as exc:
                print(f"deltatwin compensate: cannot start: {exc}\n  nothing was measured; "
                      "fix the cause and run the same command again", file=sys.stderr)
                return EXIT_INSTRUMENT_FAULT
        controller.log.sensors = tuple(instruments.thermometers.sensors)
        with Journal.open(journal_path, header) as journal:
            before = len(journal.done())
            try:
                df = run_campaign(plan, instruments, sc.settings, sc.cosine, sc.dead_path(),
                                  progress=not args.quiet, journal=journal,
                                  replay=args.instruments == "sim", controller=controller,
                                  zero_settles=args.zero_settles)
            except InstrumentError as exc:
                done = len(journal.done())
                print(f"deltatwin compensate: stopped by an instrument fault at point {done} "
                      f"of {len(plan)}: {exc}\n  {done} point(s) are safe in the journal "
                      f"{journal_path}; fix the cause and run the same command with --resume",
                      file=sys.stderr)
                return EXIT_INSTRUMENT_FAULT
            points = journal.points()
    finally:
        instruments.close()
    records = [points[k]["control"] for k in range(len(plan))]
    df["command"] = modes
    df["status"] = [r["status"] for r in records]
    err = np.full((len(df), 3), np.nan)
    for k, a in enumerate(AXES):
        df[f"target_{a}_nm"] = targets[:, k] * 1e9
        if f"{a}_nm" in df:
            err[:, k] = (df[f"{a}_nm"].to_numpy() - df[f"target_{a}_nm"].to_numpy()) * 1e-9
            df[f"error_{a}_nm"] = err[:, k] * 1e9
    is_model = np.array(modes) == "model"
    ok = df["status"].to_numpy() == "converged"
    achieved = achieved_figures(err, is_model & ok)
    uncompensated = achieved_figures(err, ~is_model & ok)
    predicted = comp.predicted(cal_df, cal_meta) if cal_df is not None else None
    zero_t_s = np.array([points[k]["zero_t_s"] for k in range(len(plan))], dtype=float)
    band = (comp.band(df, is_model & ok, zero_t_s, cal_df, cal_meta,
                      np.random.default_rng(seed), args.zero_settles)
            if cal_df is not None and (is_model & ok).any() else {})
    report_axes = {a: _axis_record(achieved[a], uncompensated.get(a, {}),
                                   (predicted or {}).get(a), band.get(a))
                   for a in AXES if a in achieved}
    model_records = [r for r, m in zip(records, modes) if m == "model"]
    not_conv = [{"target": int(plan.pos_id[k]), "status": r["status"], "reason": r["reason"]}
                for k, (r, m) in enumerate(zip(records, modes)) if r["status"] != "converged"]
    latency = {m: {"median_ms": float(np.median(v)) * 1e3, "max_ms": float(np.max(v)) * 1e3,
                   "n": len(v)} for m, v in controller.latency_s.items() if v}
    report = {"model": {"path": str(args.model), "kind": comp.kind, "sha256": model_sha},
              "scenario": sc.name, "instruments": args.instruments, "targets": args.targets,
              "seed": seed, "zero_settles": args.zero_settles, "axes": report_axes,
              "not_converged": not_conv[:20], "n_not_converged": len(not_conv),
              "prediction_from": str(data) if data is not None else None,
              "outside_calibration_range": _ranges(cal_df, model_records,
                                                   controller.log.sensors),
              "decision_latency": latency,
              "force_N": [float(min(r["force_N"] for r in records)),
                          float(max(r["force_N"] for r in records))],
              "output": str(output), "journal": str(journal_path) + " (kept)",
              "controller_file": str(args.controller) if args.controller else None,
              "resumed_with": before, "seconds": round(time.perf_counter() - t0, 2)}
    meta = sc.metadata(twin, scale) if args.instruments == "sim" else {"source": "lab",
                                                                        "scenario": sc.name}
    meta["source"] = "twin" if args.instruments == "sim" else "lab"
    meta["instruments"] = {**meta.get("instruments", {}), **described}
    meta["compensation"] = {k: v for k, v in report.items() if k not in ("output", "seconds")}
    write_dataset(df, meta, output)
    if args.view is not None:
        from deltatwin.view import LadderStep, write_recording
        target_m = targets.copy()
        steps = [LadderStep(name, np.where((np.array(modes) == mode)[:, None], target_m, np.nan))
                 for name, mode in (("uncompensated", "nominal"), (comp.kind, "model"))]
        write_recording(df, meta, steps, args.view, params=sc.params)
        report["view"] = str(args.view)
    if args.json:
        print(strict_json(report))
    else:
        print(f"compensated campaign: {sc.name}, model {args.model} ({comp.kind}), "
              f"{args.targets} targets, {len(not_conv)} not converged")
        print(f"{'axis':>4} {'achieved err90':>15} {'1.645 sigma':>12} {'uncompensated':>14} "
              f"{'predicted':>12} {'offset-fitted':>14}" + ("  95 % band" if band else ""))
        fmt = lambda v: f"{v:10.1f}" if v is not None else f"{'-':>10}"
        for a, r in report_axes.items():
            b = r.get("predicted_band_err90_nm")
            print(f"{a:>4} {fmt(r['achieved_err90_nm'])} nm {fmt(r['achieved_1645sigma_nm'])} "
                  f"{fmt(r['uncompensated_err90_nm'])} nm {fmt(r['predicted_err90_nm'])} nm "
                  f"{fmt(r.get('predicted_offset_fitted_err90_nm'))} nm"
                  + (f"  {b[0]:.1f}-{b[1]:.1f} nm{'' if r['within_band'] else ' (outside)'}"
                     if b else ""))
        if band:
            print("  (95 % band: where the achieved error 90 % falls if the model is right: "
                  "its parameters' uncertainty through the model in the conditions each target "
                  "was commanded in, and its own validation errors' differences as far apart "
                  "in time as each target from its zero)")
        if report["outside_calibration_range"]:
            print("conditions outside the calibration range: "
                  + ", ".join(report["outside_calibration_range"]))
        print(f"dataset: {output}")
        if args.controller is not None:
            print(f"controller file: {args.controller}")
    return 0
