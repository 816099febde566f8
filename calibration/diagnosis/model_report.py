"""The report of models on a dataset (``deltatwin report``, ``compare --report``, the demo's
figures): Markdown and HTML with PNG figures, for laboratory data as for the twin's.

``report_model`` evaluates a model (a fitted or loaded ``PhysicsFit``, or a DGM) on the data,
with each (session, axis) zero re-estimated on its calibration rows, as ``deltatwin compare``
does; ``report_figures`` draws the figures (figures.py) and ``report_blocks`` lays out the
document, which ``write_model_report`` writes. What the data's metadata carry is used where it
is (the twin's floors and budget); nothing needs it.
"""
from __future__ import annotations

import html
import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from deltatwin.calibration.diagnosis.attribution import Residual, attribute, laboratory_variables
from deltatwin.calibration.diagnosis.compare import evaluate, load_model_file
from deltatwin.calibration.diagnosis.figures import (
    ModelResidual,
    correlation_figure,
    distribution_figure,
    ladder_figure,
    residual_time_figure,
    residual_vs_figure,
    workspace_comparison_figure,
    workspace_figure,
)
from deltatwin.calibration.diagnosis.floor import floor_of
from deltatwin.calibration.physics.fit import PhysicsFit
from deltatwin.calibration.physics.model import figures_nm
from deltatwin.calibration.physics.table import (
    IDENTIFIED,
    ParameterTable,
    correlation_matrix,
    parameter_rows,
)
from deltatwin.calibration.tables import Table
from deltatwin.files import atomic_write, atomic_write_text
from deltatwin.twin.instruments.optics import AXES

log = logging.getLogger(__name__)
MAX_VARIABLES = 4        # residual-against-variable columns, at most
MAIN_VARIABLES = 2       # ... at least (the data's main variables fill up to it)
DPI = 110


@dataclass
class ReportModel:
    """A model as the report shows it: ``residual`` (figures.ModelResidual), ``kind`` and
    ``what`` (its effects or features), its parameter ``tables``, and for a physics model with
    saved uncertainties the ``correlation`` of its identified parameters (labels, matrix, of
    how many parameters)."""
    name: str
    source: str
    kind: str
    what: str
    residual: ModelResidual
    tables: list = field(default_factory=list)
    correlation: tuple | None = None


def report_model(name: str, model, df, meta: dict | None, source: str = "",
                 params=None) -> ReportModel:
    """``model`` (a PhysicsFit, fitted or read with ``PhysicsFit.load``, or a DGM) evaluated
    on the rows of ``df``; ``source``: where it came from (its file)."""
    df = df.reset_index(drop=True)
    physics = isinstance(model, PhysicsFit)
    ev = evaluate(df, meta, model.model_ if physics else model, params)
    residual = ModelResidual(name, ev.residual_m, ev.position_m, ev.meas.cal, ev.meas.val)
    if not physics:
        return ReportModel(name, source, "DGM", ev.description["features"], residual,
                           [model.coefficient_table(o) for o in model.output_names_])
    what = ", ".join(model.effects) or "the nominal robot"
    if model.parameters_ is None:
        return ReportModel(name, source, "physics", what, residual)
    table = ParameterTable(parameter_rows(model.parameters_, model.model_.tolerances),
                           title=f"{name}: fitted parameters (SI units)")
    keep = [j for j, p in enumerate(model.parameters_) if p["identified_fraction"] >= IDENTIFIED]
    correlation = None
    if len(keep) > 1:
        c = correlation_matrix(model.covariance_)[np.ix_(keep, keep)]
        correlation = ([model.parameters_[j]["label"] for j in keep], c, len(model.parameters_))
    return ReportModel(name, source, "physics", what, residual, [table], correlation)


def read_model(path, trust_effects=False):
    """A model file as the report takes it: a fitted physics model (``.toml``, read as a
    ``PhysicsFit`` with its uncertainties) or a DGM (``.json``); anything else is refused as
    ``deltatwin compare`` refuses it (compare.py ``load_model_file``)."""
    if Path(path).suffix.lower() == ".toml":
        return PhysicsFit.load(path, trust_effects)
    return load_model_file(path, trust_effects)


def report_variables(df, models: list[ReportModel]) -> tuple[dict, set]:
    """({name: values SI}, named): the variables the attribution names for any model's
    residual (strongest first; attribution.py), then the data's main variables (the force or
    a coil's current, the temperature that varies most) up to MAIN_VARIABLES columns, at most
    MAX_VARIABLES; ``named``: those the attribution named. Time has a figure of its own."""
    lab = laboratory_variables(df)
    variables = {v.name: v.values for v in lab}
    named = []
    for m in models:
        r = m.residual
        found = attribute(df, Residual.of(df, r.residual_m, r.cal, r.val),
                          variables=lab)["variables"]
        named += [v["variable"] for v in found if v["variable"] in variables
                  and v["variable"] != "session"]
    named = list(dict.fromkeys(named))[:MAX_VARIABLES]
    main = [c for c in ("F_N", "coil1_A") if c in variables][:1]
    temps = [c for c in variables if c.startswith("T_") and c.endswith("_C")]
    if temps:
        main.append(max(temps, key=lambda c: np.nanmax(variables[c]) - np.nanmin(variables[c])))
    chosen = named + [c for c in main if c not in named][:max(MAIN_VARIABLES - len(named), 0)]
    return {n: variables[n] for n in chosen or ["t_s"]}, set(named)


def report_figures(df, meta: dict | None, models: list[ReportModel]) -> dict:
    """{file stem: Figure} of the report (figures.py), in the order the report shows them."""
    df = df.reset_index(drop=True)
    residuals = [m.residual for m in models]
    floor, kind = floor_of(meta)
    budget = ((meta or {}).get("truth") or {}).get("floor_budget_nm") if kind == "achievable" \
        else None
    log.info("report: the variables the residuals depend on", extra={"progress": "report"})
    variables, named = report_variables(df, models)
    figures = {"ladder": ladder_figure(residuals, floor, kind if floor else "", budget),
               "residual_time": residual_time_figure(df, residuals),
               "residual_vs": residual_vs_figure(residuals, variables, named),
               "distribution": distribution_figure(residuals)}
    for k, m in enumerate(models):
        figures[f"workspace_{k + 1}"] = workspace_figure(m.residual)
    if len(models) > 1:
        figures["workspace_compare"] = workspace_comparison_figure(residuals[0], residuals[-1])
    for k, m in enumerate(models):
        if m.correlation:
            figures[f"correlation_{k + 1}"] = correlation_figure(m.name, *m.correlation)
    return figures


def error_table(models: list[ReportModel]) -> Table:
    """Each model's error 90 % per axis on the calibration and validation rows (nm)."""
    records = []
    for m in models:
        r = m.residual
        for split, rows in (("calibration", r.cal), ("validation", r.val)):
            if rows.any():
                fig = figures_nm(r.residual_m, rows)
                records.append({"model": m.name, "rows": split, **{
                    f"{a}_err90_nm": fig.get(a, {}).get("err_p90") for a in (*AXES, "all")}})
    return Table("error 90 % (nm)", ("model", "rows", "x (nm)", "y (nm)", "z (nm)",
                                      "all axes (nm)"), records,
                 lambda r: [r["model"], r["rows"], *("-" if r[f"{a}_err90_nm"] is None else
                                                     f"{r[f'{a}_err90_nm']:.1f}"
                                                     for a in (*AXES, "all"))])


# ---------------------------------------------------------------------------------------------
# the document: blocks ("h1"/"h2"/"p", text), ("table", Table), ("img", file, alt), ("md",
# Markdown text written elsewhere), written as Markdown and as HTML

SECTIONS = {   # figure: (heading, caption)
    "ladder": ("Error per axis and the floor",
               "The error 90 % of each model per axis and over all axes, against the floor the "
               "data carry: the twin's achievable floor (a line) and its budget (a bar: each "
               "source adds its share in quadrature); a laboratory's data carry none."),
    "residual_time": ("Residual against time",
                      "The residual per axis against time; calibration rows filled, validation "
                      "rows hollow; dashed lines: a session starts."),
    "residual_vs": ("Residual against the laboratory's variables",
                    "The residual per axis against the variables the attribution names "
                    "(calibration/diagnosis/attribution.py: what the residual depends on, beyond "
                    "the others) and the data's main variables."),
    "distribution": ("Residual distribution",
                     "Histogram and normal quantile plot of the residual per axis: a normal "
                     "residual lies on the dashed line through its quartiles."),
}
WORKSPACE = ("Each axis's residual over the workspace (the platform's nominal position), top "
             "and side views, each axis on its own colour scale; where a position was read "
             "more than once the largest residual is drawn on top.")
COMPARED = ("The first and the last model side by side, on a colour scale common to both for "
            "each axis.")


def data_lines(df, meta: dict | None, data_name: str) -> list[str]:
    """What the data are, in sentences."""
    split = df["split"].astype(str).value_counts().to_dict() if "split" in df else {}
    sessions = df["session"].astype(str).unique().tolist() if "session" in df else []
    hours = (df["t_s"].max() - df["t_s"].min()) / 3600.0
    floor, kind = floor_of(meta)
    lines = [f"Data: `{data_name}`, {len(df)} rows ({split.get('cal', 0)} calibration, "
             f"{split.get('val', 0)} validation), {len(sessions)} session(s) "
             f"({', '.join(sessions)}) over {hours:.2f} h."]
    if floor:
        lines.append(f"The {kind} floor (the twin's, from the data's metadata): "
                     + ", ".join(f"{a} {v:.1f} nm" for a, v in floor.items()) + ".")
    else:
        lines.append("The data carry no floor (laboratory data): the figures show the models "
                     "against each other.")
    lines.append("Residual = model minus measurement, each (session, axis) zero re-estimated "
                 "on the data's calibration rows (as `deltatwin compare`).")
    return lines


def model_list(models: list[ReportModel]) -> Table:
    return Table("models", ("model", "file", "kind", "effects or features"),
                 [{"model": m.name, "file": m.source, "kind": m.kind, "what": m.what}
                  for m in models],
                 lambda r: [r["model"], f"{r['file'] or '-'}", r["kind"], r["what"]])


def report_blocks(df, meta: dict | None, models: list[ReportModel], data_name: str,
                  figures: dict, title: str = "Models on a dataset",
                  heading: str = "h1") -> list[tuple]:
    """The report's document as blocks (see above), figures by their file stem; the title a
    ``heading`` ("h1", or "h2" below another document's title)."""
    blocks = [(heading, title), *(("p", line) for line in data_lines(df, meta, data_name)),
              ("table", model_list(models)), ("table", error_table(models))]
    for stem, (heading, caption) in SECTIONS.items():
        blocks += [("h2", heading), ("img", f"{stem}.png", heading), ("p", caption)]
    blocks += [("h2", "Residual over the workspace"), ("p", WORKSPACE)]
    for k, m in enumerate(models):
        blocks.append(("img", f"workspace_{k + 1}.png", f"{m.name} over the workspace"))
    if "workspace_compare" in figures:
        blocks += [("img", "workspace_compare.png", COMPARED), ("p", COMPARED)]
    for k, m in enumerate(models):
        blocks.append(("h2", f"Parameters of {m.name}"))
        if not m.tables:
            blocks.append(("p", "Its file holds no uncertainties (written before they were "
                                "saved): refit it with `deltatwin fit ... -o` for its table."))
        blocks += [("table", t) for t in m.tables]
        if f"correlation_{k + 1}" in figures:
            blocks.append(("img", f"correlation_{k + 1}.png",
                           f"correlation of {m.name}'s identified parameters"))
    return blocks


def markdown_of(blocks: list[tuple]) -> str:
    out = []
    for kind, *rest in blocks:
        if kind == "md":
            out.append(rest[0])
        elif kind == "table":
            out += [f"**{rest[0].title}**", "", rest[0].markdown()]
        elif kind == "img":
            out.append(f"![{rest[1]}]({rest[0]})")
        else:
            out.append({"h1": "# ", "h2": "## ", "p": ""}[kind] + rest[0])
        out.append("")
    return "\n".join(out)


def html_of(blocks: list[tuple], title: str) -> str:
    esc = html.escape
    body = []
    for kind, *rest in blocks:
        if kind == "md":                 # another document's Markdown, shown as written
            body.append(f"<pre>{esc(rest[0])}</pre>")
        elif kind == "table":
            body.append(rest[0]._repr_html_())
        elif kind == "img":
            body.append(f'<figure><img src="{esc(rest[0])}" alt="{esc(rest[1])}">'
                        f"<figcaption>{esc(rest[1])}</figcaption></figure>")
        else:
            body.append(f"<{kind}>{esc(rest[0]).replace('`', '')}</{kind}>")
    style = ("body{font-family:sans-serif;max-width:70em;margin:auto}img{max-width:100%}"
             "table{border-collapse:collapse;margin:1em 0}td,th{border:1px solid #ccc;"
             "padding:2px 6px;text-align:right}caption{font-weight:bold;text-align:left}")
    return (f"<!DOCTYPE html><html><head><meta charset=\"utf-8\"><title>{esc(title)}</title>"
            f"<style>{style}</style></head><body>{''.join(body)}</body></html>\n")


def save_figure(fig, path: Path) -> Path:
    """A figure as PNG, written atomically."""
    return atomic_write(path, lambda tmp: fig.savefig(tmp, format="png", dpi=DPI))


def write_model_report(out, df, meta: dict | None, models: list[ReportModel], data_name: str,
                       title: str = "Models on a dataset", head: list[tuple] = ()) -> Path:
    """Write the figures, ``report.md`` and ``report.html`` into the folder ``out`` (its
    caller makes it whole or not at all: files.atomic_folder); ``head``: blocks put before
    the report's own (the demo's ladder and diagnoses). Returns report.md's path."""
    out = Path(out)
    figures = report_figures(df, meta, models)
    for k, (stem, fig) in enumerate(figures.items()):
        log.info("report: drawing %s.png (%d of %d)", stem, k + 1, len(figures),
                 extra={"progress": "report"})
        save_figure(fig, out / f"{stem}.png")
    blocks = [*head, *report_blocks(df, meta, models, data_name, figures, title,
                                    "h2" if head else "h1")]
    atomic_write_text(out / "report.html", html_of(blocks, title))
    return atomic_write_text(out / "report.md", markdown_of(blocks))
