"""``deltatwin compare``: where a model fails on a dataset (calibration/diagnosis/compare.py).

    deltatwin compare DATA --model fitted.toml|model.json [--json] [--split val|cal|all]
                      [--windows N] [--bins N] [--worst N] [--params PARAMS.toml]
                      [--report FOLDER]

The residual is model minus measurement, with each (session, axis) zero re-estimated on
DATA's calibration rows.  Human output: a table per axis, the force levels, the worst regions,
time windows and variables; ``--json`` prints the whole result as one JSON object;
``--report FOLDER`` also writes the report of ``deltatwin report`` for the model.
"""
from __future__ import annotations

import sys

from deltatwin.commands.output import strict_json
from deltatwin.commands.trust import add_trust_option, trust_of


def register(sub) -> None:
    p = sub.add_parser(
        "compare", help="compare a model with measurements: where (region, time, force, "
                        "variable) it fails",
        description="Residual statistics of a model on a dataset, per axis and broken down by "
                    "workspace region, time window, force level and each recorded variable, "
                    "with the worst regions and periods. Residual = model minus measurement; "
                    "the session zeros are re-estimated on the dataset's calibration rows.")
    p.add_argument("data", metavar="DATA", help="dataset file (.parquet, or .csv + .meta.json)")
    p.add_argument("--model", required=True, metavar="MODEL",
                   help="a fitted physics model (.toml from 'deltatwin fit -o') or a DGM "
                        "(.json from 'deltatwin calibrate -o')")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--split", choices=("val", "cal", "all"), default="val",
                   help="rows the breakdowns use (default: the validation split)")
    p.add_argument("--windows", type=int, default=8, metavar="N",
                   help="equal time windows over the rows' span (8)")
    p.add_argument("--bins", type=int, default=5, metavar="N",
                   help="quantile bins per recorded variable (5)")
    p.add_argument("--worst", type=int, default=3, metavar="N",
                   help="length of the worst regions / windows / variables lists (3)")
    p.add_argument("--params", metavar="PARAMS.toml",
                   help="robot parameters placing a DGM's positions (default: nominal)")
    p.add_argument("--report", metavar="FOLDER",
                   help="also write the report of the model on the data (figures, tables: "
                        "`deltatwin report`) into this folder")
    add_trust_option(p)
    p.set_defaults(func=run)


def _f(v, width=9, digits=1) -> str:
    return f"{'-':>{width}}" if v is None else f"{v:>{width}.{digits}f}"


def _side(err, band: dict) -> str:
    """Where a validation error lies against its band: "" within, else above (the model misses
    something the validation rows show) or below it."""
    if band["within"] is not False or err is None:
        return ""
    return "  above" if err > band["high"] else "  below"


def format_report(rep: dict) -> str:
    """Compact human-readable summary of a ``compare`` result."""
    from deltatwin.calibration.diagnosis.floor import budget_lines

    m = rep["model"]
    name = ("physics model: " + ", ".join(m["effects"]) if m["kind"] == "physics"
            else f"DGM ({m['features']} features, outputs {','.join(m['outputs'])})")
    lines = [f"{name} on {rep.get('data', 'the dataset')}",
             f"residual = {rep['residual']}",
             "zeros: re-estimated per (session, axis) on this dataset ("
             + ", ".join(f"{g}: {w}" for g, w in rep["zeros"]["estimated_on"].items()) + ")"]
    floor = rep.get("noise_floor_nm")
    if isinstance(floor, dict):
        lines.append("noise floor (twin): " + ", ".join(f"{a} {v:.1f} nm"
                                                        for a, v in floor.items()))
    achievable = rep.get("achievable_floor_nm")
    if isinstance(achievable, dict):
        lines.append("achievable floor (the twin's complete model refitted on these data): "
                     + ", ".join(f"{a} {v:.1f} nm" for a, v in achievable.items()))
    lines.extend(budget_lines(rep.get("floor_budget_nm")))
    if rep.get("at_floor"):
        judged = rep["at_floor"]
        lines.append(f"at the {judged['kind']} floor (within {judged['factor']}x): "
                     + ", ".join(f"{a} {'yes' if ok else 'no'}"
                                 for a, ok in judged["axes"].items()))
    band = rep.get("validation_band_95_nm") or {}
    lines.append(f"{'split':<6}{'axis':<5}{'n':>6}{'mean nm':>9}{'p90 nm':>9}{'1.645s nm':>10}"
                 f"{'max nm':>9}" + (f"  {'p90 95 % band nm':<18}" if band else ""))
    for split, axes in rep["axes"].items():
        for a, r in axes.items():
            b = band.get(a) if split == "val" else None
            lines.append(f"{split:<6}{a:<5}{r['n']:>6}{_f(r['mean_nm'])}{_f(r['err_p90_nm'])}"
                         f"{_f(r['err_1645sigma_nm'], 10)}{_f(r['max_abs_nm'])}"
                         + (f"  {b['low']:.1f}-{b['high']:.1f}{_side(r['err_p90_nm'], b)}"
                            if b else ""))
    if band:
        lines.append("  (p90 95 % band: where the validation error 90 % falls if the model is "
                     "right: its parameters' uncertainty and the readings' noise as the "
                     "calibration rows show it)")
    rows = rep["rows"]
    if rep.get("force"):
        lines.append(f"force level ({rows} rows): p90 nm [mean x, y, z nm]")
        for b in rep["force"]["bins"]:
            means = ", ".join(_f(b["by_axis"][a]["mean_nm"], 0) for a in b["by_axis"])
            lines.append(f"  F = {b['value']:g} N: {_f(b['err_p90_nm'], 0)} [{means}] "
                         f"(n {b['n']})")
    w = rep["worst"]
    lines.append(f"worst regions ({rows} rows, {rep['regions']['scheme']}):")
    lines += [f"  {r['region']}: p90 {r['err_p90_nm']:.1f} nm ({_f(r['times_overall'], 0, 2)} x "
              f"overall, n {r['n']})" for r in w["regions"]]
    lines.append("worst time windows:")
    lines += [f"  t {r['t_from_s']:.0f}-{r['t_to_s']:.0f} s: p90 {r['err_p90_nm']:.1f} nm "
              f"({_f(r['times_overall'], 0, 2)} x overall, n {r['n']})"
              for r in w["time_windows"]]
    lines.append("variables the error varies most with (p90 of the worst bin / best bin):")
    lines += [f"  {v['variable']}: {v['p90_ratio_max_min']:.2f}" for v in w["variables"]]
    if rep["unused_temperature_columns"]:
        lines.append("temperature columns the model does not use: "
                     + ", ".join(rep["unused_temperature_columns"]))
    return "\n".join(lines)


def run(args) -> int:
    from deltatwin.calibration.diagnosis.compare import compare, load_model_and_covariance
    from deltatwin.calibration.errors import CalibrationInputError
    from deltatwin.commands.report import check_report_folder, write_report_folder
    from deltatwin.files import check_writable
    from deltatwin.twin.dataset import read_dataset

    if args.report:                      # refused before computing, as -o is
        check_writable(args.report, folder=True)
        check_report_folder(args.report)
    df, meta = read_dataset(args.data)
    model, covariance = load_model_and_covariance(args.model, trust_of(args))
    try:
        rep = compare(df, meta, model, split=args.split, n_time_windows=args.windows,
                      n_bins=args.bins, n_worst=args.worst, params=args.params,
                      covariance=covariance)
    except CalibrationInputError as exc:
        raise CalibrationInputError(f"{args.data} with model {args.model}: {exc}") from exc
    rep = {"data": str(args.data), "model_file": str(args.model), **rep}
    if rep["extrapolation"]["message"]:
        print(f"warning: {rep['extrapolation']['message']}", file=sys.stderr)
    if args.report:
        rep["report"] = str(write_report_folder(args.report, args.data, df, meta, [args.model],
                                                trust_of(args), args.params))
    if args.json:
        print(strict_json(rep, indent=1))
    else:
        print(format_report(rep))
        if args.report:
            print(f"report: {rep['report']}")
    return 0
