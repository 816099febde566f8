"""The diagnosis loop's report (``deltatwin demo``): the ladder and each diagnosis in
Markdown, then the figures and tables of the ladder's models on the data
(model_report.py: ``deltatwin report``'s), in report.md and report.html."""
from __future__ import annotations

from pathlib import Path

from deltatwin.calibration.diagnosis.model_report import report_model, write_model_report


def tried_instead_line(tried: dict, markdown: bool = False) -> str:
    """One of a diagnosis' ``tried_instead`` refits (a significant effect fitted after the named
    one was rejected, or the rejected one again held off: ``held`` "off") in words: plain, as
    the demo's progress prints it, or a Markdown sentence (the effect in bold), as the report
    writes it."""
    effect = f"**{tried['effect']}**" if markdown else tried["effect"]
    what = ("tried again held off (its free parameters at zero where the data do not "
            "determine them)" if tried.get("held") == "off" else "tried instead, also significant")
    line = (f"{what}: {effect} ({tried['val_err90_nm']:.1f} nm: "
            f"{'kept' if tried['kept'] else 'not kept'})")
    return f"{line[:1].upper()}{line[1:]}." if markdown else line


def write_report(out: Path, df, meta, ladder, diagnoses, fits, hidden=None,
                 recording: Path | None = None) -> Path:
    """Write ``report.md``, ``report.html`` and the figures into ``out``; returns the
    report's path."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    floor = (meta.get("truth") or {}).get("noise_floor_nm")
    lines = ["# deltatwin: where the model fails and which effect is missing", ""]
    if hidden:
        lines += [f"Data: scenario `{meta.get('scenario')}` (seed {meta.get('seed')}), "
                  f"{len(df)} rows; hidden effect(s): {', '.join(hidden['effects'])}; "
                  f"starting model: {', '.join(hidden['baseline']) or 'the nominal robot'}.", ""]
    lines += ["## The ladder", "",
              "| model | effects | parameters (identified) | validation error 90 % (nm) | "
              "noise floor (nm) |", "|---|---|---|---|---|"]
    for row in ladder:
        nf = ", ".join(f"{k} {v:.1f}" for k, v in (row.get("noise_floor_nm") or {}).items())
        lines.append(f"| {row['model']} | {', '.join(row['effects']) or 'nominal'} | "
                     f"{row['n_parameters']} ({row['n_identified']}) | "
                     f"{row['val_err90_nm']:.1f} | {nf or 'unknown'} |")
    lines += ["", "![ladder](ladder.png)", ""]
    for k, d in enumerate(diagnoses):
        lines += [f"## Diagnosis of model {k}: {', '.join(d['effects']) or 'nominal'}", "",
                  f"Validation error (90 %): {d['val_err90_nm']:.1f} nm.", "",
                  "| effect | explains | val err90 after (nm) | new directions | p-value | "
                  "ΔBIC | significant |", "|---|---|---|---|---|---|---|"]
        for c in d["ranking"]:
            lines.append(f"| {c['effect']} | {100 * c['explained_fraction']:.1f} % | "
                         f"{c['val_err90_after_nm']:.1f} | {c['new_directions']} | "
                         f"{c['p_value']:.2g} | {c['delta_bic']:.0f} | "
                         f"{'yes' if c['significant'] else 'no'} |")
        if d.get("refit_rejected"):
            lines += ["", f"Named: **{d['missing_effect']}**; "
                      + d["refit_rejected"]["message"] + "."]
            lines += [tried_instead_line(t, markdown=True) for t in d["tried_instead"]]
        elif d.get("pair"):
            lines += ["", "Missing effects, together (neither significant alone): "
                      + " and ".join(f"**{e}**" for e in d["pair"]["effects"])
                      + f". Add them with `{d['next_command']}`."]
        elif d["missing_effect"]:
            lines += ["", f"Missing effect: **{d['missing_effect']}**. Add it with "
                      f"`{d['next_command']}`."]
        else:
            lines += ["", d["unexplained"]["message"] + "."]
        dep = d["unexplained"]["depends_on"][:5]
        if dep:
            lines += ["", "The residual still depends on (validation rms each explains beyond "
                      "the others): " + "; ".join(f"{x['variable']} ({x['explained_nm']:.1f} nm)"
                                                  for x in dep) + "."]
        lines.append("")
    if floor:
        lines += ["Noise floor (the twin's truth: validation error 90 % of the readings against "
                  "a perfect instrument): " + ", ".join(f"{k} {v:.1f} nm" for k, v in floor.items())
                  + ".", ""]
    if recording:
        lines += [f"Rerun recording: `{recording.name}` (`rerun {recording.name}`).", ""]
    models = [report_model(f"model {k}", fit, df, meta, f"model{k}.toml")
              for k, fit in enumerate(fits)]
    return write_model_report(out, df, meta, models, "data.parquet",
                              title="Where the models fail: figures and tables",
                              head=[("md", "\n".join(lines))])
