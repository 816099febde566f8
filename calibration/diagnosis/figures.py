"""The report's figures: a model's residual on a dataset, per axis, for laboratory data as for
the twin's (nothing here needs the twin's truth; a floor is drawn where the data carry one).

Each function returns a matplotlib ``Figure`` drawn on the object API (no pyplot: writing a
report neither needs a display nor switches a notebook's backend) with constrained layout;
``report.py`` saves them. Every axis is labelled with its unit, legends sit outside the axes
(they hide no data), and a colour scale is each panel's own unless two models are compared
side by side, which the title then says. Residuals are model minus measurement (as ``deltatwin
compare`` and the Rerun recording), in nm; each (session, axis) zero re-estimated on the data's
calibration rows (compare.py ``evaluate``).
"""
from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Patch
from matplotlib.ticker import NullFormatter, ScalarFormatter
from scipy import special

from deltatwin.twin.instruments.optics import AXES

NM = 1e9
COLOURS = ("#c04030", "#3070c0", "#2a9d5c", "#8a5ab0", "#d08a1c", "#444444")
BUDGET_COLOURS = ("#cfe3f6", "#f7d9c4", "#d6ecd2", "#e6d8f0", "#f3e8b0", "#e0e0e0")
MAP_COLOURS = "RdBu_r"           # diverging: a residual's sign shows as its colour
SPLIT_NAMES = {"val": "validation rows", "cal": "calibration rows", "all": "all rows"}


@dataclass
class ModelResidual:
    """One model's residual on the dataset's rows: ``name`` (as the report calls it),
    ``residual_m`` (N,3, model minus measurement, NaN where an axis was not read),
    ``position_m`` (N,3, the platform's nominal position), ``cal``/``val`` (N,) masks."""
    name: str
    residual_m: np.ndarray
    position_m: np.ndarray
    cal: np.ndarray
    val: np.ndarray

    def axes_read(self) -> list[int]:
        return [k for k in range(3) if np.isfinite(self.residual_m[:, k]).any()]


# ---------------------------------------------------------------------------------------------
# the variables, in the words and units a researcher uses

_VARIABLES = (
    (r"t_s", "time", "h", 1 / 3600),
    (r"T_(\w+)_C", "temperature {0}", "°C", 1.0),
    (r"dT_(\w+)_dt_K_per_s", "rate of temperature {0}", "K/h", 3600.0),
    (r"dT_(\w+)_K_per_h", "rate of temperature {0}", "K/h", 1.0),
    (r"F_N", "force", "N", 1.0),
    (r"coil(\d+)_A", "coil {0} current", "A", 1.0),
    (r"q(\d)_rad", "motor {0} angle", "mrad", 1e3),
    (r"([xyz])_m", "{0} position (nominal)", "mm", 1e3),
    (r"ac(\d)_r([xyz])_arcsec", "autocollimator {0} rotation about {1}", "arcsec", 1.0),
    (r"dir_q(\d)", "direction of motor {0}'s last move", "sign", 1.0),
    (r"p_Pa", "air pressure", "hPa", 1e-2),
    (r"RH_pct", "relative humidity", "%", 1.0),
)


def variable_label(name: str) -> tuple[str, float]:
    """(axis label with its unit, factor from the column's SI value to that unit) of a data
    column or laboratory variable (``t_s`` -> ("time (h)", 1/3600)); an unknown name keeps its
    column name, its unit read from the suffix."""
    for pattern, words, unit, factor in _VARIABLES:
        m = re.fullmatch(pattern, name)
        if m:
            words = words.format(*(g.replace("_", " ") for g in m.groups()))
            return f"{words} ({unit})", factor
    stem, _, unit = name.rpartition("_")
    return f"{stem or name} ({unit if stem else 'as recorded'})", 1.0


def _figure(width: float, height: float) -> Figure:
    return Figure(figsize=(width, height), layout="constrained")


def _plain_numbers(fig: Figure) -> Figure:
    """Tick labels as the values themselves: no offset ("+2e1") beside an axis, whose label
    would then not say what the ticks are."""
    for ax in fig.axes:
        for axis in (ax.xaxis, ax.yaxis):
            formatter = axis.get_major_formatter()
            if isinstance(formatter, ScalarFormatter):
                formatter.set_useOffset(False)
    return fig


def _rows_of(models: list[ModelResidual]) -> tuple[np.ndarray, str]:
    """The rows a distribution is taken over: validation rows when there are, else all."""
    val = models[0].val
    return (val, "val") if val.any() else (np.ones(val.size, bool), "all")


def _model_handles(models: list[ModelResidual]) -> list:
    return [Patch(color=COLOURS[i % len(COLOURS)], label=m.name) for i, m in enumerate(models)]


def _split_handles() -> list:
    return [Line2D([], [], ls="", marker="o", ms=4, color="0.3", label=SPLIT_NAMES["cal"]),
            Line2D([], [], ls="", marker="o", ms=5, mfc="none", color="0.3",
                   label=SPLIT_NAMES["val"])]


def _legend_below(fig: Figure, handles: list) -> None:
    """A legend under the axes, in as many columns as the figure's width holds (an entry:
    its marker and ~0.08 in per character of its label at 10 pt)."""
    entry = max(len(h.get_label()) for h in handles) * 0.08 + 0.7
    columns = max(1, min(len(handles), int(fig.get_figwidth() / entry)))
    fig.legend(handles=handles, loc="outside lower center", ncols=columns)


def _scatter_splits(ax, x, y, model: ModelResidual, colour: str) -> None:
    """Calibration rows filled, validation rows hollow."""
    for rows, hollow in ((model.cal, False), (model.val, True)):
        ok = rows & np.isfinite(x) & np.isfinite(y)
        ax.scatter(x[ok], y[ok], s=9 if hollow else 6, linewidths=0.7,
                   facecolors="none" if hollow else colour, edgecolors=colour,
                   alpha=0.8, rasterized=True)


# ---------------------------------------------------------------------------------------------
# residual against time and against variables

def session_starts(df) -> list[tuple[float, str]]:
    """(start time s, session name) of every session after the first, in time order."""
    if "session" not in df:
        return []
    t = df["t_s"].to_numpy(dtype=float)
    starts = sorted((float(t[(df["session"] == s).to_numpy()].min()), str(s))
                    for s in df["session"].astype(str).unique())
    return starts[1:]


def residual_time_figure(df, models: list[ModelResidual]) -> Figure:
    """The residual per axis against time, session starts marked."""
    axes_read = models[0].axes_read()
    label, factor = variable_label("t_s")
    t = df["t_s"].to_numpy(dtype=float) * factor
    fig = _figure(10, 2.3 * len(axes_read) + 1.2)
    axs = fig.subplots(len(axes_read), 1, sharex=True, squeeze=False)[:, 0]
    for ax, k in zip(axs, axes_read):
        for i, m in enumerate(models):
            _scatter_splits(ax, t, m.residual_m[:, k] * NM, m, COLOURS[i % len(COLOURS)])
        for start, _ in session_starts(df):
            ax.axvline(start * factor, color="k", ls="--", lw=0.8)
        ax.axhline(0.0, color="0.6", lw=0.6)
        ax.set_ylabel(f"{AXES[k]} residual (nm)")
    axs[-1].set_xlabel(label)
    handles = _model_handles(models) + _split_handles()
    starts = session_starts(df)
    if starts:
        handles.append(Line2D([], [], color="k", ls="--", lw=0.8, label="session " + ", ".join(
            name for _, name in starts) + " starts"))
    _legend_below(fig, handles)
    fig.suptitle("Residual per axis against time (model minus measurement)")
    return _plain_numbers(fig)


def residual_vs_figure(models: list[ModelResidual], variables: dict, named: set) -> Figure:
    """The residual per axis (rows) against each variable (columns; ``variables``: {name:
    values in SI}); ``named``: those the attribution names (the others are the dataset's
    main variables), said above each column."""
    axes_read = models[0].axes_read()
    names = list(variables)
    fig = _figure(max(7.5, 3.0 * len(names) + 1.0), 2.2 * len(axes_read) + 1.6)
    axs = fig.subplots(len(axes_read), len(names), sharex="col", sharey="row", squeeze=False)
    for c, name in enumerate(names):
        label, factor = variable_label(name)
        x = np.asarray(variables[name], dtype=float) * factor
        for r, k in enumerate(axes_read):
            ax = axs[r, c]
            for i, m in enumerate(models):
                _scatter_splits(ax, x, m.residual_m[:, k] * NM, m, COLOURS[i % len(COLOURS)])
            ax.axhline(0.0, color="0.6", lw=0.6)
            if c == 0:
                ax.set_ylabel(f"{AXES[k]} residual (nm)")
        axs[-1, c].set_xlabel(label)
        axs[0, c].set_title("named by the attribution" if name in named
                            else "a main variable of the data", fontsize=9)
    handles = _model_handles(models) + _split_handles()
    _legend_below(fig, handles)
    fig.suptitle("Residual per axis against the laboratory's variables")
    return _plain_numbers(fig)


# ---------------------------------------------------------------------------------------------
# the workspace

VIEWS = (("top view", 0, 1), ("side view", 0, 2))     # (title, horizontal, vertical) axes


def _map_panel(fig, ax, model: ModelResidual, k: int, view: tuple, limit: float):
    """One view of axis ``k``'s residual over the workspace, colour scale +-``limit`` nm;
    the largest residuals drawn last (on top)."""
    _, h, v = view
    r = model.residual_m[:, k] * NM
    ok = np.isfinite(r)
    order = np.flatnonzero(ok)[np.argsort(np.abs(r[ok]), kind="stable")]
    p = model.position_m * 1e3
    # a grey rim: a reading near zero (white) still shows where it was taken
    sc = ax.scatter(p[order, h], p[order, v], c=r[order], s=16, cmap=MAP_COLOURS,
                    vmin=-limit, vmax=limit, edgecolors="0.55", linewidths=0.3,
                    rasterized=True)
    ax.set_xlabel(f"{AXES[h]} (mm)")
    ax.set_ylabel(f"{AXES[v]} (mm)")
    ax.set_aspect("equal", adjustable="box")
    return sc


def _limit(values_nm: np.ndarray) -> float:
    """A colour scale's half range: the 98th percentile of |residual| (a few outliers do not
    wash the map out; they show at the scale's ends)."""
    v = np.abs(values_nm[np.isfinite(values_nm)])
    return float(np.percentile(v, 98)) if v.size and np.percentile(v, 98) > 0 else 1.0


def workspace_figure(model: ModelResidual) -> Figure:
    """One model's residual over the workspace: per axis (columns) a top and a side view
    (rows), each axis with its own colour scale in nm."""
    axes_read = model.axes_read()
    fig = _figure(3.6 * len(axes_read) + 0.6, 7.6)
    axs = fig.subplots(2, len(axes_read), squeeze=False)
    for c, k in enumerate(axes_read):
        limit = _limit(model.residual_m[:, k] * NM)
        for r, view in enumerate(VIEWS):
            sc = _map_panel(fig, axs[r, c], model, k, view, limit)
            axs[r, c].set_title(f"{AXES[k]} residual, {view[0]}", fontsize=10)
        fig.colorbar(sc, ax=axs[:, c], location="bottom", shrink=0.9,
                     label=f"{AXES[k]} residual (nm)")
    fig.suptitle(f"{model.name}: residual over the workspace (each axis its own colour scale)")
    return _plain_numbers(fig)


def workspace_comparison_figure(a: ModelResidual, b: ModelResidual) -> Figure:
    """Two models side by side (columns: a's top and side views, then b's), per axis (rows),
    on a colour scale common to both models for each axis."""
    axes_read = a.axes_read()
    fig = _figure(14, 3.3 * len(axes_read) + 1.0)
    axs = fig.subplots(len(axes_read), 4, squeeze=False)
    for r, k in enumerate(axes_read):
        limit = max(_limit(a.residual_m[:, k] * NM), _limit(b.residual_m[:, k] * NM))
        for c, (model, view) in enumerate((m, v) for m in (a, b) for v in VIEWS):
            sc = _map_panel(fig, axs[r, c], model, k, view, limit)
            axs[r, c].set_title(f"{model.name}\n{AXES[k]} residual, {view[0]}", fontsize=9)
        fig.colorbar(sc, ax=axs[r, :], location="right", shrink=0.9,
                     label=f"{AXES[k]} residual (nm)")
    fig.suptitle(f"Residual over the workspace: {a.name} and {b.name} side by side, on a "
                 "colour scale common to both for each axis")
    return _plain_numbers(fig)


# ---------------------------------------------------------------------------------------------
# the residual's distribution

def distribution_figure(models: list[ModelResidual]) -> Figure:
    """Per axis (columns): a histogram of the residual (top) and its normal quantile-quantile
    plot (bottom), on the validation rows (all rows without a validation split)."""
    axes_read = models[0].axes_read()
    rows, which = _rows_of(models)
    fig = _figure(3.4 * len(axes_read) + 0.8, 7.4)
    axs = fig.subplots(2, len(axes_read), squeeze=False)
    for c, k in enumerate(axes_read):
        every = np.concatenate([m.residual_m[rows, k] * NM for m in models])
        every = every[np.isfinite(every)]
        # one set of bins for every model: their histograms compare bar for bar
        edges = np.histogram_bin_edges(every, bins=min(40, max(10, every.size // (4 * len(
            models))))) if every.size else 10
        for i, m in enumerate(models):
            colour = COLOURS[i % len(COLOURS)]
            r = m.residual_m[rows, k] * NM
            r = np.sort(r[np.isfinite(r)])
            if r.size < 2:
                continue
            axs[0, c].hist(r, bins=edges, histtype="step", color=colour, lw=1.4)
            q = special.ndtri((np.arange(1, r.size + 1) - 0.5) / r.size)
            axs[1, c].plot(q, r, ".", ms=3, color=colour)
            # the normal line through the quartiles: a normal residual lies on it
            q1, q3 = np.percentile(r, [25, 75])
            slope = (q3 - q1) / (2 * special.ndtri(0.75))
            axs[1, c].plot(q[[0, -1]], (q1 + q3) / 2 + slope * q[[0, -1]], color=colour,
                           lw=0.9, ls="--")
        axs[0, c].set_xlabel(f"{AXES[k]} residual (nm)")
        axs[0, c].set_ylabel("readings (count)")
        axs[1, c].set_xlabel("normal quantile (σ)")
        axs[1, c].set_ylabel(f"{AXES[k]} residual (nm)")
    handles = _model_handles(models) + [Line2D([], [], color="0.3", ls="--", lw=0.9,
                                               label="normal through the quartiles")]
    _legend_below(fig, handles)
    fig.suptitle(f"Residual distribution per axis, {SPLIT_NAMES[which]}: histogram and "
                 "normal quantile plot")
    return _plain_numbers(fig)


# ---------------------------------------------------------------------------------------------
# the ladder, with the floor and its budget

def _p90_nm(model: ModelResidual, rows: np.ndarray, k: int | None) -> float:
    r = model.residual_m[rows] if k is None else model.residual_m[rows, k]
    r = np.abs(r[np.isfinite(r)])
    return float(np.percentile(r, 90)) * NM if r.size else np.nan


def _budget_bar(ax, budget: dict, groups: list[str], x: np.ndarray, width: float) -> list:
    """The floor's budget per group as one stacked bar at ``x``: each source adds its share
    in quadrature (a segment's top is the root sum of squares up to it). Returns legend
    handles."""
    sources = list(dict.fromkeys(s for g in groups for s in budget.get(g) or {}
                                 if s not in ("quadrature_sum_nm", "achievable_floor_nm")))
    handles = []
    for j, source in enumerate(sources):
        colour = BUDGET_COLOURS[j % len(BUDGET_COLOURS)]
        for g, name in enumerate(groups):
            shares = budget.get(name, {})
            if source in shares:
                low = np.sqrt(sum(shares[s] ** 2 for s in sources[:j] if s in shares))
                high = np.hypot(low, shares[source])
                ax.bar(x[g], high - low, width, bottom=low, color=colour, edgecolor="0.5",
                       lw=0.5, zorder=2)
        handles.append(Patch(facecolor=colour, edgecolor="0.5", lw=0.5,
                             label=f"budget: {source[:-3].replace('_', ' ')}"))
    return handles


def _smallest_share(budget: dict | None, groups: list[str]) -> float:
    shares = [v for g in groups for k, v in (budget or {}).get(g, {}).items()
              if k.endswith("_nm") and v and v > 0]
    return min(shares, default=np.inf)


def _log_axis(ax, low: float, high: float) -> None:
    """A logarithmic y axis from ``low`` to ``high`` with ticks at 1, 2 and 5 times the powers
    of ten between, labelled as plain numbers."""
    ax.set_yscale("log")
    ax.set_ylim(low, high)
    decades = range(int(np.floor(np.log10(low))), int(np.ceil(np.log10(high))) + 1)
    ticks = [m * 10.0 ** d for d in decades for m in (1, 2, 5) if low <= m * 10.0 ** d <= high]
    ax.set_yticks(ticks, [f"{t:g}" for t in ticks])
    ax.yaxis.set_minor_formatter(NullFormatter())


def ladder_figure(models: list[ModelResidual], floor: dict | None, floor_kind: str,
                  budget: dict | None) -> Figure:
    """Each model's error 90 % per axis and over all axes (grouped bars; validation rows, all
    rows without a validation split), with the floor per axis (a line across the group) and
    its budget (a bar of the sources stacked in quadrature) where the data carry them
    (``floor_kind``: "achievable" or "noise")."""
    rows, which = _rows_of(models)
    groups = [AXES[k] for k in models[0].axes_read()] + ["all"]
    bars = len(models) + (1 if budget else 0)
    width, step = 0.84, 0.84 / bars
    fig = _figure(max(7.5, 0.45 * bars * len(groups) + 4.5), 4.8)
    ax = fig.subplots()
    left = np.arange(len(groups)) - width / 2
    handles = _budget_bar(ax, budget, groups, left + step / 2, step * 0.9) if budget else []
    heights = []
    for i, m in enumerate(models):
        vals = [_p90_nm(m, rows, None if g == "all" else AXES.index(g)) for g in groups]
        ax.bar(left + step * (i + (1 if budget else 0) + 0.5), vals, step * 0.9,
               color=COLOURS[i % len(COLOURS)], zorder=2)
        heights += vals
    heights = np.array([h for h in heights + list((floor or {}).values()) if h and h > 0])
    if heights.size and heights.max() > 8 * heights.min():
        _log_axis(ax, 0.5 * min(heights.min(), _smallest_share(budget, groups)),
                  1.3 * heights.max())  # a model 20x its floor and one at it, both readable
    for g, name in enumerate(groups):
        if floor and floor.get(name) is not None:
            ax.hlines(floor[name], g - width / 2 - 0.04, g + width / 2 + 0.04, color="k",
                      lw=1.6, zorder=3)
    if floor:
        handles.insert(0, Line2D([], [], color="k", lw=1.6, label=f"{floor_kind} floor"))
    ax.set_xticks(range(len(groups)), [f"axis {g}" if g != "all" else "all axes"
                                       for g in groups])
    ax.set_ylabel(f"error 90 %, {SPLIT_NAMES[which]} (nm)")
    handles = _model_handles(models) + handles
    fig.legend(handles=handles, loc="outside right center")
    fig.suptitle("Error 90 % per axis" + (f" against the {floor_kind} floor"
                                            + (" and its budget" if budget else "")
                                            if floor else " (no floor in the data's metadata)"))
    return _plain_numbers(fig)


# ---------------------------------------------------------------------------------------------
# the parameters' correlation

def short_labels(labels: list[str]) -> list[str]:
    """Parameter labels without their effect's name when one effect holds them all."""
    effects = {lab.split(".", 1)[0] for lab in labels}
    return [lab.split(".", 1)[1] for lab in labels] if len(effects) == 1 else labels


def correlation_figure(name: str, labels: list[str], correlation: np.ndarray,
                       n_parameters: int) -> Figure:
    """The correlation matrix of the identified parameters (``labels``, of the model's
    ``n_parameters``)."""
    n = len(labels)
    size = max(5.5, 0.19 * n + 3.5)
    fig = _figure(size + 1.2, size)
    ax = fig.subplots()
    im = ax.imshow(correlation, cmap=MAP_COLOURS, vmin=-1, vmax=1, interpolation="nearest")
    short = short_labels(labels)
    ax.set_xticks(range(n), short, rotation=90, fontsize=7)
    ax.set_yticks(range(n), short, fontsize=7)
    fig.colorbar(im, ax=ax, shrink=0.6, label="correlation coefficient (dimensionless)")
    fig.suptitle(f"{name}: correlation of the {n} identified parameters (of {n_parameters})")
    return _plain_numbers(fig)
