"""``deltatwin demo``: the main job on the embedded twin, end to end.

Simulate a campaign whose data hold an effect the starting model lacks (a scenario of
scenarios/quiet/, a quiet laboratory, by default; scenarios/hidden/ in the papers' conditions),
fit the starting model, show where it fails, name the missing effect, add
it, refit, and print the falling-error ladder; write the dataset, the fitted models, a report
(Markdown + PNG) and a Rerun recording into ``--out``."""
from __future__ import annotations

import sys
import time
from pathlib import Path

from deltatwin.commands.output import strict_json
from deltatwin.commands.trust import add_trust_option, trust_of

DEFAULT_SCENARIO = "quiet/magnetic-force"


def register(sub) -> None:
    p = sub.add_parser("demo", help="run the main job on the embedded twin: find a hidden effect")
    p.add_argument("--scenario", default=DEFAULT_SCENARIO,
                   help=f"a scenario with a [hidden] table (default {DEFAULT_SCENARIO})")
    p.add_argument("--scale", type=float, default=1.0,
                   help="campaign size relative to the scenario's full scale, 0 < SCALE <= 1 "
                        "(default 1)")
    p.add_argument("--seed", type=int, default=None, help="override the scenario's seed")
    p.add_argument("--out", default="deltatwin-demo", help="output folder (default deltatwin-demo)")
    p.add_argument("--json", action="store_true", help="also print one JSON object")
    p.add_argument("--no-recording", action="store_true", help="skip the Rerun recording")
    p.add_argument("--measured-budget", action="store_true",
                   help="split the floor's budget per source on the twin (one twin run and "
                        "refit of the complete model per source, as `deltatwin simulate` "
                        "records it: several times the demo's time); without it the budget is "
                        "the noise floor's share and the other instruments'")
    add_trust_option(p)
    p.set_defaults(func=run)


def run(args) -> int:
    from deltatwin.calibration.diagnosis.diagnose import effect_ladder
    from deltatwin.calibration.diagnosis.floor import budget_lines, record_achievable_floor
    from deltatwin.calibration.diagnosis.report import tried_instead_line, write_report
    from deltatwin.calibration.physics.model_file import fitted_toml
    from deltatwin.calibration.stats import AT_FLOOR
    from deltatwin.files import atomic_folder, atomic_write_text
    from deltatwin.twin.dataset import write_dataset
    from deltatwin.twin.scenario import Scenario, check_scale
    from deltatwin.view import LadderStep, write_recording

    check_scale(args.scale, "--scale")
    t0 = time.perf_counter()
    sc = Scenario.load(args.scenario, seed=args.seed, trust_effects=trust_of(args))
    if not sc.hidden:
        raise ValueError(f"{sc.path}: no [hidden] table (effects = [...], baseline = [...]); "
                         "the demo needs a scenario of scenarios/quiet/ or scenarios/hidden/")
    final = Path(args.out)
    shown = sc.file_name()

    def say(message: str) -> None:
        """The story as it unfolds: progress, so on stderr (stdout holds the results)."""
        if not args.quiet:
            print(f"[{time.perf_counter() - t0:5.1f} s] {message}", file=sys.stderr, flush=True)

    # everything is written into a temporary folder that takes --out's place once complete:
    # an interrupted or failed demo leaves no half-filled folder (the paths files and
    # messages record are the final ones)
    with atomic_folder(final) as out:
        say(f"simulating {shown} (hidden from the model: {', '.join(sc.hidden['effects'])})")
        df, meta = sc.simulate(None if args.scale == 1 else args.scale)
        data = final / "data.parquet"
        floor = meta["truth"]["noise_floor_nm"]
        scale = None if args.scale == 1 else args.scale
        if args.measured_budget:
            say("refitting the twin's complete model: the achievable floor, and once per source of "
                "it (that source alone in the twin, the others perfect): its budget")
            achievable, floor_fit = record_achievable_floor(df, meta, sc, scale)
        else:
            say("refitting the twin's complete model: the achievable floor")
            achievable, floor_fit = record_achievable_floor(df, meta)
        write_dataset(df, meta, out / data.name)
        say(f"{len(df)} rows -> {data}; noise floor (interferometers and servo settling) "
            + ", ".join(f"{k} {v:.1f}" for k, v in floor.items()) + " nm; achievable floor (the "
            "complete model, reading its conditions through the lab's other instruments) "
            + ", ".join(f"{k} {v:.1f}" for k, v in achievable.items()) + " nm")
        # the floor's fits of the complete model: the last rung's fit from the library's starting
        # values is one of them (the same problem on the same rows), not made twice
        ladder, diagnoses, fits = effect_ladder(df, meta, sc.hidden["baseline"], data=str(data),
                                                progress=say, known=sc.hidden.get("known"),
                                                made=list(floor_fit.start_fits_.values()))
        for k, (row, fit) in enumerate(zip(ladder, fits)):
            atomic_write_text(out / f"model{k}.toml", fitted_toml(fit, str(data)))
            d = diagnoses[k]
            say(f"model {k} ({', '.join(row['effects']) or 'nominal robot'}): validation error 90 % "
                f"{row['val_err90_nm']:.1f} nm")
            if k == 0:
                worst = sorted(((v, a) for a, v in row["val_err90_by_axis_nm"].items()), reverse=True)
                say(f"  where it fails: worst axis {worst[0][1]} ({worst[0][0]:.1f} nm); the residual "
                    "depends on " + (", ".join(x["variable"] for x in
                                               d["unexplained"]["depends_on"][:6]) or "nothing"))
            top = d["ranking"][:3]
            say("  diagnosis: " + "; ".join(f"{c['effect']} explains {100 * c['explained_fraction']:.0f} %"
                                            f"{' (significant)' if c['significant'] else ''}" for c in top))
            if d["missing_effect"]:
                say(f"  missing effect: {d['missing_effect']} -> {d['next_command']}")
                if d.get("refit_rejected"):
                    say("  " + d["refit_rejected"]["message"])
                    for t in d["tried_instead"]:
                        say("  " + tried_instead_line(t))
            else:
                say("  " + d["unexplained"]["message"])
        recording = None
        if not args.no_recording:
            say("writing the Rerun recording")
            steps = [LadderStep(row["model"], fit.reading_m_, tuple(row["effects"]))
                     for row, fit in zip(ladder, fits)]
            recording = final / "recording.rrd"
            write_recording(df, meta, steps, out / recording.name)
        say("writing the report: figures and tables of the ladder's models")
        report = final / write_report(out, df, meta, ladder, diagnoses, fits, sc.hidden,
                                      recording).name
        diagnosed = next((d["missing_effect"] for d in diagnoses if d["missing_effect"]), None)
        summary = {"scenario": sc.name, "scenario_file": shown, "hidden_effect": sc.hidden["effects"],
                   "diagnosed_effect": diagnosed,
                   "diagnosed_effects": [d["missing_effect"] for d in diagnoses if d["missing_effect"]],
                   # a named effect whose refit predicted validation worse (the ladder kept none)
                   "rejected_effects": [d["refit_rejected"]["effect"] for d in diagnoses
                                        if d.get("refit_rejected")],
                   "noise_floor_nm": floor, "achievable_floor_nm": achievable,
                   "floor_budget_nm": meta["truth"]["floor_budget_nm"],
                   "floor_budget_kind": ("per source" if args.measured_budget else
                                         "interferometers and the rest"),
                   "ladder": [{"model": r["model"], "effects": r["effects"],
                               "val_err90_nm": r["val_err90_nm"],
                               "at_floor": r["val_err90_nm"] <= AT_FLOOR * achievable["all"]}
                              for r in ladder],
                   "report": str(report), "recording": str(recording) if recording else None,
                   "seconds": round(time.perf_counter() - t0, 1)}
    if args.json:
        print(strict_json(summary))
        return 0
    print(f"\nladder ({shown}; hidden: {', '.join(sc.hidden['effects'])}):")
    print(f"  {'model':<28} {'val err90 nm':>13}")
    for r in ladder:
        print(f"  {r['model'] + ' (' + (', '.join(r['effects']) or 'nominal') + ')':<60.60} "
              f"{r['val_err90_nm']:10.1f}")
    print("  noise floor: " + ", ".join(f"{k} {v:.1f}" for k, v in floor.items()) + " nm "
          "(the readings' own noise: interferometers and servo settling)")
    print("  achievable floor: " + ", ".join(f"{k} {v:.1f}" for k, v in achievable.items())
          + f" nm (the twin's complete model fitted on these data from the library's starting "
          f"values and from the baseline's fit; at the floor: within "
          f"{AT_FLOOR}x). No effect added brings a model much below it: the model reads the "
          "robot's conditions through the lab's instruments, whose errors no effect can remove")
    # measured either way: the complete model's refit gives the noise floor's share and the
    # rest's; --measured-budget splits the rest per source (a twin run and refit per source)
    print("  the floor's budget, measured on the twin " + (
        "(each source alone, the complete model refitted):" if args.measured_budget else
        "(the noise floor's share and the other instruments'; --measured-budget splits it "
        "per source):"))
    for line in budget_lines(meta["truth"]["floor_budget_nm"]):
        print("  " + line)
    print(f"report: {report}" + (f"; recording: {recording}" if recording else ""))
    return 0
