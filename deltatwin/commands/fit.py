"""``deltatwin fit`` and ``deltatwin diagnose``: physics models from the effect library fitted to a
dataset, and which effect they miss (calibration/physics/fit.py,
calibration/diagnosis/diagnose.py)."""
from __future__ import annotations

import sys

from deltatwin.commands.output import strict_json
from deltatwin.commands.trust import add_trust_option, trust_of


def register(sub) -> None:
    p = sub.add_parser("fit", help="fit a physics model (library effects) to a dataset")
    p.add_argument("data", help="dataset (.parquet, or .csv with its .meta.json)")
    p.add_argument("--effects",
                   help="comma-separated library effects, e.g. geometric_errors,thermal_expansion "
                        "('none' for the nominal robot); `deltatwin effects` lists them "
                        "(default: the baseline the data's setup declares)")
    p.add_argument("--noise-nm", type=float, default=5.0,
                   help="the readings' noise (nm): directions the data determine to better than "
                        "a third of their parameters' typical size are fitted (default 5)")
    p.add_argument("--set", action="append", default=[], metavar="EFFECT.PARAM=VALUE",
                   help="a known constant of the laboratory, SI units, comma-separated for a "
                        "vector, e.g. loop_drift.frame_arm_m=-0.6,0 (repeatable; a free "
                        "parameter set this way is the fit's start). The data's setup gives "
                        "its constants already (`deltatwin setup DATA` shows them): --set "
                        "overrides one, and says so")
    p.add_argument("--max-evaluations", type=int, default=80, metavar="N",
                   help="the trial points the solver may evaluate, the start included (a "
                        "Jacobian is not counted; default 80, as the diagnosis's own fits)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("-o", "--output", help="write the fitted model (TOML) here")
    p.set_defaults(func=run_fit)
    d = sub.add_parser("diagnose", help="rank the library effects a fitted model lacks (or, for "
                       "a stepwise DGM, the feature families its residual correlates with)")
    d.add_argument("data", help="dataset (.parquet, or .csv with its .meta.json)")
    d.add_argument("--model", required=True,
                   help="fitted physics model (TOML from `deltatwin fit -o`) or stepwise DGM "
                        "(JSON from `deltatwin calibrate -o`)")
    d.add_argument("--json", action="store_true", help="print one JSON object")
    add_trust_option(d)
    d.set_defaults(func=run_diagnose)


def _effects(text: str) -> list[str]:
    names = [e.strip() for e in text.split(",") if e.strip()]
    return [] if names == ["none"] else names


def _known_values(settings: list[str]) -> dict:
    """{effect: {parameter: value}} from ``--set EFFECT.PARAM=VALUE`` options; an unknown
    effect or parameter, or a value of the wrong shape, is a FitError quoting the option as
    the user wrote it, with the valid names."""
    from deltatwin.calibration.errors import FitError

    out: dict = {}
    for item in settings:
        key, sep, text = item.partition("=")
        effect, dot, param = key.strip().partition(".")
        if not (sep and dot and effect and param and text.strip()):
            raise FitError(f"--set {item!r}: expected EFFECT.PARAM=VALUE, e.g. "
                           "loop_drift.frame_arm_m=-0.6,0")
        try:
            numbers = [float(x) for x in text.split(",")]
        except ValueError:
            raise FitError(f"--set {item!r}: {text!r} is not a number or a comma-separated "
                           "list of numbers (SI units)") from None
        value = numbers[0] if len(numbers) == 1 else numbers
        _check_setting(item, effect.strip(), param.strip(), value)
        out.setdefault(effect.strip(), {})[param.strip()] = value
    return out


def _check_setting(item: str, effect: str, param: str, value) -> None:
    """``--set item`` names a known effect and one of its parameters, with a valid value."""
    import difflib

    from deltatwin.calibration.errors import FitError
    from deltatwin.twin.effects import EffectError, effect_class, make_effect

    try:
        cls = effect_class(effect, where=f"--set {item}")
    except EffectError as exc:
        raise FitError(str(exc)) from None
    names = [p.name for p in cls.parameters]
    if param not in names:
        close = difflib.get_close_matches(param, names, n=1)
        raise FitError(f"--set {item}: effect {effect!r} has no parameter {param!r}"
                       + (f" (did you mean {close[0]!r}?)" if close else "")
                       + f"; its parameters: {names}")
    try:
        make_effect(cls, {param: value}, where=effect, check_minimum=False)
    except EffectError as exc:
        raise FitError(f"--set {item}: {str(exc).split(': ', 1)[-1]}") from None


def _model_effects(args, meta: dict) -> list[str]:
    """``--effects``, else the baseline the data's setup declares."""
    from deltatwin.twin.lab_setup import baseline_of

    if args.effects is not None:
        return _effects(args.effects)
    baseline = baseline_of(meta)
    if baseline is None:
        raise ValueError(f"{args.data}: its setup declares no baseline: name the model's "
                         "effects with --effects (`deltatwin effects` lists them)")
    return baseline


def _constants_used(fit, known: dict, setup: dict) -> dict:
    """The laboratory's constants the model used and where each came from (``known``: --set,
    else the data's ``setup``)."""
    from deltatwin.twin.lab_setup import used_constants

    constants = used_constants(fit.model_.effects, fit.known_, setup)
    return {"constants": constants,
            "constants_from": {f"{e}.{p}": "--set" if p in known.get(e, {}) else
                               "the data's setup" for e, values in constants.items()
                               for p in values}}


def run_fit(args) -> int:
    from deltatwin.calibration.physics.fit import PhysicsFit
    from deltatwin.twin.dataset import read_dataset
    from deltatwin.twin.lab_setup import known_constants, overridden

    known = _known_values(args.set)
    df, meta = read_dataset(args.data)
    setup = known_constants(meta, str(args.data))
    for key, _, value in overridden(known, setup):
        print(f"--set {key} overrides the data's setup value {value}", file=sys.stderr)
    fit = PhysicsFit(_model_effects(args, meta), start=known or None, noise_nm=args.noise_nm,
                     max_evaluations=args.max_evaluations,
                     progress=not args.json).fit(df, meta, where=str(args.data))
    if args.output:
        fit.save(args.output, data=str(args.data))
    summary = fit.summary()
    s = summary.as_dict()
    band = fit.validation_band()
    s["val_band_95_nm"] = {a: list(v) for a, v in band.items()}
    s.update(_constants_used(fit, known, setup))
    if args.json:
        print(strict_json(s))
        return 0
    ident = s["identifiability"]
    print(f"fitted {', '.join(fit.effects) or 'the nominal robot'} to {args.data}: "
          f"{ident['n_parameters']} parameters, {ident['n_identified_directions']} directions "
          f"identified (condition {ident['condition_number_identified'] or 0:.3g})")
    if s["constants"]:
        print("  the laboratory's constants: " + "; ".join(
            f"{e}.{p} = {v} ({s['constants_from'][f'{e}.{p}']})"
            for e, values in s["constants"].items() for p, v in values.items()))
    print(f"  {'axis':>4} {'cal err90 nm':>13} {'val err90 nm':>13} {'if the model is right':>22}")
    for a in ("x", "y", "z", "all"):
        if a in s["val"]:
            lo, hi = band.get(a, (float("nan"),) * 2)
            above = "  above" if s["val"][a] > hi else ""
            print(f"  {a:>4} {s['cal'].get(a, float('nan')):13.1f} {s['val'][a]:13.1f} "
                  f"{lo:10.1f} - {hi:<9.1f}{above}")
    print("  (the validation error's 95 % band from the parameters' uncertainty and the "
          "calibration residual's noise; above it, the model or its noise model misses "
          "something the validation conditions show)")
    floor = (meta.get("truth") or {}).get("noise_floor_nm")
    if floor:
        print("  noise floor (twin's truth): " + ", ".join(f"{k} {v:.1f}" for k, v in floor.items())
              + " nm")
    if not fit.converged_:
        print(f"  {fit.status_}: the best fit found is shown (a model that lacks an effect "
              "can fit badly; `deltatwin diagnose` says what is missing)")
    if ident["not_identifiable"]:
        print(f"  not identifiable from these data (held at their start): "
              f"{len(ident['not_identifiable'])} parameters, e.g. "
              + ", ".join(ident["not_identifiable"][:6]))
    if ident["outside_physical_range"]:
        print("  fitted outside their physical range (standing in for a missing effect?): "
              + ", ".join(ident["outside_physical_range"]))
    print()
    print(summary.table)
    if args.output:
        print(f"  model written to {args.output}")
    return 0


def run_diagnose(args) -> int:
    from deltatwin.calibration.diagnosis.attribution import laboratory_variables
    from deltatwin.calibration.diagnosis.diagnose import diagnose
    from deltatwin.calibration.physics.fit import PhysicsFit
    from deltatwin.calibration.physics.model_file import fitted_on, load_fitted, saved_directions
    from deltatwin.models.batched import in_background
    from deltatwin.twin.dataset import read_dataset
    from deltatwin.twin.lab_setup import model_overrides

    df, meta = read_dataset(args.data)
    if str(args.model).lower().endswith(".json"):
        return _diagnose_stepwise(args, df, meta)
    model, doc = load_fitted(args.model, trust_of(args))
    # the constants the model was fitted with (the file's [known], its [effects]) stand over
    # the data's setup: said where they differ
    outside = {e: v for e, v in doc.get("known", {}).items() if e not in model.names}
    for line in model_overrides(model.effects, outside, meta, str(args.data)):
        print(f"{args.model}: {line}", file=sys.stderr)
    # the laboratory variables the diagnosis scans depend on the data alone: made beside the
    # model's Jacobian on a second core where the command has one (docs/performance.md)
    variables = in_background(laboratory_variables, df)
    # the file's values on this dataset (its zeros are new): kept as fitted when these are the
    # data it was fitted on by this code (its status says how converged), or when they are converged here in
    # the directions the fit determined (one Jacobian); else refined on its calibration rows
    fit = PhysicsFit(model.names, start={**outside, **model.values()},
                     noise_nm=float(doc["model"].get("noise_nm", 5.0)),
                     progress=not args.json).fit(df, meta, where=str(args.data),
                                                 keep_converged_start=True,
                                                 start_directions=saved_directions(doc),
                                                 fitted_on=fitted_on(doc, model),
                                                 start_corrected=doc["model"].get(
                                                     "thermometer_corrected", True))
    d = diagnose(fit, str(args.data), variables=variables())
    if args.json:
        print(strict_json(d))
        return 0
    print(f"model {', '.join(fit.effects) or 'nominal robot'}: validation error (90 %) "
          f"{d['val_err90_nm']:.1f} nm")
    print(f"  {'effect':<20} {'explains':>9} {'val err90 after':>16} {'p-value':>9} "
          f"{'dBIC':>8} {'absorbed':>9}  significant")
    for c in d["ranking"]:
        # the figures the verdict rests on (a refit's when the refit decided)
        explained, after, p, d_bic = c.table_figures()
        how = {"refit": "yes (refitted)", "validation": "yes (with validation)",
               "calibration": "yes"}.get(c.decided_by(), "no")
        print(f"  {c['effect']:<20} {100 * explained:8.1f}% {after:13.1f} nm {p:9.2g} "
              f"{d_bic:8.0f} {100 * c['absorbed_fraction']:8.0f}%  "
              f"{'failed' if 'failed' in c else how}")
    for line in d["absorbed"] + d["failed_candidates"]:
        print(f"  {line}")
    floor = d["floor_nm"]
    if floor:
        print(f"  {d['floor_kind']} floor: " + ", ".join(f"{a} {v:.1f}" for a, v in floor.items())
              + f" nm; at the floor (within 1.1x): {'yes' if d['at_floor'] else 'no'}")
    if d["extrapolation"]["message"]:
        print(f"warning: {d['extrapolation']['message']}", file=sys.stderr)
    if d["missing_effect"]:
        print(f"\nmissing effect: {d['missing_effect']}; add it with:\n  {d['next_command']}")
    else:
        print("\nno library effect explains the residual significantly")
        _print_unexplained(d["unexplained"])
    return 0


def _print_unexplained(u: dict) -> None:
    """What the residual still depends on and the proposed form, one line each."""
    if u.get("at_floor"):                   # the message's second part: the floor's
        print(u["message"].split("; ", 1)[-1])
        return
    if not u["depends_on"]:
        print("the residual does not depend on any recorded variable (noise-like)")
        return
    print("it depends on (strongest first: rms of the validation residual each explains beyond "
          "the others):")
    for v in u["depends_on"]:
        axes = ", ".join(f"{a} {x:.1f}" for a, x in v["by_axis_nm"].items())
        print(f"  {v['variable']:<24} {v['explained_nm']:6.1f} nm  ({axes} nm)")
    if u.get("form"):
        print("proposed form of the missing term (share of the validation residual explained):")
        for f in u["form"]:
            print(f"  {f['axis']}: " + " + ".join(t["formula"] for t in f["terms"])
                  + f"  ({100 * f['explained_fraction']:.0f} %)")
        print("write it as your own effect (docs/effects.md):\n  deltatwin diagnose ... --json "
              "> diagnosis.json && deltatwin effect new NAME --from diagnosis.json")


def _diagnose_stepwise(args, df, meta) -> int:
    """The black-box view: a DGM's residual against the feature families."""
    from deltatwin.calibration.diagnosis.compare import load_model_file
    from deltatwin.calibration.diagnosis.diagnose import diagnose_families

    d = diagnose_families(df, meta, load_model_file(args.model), str(args.data))
    if args.json:
        print(strict_json(d))
        return 0
    print(f"stepwise DGM ({d['features']}): validation error (90 %) {d['val_err90_nm']:.1f} nm")
    print(f"  {'feature family':<28} {'terms':>5} {'in model':>9} {'explains':>9} "
          f"{'val err90 after':>16} {'p-value':>9}  significant")
    for c in d["ranking"]:
        print(f"  {c['family']:<28} {c['n_terms']:5d} {'yes' if c['in_model'] else 'no':>9} "
              f"{100 * c['explained_fraction']:8.1f}% {c['val_err90_after_nm']:13.1f} nm "
              f"{c['p_value']:9.2g}  {'yes' if c['significant'] else 'no'}")
    print("\n" + (f"the residual correlates with the {d['correlated_family']!r} family"
                  if d["correlated_family"] else
                  "no feature family explains the residual significantly"))
    _print_unexplained(d["unexplained"])
    return 0
