"""``deltatwin calibrate``: fit the papers' models on a dataset and report the error figures.

    deltatwin calibrate DATA --features thermal|force [--ladder] [--json] [-o model.json]
                        [--model model.json] [--sensors a,b,c] [--penter P] [--premove P]
                        [--window-s S] [--t-ref-c C]

thermal: DGM per measured axis (reading = f(q, T, dT/dt, d2T/dt2)); force: direct IGM per
motor (q_i = f(X, Y, Z, F)).  ``--model`` evaluates a saved model on DATA instead of fitting.
See docs/calibration.md for the JSON schema.
"""
from __future__ import annotations

import math
import sys
import warnings

from deltatwin.calibration.errors import CalibrationInputError, CalibrationWarning
from deltatwin.commands.output import strict_json

FEATURES = ("thermal", "force")


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "calibrate", help="fit the papers' calibration (DGM per axis or direct IGM per motor)",
        description="Fit the papers' calibration on a dataset and report the error figures: "
                    "thermal = DGM per measured axis (first paper), force = direct IGM per "
                    "motor (second paper); see docs/calibration.md.")
    p.add_argument("data", metavar="DATA", help="dataset file (.parquet, or .csv + .meta.json)")
    p.add_argument("--features", choices=FEATURES, required=True,
                   help="thermal: first paper (217 terms with 9 sensors); force: second (79)")
    p.add_argument("--ladder", action="store_true",
                   help="also refit with the papers' growing feature sets and report them")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("-o", "--output", metavar="MODEL.json", help="write the model as JSON")
    p.add_argument("--model", metavar="MODEL.json",
                   help="evaluate this saved model on DATA instead of fitting one")
    p.add_argument("--sensors", metavar="A,B,...",
                   help="temperature sensors for the thermal features (default: the "
                        "metadata's sensors that are not 'air')")
    p.add_argument("--penter", type=float, default=None, help="entry p-value (default 0.05)")
    p.add_argument("--premove", type=float, default=None,
                   help="removal p-value (default max(penter, 0.10))")
    p.add_argument("--window-s", type=float, default=600.0,
                   help="trailing window of the causal temperature derivatives, s (600)")
    p.add_argument("--t-ref-c", type=float, default=20.0,
                   help="reference temperature the temperature terms are relative to, degC (20)")
    p.set_defaults(func=run)




def _axis_record(rec: dict) -> dict:
    out = {"terms_kept": rec["terms_kept"],
           "n_cal": rec["cal"]["n"], "n_val": rec.get("val", {}).get("n", 0),
           "cal_err90_nm": rec["cal"]["err_p90"],
           "val_err90_nm": rec.get("val", {}).get("err_p90"),
           "cal_err1645sigma_nm": rec["cal"]["err_1645sigma"],
           "val_err1645sigma_nm": rec.get("val", {}).get("err_1645sigma"),
           "val_mean_nm": rec.get("val", {}).get("mean")}
    if "cal_urad" in rec:
        out["cal_err90_urad"] = rec["cal_urad"]["err_p90"]
        out["val_err90_urad"] = rec["val_urad"]["err_p90"]
    return out


def build_report(df, meta, args) -> tuple[dict, object]:
    """Fit (or load) and evaluate; returns (report dict, model)."""
    from deltatwin.calibration.blackbox.dgm import DGM
    from deltatwin.calibration.blackbox.direct_igm import DirectIGM
    from deltatwin.calibration.blackbox.model_file import load_model
    from deltatwin.calibration.blackbox.validation import evaluate, ladder
    from deltatwin.calibration.metrics import check_disjoint

    check_disjoint(df)
    kind = "DGM" if args.features == "thermal" else "DirectIGM"
    sensors = None
    if args.sensors:
        sensors = [s.strip() for s in args.sensors.split(",") if s.strip()]
        if args.features != "thermal":
            raise CalibrationInputError("--sensors applies to --features thermal only")
    kw = dict(penter=args.penter if args.penter is not None else 0.05, premove=args.premove,
              window_s=args.window_s, T_ref_K=args.t_ref_c + 273.15)
    if args.penter is None:
        kw.pop("penter")
    if args.model:
        model = load_model(args.model, expect_kind=kind, expect_features=args.features)
    else:
        cls = DGM if kind == "DGM" else DirectIGM
        model = cls(sensors=sensors, **kw).fit(df, meta)
    ev = evaluate(model, df)
    report = {"data": str(args.data), "features": args.features, "kind": kind,
              "n_candidates": len(model.features_), "sensors": list(model.sensors_),
              "model_file": args.model, "axes": {}}
    for name, rec in ev["outputs"].items():
        report["axes"][name] = _axis_record(rec)
        # the kept terms as stepwisefit lists them (coefficients and standard errors in SI)
        report["axes"][name]["terms"] = model.output(name).coefficient_rows()
    if "position" in ev:
        report["position"] = {ax: {"cal_err90_nm": r["cal"]["err_p90"],
                                   "val_err90_nm": r["val"]["err_p90"],
                                   "cal_err1645sigma_nm": r["cal"]["err_1645sigma"],
                                   "val_err1645sigma_nm": r["val"]["err_1645sigma"]}
                              for ax, r in ev["position"].items()}
    if args.ladder:
        lkw = dict(kw)
        if sensors is not None:
            lkw["sensors"] = sensors
        elif args.model and args.features == "thermal":
            lkw["sensors"] = list(model.sensors_)
        rungs = ladder(df, meta, args.features, **lkw)
        for name in report["axes"]:
            report["axes"][name]["ladder"] = [
                {"name": r["name"], "terms_kept": r["outputs"][name]["terms_kept"],
                 "val_err90_nm": r["outputs"][name]["val"]["err_p90"],
                 "val_err1645sigma_nm": r["outputs"][name]["val"]["err_1645sigma"]}
                for r in rungs if name in r["outputs"]]
    return report, model


def _fmt(v, width=10):
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return f"{'-':>{width}}"
    return f"{v:>{width}.1f}"


def format_report(rep: dict) -> str:
    lines = [f"{rep['kind']} ({rep['features']} features, {rep['n_candidates']} candidate "
             f"terms) on {rep['data']}" + (f", model {rep['model_file']}" if rep['model_file']
                                            else "")]
    unit = "nm" + (" at the end-effector" if rep["kind"] == "DirectIGM" else "")
    lines.append(f"errors in {unit}; p90 = empirical 90th percentile of |error|, "
                 "1.645s = 1.645 x standard deviation")
    lines.append(f"{'output':<8}{'terms':>6}{'cal rows':>10}{'val rows':>10}"
                 f"{'cal p90':>10}{'val p90':>10}{'cal 1.645s':>11}{'val 1.645s':>11}")
    for name, r in rep["axes"].items():
        lines.append(f"{name:<8}{r['terms_kept']:>6}{r['n_cal']:>10}{r['n_val']:>10}"
                     f"{_fmt(r['cal_err90_nm'])}{_fmt(r['val_err90_nm'])}"
                     f"{_fmt(r['cal_err1645sigma_nm'], 11)}{_fmt(r['val_err1645sigma_nm'], 11)}")
    if "position" in rep:
        lines.append("end-effector position error from the three motor models, nm:")
        for ax, r in rep["position"].items():
            lines.append(f"  {ax}: cal p90 {_fmt(r['cal_err90_nm'], 0).strip()}, "
                         f"val p90 {_fmt(r['val_err90_nm'], 0).strip()}")
    names = list(rep["axes"])
    if names and "ladder" in rep["axes"][names[0]]:
        lines.append("ladder: validation p90 |error| nm (terms kept)")
        lines.append(f"{'rung':<32}" + "".join(f"{n:>16}" for n in names))
        for i, rung in enumerate(rep["axes"][names[0]]["ladder"]):
            cells = []
            for n in names:
                r = rep["axes"][n]["ladder"][i]
                cells.append(f"{_fmt(r['val_err90_nm'], 0).strip()} ({r['terms_kept']})")
            lines.append(f"{rung['name']:<32}" + "".join(f"{c:>16}" for c in cells))
    for w in rep.get("warnings", []):
        lines.append(f"warning: {w}")
    return "\n".join(lines)


def run(args) -> int:
    from deltatwin.twin.dataset import read_dataset

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        df, meta = read_dataset(args.data)
        report, model = build_report(df, meta, args)
    msgs = []
    for w in caught:
        if not issubclass(w.category, CalibrationWarning):
            warnings.showwarning(w.message, w.category, w.filename, w.lineno)
            continue
        m = f"{w.category.__name__}: {w.message}"
        if m not in msgs:
            msgs.append(m)
    report["warnings"] = msgs
    if args.output:
        model.save(args.output)
        report["model_written"] = str(args.output)
    if args.json:
        print(strict_json(report, indent=1))
    else:
        print(format_report(report))
        for name in report["axes"]:
            print()
            print(model.coefficient_table(name))
        if args.output:
            print(f"model written to {args.output}")
    if msgs and args.json:
        for m in msgs:
            print(f"deltatwin calibrate: warning: {m}", file=sys.stderr)
    return 0
