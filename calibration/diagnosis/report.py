"""The diagnosis loop's report: Markdown with PNG figures (matplotlib, no display needed).

Figures: the ladder (validation error 90 % per model, with the noise floor), residual maps over
the workspace (baseline and final model), and the residual against time, force and the
temperature it correlates with most. Files are written to temporary names and renamed."""
from __future__ import annotations

from pathlib import Path

import numpy as np

# Figures are drawn on matplotlib's object API (Figure + its own Agg canvas), not pyplot:
# writing a report neither needs a display nor switches the backend of a user's notebook.
from matplotlib.figure import Figure

from deltatwin.files import atomic_write, atomic_write_text
from deltatwin.models.geometry import build_geometry
from deltatwin.models.kinematics import forward
from deltatwin.models.params import load_params

NM = 1e9


def _save(fig, path: Path) -> None:
    atomic_write(path, lambda tmp: fig.savefig(tmp, format="png", dpi=110, bbox_inches="tight"))


def _magnitude_nm(res: np.ndarray) -> np.ndarray:
    """Per row: rms over the measured axes of the residual (nm)."""
    r = res * NM
    return np.sqrt(np.nanmean(r ** 2, axis=1))


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


def ladder_figure(ladder: list[dict], path: Path) -> None:
    fig = Figure(figsize=(6, 3.2))
    ax = fig.subplots()
    names = [row["model"] for row in ladder]
    vals = [row["val_err90_nm"] for row in ladder]
    ax.bar(range(len(vals)), vals, color="#3070c0")
    floor = ladder[0].get("noise_floor_nm")
    if floor:
        f = float(np.max(list(floor.values())))
        ax.axhline(f, color="k", ls="--", lw=1, label=f"noise floor {f:.1f} nm")
        ax.legend()
    ax.set_xticks(range(len(vals)), names, rotation=15)
    ax.set_yscale("log")
    ax.set_ylabel("validation error 90 % (nm)")
    ax.set_title("error falls as the missing effects are added")
    _save(fig, path)


def residual_maps(df, fits, path: Path) -> None:
    params = load_params(None)
    p = forward(build_geometry(params), df[["q1_rad", "q2_rad", "q3_rad"]].to_numpy()).p * 1e3
    ends = [fits[0], fits[-1]]
    mags = [_magnitude_nm(f.residual_) for f in ends]
    vmax = float(np.nanpercentile(mags[0], 99))
    fig = Figure(figsize=(9, 4))
    axes = fig.subplots(1, 2, sharex=True, sharey=True)
    for ax, f, m in zip(axes, ends, mags):
        sc = ax.scatter(p[:, 0], p[:, 1], c=m, s=8, cmap="viridis", vmin=0, vmax=vmax)
        ax.set_title(f"{'+'.join(f.effects) or 'nominal'}", fontsize=8)
        ax.set_xlabel("x (mm)")
        ax.set_aspect("equal")
    axes[0].set_ylabel("y (mm)")
    fig.colorbar(sc, ax=axes, label="|residual| rms over axes (nm)")
    fig.suptitle("residual over the workspace (top view): baseline vs final model")
    _save(fig, path)


def error_vs_figure(df, fits, variables: list[str], path: Path) -> None:
    variables = [v for v in variables if v in df.columns and np.nanstd(df[v]) > 0]
    if not variables:
        variables = ["t_s"]
    fig = Figure(figsize=(4 * len(variables), 3.4))
    axes = fig.subplots(1, len(variables), squeeze=False)
    for ax, v in zip(axes[0], variables):
        x = df[v].to_numpy(dtype=float)
        for f, colour in ((fits[0], "#c04030"), (fits[-1], "#3070c0")):
            ax.scatter(x, _magnitude_nm(f.residual_), s=4, alpha=0.5, color=colour,
                       label="+".join(f.effects) or "nominal")
        ax.set_xlabel(v)
        ax.set_yscale("log")
    axes[0][0].set_ylabel("|residual| (nm)")
    axes[0][0].legend(fontsize=7)
    _save(fig, path)


def write_report(out: Path, df, meta, ladder, diagnoses, fits, hidden=None,
                 recording: Path | None = None) -> Path:
    """Write ``report.md`` and its figures into ``out``; returns the report's path."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    ladder_figure(ladder, out / "ladder.png")
    residual_maps(df, fits, out / "residual_map.png")
    first = diagnoses[0]
    temps = [d["variable"] for d in first.get("unexplained", {}).get("depends_on", [])
             if d["variable"].startswith("T_")]
    variables = ["t_s"] + (["F_N"] if "F_N" in df else []) + temps[:1]
    error_vs_figure(df, fits, variables, out / "error_vs.png")
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
    lines += ["## Where it fails", "", "![residual map](residual_map.png)", "",
              "![error vs variables](error_vs.png)", ""]
    if floor:
        lines += ["Noise floor (the twin's truth: validation error 90 % of the readings against "
                  "a perfect instrument): " + ", ".join(f"{k} {v:.1f} nm" for k, v in floor.items())
                  + ".", ""]
    if recording:
        lines += [f"Rerun recording: `{recording.name}` (`rerun {recording.name}`).", ""]
    return atomic_write_text(out / "report.md", "\n".join(lines))
