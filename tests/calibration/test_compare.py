"""calibration/diagnosis/compare.py and ``deltatwin compare``: where a model fails, on data with a hidden
effect (scenarios/quiet/magnetic-force, reduced scale), with real fits, real files and the
real command line."""
import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from deltatwin.calibration.blackbox.dgm import DGM
from deltatwin.calibration.diagnosis.compare import (
    compare,
    evaluate,
    load_model_and_covariance,
    load_model_file,
)
from deltatwin.calibration.physics.fit import PhysicsFit
from deltatwin.calibration.physics.model_file import fitted_toml, load_fitted
from deltatwin.cli import main
from deltatwin.models.geometry import build_geometry
from deltatwin.models.kinematics import forward
from deltatwin.models.params import load_params
from deltatwin.twin.dataset import write_dataset
from deltatwin.twin.scenario import Scenario

REPO = Path(__file__).resolve().parents[2]
SCALE = 0.15          # 270 readings: 27 calibration and 27 validation positions x 5 forces
FORCES_N = [0.0, 0.5, 1.0, 1.5, 2.0]


@pytest.fixture(scope="module")
def magnetic():
    df, meta = Scenario.load("quiet/magnetic-force").simulate(SCALE)
    return df, meta


@pytest.fixture(scope="module")
def baseline(magnetic):
    return PhysicsFit(["geometric_errors"]).fit(*magnetic)


@pytest.fixture(scope="module")
def with_force(magnetic):
    return PhysicsFit(["geometric_errors", "magnetic_force"]).fit(*magnetic)


@pytest.fixture(scope="module")
def files(magnetic, baseline, tmp_path_factory):
    d = tmp_path_factory.mktemp("compare")
    write_dataset(*magnetic, d / "magnetic.parquet")
    (d / "fitted.toml").write_text(fitted_toml(baseline, str(d / "magnetic.parquet")))
    return d


@pytest.fixture(scope="module")
def report(magnetic, files):
    model, covariance = load_model_and_covariance(files / "fitted.toml")
    return compare(*magnetic, model, covariance=covariance)


def _p90(v):
    v = np.abs(v[np.isfinite(v)])
    return float(np.percentile(v, 90))


def test_residual_is_model_minus_measurement_with_the_fit_zeros(magnetic, baseline, files,
                                                                report):
    """The model read back from its TOML, on the same data and calibration rows: the
    re-estimated zeros are the fit's, and the residual is the fit's own (measurement minus
    model) with the sign flipped."""
    df, meta = magnetic
    model, doc = load_fitted(files / "fitted.toml")
    assert doc["model"]["effects"] == ["geometric_errors"]
    ev = evaluate(df, meta, model)
    np.testing.assert_allclose(ev.residual_m, -baseline.residual_, rtol=0, atol=1e-13)
    np.testing.assert_allclose(ev.offsets_m, baseline.offsets_, rtol=0, atol=1e-13)
    val = report["axes"]["val"]
    for a in ("x", "y", "z", "all"):
        assert val[a]["err_p90_nm"] == pytest.approx(baseline.val_[a]["err_p90"], rel=1e-9)
        assert val[a]["mean_nm"] == pytest.approx(-baseline.val_[a]["mean"], rel=1e-6)
    assert report["residual"].startswith("model minus measurement")
    assert "new zeros" in report["zeros"]["note"]
    assert set(report["zeros"]["estimated_on"].values()) == {"cal"}


def test_force_breakdown_shows_the_hidden_force(magnetic, baseline, report):
    """The geometric fit absorbs the deflection at the mean force, so what is left is linear
    in F_N: the mean residual of every axis moves monotonically with the force level, by far
    more than the noise, and the error is largest at the extreme forces."""
    df, meta = magnetic
    bins = report["force"]["bins"]
    assert [b["value"] for b in bins] == FORCES_N
    floor = max(meta["truth"]["noise_floor_nm"].values())
    for a in ("x", "y", "z"):
        means = np.array([b["by_axis"][a]["mean_nm"] for b in bins])
        steps = np.diff(means)
        assert np.all(steps < 0) or np.all(steps > 0), (a, means)
        assert abs(means[-1] - means[0]) > 10 * floor, (a, means)
    p90 = np.array([b["err_p90_nm"] for b in bins])
    assert p90[0] > 2.5 * p90[2] and p90[-1] > 2.5 * p90[2]
    assert p90[-1] > 10 * floor
    # the numbers, recomputed independently from the fit's own residual
    res = -baseline.residual_ * 1e9
    val = (df["split"] == "val").to_numpy()
    F = df["F_N"].to_numpy()
    for b in bins:
        rows = val & (F == b["value"])
        assert b["n"] == int(np.isfinite(res[rows]).sum())
        assert b["err_p90_nm"] == pytest.approx(_p90(res[rows]), rel=1e-12)
    # the coil currents drive the force: they are the variables the error varies most with
    top = [v["variable"] for v in report["worst"]["variables"]]
    assert set(top) == {"coil1_A", "coil2_A", "coil3_A"}


def test_adding_the_force_lowers_the_error_at_2N(magnetic, report, with_force):
    df, meta = magnetic
    rep = compare(df, meta, with_force.model_)
    at = {b["value"]: b["err_p90_nm"] for b in rep["force"]["bins"]}
    before = {b["value"]: b["err_p90_nm"] for b in report["force"]["bins"]}
    floor = max(meta["truth"]["noise_floor_nm"].values())
    assert at[2.0] < before[2.0] / 5
    assert at[2.0] < 3 * floor
    assert max(at.values()) < 2 * min(at.values())           # no force level stands out
    assert rep["axes"]["val"]["all"]["err_p90_nm"] < report["axes"]["val"]["all"]["err_p90_nm"] / 5


def test_regions_windows_and_variables_recomputed(magnetic, baseline, report):
    df, meta = magnetic
    res = -baseline.residual_ * 1e9
    val = (df["split"] == "val").to_numpy()
    # octants of the nominal kinematic position about the centre of the val positions' box
    p = forward(build_geometry(load_params()), df[["q1_rad", "q2_rad", "q3_rad"]].to_numpy()).p
    centre = (p[val].min(axis=0) + p[val].max(axis=0)) / 2
    np.testing.assert_allclose(report["regions"]["centre_mm"], centre * 1e3, rtol=0, atol=1e-9)
    label = np.array(["".join(f"{a}{'+' if s else '-'}" for a, s in zip("xyz", row))
                      for row in p > centre])
    for b in report["regions"]["bins"]:
        rows = val & (label == b["region"])
        assert b["n"] == int(np.isfinite(res[rows]).sum()), b["region"]
        if b["n"]:
            assert b["err_p90_nm"] == pytest.approx(_p90(res[rows]), rel=1e-12)
    worst = report["worst"]["regions"]
    assert worst[0]["err_p90_nm"] == max(b["err_p90_nm"] for b in report["regions"]["bins"]
                                         if b["n"] >= 10)
    # 8 equal windows over the validation rows' time span
    t = df["t_s"].to_numpy()
    edges = np.linspace(t[val].min(), t[val].max(), 9)
    windows = report["time_windows"]["bins"]
    assert len(windows) == 8 and sum(w["n"] for w in windows) == np.isfinite(res[val]).sum()
    for w, lo, hi in zip(windows, edges[:-1], edges[1:]):
        rows = val & (t >= lo) & ((t < hi) if w["window"] < 7 else (t <= hi))
        assert w["t_from_s"] == pytest.approx(lo) and w["t_to_s"] == pytest.approx(hi)
        assert w["err_p90_nm"] == pytest.approx(_p90(res[rows]), rel=1e-12)
    assert [w["window"] for w in report["worst"]["time_windows"]] == \
        [w["window"] for w in sorted(windows, key=lambda w: -w["err_p90_nm"])][:3]
    # every recorded variable, with quantile bins (few-valued ones: one bin per value)
    v = report["variables"]
    for s in ("air_x", "air_y", "air_z", "base", "coil_box"):
        assert f"T_{s}_C" in v and f"dT_{s}_K_per_h" in v
    assert {"q1_rad", "coil1_A", "ac1_ry_arcsec", "ac2_rz_arcsec"} <= set(v)
    bins = v["T_base_C"]["bins"]
    assert len(bins) == 5
    T = df["T_base_C"].to_numpy()
    edges = np.quantile(T[val], [0, 0.2, 0.4, 0.6, 0.8, 1])
    for k, (b, lo, hi) in enumerate(zip(bins, edges[:-1], edges[1:])):
        assert (b["lo"], b["hi"]) == (lo, hi)
        rows = val & (T <= hi) & ((T > lo) if k else (T >= lo))
        assert b["err_p90_nm"] == pytest.approx(_p90(res[rows]), rel=1e-12)
    assert [b["value"] for b in v["coil1_A"]["bins"]] == FORCES_N
    json.dumps(report, allow_nan=False)                    # JSON-ready as returned


def test_new_zeros_are_re_estimated(magnetic, files):
    """A new campaign's zeros: a shifted axis gives the same errors and a shifted offset; a
    session without calibration rows takes its zero from its own rows, and says so."""
    df, meta = magnetic
    model = load_model_file(files / "fitted.toml")
    ref = compare(df, meta, model)
    moved = df.copy()
    moved["z_nm"] += 5000.0
    rep = compare(moved, meta, model)
    assert rep["axes"]["val"]["z"]["err_p90_nm"] == pytest.approx(
        ref["axes"]["val"]["z"]["err_p90_nm"], abs=1e-6)
    assert rep["zeros"]["offsets_nm"]["xyz.z"] - ref["zeros"]["offsets_nm"]["xyz.z"] == \
        pytest.approx(5000.0, abs=1e-6)
    split = df.copy()
    split.loc[split["split"] == "val", "session"] = "later"
    rep = compare(split, meta, model)
    assert rep["zeros"]["estimated_on"] == {"xyz.x": "cal", "xyz.y": "cal", "xyz.z": "cal",
                                            "later.x": "own rows", "later.y": "own rows",
                                            "later.z": "own rows"}
    assert abs(rep["axes"]["val"]["all"]["mean_nm"]) < 1e-6


def test_dgm_gets_the_same_view(tmp_path, small_thermal_campaign):
    """The black-box path: a DGM (model.json) compared on data whose session zeros moved."""
    df, meta = small_thermal_campaign
    dgm = DGM().fit(df, meta)
    dgm.save(tmp_path / "model.json")
    model = load_model_file(tmp_path / "model.json")
    moved = df.copy()
    moved.loc[moved["session"] == "z", "z_nm"] -= 1234.0
    rep = compare(moved, meta, model)
    assert rep["model"]["kind"] == "DGM" and rep["model"]["sensors"] == ["base", "arm1", "rod1"]
    # expected: DGM prediction + per (session, axis) zero from the calibration rows - reading
    pred = dgm.predict(moved) * 1e9
    res = np.full((len(df), 3), np.nan)
    cal = (moved["split"] == "cal").to_numpy()
    for k, a in enumerate("xyz"):
        y = moved[f"{a}_nm"].to_numpy()
        zero = pd.Series(y - pred[:, k])[cal].groupby(moved["session"][cal]).mean()
        res[:, k] = pred[:, k] + moved["session"].map(zero).to_numpy() - y
    val = (moved["split"] == "val").to_numpy()
    for k, a in enumerate("xyz"):
        assert rep["axes"]["val"][a]["err_p90_nm"] == pytest.approx(_p90(res[val, k]), rel=1e-6)
    assert rep["force"] is None                         # F_N is 0 throughout: no levels
    assert "F_N" not in rep["variables"]
    assert "dT_base_K_per_h" in rep["variables"] and "T_air_x_C" in rep["variables"]
    assert rep["unused_temperature_columns"] == ["T_air_x_C"]
    # a DGM whose sensors the data lacks
    code = main(["compare", str(_write(moved.drop(columns=["T_arm1_C"]), meta, tmp_path)),
                 "--model", str(tmp_path / "model.json")])
    assert code == 2


def _write(df, meta, d):
    path = d / "data.parquet"
    write_dataset(df, meta, path)
    return path


def test_cli_json_round_trip(magnetic, files, report, capsys):
    code = main(["compare", str(files / "magnetic.parquet"), "--model",
                 str(files / "fitted.toml"), "--json"])
    out, err = capsys.readouterr()
    assert code == 0, err
    got = json.loads(out)
    assert got["data"] == str(files / "magnetic.parquet")
    assert got["model_file"] == str(files / "fitted.toml")
    # the dataset file and the TOML keep every float64 exactly: the same numbers as in memory
    assert got == {"data": got["data"], "model_file": got["model_file"],
                   **json.loads(json.dumps(report))}
    code = main(["compare", str(files / "magnetic.parquet"), "--model",
                 str(files / "fitted.toml")])
    out, _ = capsys.readouterr()
    assert code == 0
    assert "model minus measurement" in out and "F = 2 N" in out and "worst regions" in out
    assert "coil1_A" in out


@pytest.mark.parametrize("case, needle", [
    ("missing_sensor_column", "'T_base_C'"),
    ("unknown_type", "unknown model file type '.txt'"),
    ("scenario_as_model", "not a fitted physics model"),
    ("json_not_a_model", "not a deltatwin-calibration-model file"),
    ("no_such_model", "no such model file"),
    ("thermal_model_without_sensors", "names no temperature sensor"),
])
def test_bad_input_exit_2_naming_the_problem(magnetic, files, tmp_path, capsys, case, needle):
    df, meta = magnetic
    data, model = files / "magnetic.parquet", files / "fitted.toml"
    if case == "missing_sensor_column":
        data = _write(df.drop(columns=["T_base_C"]), meta, tmp_path)
    elif case == "unknown_type":
        model = tmp_path / "fitted.txt"
        model.write_text((files / "fitted.toml").read_text())
    elif case == "scenario_as_model":
        model = REPO / "scenarios" / "quiet" / "magnetic-force.toml"
    elif case == "json_not_a_model":
        model = tmp_path / "model.json"
        model.write_text(json.dumps({"effects": ["geometric_errors"]}))
    elif case == "thermal_model_without_sensors":
        data = _write(df, {k: v for k, v in meta.items() if k != "sensors"}, tmp_path)
        model = tmp_path / "thermal.toml"                  # a model at its starting values
        model.write_text('[model]\neffects = ["thermal_expansion"]\n')
    else:
        model = tmp_path / "missing.toml"
    code = main(["compare", str(data), "--model", str(model), "--json"])
    out, err = capsys.readouterr()
    assert code == 2 and out == ""
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("deltatwin compare: error: "), err
    assert needle in lines[0], lines[0]
    assert str(model) in lines[0]
    if case in ("missing_sensor_column", "thermal_model_without_sensors"):
        assert str(data) in lines[0]


def test_direct_igm_is_refused(force_igm, tmp_path):
    """A direct IGM predicts motor coordinates, not readings: named, not compared."""
    force_igm.save(tmp_path / "igm.json")
    with pytest.raises(ValueError, match=r"igm\.json: holds a DirectIGM, which predicts motor"):
        load_model_file(tmp_path / "igm.json")


def test_a_model_file_s_covariance_gives_the_validation_band(magnetic, with_force, tmp_path,
                                                             capsys):
    """With a fitted model's covariance, compare draws the validation error's 95 % band on the
    data: on the data it was fitted to, the fit's own band draw for draw (the same Jacobian,
    covariance, residual and seed); 'within' is the printed numbers' comparison; a model
    file carries the covariance to the command line, and a DGM has no band."""
    df, meta = magnetic
    own = with_force.validation_band(np.random.default_rng(0))
    rep = compare(df, meta, with_force.model_, covariance=with_force.covariance_,
                  rng=np.random.default_rng(0))
    band = rep["validation_band_95_nm"]
    for axis, (low, high) in own.items():
        assert band[axis]["low"] == pytest.approx(low, rel=1e-9)
        assert band[axis]["high"] == pytest.approx(high, rel=1e-9)
        err = rep["axes"]["val"][axis]["err_p90_nm"]
        assert band[axis]["within"] == (low <= err <= high)
    assert compare(df, meta, with_force.model_)["validation_band_95_nm"] is None
    with pytest.raises(Exception, match="one row per parameter"):
        compare(df, meta, with_force.model_, covariance=np.eye(2))
    data = tmp_path / "magnetic.parquet"
    write_dataset(df, meta, data)
    with_force.save(tmp_path / "force.toml", str(data))
    assert main(["compare", str(data), "--model", str(tmp_path / "force.toml")]) == 0
    out = capsys.readouterr().out
    assert "p90 95 % band nm" in out
    # the file's correlations are rounded: the band as drawn in memory, to a few per cent
    printed = next(line for line in out.splitlines() if line.startswith("val   x")).split()[7]
    low, high = (float(v) for v in printed.split("-"))
    assert low == pytest.approx(band["x"]["low"], rel=0.05)
    assert high == pytest.approx(band["x"]["high"], rel=0.05)
