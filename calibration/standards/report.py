"""The standards' report: the figures with their expanded uncertainties and, given a tolerance,
the ISO 14253-1 decision; Markdown with PNG figures (matplotlib's object API, no display):

* ISO 230-2: x̄↑ and x̄↓ against the target with their ±2s bands, per axis;
* ISO 9283: the attained positions of each pose about their barycentre (x-y and x-z), the
  RP sphere's section, the AP in the title;
* ISO 230-3: the drift against time with the temperatures;
* the uncertainty budget of the largest position figure.

``figure_rows`` gives the table the report, the JSON and the command line print. Several
arms (uncompensated, compensated through a model) are reported side by side.
"""
from __future__ import annotations

from pathlib import Path

import matplotlib
import numpy as np
from matplotlib.figure import Figure

from deltatwin.calibration.standards.gaussian import rp_gaussian
from deltatwin.calibration.standards.iso230_2 import AXIS_FIGURES
from deltatwin.calibration.standards.uncertainty import SOURCES, conformance, expanded
from deltatwin.files import atomic_write, atomic_write_text

NM = 1e9
TITLES = {"iso9283": "ISO 9283", "iso230-2": "ISO 230-2", "iso230-3": "ISO 230-3 ETVE"}
COLOURS = ("#c03030", "#3070c0", "#30a050", "#a060c0")
# which uncertainty each ISO 230-2 axis figure takes (uncertainty.expanded)
KIND_230_2 = {"B": "difference", "B_mean": "difference", "R_up": "repeatability",
              "R_down": "repeatability", "R": "repeatability"}


def _save(fig, path: Path) -> None:
    atomic_write(path, lambda tmp: fig.savefig(tmp, format="png", dpi=110, bbox_inches="tight"))


def _row(arm, figure, value_m, U_m, tolerance_nm, budget=None, unit="nm"):
    row = {"arm": arm, "figure": figure, "value_nm": value_m * NM, "U_nm": U_m * NM}
    if tolerance_nm is not None and figure.split(" ")[0] in tolerance_nm:
        T = tolerance_nm[figure.split(" ")[0]]
        row.update(tolerance_nm=T, decision=conformance(value_m * NM, U_m * NM, T))
    if budget is not None:
        row["budget_nm"] = {k: v * NM for k, v in budget.items()}
    return row


def figure_rows(test, arm: str, result, specs: dict, tolerance_nm: dict | None = None):
    """Rows {arm, figure, value_nm, U_nm[, tolerance_nm, decision]} of a test's result.
    ``specs`` {axis: MeasurementSpec}; ``tolerance_nm`` {figure name: largest allowed nm}
    (e.g. {"AP": 500, "R": 50})."""
    rows = []
    if test.test == "iso9283":
        spec = max(specs.values(), key=lambda s: s.dead_path_m)
        for p in result.poses:
            L = float(np.linalg.norm(p.command_m))
            U, b = expanded(spec, "position", L, p.n)
            for k in ("APx", "APy", "APz", "AP"):
                rows.append(_row(arm, f"{k} {p.name}", getattr(p, k), U, tolerance_nm, b))
            Ur, br = expanded(spec, "repeatability", multiplier=rp_gaussian(1.0, p.n))
            rows.append(_row(arm, f"RP {p.name}", p.RP, Ur, tolerance_nm, br))
            if p.dAP is not None:
                rows.append(_row(arm, f"dAP {p.name}", p.dAP, U, tolerance_nm, b))
                rows.append(_row(arm, f"dRP {p.name}", p.dRP, Ur, tolerance_nm, br))
    elif test.test == "iso230-2":
        for a, r in result.items():
            L = float(np.max(np.abs(r.targets_m - np.mean(r.targets_m)))) + float(
                np.max(np.abs(test.positions_m[a])))
            for k in AXIS_FIGURES:
                U, b = expanded(specs[a], KIND_230_2.get(k, "position"), L, r.n_up)
                rows.append(_row(arm, f"{k} {a}", getattr(r, k), U, tolerance_nm, b))
    else:
        L = float(np.max(np.abs(test.positions_m["rest"])))
        for d in result.directions:
            U, b = expanded(specs[d.axis], "position", L, 1)
            rows.append(_row(arm, f"ETVE {d.axis}", d.etve, U, tolerance_nm, b))
            rows.append(_row(arm, f"drift {d.axis}", d.drift, U, tolerance_nm, b))
            rows.append(_row(arm, f"slope {d.axis} (nm/K)", d.slope_m_per_K,
                             2 * d.slope_std_m_per_K, None))
    return rows


def plot_iso230_2(results: dict, path: Path) -> None:
    """``results`` {arm: {axis: Iso230_2Result}}: x̄↑, x̄↓ with ±2s bands, one column per
    axis; below, each arm less its own straight line through x̄ (a scale error hides the
    bands at full scale); under them the standard's axis figures per arm."""
    axes = list(next(iter(results.values())))
    fig = Figure(figsize=(4.2 * len(axes), 7.4))
    grid = fig.subplots(3, len(axes), squeeze=False,
                        gridspec_kw={"height_ratios": [3, 3, 0.25 + 0.3 * len(results)]})
    for j, a in enumerate(axes):
        for c, (arm, res) in zip(COLOURS, results.items()):
            r = res[a]
            P = r.targets_m * 1e3
            line = np.polyfit(r.targets_m, r.xbar, 1)
            for row, base in enumerate((0.0, np.polyval(line, r.targets_m))):
                for x, s, ls, name in ((r.xbar_up, r.s_up, "-", "↑"),
                                       (r.xbar_down, r.s_down, "--", "↓")):
                    grid[row, j].plot(P, (x - base) * NM, ls, color=c, marker="o", ms=3,
                                      label=f"{arm} x̄{name}")
                    grid[row, j].fill_between(P, (x - base - 2 * s) * NM,
                                              (x - base + 2 * s) * NM, color=c, alpha=0.15)
            k = list(results).index(arm)
            grid[2, j].text(0.0, 1.0 - 0.9 * (k + 0.5) / len(results),
                            f"A {r.A * NM:.0f}  E {r.E * NM:.0f}  M {r.M * NM:.0f}  "
                            f"R {r.R * NM:.0f}  B {r.B * NM:.0f} nm  (slope "
                            f"{line[0] * 1e6:.0f} nm/mm)", color=c, fontsize=8,
                            transform=grid[2, j].transAxes, va="center")
        grid[2, j].axis("off")
        grid[0, j].set_title(f"ISO 230-2 axis {a}: x̄ ± 2s")
        grid[0, j].set_ylabel("positional deviation (nm)")
        grid[1, j].set_title("less each arm's straight line through x̄", fontsize=9)
        grid[1, j].set_ylabel("less the line (nm)")
        for row in (0, 1):
            grid[row, j].set_xlabel(f"target {a} (mm)")
            grid[row, j].grid(alpha=0.3)
    grid[0, 0].legend(fontsize=7)
    fig.tight_layout()
    _save(fig, path)


def plot_iso9283(clusters: dict, results: dict, path: Path) -> None:
    """``clusters`` {arm: {pose: attained (n, 3) m}}, ``results`` {arm: Iso9283Result}: the
    attained positions about their barycentre (x-y above, x-z below) with the RP circle."""
    arms = list(results)
    names = [p.name for p in results[arms[0]].poses]
    fig = Figure(figsize=(2.7 * len(names), 5.4))
    grid = fig.subplots(2, len(names), squeeze=False)
    t = np.linspace(0, 2 * np.pi, 100)
    for j, name in enumerate(names):
        title = []
        for c, arm in zip(COLOURS, arms):
            p = next(p for p in results[arm].poses if p.name == name)
            d = (clusters[arm][name] - p.barycentre_m) * NM
            for row, (i, k) in enumerate(((0, 1), (0, 2))):
                ax = grid[row, j]
                ax.plot(d[:, i], d[:, k], ".", color=c, ms=4, label=arm)
                ax.plot(p.RP * NM * np.cos(t), p.RP * NM * np.sin(t), "-", color=c, lw=0.8)
                ax.plot(0, 0, "+", color="k")
                to_cmd = (p.command_m - p.barycentre_m)[[i, k]]
                if np.linalg.norm(to_cmd) > 0:        # towards the command, |AP| off the plot
                    u = to_cmd / np.linalg.norm(to_cmd) * p.RP * NM
                    ax.annotate("", xy=tuple(u), xytext=(0, 0),
                                arrowprops={"arrowstyle": "->", "color": c, "lw": 0.8})
                ax.set_aspect("equal")
                ax.set_xlabel("x - x̄ (nm)", fontsize=8)
                ax.set_ylabel(("y - ȳ", "z - z̄")[row] + " (nm)", fontsize=8)
            title.append(f"AP {p.AP * NM:.0f} RP {p.RP * NM:.0f}")
        grid[0, j].set_title(f"{name}\n" + "\n".join(title), fontsize=8)
    handles, labels = grid[0, 0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=len(arms), fontsize=8)
    fig.suptitle("ISO 9283: attained positions about their barycentre (+), RP circle, arrow "
                 "towards the command (nm)", fontsize=9)
    fig.tight_layout(rect=(0, 0.05, 1, 1))
    _save(fig, path)


def plot_etve(series: dict, temperatures: dict, path: Path) -> None:
    """``series`` {arm: (t_s, {axis: displacement m})}, ``temperatures`` {sensor: (t_s, T_C)}:
    the drift against time, the temperatures below."""
    fig = Figure(figsize=(8, 5.4))
    top, bottom = fig.subplots(2, 1, sharex=True)
    styles = {"x": "-", "y": "--", "z": ":"}
    for c, (arm, (t, disp)) in zip(COLOURS, series.items()):
        for a, d in disp.items():
            top.plot(t / 3600, d * NM, styles[a], color=c, lw=1, label=f"{arm} {a}")
    top.set_ylabel("displacement (nm)")
    top.set_title("ISO 230-3 ETVE: the robot at rest")
    top.legend(fontsize=7, ncol=3)
    top.grid(alpha=0.3)
    palette = matplotlib.colormaps["tab20"]
    for k, (name, (t, T)) in enumerate(temperatures.items()):
        bottom.plot(t / 3600, T, lw=1, label=name, color=palette(k % 20))
    bottom.set_xlabel("time on the campaign's clock (h)")
    bottom.set_ylabel("temperature (°C)")
    bottom.legend(fontsize=7, ncol=4)
    bottom.grid(alpha=0.3)
    fig.tight_layout()
    _save(fig, path)


def budget_table(row: dict) -> str:
    """The Markdown budget of one row: source, standard uncertainty (nm), share of U²."""
    b = row["budget_nm"]
    total = sum(v * v for v in b.values()) or 1.0
    lines = [f"Budget of {row['figure']} ({row['arm']}): U = {row['U_nm']:.2f} nm (k = 2)", "",
             "| source | u (nm) | share of u² |", "|---|---:|---:|"]
    lines += [f"| {k} | {b[k]:.3f} | {100 * b[k] ** 2 / total:.1f} % |" for k in SOURCES
              if k in b]
    return "\n".join(lines)


def per_target_tables(results: dict) -> str:
    """ISO 230-2's per-target table (nm) of every arm and axis, in Markdown."""
    from deltatwin.calibration.standards.iso230_2 import TARGET_FIGURES

    out = []
    for arm, res in results.items():
        for a, r in res.items():
            out += [f"### {arm}, axis {a} (nm; targets in mm)", "",
                    "| target | " + " | ".join(TARGET_FIGURES) + " |",
                    "|" + "---:|" * (len(TARGET_FIGURES) + 1)]
            out += [f"| {p * 1e3:.4f} | " + " | ".join(f"{getattr(r, k)[i] * NM:.1f}"
                                                       for k in TARGET_FIGURES) + " |"
                    for i, p in enumerate(r.targets_m)]
            out.append("")
    return "\n".join(out)


def markdown(title: str, rows: list[dict], figures: list[str], intro: str,
             extra: str = "") -> str:
    """The report's text: the table of every figure, the figures, ``extra`` (Markdown), the
    largest position figure's budget."""
    has_tol = any("decision" in r for r in rows)
    head = "| arm | figure | value (nm) | U (nm, k = 2) |" + (" tolerance | decision |"
                                                          if has_tol else "")
    lines = [f"# {title}", "", intro, "", head,
             "|---|---|---:|---:|" + ("---:|---|" if has_tol else "")]
    for r in rows:
        tail = (f" {r.get('tolerance_nm', '')} | {r.get('decision', '')} |" if has_tol else "")
        lines.append(f"| {r['arm']} | {r['figure']} | {r['value_nm']:.1f} | {r['U_nm']:.1f} |"
                     + tail)
    lines += ["", "U: expanded uncertainty (k = 2) from the measuring chain's budget; for a "
              "repeatability figure (RP, R, R_up, R_down) the instrument's share: its own "
              "repeatability times the figure's multiplier, what the figure would be for a "
              "perfect robot (docs/standards.md).", ""]
    lines += [f"![{f}]({f})" for f in figures]
    if extra:
        lines += ["", extra]
    budgets = [r for r in rows if "budget_nm" in r and "air refraction" in r["budget_nm"]]
    if budgets:
        lines += ["", "## Uncertainty budget", "",
                  budget_table(max(budgets, key=lambda r: r["U_nm"]))]
    return "\n".join(lines) + "\n"


def write_markdown(path: Path, text: str) -> None:
    atomic_write_text(path, text)
