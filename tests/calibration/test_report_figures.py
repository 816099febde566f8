"""The report's figures (calibration/diagnosis/figures.py, model_report.py) as a reader sees
them: every numeric axis labelled with its unit, titles, labels and legends inside the figure
and clear of one another, legends clear of the data; the variables in words with units."""
import re

import numpy as np
import pytest
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from deltatwin.calibration.diagnosis.figures import (
    ModelResidual,
    ladder_figure,
    session_starts,
    variable_label,
)
from deltatwin.calibration.diagnosis.model_report import report_figures, report_model
from deltatwin.calibration.physics.fit import PhysicsFit

UNIT = re.compile(r"\([^()]+\)\s*$")        # a label ends with its unit in parentheses


def _numeric(text: str) -> bool:
    try:
        float(text.replace("\u2212", "-"))
        return True
    except ValueError:
        return False


def _shown_ticklabels(axis) -> list:
    """The tick labels drawn: visible, with text, at a location inside the axis's view (the
    locator's ticks beyond it are not drawn)."""
    low, high = sorted(axis.get_view_interval())
    span = (high - low) * 1e-9
    return [t for loc, t in zip(axis.get_majorticklocs(), axis.get_majorticklabels())
            if t.get_visible() and t.get_text() and low - span <= loc <= high + span]


def _text_boxes(fig: Figure) -> list[tuple[str, object]]:
    """(what, window extent) of the figure's words: its titles, every axis's title and
    labels, the legends."""
    renderer = fig.canvas.get_renderer()
    boxes = [(f"figure title {t.get_text()!r}", t.get_window_extent(renderer))
             for t in fig.texts if t.get_text()]
    for ax in fig.axes:
        for t in (ax.title, ax.xaxis.label, ax.yaxis.label):
            if t.get_text() and t.get_visible():
                boxes.append((repr(t.get_text()), t.get_window_extent(renderer)))
    legends = fig.legends + [ax.get_legend() for ax in fig.axes if ax.get_legend()]
    boxes += [(f"legend {k}", lg.get_window_extent(renderer)) for k, lg in enumerate(legends)]
    return boxes


def layout_problems(fig: Figure) -> list[str]:
    """What a reader would stumble on: a numeric axis without a unit, words outside the
    figure or over one another, a legend over an axes' data area."""
    FigureCanvasAgg(fig)
    fig.canvas.draw()
    problems = []
    for ax in fig.axes:
        for name, axis in (("x", ax.xaxis), ("y", ax.yaxis)):
            ticks = [t.get_text() for t in _shown_ticklabels(axis)]
            if ticks and all(map(_numeric, ticks)) and not UNIT.search(axis.label.get_text()):
                problems.append(f"{name} axis labelled {axis.label.get_text()!r}: no unit")
            if axis.get_offset_text().get_text():        # "+2e1": the ticks are not the values
                problems.append(f"{name} axis {axis.label.get_text()!r}: offset "
                                f"{axis.get_offset_text().get_text()!r}")
    boxes = _text_boxes(fig)
    frame = fig.bbox
    ticks = [(f"tick label {t.get_text()!r}", t.get_window_extent())
             for ax in fig.axes for axis in (ax.xaxis, ax.yaxis) for t in _shown_ticklabels(axis)]
    for what, box in boxes + ticks:
        if (box.x0 < frame.x0 - 1 or box.y0 < frame.y0 - 1 or box.x1 > frame.x1 + 1
                or box.y1 > frame.y1 + 1):
            problems.append(f"{what} outside the figure")
    for i, (a, box_a) in enumerate(boxes):
        for b, box_b in boxes[i + 1:]:
            if box_a.overlaps(box_b):
                problems.append(f"{a} overlaps {b}")
    data_areas = [ax.get_window_extent() for ax in fig.axes if ax.get_label() != "<colorbar>"]
    for what, box in boxes:
        if what.startswith("legend") and any(box.overlaps(area) for area in data_areas):
            problems.append(f"{what} over an axes' data")
    return problems


def test_the_layout_check_finds_what_a_reader_would_stumble_on():
    fig = Figure(figsize=(3, 2))
    ax = fig.subplots()
    ax.plot([0, 1], [20.001, 20.002], label="a line")
    ax.set_xlabel("time")                                      # no unit
    ax.set_ylabel("error (nm)")
    ax.set_title("a title much too long for so small a figure, running off its edge")
    ax.legend(loc="center")                                    # over the data
    found = " | ".join(layout_problems(fig))
    assert "'time': no unit" in found and "outside the figure" in found
    assert "legend 0 over an axes' data" in found and "'error (nm)': no unit" not in found
    assert "y axis 'error (nm)': offset" in found


@pytest.fixture(scope="module")
def two_models(force_data):
    """The force campaign (conftest.py), its achievable floor and budget recorded as
    `deltatwin simulate` records them, with the model lacking the magnetic force and the one
    that has it."""
    import copy

    from deltatwin.calibration.diagnosis.floor import record_achievable_floor
    df, meta = force_data[0], copy.deepcopy(force_data[1])
    record_achievable_floor(df, meta)
    base = PhysicsFit(["geometric_errors"]).fit(df, meta)
    full = PhysicsFit(["geometric_errors", "magnetic_force"]).fit(df, meta)
    return df, meta, [report_model("without the force", base, df, meta),
                      report_model("with the magnetic force", full, df, meta)]


@pytest.mark.slow
def test_every_report_figure_reads_with_units_and_nothing_overprinted(two_models):
    df, meta, models = two_models
    figures = report_figures(df, meta, models)
    assert set(figures) == {"ladder", "residual_time", "residual_vs", "distribution",
                            "workspace_1", "workspace_2", "workspace_compare",
                            "correlation_1", "correlation_2"}
    problems = {name: layout_problems(fig) for name, fig in figures.items()}
    assert not any(problems.values()), problems
    # the floor and its budget on twin data: a line and a bar of the sources
    legend = [t.get_text() for t in figures["ladder"].legends[0].get_texts()]
    assert "achievable floor" in legend and any(t.startswith("budget: ") for t in legend)
    # each model's map has its own colour scale; side by side they share one, and say so
    limits = [next(c.get_clim() for c in figures[f"workspace_{k}"].axes[0].collections)
              for k in (1, 2)]
    assert limits[0] != limits[1]
    assert "common to both" in figures["workspace_compare"].get_suptitle()


@pytest.mark.slow
def test_laboratory_data_without_truth_get_figures_without_a_floor(two_models):
    df, meta, models = two_models
    lab = {k: v for k, v in meta.items() if k != "truth"}
    figures = report_figures(df, lab, models[:1])
    assert "workspace_compare" not in figures
    for name in ("ladder", "residual_vs"):
        assert not layout_problems(figures[name]), name
    assert "no floor" in figures["ladder"].get_suptitle()


def test_variables_are_named_in_words_with_their_units():
    assert variable_label("t_s") == ("time (h)", 1 / 3600)
    assert variable_label("T_coil_box_C")[0] == "temperature coil box (°C)"
    assert variable_label("dT_base_dt_K_per_s") == ("rate of temperature base (K/h)", 3600.0)
    assert variable_label("q2_rad") == ("motor 2 angle (mrad)", 1e3)
    assert variable_label("ac2_rx_arcsec")[0] == "autocollimator 2 rotation about x (arcsec)"
    assert variable_label("p_Pa") == ("air pressure (hPa)", 1e-2)


def test_session_starts_are_the_later_sessions_first_times():
    import pandas as pd
    df = pd.DataFrame({"t_s": [5.0, 1.0, 9.0, 12.0, 20.0], "session": ["xy", "xy", "z", "z", "w"]})
    assert session_starts(df) == [(9.0, "z"), (20.0, "w")]


def test_the_ladder_without_validation_rows_says_it_shows_all_rows():
    rng = np.random.default_rng(3)
    n = 50
    res = ModelResidual("m", rng.normal(size=(n, 3)) * 1e-8, np.zeros((n, 3)),
                        np.ones(n, bool), np.zeros(n, bool))
    fig = ladder_figure([res], None, "", None)
    assert fig.axes[0].get_ylabel() == "error 90 %, all rows (nm)"
    assert not layout_problems(fig)
