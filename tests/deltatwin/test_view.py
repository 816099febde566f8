"""``deltatwin view``: real .rrd files written from a small campaign of the twin and a ladder of
fitted DGMs, read back with rerun.chunk.RrdReader and compared with the data; the default
blueprint read back from the file (views, names, scales, ranges), not from the pixels."""
import json
import os
import re
import subprocess
import uuid
from collections import defaultdict
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from rerun.chunk import RrdReader

from deltatwin import view
from deltatwin.calibration.blackbox.dgm import DGM
from deltatwin.calibration.blackbox.direct_igm import DirectIGM
from deltatwin.calibration.blackbox.estimator import thermal_sensors
from deltatwin.calibration.blackbox.features import thermal_ladder
from deltatwin.calibration.physics.fit import PhysicsFit
from deltatwin.calibration.physics.model_file import fitted_toml
from deltatwin.cli import main
from deltatwin.models.geometry import build_geometry
from deltatwin.models.kinematics import forward
from deltatwin.models.mjcf import INSTRUMENT_SITES, PLATE_THICKNESS_M, build_model
from deltatwin.models.params import load_params
from deltatwin.twin.dataset import read_dataset, write_dataset
from deltatwin.twin.scenario import Scenario
from deltatwin.twin.workspace import hull
from deltatwin.view import LadderStep, calibration_step, write_recording

REPO = Path(__file__).resolve().parents[2]
MAX_POSES = 30
F32_REL = 2.0 ** -23          # float32 spacing relative to the value


def read_rrd(path):
    """entity -> list of (time columns as numpy, component columns as python lists)."""
    out = defaultdict(list)
    for chunk in RrdReader(str(path)).stream().to_chunks():
        b = chunk.to_record_batch()
        times, comps = {}, {}
        for name in b.schema.names:
            col = b.column(name)
            if name == view.CAMPAIGN_TIMELINE:
                v = col.to_numpy()
                times[name] = (v.astype("timedelta64[ns]").astype(np.int64) / 1e9
                               if v.dtype.kind == "m" else v)
            elif ":" in name:
                comps[name] = col.to_pylist()
        out[chunk.entity_path].append((times, comps))
    return out


def timelines_of(path):
    """Every timeline column in the recording's chunks (not Rerun's own row ids)."""
    names = set()
    for chunk in RrdReader(str(path)).stream().to_chunks():
        names |= {n for n in chunk.to_record_batch().schema.names
                  if ":" not in n and not n.startswith("rerun.")}
    return names


class Layout:
    """The default blueprint stored in a recording, by blueprint entity: views are
    ``view/<uuid>`` (kind, name, origin; sub-entities hold contents, axes, legend),
    containers ``container/<uuid>`` (kind, contents, active tab, name)."""

    TABS, HORIZONTAL, VERTICAL, GRID = 1, 2, 3, 4

    def __init__(self, path):
        reader = RrdReader(str(path))
        (store,) = reader.blueprints()
        self.parts = defaultdict(dict)
        for chunk in reader.stream(store=store).to_chunks():
            b = chunk.to_record_batch()
            for name in b.schema.names:
                if ":" in name:
                    v = b.column(name).to_pylist()[-1]
                    self.parts[chunk.entity_path[1:]][name.split(":")[1]] = (
                        v[0] if isinstance(v, list) and len(v) == 1 else v)
        self.root = "container/" + str(uuid.UUID(bytes=bytes(
            self.parts["viewport"]["root_container"])))

    def __getitem__(self, ref):
        return self.parts[ref]

    def children(self, ref):
        contents = self.parts[ref]["contents"]
        return contents if isinstance(contents, list) else [contents]

    def active(self, ref):
        return self.parts[ref].get("active_tab")

    def contents(self, view_ref):
        query = self.parts[f"{view_ref}/ViewContents"]["query"]
        return query if isinstance(query, list) else [query]

    def views(self, kind=None):
        return {ref: p for ref, p in self.parts.items() if ref.startswith("view/")
                and ref.count("/") == 1 and kind in (None, p["class_identifier"])}

    def named(self, name):
        (ref,) = [r for r, p in self.parts.items() if r.count("/") == 1
                  and p.get("display_name") == name]
        return ref


def rows_of(rrd, entity, component, timeline=None):
    """(times on ``timeline`` or None, values) of every row holding ``component``."""
    ts, vals = [], []
    for times, comps in rrd[entity]:
        if component not in comps:
            continue
        if timeline is not None and timeline not in times:
            continue
        if timeline is None and times:
            continue
        vals += comps[component]
        if timeline is not None:
            ts += list(times[timeline])
    return np.array(ts), vals


@pytest.fixture(scope="module")
def campaign(small_thermal_campaign):
    """The twin's thermal campaign (tests/conftest.py: three structure sensors and one in the
    air), with what the twin's quiet thermal campaign lacks and a laboratory file may hold:
    coil currents and autocollimator readings out of range (NaN)."""
    df, meta = small_thermal_campaign
    df = df.copy()
    rng = np.random.default_rng(7)
    for i in (1, 2, 3):
        df[f"coil{i}_A"] = rng.uniform(-0.2, 0.2, len(df))
    for c in ("ac1_ry_arcsec", "ac2_rx_arcsec"):
        df[c] = df[c].where(rng.uniform(size=len(df)) >= 0.1)
    rungs = thermal_ladder(thermal_sensors(df, meta))
    models = [(name, DGM(features=fs).fit(df, meta)) for name, fs in (rungs[0], rungs[3])]
    return df, meta, models


@pytest.fixture(scope="module")
def written(campaign, tmp_path_factory):
    df, meta, models = campaign
    ladder = [calibration_step(name, m, df) for name, m in models]
    path = tmp_path_factory.mktemp("view") / "run.rrd"
    summary = write_recording(df, meta, ladder, path, max_poses=MAX_POSES)
    return df, ladder, summary, read_rrd(path)


def field_entity(summary, k, part=""):
    """The arrows of model k's field (``part``: "/x", "/y", "/z" for a component's)."""
    return f"/world/error/{summary.ladder[k]['entity']}{part}/arrows"


def static_arrows(rrd, entity):
    """(origins, vectors) of a static Arrows3D, float64."""
    _, origins = rows_of(rrd, entity, "Arrows3D:origins")
    _, vectors = rows_of(rrd, entity, "Arrows3D:vectors")
    assert len(vectors) == 1, entity
    return (np.array(origins[0], dtype=np.float64), np.array(vectors[0], dtype=np.float64))


def expected_field_nm(df, step):
    """Mean residual (model - measurement) per position, nm, computed with pandas."""
    res = pd.DataFrame({a: step.reading_m[:, k] * 1e9 - df[f"{a}_nm"].to_numpy()
                        for k, a in enumerate("xyz")})
    res["pos_id"] = df["pos_id"].to_numpy()
    mean = res.groupby("pos_id")[["x", "y", "z"]].mean()
    return mean.dropna()


def test_entities_exist(written):
    df, ladder, summary, rrd = written
    _, model = build_model(load_params())
    geoms = {model.geom(g).name for g in range(model.ngeom)} - {"table"}
    assert {f"/world/robot/{g}" for g in geoms} <= set(rrd)
    assert {f"/world/instruments/{s}" for s in INSTRUMENT_SITES} <= set(rrd)
    entities = [r["entity"] for r in summary.ladder]
    # each model's field its own entity; the ladder is named after the models' effects
    assert entities == ["0_geometric", "1_temperatures_geometric_x_temperature_temperature_"
                        "rates_temperature_accelerations"]
    assert [r["label"] for r in summary.ladder] == [
        "geometric", "+ temperatures + geometric x temperature + temperature rates + "
        "temperature accelerations"]
    for e in ("/world/workspace/hull", "/world/workspace/cal", "/world/workspace/val",
              f"/world/error/{entities[0]}/arrows", f"/world/error/{entities[1]}/arrows",
              f"/world/step/{entities[1]}/after/arrows", f"/ladder/{entities[0]}",
              f"/ladder/{entities[1]}", "/ladder/table", "/info", "/world/axes/workspace",
              "/world/axes/robot", f"/world/legend/{entities[0]}/colours",
              f"/world/legend/{entities[1]}/caption", f"/world/step/{entities[1]}/legend/colours",
              *(f"/world/error/{e}/{a}/arrows" for e in entities for a in "xyz")):
        assert e in rrd, e
    # one timeline, the campaign's: comparing models never leaves the time series blank
    assert timelines_of(summary.path) == {view.CAMPAIGN_TIMELINE}


def test_rerun_verifies_the_file(written):
    """Rerun's own CLI loads and interprets every chunk (and the blueprint)."""
    import rerun_cli
    rerun = Path(rerun_cli.__file__).parent / "rerun"    # `python -m rerun_cli` drops the code
    done = subprocess.run([str(rerun), "rrd", "verify", str(written[2].path)],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stdout + done.stderr
    assert "verified without error" in done.stdout + done.stderr


def test_arrows_are_the_residuals_in_the_stated_unit(written):
    """Arrow vector x the model's scale = mean residual per position, to float32's relative
    precision: no nm detail is lost, even for the few-nm residuals of the complete model."""
    df, ladder, summary, rrd = written
    small = []
    for k, step in enumerate(ladder):
        scale = summary.ladder[k]["arrow_scale_nm_per_mm"]
        exp = expected_field_nm(df, step)
        _, vec = static_arrows(rrd, field_entity(summary, k))
        got = vec * scale
        assert got.shape == exp.shape
        norm = np.linalg.norm(exp.to_numpy(), axis=1, keepdims=True)
        assert np.all(np.abs(got - exp.to_numpy()) <= F32_REL * norm)
        small.append(np.median(norm))
    # temperatures matter (as in test_models.py's ladder): the complete model's arrows are
    # 5 x shorter than the geometric model's thermal drift (measured: 2382 -> 64 nm)
    assert small[-1] < small[0] / 5
    # arrows sit at the positions in the stated frame: mm from the workspace centre, ~1 nm
    geom = build_geometry(load_params())
    origin = hull(geom, point=geom.cube_offset).bounds.mean(axis=0)
    np.testing.assert_allclose(summary.origin_m, origin, rtol=0, atol=0)
    exp = expected_field_nm(df, ladder[0])
    q = df.groupby("pos_id")[["q1_rad", "q2_rad", "q3_rad"]].mean().loc[exp.index].to_numpy()
    p_m = forward(geom, q).point(geom.cube_offset)      # the measured point, the cube's centre
    got_mm, _ = static_arrows(rrd, field_entity(summary, 0))
    assert np.max(np.abs(got_mm - (p_m - origin) * 1e3)) < 1e-6           # < 1 nm
    # what the local origin avoids: absolute metres in float32 lose more than 1 nm here
    assert np.max(np.abs(p_m.astype(np.float32).astype(np.float64) - p_m)) > 1e-9


def one_two_five(scale):
    mantissa = scale / 10.0 ** np.floor(np.log10(scale) + 1e-12)
    return any(np.isclose(mantissa, m, rtol=1e-9) for m in (1.0, 2.0, 5.0))


def span_gap(magnitude_nm, scale, extent_mm):
    """How far (log) the 90th-95th percentile arrows' span misses 15-20 % of the extent."""
    lo, hi = np.percentile(magnitude_nm, [90, 95]) / scale / extent_mm
    return max(0.0, np.log(0.15 / hi), np.log(lo / 0.20))


def best_possible_gap(magnitude_nm, extent_mm):
    steps = [m * 10.0 ** d for d in range(-6, 9) for m in (1.0, 2.0, 5.0)]
    return min(span_gap(magnitude_nm, s, extent_mm) for s in steps)


def test_each_field_has_its_own_readable_scale(written):
    """Per model, 1 mm of arrow = a 1-2-5 step of nm for which the 90th-95th percentile
    arrow spans 15-20 % of the workspace (or the nearest step when none does), stated in its
    view's name; the 18.6 mm workspace shows the complete model's few-nm field too."""
    df, ladder, summary, rrd = written
    layout = Layout(summary.path)
    geom = build_geometry(load_params())
    extent_mm = float(np.max(hull(geom, point=geom.cube_offset).extents) * 1e3)
    assert summary.extent_mm == pytest.approx(extent_mm, rel=1e-12)
    scales = []
    for k, step in enumerate(ladder):
        r = summary.ladder[k]
        scale = r["arrow_scale_nm_per_mm"]
        mag = np.linalg.norm(expected_field_nm(df, step).to_numpy(), axis=1)
        assert one_two_five(scale)
        assert span_gap(mag, scale, extent_mm) == pytest.approx(
            best_possible_gap(mag, extent_mm), abs=1e-12)
        lengths_mm = np.linalg.norm(static_arrows(rrd, field_entity(summary, k))[1], axis=1)
        p95_share = np.percentile(lengths_mm, 95) / extent_mm
        assert 0.15 / 2.5 < p95_share < 0.20 * 2.5          # readable, never 1 % of it
        # the scale in the view's name (its tab's title, cut to fit beside the others)
        # and, whole, in the caption of the view's legend
        full = f"{r['label']}: 1 mm = {scale:g} nm"
        fields = layout.children(layout.children(layout.root)[0])[0]
        shown = layout[layout.children(fields)[k]]["display_name"]
        assert shown == full or (shown.endswith("\u2026") and full.startswith(shown[:-1]))
        (caption,) = rows_of(rrd, f"/world/legend/{r['entity']}/caption", "Points3D:labels")[1]
        assert caption[0].startswith(f"{r['label']}: |model - measurement|, 1 mm = {scale:g} nm\n")
        scales.append(scale)
    assert scales[1] < scales[0]                 # the second model's field gets a finer scale


def rgb(packed):
    """(r, g, b) of Rerun's packed 0xRRGGBBAA colour."""
    return ((packed >> 24) & 255, (packed >> 16) & 255, (packed >> 8) & 255)


def colour_of(magnitude_nm, top_nm):
    """The stated colour rule: YlOrRd_r from 0 to 0.85 of its range as the magnitude goes
    from 0 to the arrow spanning 20 % of the workspace (``top_nm``), saturating above."""
    import matplotlib
    c = matplotlib.colormaps["YlOrRd_r"](0.85 * np.clip(np.asarray(magnitude_nm) / top_nm, 0, 1))
    return [tuple(int(v) for v in row) for row in np.round(np.atleast_2d(c)[:, :3] * 255)]


def annotations(rrd, entity):
    """{class id: (label, rgb)} of the annotation context at ``entity``."""
    (row,) = rows_of(rrd, entity, "AnnotationContext:context")[1]
    (context,) = row                                  # one context: a list of classes
    return {c["class_id"]: (c["class_description"]["info"]["label"],
                            rgb(c["class_description"]["info"]["color"])) for c in context}


def test_colour_legend_in_nm_in_every_field_view(written):
    """Each field view holds its scale's legend: arrows drawn at that scale (length x scale =
    the nm in its label), in the colour the rule gives that many nm, from round values to
    the top of the colour map; and the field's arrows are coloured by the same rule."""
    df, ladder, summary, rrd = written
    layout = Layout(summary.path)
    extent = summary.extent_mm
    legends = set()
    for ref in layout.views("3D"):
        contents = layout.contents(ref)
        legend = [c for c in contents if "legend" in c]
        if "$origin/robot/**" in contents:
            continue
        assert len(legend) == 1, layout[ref]["display_name"]     # every field view has one
        legends.add(legend[0].replace("$origin", "/world")[:-3])
    assert len(legends) == 3                # two models' own scales, the step's after view
    for entity in legends:
        _, labels = rows_of(rrd, f"{entity}/colours", "Arrows3D:labels")
        _, vectors = rows_of(rrd, f"{entity}/colours", "Arrows3D:vectors")
        _, colours = rows_of(rrd, f"{entity}/colours", "Arrows3D:colors")
        caption = rows_of(rrd, f"{entity}/caption", "Points3D:labels")[1][0][0]
        scale = float(re.search(r"1 mm = ([0-9.e+-]+) nm", caption).group(1))
        top = scale * 0.20 * extent
        nm = [float(t.split()[-2]) for t in labels[0]]
        assert labels[0][-1].startswith("\u2265 ") and nm[-1] == pytest.approx(top, rel=2e-3)
        assert 3 <= len(nm) - 1 <= 7 and np.all(np.diff(nm) > 0)
        lengths = np.linalg.norm(np.array(vectors[0], dtype=float), axis=1)
        np.testing.assert_allclose(lengths * scale, [*nm[:-1], top], rtol=1e-6)
        assert [rgb(c) for c in colours[0]] == colour_of([*nm[:-1], top], top)
    for k, r in enumerate(summary.ladder):
        scale = r["arrow_scale_nm_per_mm"]
        exp = expected_field_nm(df, ladder[k])
        got = annotations(rrd, f"/world/error/{r['entity']}")
        assert [got[int(i)][1] for i in exp.index] == colour_of(
            np.linalg.norm(exp.to_numpy(), axis=1), scale * 0.20 * extent)


def test_hovering_an_arrow_gives_its_residual_in_nm(written):
    """The viewer's hover card lists an instance's components only when it has three or
    fewer (measured in the real viewer, Rerun 0.41: docs/view-hover.png): every field's
    arrows hold origins, vectors and class ids alone, and each class's label (the card shows
    it) starts with the arrow's residual in nm; the hull does not take the pointer."""
    df, ladder, summary, rrd = written
    for k in range(len(summary.ladder)):
        exp = expected_field_nm(df, ladder[k])
        for part in ("", "/x", "/y", "/z"):
            arrows = field_entity(summary, k, part)
            assert {c for _, comps in rrd[arrows] for c in comps} == {
                "Arrows3D:origins", "Arrows3D:vectors", "Arrows3D:class_ids"}, arrows
            (ids,) = rows_of(rrd, arrows, "Arrows3D:class_ids")[1]
            assert ids == list(exp.index)                       # the positions' ids
            labels = annotations(rrd, arrows.rsplit("/", 1)[0])
            for i, v in zip(exp.index, exp.to_numpy()):
                text = labels[int(i)][0]
                if part:
                    a = part[1]
                    assert text.startswith(f"{a} {v['xyz'.index(a)]:+.1f} nm at pos {i} ")
                else:
                    assert text.startswith(f"{np.linalg.norm(v):.1f} nm at pos {i} ")
                    assert text.endswith(f"x {v[0]:+.1f}, y {v[1]:+.1f}, z {v[2]:+.1f} nm")
    layout = Layout(summary.path)
    fields = [ref for ref in layout.views("3D") if "$origin/robot/**" not in layout.contents(ref)]
    for ref in fields:
        for entity in ("hull", "hull_edges"):
            assert layout[f"{ref}/ViewContents/overrides/world/workspace/{entity}/visualizers"
                          ] == {"interactive": False}


def test_per_axis_fields(written):
    """Each model's x, y and z residuals are fields of their own, at the model's scale, with
    a tab per model ("per axis") showing the three and the whole field."""
    df, ladder, summary, rrd = written
    layout = Layout(summary.path)
    per_axis = layout.named("per axis")
    for k, r in enumerate(summary.ladder):
        exp = expected_field_nm(df, ladder[k]).to_numpy()
        for a, axis in enumerate("xyz"):
            _, vec = static_arrows(rrd, field_entity(summary, k, f"/{axis}"))
            got = vec * r["arrow_scale_nm_per_mm"]
            assert np.all(np.abs(got[:, a] - exp[:, a]) <= F32_REL * np.abs(exp[:, a]))
            assert not np.delete(got, a, axis=1).any()          # along its axis only
        grid = layout.children(per_axis)[k]
        assert layout[grid]["container_kind"] == Layout.GRID
        assert [layout.contents(v)[2] for v in layout.children(grid)] == [
            f"$origin/error/{r['entity']}{part}/arrows" for part in ("/x", "/y", "/z", "")]


def test_axes_in_mm_with_a_triad(written):
    """The scene is in mm: a triad X, Y, Z (red, green, blue) of a round length in mm, so
    labelled, beside the workspace in every field view, and a larger one by the robot."""
    df, ladder, summary, rrd = written
    geom = build_geometry(load_params())
    ws = hull(geom, point=geom.cube_offset)
    for entity, (lo, hi) in (("/world/axes/workspace", (0.2, 0.3)),
                             ("/world/axes/robot", (0.1, 0.25))):
        (vectors,) = rows_of(rrd, entity, "Arrows3D:vectors")[1]
        (origins,) = rows_of(rrd, entity, "Arrows3D:origins")[1]
        (labels,) = rows_of(rrd, f"{entity}/labels", "Points3D:labels")[1]
        (colours,) = rows_of(rrd, entity, "Arrows3D:colors")[1]
        length = vectors[0][0]
        np.testing.assert_array_equal(vectors, length * np.eye(3))
        assert len({tuple(o) for o in origins}) == 1
        assert one_two_five(length) or one_two_five(length / 2.5)   # 1, 2, 2.5, 5 x 10^n
        assert labels == [f"{a} {length:g} mm" for a in "XYZ"]
        assert [rgb(c) for c in colours] == [view.AXIS_COLOURS[a] for a in "xyz"]
        if entity.endswith("workspace"):       # beside the workspace: outside its hull
            assert lo * summary.extent_mm <= length <= hi * summary.extent_mm
            o_m = np.array(origins[0]) / 1e3 + summary.origin_m
            assert not ws.contains([o_m])[0]
        else:                                   # mm: the robot is ~0.4 m tall
            assert 50.0 <= length <= 200.0


def test_arrow_scale_rule_on_random_fields():
    """``arrow_scale_nm_per_mm`` against a brute force over 1-2-5 steps, on fields with a
    span of 1 nm to 100 um and spreads from none to wide."""
    rng = np.random.default_rng(18)
    hit = 0
    for _ in range(300):
        extent = rng.uniform(5.0, 50.0)
        mag = rng.lognormal(rng.uniform(0, 11), rng.uniform(0, 1.5), rng.integers(5, 400))
        scale = view.arrow_scale_nm_per_mm(mag, extent)
        assert one_two_five(scale)
        best = best_possible_gap(mag, extent)
        assert span_gap(mag, scale, extent) == pytest.approx(best, abs=1e-12)
        hit += best == 0.0
    assert 50 < hit < 300                 # both cases (a step in the band, none) were met
    assert view.arrow_scale_nm_per_mm(np.zeros(4), 10.0) == 1.0
    assert view.arrow_scale_nm_per_mm([np.nan], 10.0) == 1.0
    with pytest.raises(ValueError, match="extent"):
        view.arrow_scale_nm_per_mm([1.0, 2.0], 0.0)


def test_residual_before_and_after_a_step_shown_the_same_way(written):
    """The step's tab sets the previous model's field beside the new model's, both at the
    previous model's scale (the error falls as the arrows shrink)."""
    df, ladder, summary, rrd = written
    scale0 = summary.ladder[0]["arrow_scale_nm_per_mm"]
    e0, e1 = (r["entity"] for r in summary.ladder)
    f1 = expected_field_nm(df, ladder[1]).to_numpy()
    _, after = static_arrows(rrd, f"/world/step/{e1}/after/arrows")
    assert np.all(np.abs(after * scale0 - f1) <= F32_REL * np.linalg.norm(f1, axis=1,
                                                                            keepdims=True))
    layout = Layout(summary.path)
    label = summary.ladder[1]["label"]
    step = layout.named(f"before/after {label}")
    assert layout[step]["container_kind"] == Layout.VERTICAL
    before, after_view = layout.children(step)
    assert layout.contents(before) == ["$origin/workspace/**", "$origin/axes/workspace/**",
                                       f"$origin/error/{e0}/arrows", f"$origin/legend/{e0}/**"]
    assert layout.contents(after_view) == ["$origin/workspace/**", "$origin/axes/workspace/**",
                                           f"$origin/step/{e1}/after/arrows",
                                           f"$origin/step/{e1}/legend/**"]
    assert layout[before]["display_name"].endswith(f"1 mm = {scale0:g} nm")
    assert layout[after_view]["display_name"].endswith(f"1 mm = {scale0:g} nm")


def test_ladder_bar_chart_and_table(written):
    """The bars and the table give what ``deltatwin compare`` and ``diagnose`` print: the 90th
    percentile of |model - measurement| over the validation readings, pooled over the axes
    (bars, table) and per axis (table), here computed with numpy from the dataset."""
    df, ladder, summary, rrd = written
    val = (df["split"] == "val").to_numpy()
    bars = [rows_of(rrd, f"/ladder/{r['entity']}", "BarChart:values")[1][0][0]["buffer"]
            for r in summary.ladder]
    table = rows_of(rrd, "/ladder/table", "TextDocument:text")[1][0][0]
    for k, step in enumerate(ladder):
        r = step.reading_m[val] * 1e9 - df.loc[val, ["x_nm", "y_nm", "z_nm"]].to_numpy()
        pooled = np.abs(r[np.isfinite(r)])
        assert bars[k] == [pytest.approx(np.percentile(pooled, 90), rel=1e-9)]
        per_axis = [np.percentile(np.abs(c[np.isfinite(c)]), 90) for c in r.T]
        row = summary.ladder[k]
        assert row["p90_nm"] == pytest.approx({"all": bars[k][0],
                                               **dict(zip("xyz", per_axis))}, rel=1e-9)
        assert row["rms_val_nm"] == pytest.approx(np.sqrt(np.mean(pooled ** 2)), rel=1e-9)
        cells = " | ".join(f"{v:.1f}" for v in (bars[k][0], *per_axis))
        assert f"| {k} | {row['label']} | {cells} |" in table
        assert f"{row['arrow_scale_nm_per_mm']:g} nm |" in table
    assert bars[1][0] < bars[0][0]
    assert "validation split" in table and "p90" in table


def floor_recording(campaign, tmp_path, truth):
    """The campaign's ladder recorded with ``truth`` as the metadata's truth."""
    df, meta, models = campaign
    meta = {**meta, "truth": truth}
    ladder = [calibration_step(name, m, df) for name, m in models]
    summary = write_recording(df, meta, ladder, tmp_path / "floor.rrd", max_poses=2)
    return summary, read_rrd(summary.path)


def test_floor_beside_each_models_figure(campaign, tmp_path):
    """The floor of ``floor_of`` (the achievable floor where the data carry it, else the
    noise floor, else none), in the models' statistic, beside every model's figure: in each
    field view's caption, as the ladder table's last row, and (pooled) as a grey bar."""
    achievable = {"x": 1.25, "y": 2.5, "z": 3.75, "all": 2.875}
    summary, rrd = floor_recording(campaign, tmp_path, {"achievable_floor_nm": achievable,
                                                        "noise_floor_nm": {"x": 0.5}})
    assert (summary.floor_nm, summary.floor_kind) == (achievable, "achievable")
    line = "achievable floor 2.9 nm (x 1.2, y 2.5, z 3.8)"     # as compare prints: .1f
    for r in summary.ladder:
        for entity in (f"/world/legend/{r['entity']}", f"/world/step/{r['entity']}/legend"):
            if entity in {e.rsplit("/", 1)[0] for e in rrd}:
                caption = rows_of(rrd, f"{entity}/caption", "Points3D:labels")[1][0][0]
                assert caption.splitlines()[1:] == [
                    f"validation p90 {view.p90_text(r['p90_nm'])}", line]
    table = rows_of(rrd, "/ladder/table", "TextDocument:text")[1][0][0]
    assert "| | **achievable floor** | 2.9 | 1.2 | 2.5 | 3.8 | | | |" in table
    (bar,) = rows_of(rrd, "/ladder/floor", "BarChart:values")[1]
    assert bar[0]["buffer"] == [achievable["all"]]
    noise = {"x": 4.0, "y": 3.0, "z": 5.0}
    summary, rrd = floor_recording(campaign, tmp_path, {"noise_floor_nm": noise})
    caption = rows_of(rrd, f"/world/legend/{summary.ladder[0]['entity']}/caption",
                      "Points3D:labels")[1][0][0]
    assert caption.splitlines()[-1] == "noise floor (x 4.0, y 3.0, z 5.0 nm)"
    assert "/ladder/floor" not in rrd                          # no pooled noise floor
    table = rows_of(rrd, "/ladder/table", "TextDocument:text")[1][0][0]
    assert "| | **noise floor** | - | 4.0 | 3.0 | 5.0 | | | |" in table
    assert "the noise floor (per axis only) in the table's last row" in table
    summary, rrd = floor_recording(campaign, tmp_path, {})     # laboratory data
    caption = rows_of(rrd, f"/world/legend/{summary.ladder[1]['entity']}/caption",
                      "Points3D:labels")[1][0][0]
    assert caption.splitlines()[-1] == "floor: none recorded with the data"
    assert "/ladder/floor" not in rrd


def test_time_series_match_the_dataset(written):
    df, ladder, summary, rrd = written
    t = df["t_s"].to_numpy()
    cols = {f"/timeseries/temperature_C/{c[2:-2]}": c for c in df.columns if c.startswith("T_")}
    cols.update({f"/timeseries/coil_current_A/coil{i}": f"coil{i}_A" for i in (1, 2, 3)})
    cols["/timeseries/force_N/F"] = "F_N"
    cols.update({f"/timeseries/std_nm/{a}_std_nm": f"{a}_std_nm" for a in "xyz"})
    cols.update({f"/timeseries/autocollimator_arcsec/{c[:-7]}": c
                 for c in ("ac1_ry_arcsec", "ac1_rz_arcsec", "ac2_rx_arcsec", "ac2_rz_arcsec")})
    assert len(cols) == 4 + 3 + 1 + 3 + 4
    assert df[["ac1_ry_arcsec", "ac2_rx_arcsec"]].isna().any().all()   # gaps are skipped
    for entity, c in cols.items():
        ts, vals = rows_of(rrd, entity, "Scalars:scalars", view.CAMPAIGN_TIMELINE)
        ok = np.isfinite(df[c].to_numpy())
        np.testing.assert_array_equal(np.array(vals)[:, 0], df[c].to_numpy()[ok], err_msg=c)
        np.testing.assert_allclose(ts, t[ok], rtol=0, atol=1e-9)
    for k, step in enumerate(ladder):
        for a, axis in enumerate("xyz"):
            entity = f"/timeseries/residual_nm/{summary.ladder[k]['entity']}/{axis}"
            ts, vals = rows_of(rrd, entity, "Scalars:scalars", view.CAMPAIGN_TIMELINE)
            r = step.reading_m[:, a] * 1e9 - df[f"{axis}_nm"].to_numpy()
            ok = np.isfinite(r)
            # m <-> nm conversions of cm-sized readings round at ~1e-9 nm
            np.testing.assert_allclose(np.array(vals)[:, 0], r[ok], rtol=0, atol=1e-6)
            np.testing.assert_allclose(ts, t[ok], rtol=0, atol=1e-9)


def test_layout_opens_on_the_first_field(written):
    """What the viewer shows on opening: the first model's field alone (workspace, points,
    arrows; the robot in another tab), paused, the side and time panels collapsed."""
    df, ladder, summary, rrd = written
    layout = Layout(summary.path)
    root = layout.root
    assert layout[root]["container_kind"] == Layout.TABS
    tabs = layout.children(root)
    assert [layout[t]["display_name"] for t in tabs] == [
        "error fields", "per axis", "before/after", "robot and beams", "campaign"]
    error_tab = tabs[0]
    assert layout.active(root) == error_tab
    fields, side = layout.children(error_tab)
    assert layout[fields]["container_kind"] == Layout.TABS
    first = layout.active(fields)
    assert first == layout.children(fields)[0]
    r0 = summary.ladder[0]
    assert layout[first]["display_name"] == (f"{r0['label']}: 1 mm = "
                                             f"{r0['arrow_scale_nm_per_mm']:g} nm")
    assert layout[first]["class_identifier"] == "3D"
    assert layout.contents(first) == ["$origin/workspace/**", "$origin/axes/workspace/**",
                                      f"$origin/error/{r0['entity']}/arrows",
                                      f"$origin/legend/{r0['entity']}/**"]
    robot = layout.named("robot and beams")
    assert robot == tabs[3]
    assert "$origin/robot/**" in layout.contents(robot)
    assert "$origin/axes/robot/**" in layout.contents(robot)
    assert layout["time_panel"]["play_state"] == 1                 # PlayState.Paused
    assert layout["time_panel"]["timeline"] == view.CAMPAIGN_TIMELINE
    for panel in ("time_panel", "blueprint_panel", "selection_panel"):
        assert layout[panel]["state"] == 2                          # PanelState.Collapsed
    # the ladder: bar chart (one entity per model: the legend names them) and table
    bars = layout.named("validation p90 |model - measurement| per model, and the floor (nm)")
    assert layout[bars]["space_origin"] == "ladder"
    assert layout[f"{bars}/PlotLegend"]["corner"] == 2              # Corner2D.RightTop


def test_time_series_views_span_the_campaign(written):
    """Every plot spans the whole campaign, the same x range in every plot (stacked plots line
    up in time), one unit per plot, explicit and distinct colours, readings as points, and x
    room after the last reading for the legend (top right), so the legend covers no data."""
    df, ladder, summary, rrd = written
    layout = Layout(summary.path)
    t0, t1 = df["t_s"].min() * 1e9, df["t_s"].max() * 1e9
    plots = layout.views("TimeSeries")
    assert len(plots) == len(ladder) + 5      # residual per model; T, coils, force, std, ac
    units = re.compile(r"_(C|A|N|nm|arcsec)$")
    ranges = {str(layout[f"{ref}/TimeAxis"]["view_range"]) for ref in plots}
    assert len(ranges) == 1                                     # one x range for all
    for ref, p in plots.items():
        rng = layout[f"{ref}/TimeAxis"]["view_range"]
        assert rng["start"] <= t0 and rng["end"] >= t1 + 0.1 * (t1 - t0), p["display_name"]
        assert layout[f"{ref}/PlotLegend"] == {"corner": 2, "visible": True}
        origin = "/" + p["space_origin"]
        assert units.search(origin.split("/")[2]), origin      # one unit per plot
        series = [e for e in rrd if e.startswith(origin + "/") or e == origin]
        assert series, origin
        colours = []
        for e in series:
            assert not any("SeriesLines" in c for _, comps in rrd[e] for c in comps), e
            _, colour = rows_of(rrd, e, "SeriesPoints:colors")      # readings as points,
            colours.append(colour[0][0])                             # explicit colour
        assert len(set(colours)) == len(colours), origin            # distinct in a plot
    origins = {p["space_origin"] for p in plots.values()}
    assert {"timeseries/coil_current_A", "timeseries/force_N"} <= origins   # A apart from N


def planned_boxes(layout):
    """{ref: (width, height) px} of every container and view as the default layout plans
    them at view.SCREEN_PX: the window less the viewer's own bars, split by the containers'
    shares; a view's box holds its title bar (or, in tabs, the tab bar)."""
    def walk(ref, w, h):
        boxes[ref] = (w, h)
        if not ref.startswith("container/"):
            return
        part, kids = layout[ref], layout.children(ref)
        kind = part["container_kind"]
        if kind == Layout.TABS:
            inner = [(w, h)] * len(kids)
        elif kind == Layout.GRID:
            cols = part.get("grid_columns") or 1
            rows = -(-len(kids) // cols)
            inner = [(w / cols, h / rows)] * len(kids)
        else:
            key = "col_shares" if kind == Layout.HORIZONTAL else "row_shares"
            shares = np.asarray(part.get(key) or [1.0] * len(kids), dtype=float)
            shares = shares / shares.sum()
            inner = [(w * f, h) if kind == Layout.HORIZONTAL else (w, h * f) for f in shares]
        for kid, (kw, kh) in zip(kids, inner):
            walk(kid, kw, kh)
    boxes = {}
    walk(layout.root, view.SCREEN_PX[0], view.SCREEN_PX[1] - view.WINDOW_CHROME_PX)
    return boxes


def long_ladder(campaign):
    """Four steps with long effect names (titles that must be cut to fit)."""
    df, meta, models = campaign
    steps = [calibration_step(name, m, df) for name, m in models]
    effects = ["geometric_errors", "thermal_expansion_of_the_frame", "loop_drift_with_lag",
               "magnetic_force_of_the_coils", "air_refraction_by_pressure_and_humidity"]
    return [LadderStep("m", steps[k % 2].reading_m, tuple(effects[:k + 1])) for k in range(4)]


@pytest.mark.parametrize("ladder_of", ["two", "four"])
def test_every_tab_title_and_every_plots_tick_labels_fit(campaign, written, tmp_path,
                                                          ladder_of):
    """In the default layout at SCREEN_PX, every tab bar holds its tabs' titles whole
    beside the view's buttons (measured on screenshots: at most 6.4 px a character, 41 px a
    tab's icon and gaps, 70 px the buttons; view.TAB_CHAR_PX, TAB_CHROME_PX, TAB_BUTTONS_PX
    add a margin), and every plot keeps the height at which
    its y tick labels show at any data range: egui_plot labels a grid line a power of ten
    apart only when such lines lie more than 20 px apart, which is a tenth of the plot's
    height at worst (view.PLOT_MIN_PX)."""
    if ladder_of == "two":
        summary = written[2]
    else:
        df, meta, _ = campaign
        summary = write_recording(df, meta, long_ladder(campaign), tmp_path / "long.rrd",
                                  max_poses=2)
    layout = Layout(summary.path)
    boxes = planned_boxes(layout)
    tab_bars = [ref for ref in boxes if ref.startswith("container/")
                and layout[ref]["container_kind"] == Layout.TABS]
    assert len(tab_bars) >= 5
    for ref in tab_bars:
        titles = [layout[kid]["display_name"] for kid in layout.children(ref)]
        needed = sum(view.TAB_CHAR_PX * len(t) + view.TAB_CHROME_PX for t in titles)
        assert needed + view.TAB_BUTTONS_PX <= boxes[ref][0], titles
    plots = {**layout.views("TimeSeries"), **layout.views("BarChart")}
    assert len(plots) >= 7
    for ref in plots:
        assert boxes[ref][1] >= view.PLOT_MIN_PX + view.PLOT_CHROME_PX - 1e-9, \
            layout[ref]["display_name"]


def test_robot_posed_along_the_campaign(written):
    df, ladder, summary, rrd = written
    geom = build_geometry(load_params())
    rows = summary.pose_rows
    assert rows.size == MAX_POSES and rows[0] == 0 and rows[-1] == len(df) - 1
    ts, trans = rows_of(rrd, "/world/robot/mirror_cube", "Transform3D:translation",
                        view.CAMPAIGN_TIMELINE)
    np.testing.assert_allclose(ts, df["t_s"].to_numpy()[rows], rtol=0, atol=1e-9)
    q = df[["q1_rad", "q2_rad", "q3_rad"]].to_numpy()[rows]
    cube_mm = (forward(geom, q).point(geom.cube_offset) - summary.origin_m) * 1e3
    got = np.array([v[0] for v in trans], dtype=np.float64)
    np.testing.assert_allclose(got, cube_mm, rtol=0, atol=1e-4)
    _, fixed = rows_of(rrd, "/world/robot/base_plate", "Transform3D:translation")
    assert len(fixed) == 1                                # fixed to the room: logged once
    # the X interferometer's beam ends on the cube's -x face
    _, strips = rows_of(rrd, "/world/instruments/interferometer_x", "LineStrips3D:strips",
                        view.CAMPAIGN_TIMELINE)
    ends = np.array([s[0][-1] for s in strips], dtype=np.float64)
    half_mm = load_params().mirror_cube_size_m / 2 * 1e3
    np.testing.assert_allclose(ends[:, 0], cube_mm[:, 0] - half_mm, atol=1e-4)
    # the workspace hull, and the points coloured by split
    _, verts = rows_of(rrd, "/world/workspace/hull", "Mesh3D:vertex_positions")
    ws = hull(geom, point=geom.cube_offset)
    lo, hi = ws.bounds                           # drawn where the posed cube is ...
    assert np.all((cube_mm / 1e3 + summary.origin_m >= lo - 1e-9)
                  & (cube_mm / 1e3 + summary.origin_m <= hi + 1e-9))
    plate_bottom = forward(geom, np.zeros((1, 3))).p[0, 2] - PLATE_THICKNESS_M
    assert hi[2] < plate_bottom - 0.01           # ... not inside the platform plate
    np.testing.assert_allclose(np.array(verts[0]), (ws.vertices - summary.origin_m) * 1e3,
                               atol=1e-5)
    for s in ("cal", "val"):
        _, pts = rows_of(rrd, f"/world/workspace/{s}", "Points3D:positions")
        assert len(pts[0]) == df.loc[df["split"] == s, "pos_id"].nunique()


def test_direct_igm_step_is_its_end_effector_error(tmp_path):
    """A direct IGM (q = f(X, Y, Z, F)) enters the ladder through its end-effector error."""
    sc = Scenario.load("paper-force")
    df, meta = sc.simulate(sc.reduced_scale)
    igm = DirectIGM().fit(df, meta)
    step = calibration_step("force IGM", igm, df)
    res = view.residuals_m(df, step)
    np.testing.assert_allclose(res, igm.position_error(df), rtol=1e-9, atol=1e-15)
    summary = write_recording(df, meta, [step], tmp_path / "force.rrd", max_poses=3)
    rrd = read_rrd(tmp_path / "force.rrd")
    _, vec = static_arrows(rrd, field_entity(summary, 0))
    assert summary.ladder[0]["label"] == "geometric + force + geometric x force"
    ids, field = view.position_field(df["pos_id"].to_numpy(), igm.position_error(df))
    got = vec * summary.ladder[0]["arrow_scale_nm_per_mm"]
    exp = field * 1e9
    assert np.all(np.abs(got - exp) <= F32_REL * np.linalg.norm(exp, axis=1, keepdims=True))
    with pytest.raises(TypeError, match="not a calibration model"):
        calibration_step("x", object(), df)


def test_nothing_half_written(campaign, tmp_path, monkeypatch):
    df, meta, models = campaign
    path = tmp_path / "run.rrd"
    path.write_bytes(b"previous recording")

    def fail(*a, **k):
        raise RuntimeError("disk full")
    monkeypatch.setattr(view, "_log_panel", fail)
    with pytest.raises(RuntimeError, match="disk full"):
        write_recording(df, meta, [], path, max_poses=2)
    assert path.read_bytes() == b"previous recording"
    assert sorted(os.listdir(tmp_path)) == ["run.rrd"]


def test_without_models_the_workspace_and_the_campaign(campaign, tmp_path):
    df, meta, _ = campaign
    summary = write_recording(df, meta, [], tmp_path / "plain.rrd", max_poses=2)
    layout = Layout(summary.path)
    error_tab, robot_tab, campaign_tab = layout.children(layout.root)
    assert layout[robot_tab]["display_name"] == "robot and beams"
    fields, side = layout.children(error_tab)
    (info,) = layout.children(side)
    first = layout.active(fields)
    assert layout[first]["display_name"] == "workspace: calibration and validation positions"
    assert layout.contents(first) == ["$origin/workspace/**", "$origin/axes/workspace/**"]
    assert layout[info]["space_origin"] == "info"
    assert len(layout.children(campaign_tab)) == 5
    assert not [e for e in read_rrd(summary.path) if e.startswith(("/world/error", "/ladder"))]


def test_bad_input_is_named(campaign, tmp_path):
    df, meta, _ = campaign
    bad = LadderStep("thermal", np.zeros((len(df) - 1, 3)))
    with pytest.raises(ValueError, match=r"ladder step 'thermal'.*shape"):
        write_recording(df, meta, [bad], tmp_path / "a.rrd")
    far = df.copy()
    far.loc[5, "q2_rad"] = 1.0
    with pytest.raises(ValueError, match=r"row.* 5 .*outside the actuator stroke"):
        write_recording(far, meta, [], tmp_path / "b.rrd")
    assert not list(tmp_path.iterdir())


def test_cli_writes_a_recording_without_a_viewer(campaign, tmp_path, capsys, monkeypatch):
    df, meta, models = campaign
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    data = tmp_path / "campaign.parquet"
    write_dataset(df, meta, data)
    for name, m in models:
        m.save(tmp_path / f"{name.split(':')[0].split()[0]}.json")
    code = main(["view", str(data), "--model", str(tmp_path / "geometric.json"),
                 "--model", str(tmp_path / "C.json"), "--max-poses", "5"])
    out, err = capsys.readouterr()
    assert code == 0, err
    rrd = read_rrd(tmp_path / "campaign.rrd")                   # default: next to the data
    # named after the models' feature families, not after the files
    assert "/world/error/0_geometric" in rrd and "/timeseries/residual_nm/0_geometric/x" in rrd
    assert "ladder 1: + temperatures + geometric x temperature" in out
    assert "C.json" not in out and "/world/error/1_C" not in rrd
    assert out.count("residual arrows: 1 mm =") == 2
    (tmp_path / "fitted.toml").write_text("")
    code = main(["view", str(data), "--model", str(tmp_path / "fitted.toml"),
                 "-o", str(tmp_path / "x.rrd")])
    assert code == 2 and "fitted.toml" in capsys.readouterr().err
    assert not (tmp_path / "x.rrd").exists()


@pytest.fixture(scope="module")
def fitted_model(tmp_path_factory):
    """A physics model fitted to quiet/magnetic-force (reduced) and written as fitted.toml:
    the geometric baseline, which leaves the hidden coil force in its residual."""
    df, meta = Scenario.load("quiet/magnetic-force").simulate(0.15)
    fit = PhysicsFit(["geometric_errors"]).fit(df, meta)
    d = tmp_path_factory.mktemp("fitted")
    write_dataset(df, meta, d / "magnetic.parquet")
    (d / "fitted.toml").write_text(fitted_toml(fit, str(d / "magnetic.parquet")))
    return df, fit, d


def test_fitted_toml_arrows_are_its_residuals(fitted_model, capsys):
    """``--model fitted.toml``: the ladder step is the physics model's residual field, model
    minus measurement with the session zeros estimated on the calibration rows, i.e. the
    fit's own residual (measurement minus model) negated; arrow x scale = that field in nm."""
    df, fit, d = fitted_model
    code = main(["view", str(d / "magnetic.parquet"), "--model", str(d / "fitted.toml"),
                 "-o", str(d / "fit.rrd"), "--max-poses", "3"])
    out, err = capsys.readouterr()
    assert code == 0, err
    m = re.search(r"ladder 0: geometric_errors: .* residual arrows: 1 mm = ([0-9.e+-]+) nm",
                  out)                                     # named after its effects
    scale = float(m.group(1))
    rrd = read_rrd(d / "fit.rrd")
    assert sorted(e for e in rrd if e.startswith("/world/error/") and e.endswith("/arrows")) == [
        f"/world/error/0_geometric_errors{a}/arrows" for a in ("", "/x", "/y", "/z")]
    _, vec = static_arrows(rrd, "/world/error/0_geometric_errors/arrows")
    res_nm = -fit.residual_ * 1e9                          # model minus measurement, nm
    exp = pd.DataFrame(res_nm, columns=list("xyz")).groupby(df["pos_id"].to_numpy()).mean()
    got = vec * scale
    assert got.shape == exp.shape == (df["pos_id"].nunique(), 3)
    norm = np.linalg.norm(exp.to_numpy(), axis=1, keepdims=True)
    assert np.all(np.abs(got - exp.to_numpy()) <= F32_REL * norm)
    assert np.median(norm) > 20.0                           # the hidden force is left in it
    for a, axis in enumerate("xyz"):
        ts, vals = rows_of(rrd, f"/timeseries/residual_nm/0_geometric_errors/{axis}",
                           "Scalars:scalars", view.CAMPAIGN_TIMELINE)
        np.testing.assert_allclose(np.array(vals)[:, 0], res_nm[:, a], rtol=0, atol=1e-6)
    assert re.search(r"ladder 0: geometric_errors: .*RMS residual cal [0-9.]+ nm, val "
                     f"{np.sqrt(np.mean(res_nm[(df['split'] == 'val').to_numpy()] ** 2)):.3g} nm",
                     out)


def test_view_prints_the_figures_compare_prints(fitted_model, capsys):
    """``deltatwin view`` and ``deltatwin compare`` on the same data and model give the same
    validation p90 per axis and pooled, and the same floor (the twin's noise floor here: the
    data carry no achievable floor)."""
    df, fit, d = fitted_model
    data, model = str(d / "magnetic.parquet"), str(d / "fitted.toml")
    assert main(["compare", data, "--model", model, "--json"]) == 0
    rep = json.loads(capsys.readouterr().out)
    assert main(["view", data, "--model", model, "-o", str(d / "p90.rrd"),
                 "--max-poses", "2"]) == 0
    out = capsys.readouterr().out
    p90 = {a: rep["axes"]["val"][a]["err_p90_nm"] for a in ("all", "x", "y", "z")}
    assert (f"ladder 0: geometric_errors: validation p90 {p90['all']:.1f} nm (x {p90['x']:.1f}, "
            f"y {p90['y']:.1f}, z {p90['z']:.1f});") in out
    noise = rep["noise_floor_nm"]
    assert f"  noise floor (x {noise['x']:.1f}, y {noise['y']:.1f}, z {noise['z']:.1f} nm)" in out
    df, meta = read_dataset(data)                     # the unrounded figures
    summary = write_recording(df, meta, [view.model_file_step(model, df, meta)],
                              d / "p90.rrd", max_poses=2)
    # the same residuals, reached through other m <-> nm conversions: equal to ~1e-11
    assert summary.ladder[0]["p90_nm"] == pytest.approx(p90, rel=1e-9)
    assert summary.floor_nm == pytest.approx(noise, rel=1e-12)


def test_spawn_is_used_nowhere_in_tests_or_ci():
    """The tests and CI never open a viewer: no test or CI script passes --spawn."""
    here = Path(__file__).resolve()
    files = [p for p in (REPO / "tests").rglob("*.py") if p.resolve() != here]
    files += [p for p in (REPO / ".ci").rglob("*") if p.is_file()]
    assert files
    users = [str(p) for p in files if "--spawn" in p.read_text(errors="replace")]
    assert users == []
