"""DGM, IGM (Newton-Raphson), direct IGM, JSON export/load, validation figures, bad input."""
import json
import warnings

import numpy as np
import pytest

from deltatwin.calibration.blackbox.dgm import DGM
from deltatwin.calibration.blackbox.direct_igm import DirectIGM
from deltatwin.calibration.blackbox.estimator import OutputModel
from deltatwin.calibration.blackbox.features import FeatureSet, Term, geometric, thermal_preset
from deltatwin.calibration.blackbox.igm import IGM
from deltatwin.calibration.blackbox.model_file import load_model
from deltatwin.calibration.blackbox.validation import evaluate, ladder
from deltatwin.calibration.errors import (
    DroppedRowsWarning,
    MissingColumnsError,
    MissingMetadataWarning,
    ModelFileError,
    ModelMismatchError,
    NoValidationWarning,
    TooFewPointsError,
    ValidationOverlapError,
)
from deltatwin.calibration.metrics import error_figures
from deltatwin.files import content_sha256


def test_error_figures_label_both_90_percent_figures():
    e = np.array([-3.0, -1.0, 0.0, 1.0, 2.0, 10.0, np.nan]) * 1e-9
    f = error_figures(e)
    assert f["n"] == 6
    assert f["err_1645sigma"] == pytest.approx(1.645 * np.std(e[:6] * 1e9, ddof=1))
    assert f["err_p90"] == pytest.approx(np.percentile(np.abs(e[:6] * 1e9), 90))
    assert f["max_abs"] == pytest.approx(10.0)


def test_dgm_fits_the_twins_thermal_campaign(thermal_data, thermal_dgm):
    df, meta = thermal_data
    m = thermal_dgm
    assert m.output_names_ == ["x", "y", "z"]
    assert len(m.features_) == 217                      # 9 structure sensors, air excluded
    assert "air_x" not in m.sensors_ and "base" in m.sensors_
    floor = meta["truth"]["noise_floor_nm"]
    ev = evaluate(m, df)
    for ax, rec in ev["outputs"].items():
        assert 3 <= rec["terms_kept"] <= 60
        measured = df[f"{ax}_nm"].notna()
        assert rec["val"]["n"] == int(((df.split == "val") & measured).sum()), ax
        # the twin's data hold what a polynomial DGM cannot follow (loop drift, the air's
        # index, sensor lag): the paper's complete model reached 9-19 x its noise floor
        # (+-71..150 nm against 5 nm std); 25 x leaves room for 3 % of its rows
        assert rec["val"]["err_p90"] < 25 * floor[ax], ax
        assert rec["cal"]["err_p90"] < 25 * floor[ax], ax
        # validation rows are not fitted: they cannot beat the noise
        assert rec["val"]["err_p90"] > floor[ax], ax
    # the fit uses only the rows where the axis was measured, calibration split
    assert m.output("z").n_cal == int(((df.split == "cal") & df.z_nm.notna()).sum())


def test_dgm_predict_matches_the_regression_it_came_from(thermal_data, thermal_dgm):
    df, _ = thermal_data
    m = thermal_dgm
    from deltatwin.calibration.blackbox.estimator import base_variables
    vals = base_variables(df, m.features_.variables, m.sensors_, m.T_ref_K, m.window_s)
    X = m.features_.matrix(vals)
    P = m.predict(df)
    for i, ax in enumerate(m.output_names_):
        ref = m.stepwise_result(ax).predict(X)
        assert np.allclose(P[:, i], ref, rtol=0, atol=1e-15)


def test_thermal_ladder_has_the_papers_structure(thermal_data):
    df, meta = thermal_data
    rungs = ladder(df, meta, "thermal")
    assert [r["name"][:1] for r in rungs] == ["g", "A", "B", "C"]
    for ax in ("x", "y", "z"):
        geo = rungs[0]["outputs"][ax]["val"]["err_p90"]
        full = rungs[-1]["outputs"][ax]["val"]["err_p90"]
        assert geo > 5 * full, ax                        # temperatures matter
        assert rungs[1]["outputs"][ax]["val"]["err_p90"] < geo


def test_igm_round_trip_within_0_001_nm(thermal_data, thermal_dgm):
    df, _ = thermal_data
    m = thermal_dgm
    igm = IGM(m)
    rng = np.random.default_rng(9)
    n = 5000
    vals = m.variables(df)
    rows = rng.integers(0, len(df), n)
    aux = {v: vals[v][rows] for v in igm.aux_variables}
    q_true = rng.uniform(-0.045, 0.045, (n, 3))
    target = m.predict_values({**aux, "q1": q_true[:, 0], "q2": q_true[:, 1],
                               "q3": q_true[:, 2]})
    res = igm.solve(target, aux)
    assert res.converged.all() and res.n_failed == 0
    assert res.residual_m.max() <= 1e-12
    back = m.predict_values({**aux, "q1": res.q[:, 0], "q2": res.q[:, 1], "q3": res.q[:, 2]})
    assert np.abs(back - target).max() <= 1e-12
    assert np.abs(res.q - q_true).max() < 1e-9
    # the same through a data frame's temperatures
    r2 = igm.solve_frame(df.iloc[rows[:50]], target[:50])
    assert r2.converged.all()


def test_igm_reports_points_that_do_not_converge(thermal_data, thermal_dgm):
    df, _ = thermal_data
    m = thermal_dgm
    vals = m.variables(df)
    aux = {v: vals[v][:3] for v in IGM(m).aux_variables}
    q = np.array([[0.01, -0.02, 0.03]] * 3)
    target = m.predict_values({**aux, "q1": q[:, 0], "q2": q[:, 1], "q3": q[:, 2]})
    target[1, 0] = np.nan
    res = IGM(m, max_iter=1).solve(target, aux)
    assert not res.converged.any()                       # one Newton step is not enough
    assert np.all(res.residual_m[[0, 2]] > 1e-12)
    assert np.isinf(res.residual_m[1])                   # NaN target: never "converged"
    # a singular Jacobian at the start point is reported, not divided by
    geo = geometric()
    fs = FeatureSet([geo])
    mk = lambda name, term, c: OutputModel(name, "m", f"{name}_nm", 1e-9, [term],
                                           np.array([c]), 0.0, np.zeros(1), np.ones(1), 0.0, 1.0)
    dgm = DGM.from_outputs(fs, [mk("x", Term((("q1", 2),)), 1.0),
                                mk("y", Term((("q2", 1),)), 0.1),
                                mk("z", Term((("q3", 1),)), 0.1)])
    # the first pass stops at q0 = 0 (singular); the in-stroke starts find q1 = +-0.01
    res = IGM(dgm).solve(np.array([[1e-4, 1e-3, 1e-3]]))
    assert res.converged[0] and abs(res.q[0, 0]) == pytest.approx(0.01, abs=1e-12)
    assert res.iterations[0] == 0
    res = IGM(dgm).solve(np.array([[1e-4, 1e-3, 1e-3]]), q0=[0.02, 0.0, 0.0])
    assert res.converged[0] and res.q[0, 0] == pytest.approx(0.01, abs=1e-12)
    # x = q1^2 cannot be negative: out of reach from every start, never "converged"
    res = IGM(dgm).solve(np.array([[-1e-4, 1e-3, 1e-3]]))
    assert res.status[0] == "out_of_reach" and not res.converged[0]
    assert res.residual_m[0] >= 1e-4 - 1e-12 and "out of reach" in res.reason(0)


def test_json_export_load_predicts_identically(tmp_path, thermal_data, thermal_dgm,
                                               force_data, force_igm):
    df, _ = thermal_data
    p = thermal_dgm.save(tmp_path / "dgm.json")
    d = json.loads(p.read_text())
    assert d["kind"] == "DGM" and d["features"]["preset"] == "thermal"
    assert d["inputs"]["q1"]["unit"] == "rad" and d["outputs"][0]["unit"] == "m"
    out0 = d["outputs"][0]
    assert len(out0["terms"]) == len(out0["coef"]) == len(out0["scaling"]["term_std"])
    back = load_model(p, expect_features="thermal")
    assert np.array_equal(back.predict(df), thermal_dgm.predict(df), equal_nan=True)
    q = IGM(back).solve(np.array([[1e-3, -2e-3, 5e-4]]), {v: 0.0 for v in
                                                          IGM(back).aux_variables}).q
    q0 = IGM(thermal_dgm).solve(np.array([[1e-3, -2e-3, 5e-4]]),
                                {v: 0.0 for v in IGM(thermal_dgm).aux_variables}).q
    assert np.array_equal(q, q0)
    fdf, _ = force_data
    p2 = force_igm.save(tmp_path / "igm.json")
    back2 = load_model(p2, expect_kind="DirectIGM")
    assert np.array_equal(back2.predict(fdf), force_igm.predict(fdf))
    assert not list(tmp_path.glob(".*.tmp"))             # atomic write left no temporary


def test_direct_igm_force_model(force_data, force_igm):
    df, meta = force_data
    ev = evaluate(force_igm, df)
    assert len(force_igm.features_) == 79
    # the second paper's validation at the end-effector, +-159/143/142 nm: the same model
    # class on the twin's force campaign (its cubic in X, Y, Z cannot follow the Delta's
    # inverse kinematics to the noise floor, a few nm here)
    paper_val_nm = {"x": 159.0, "y": 143.0, "z": 142.0}
    for mot, rec in ev["outputs"].items():
        assert rec["val"]["err_p90"] < max(paper_val_nm.values()), mot
        assert 5 <= rec["terms_kept"] <= 60
    floor = meta["truth"]["noise_floor_nm"]
    for ax in "xyz":
        assert floor[ax] < ev["position"][ax]["val"]["err_p90"] < paper_val_nm[ax], ax
    rungs = ladder(df, meta, "force")
    worst_geo = max(rungs[0]["outputs"][k]["val"]["err_p90"] for k in ("q1", "q2", "q3"))
    worst_force = max(rungs[1]["outputs"][k]["val"]["err_p90"] for k in ("q1", "q2", "q3"))
    # force terms matter: they remove an order of magnitude more than the noise floor
    assert worst_geo - worst_force > 10 * max(floor.values())


# ----- bad input --------------------------------------------------------------------------

def test_missing_columns_are_named(thermal_data, force_data):
    df, meta = thermal_data
    temps = [c for c in df.columns if c.startswith("T_")]
    with pytest.raises(MissingColumnsError, match="structure temperature"):
        DGM().fit(df.drop(columns=temps), meta)
    with pytest.raises(MissingColumnsError, match="T_nope_C"):
        DGM(sensors=["base", "nope"]).fit(df, meta)
    fdf, fmeta = force_data
    with pytest.raises(MissingColumnsError, match="F_N"):
        DirectIGM().fit(fdf.drop(columns="F_N"), fmeta)


def test_missing_sensor_metadata_warns_and_excludes_air(thermal_data):
    df, _ = thermal_data
    sub = df[df.session == "xy"].iloc[:400]
    with pytest.warns(MissingMetadataWarning, match="air"):
        m = DGM(outputs=["x"]).fit(sub, None)
    assert len(m.sensors_) == 9 and not any(s.startswith("air") for s in m.sensors_)
    # an explicit feature set needs no metadata
    with warnings.catch_warnings():
        warnings.simplefilter("error", MissingMetadataWarning)
        m = DGM(outputs=["x"], features=thermal_preset(["base", "arm1"])).fit(sub, None)
    assert m.sensors_ == ["base", "arm1"]


def test_nan_rows_are_dropped_with_a_named_warning(thermal_data):
    df, meta = thermal_data
    bad = df.copy()
    idx = bad.index[(bad.session == "xy") & (bad.split == "cal")][:7]
    bad.loc[idx, "T_base_C"] = np.nan
    bad.loc[bad.index[(bad.session == "xy") & (bad.split == "cal")][10:13], "x_nm"] = np.nan
    with pytest.warns(DroppedRowsWarning) as rec:
        m = DGM(outputs=["x"]).fit(bad, meta)
    text = " ".join(str(w.message) for w in rec)
    assert "7 row(s) with NaN inputs" in text and "dT_base" in text or "T_base" in text
    assert "3 row(s) of a session" in text
    ref = int(((df.session == "xy") & (df.split == "cal")).sum())
    assert m.output("x").n_cal == ref - 7 - 3
    assert np.isnan(m.predict(bad)[idx]).all()           # no prediction without inputs


def test_too_few_points_for_the_terms(thermal_data):
    df, meta = thermal_data
    small = df.iloc[:150]
    with pytest.raises(TooFewPointsError, match="217 candidate terms"):
        DGM(outputs=["x"]).fit(small, meta)


def test_validation_positions_must_be_disjoint(thermal_data):
    df, meta = thermal_data
    same_id = df.copy()
    pid = same_id.loc[same_id.split == "cal", "pos_id"].iloc[0]
    same_id.loc[same_id.index[same_id.split == "val"][:2], "pos_id"] = pid
    with pytest.raises(ValidationOverlapError, match="position id"):
        DGM().fit(same_id, meta)
    same_q = df.copy()
    vi = same_q.index[same_q.split == "val"][0]
    ci = same_q.index[same_q.split == "cal"][0]
    same_q.loc[vi, ["q1_rad", "q2_rad", "q3_rad"]] = same_q.loc[ci, ["q1_rad", "q2_rad",
                                                                     "q3_rad"]].to_numpy()
    with pytest.raises(ValidationOverlapError, match="same coordinates"):
        DGM().fit(same_q, meta)


def test_no_validation_rows_warns(thermal_data, thermal_dgm):
    df, _ = thermal_data
    with pytest.warns(NoValidationWarning):
        ev = evaluate(thermal_dgm, df[df.split == "cal"])
    assert ev["outputs"]["x"]["val"]["err_p90"] is None


def test_model_file_from_another_feature_set_or_edited(tmp_path, thermal_data, thermal_dgm,
                                                        force_igm):
    df, _ = thermal_data
    p = force_igm.save(tmp_path / "force.json")
    with pytest.raises(ModelMismatchError, match="'force' feature set"):
        load_model(p, expect_features="thermal")
    with pytest.raises(ModelMismatchError, match="DGM"):
        load_model(p, expect_kind="DGM")
    p2 = thermal_dgm.save(tmp_path / "th.json")
    d = json.loads(p2.read_text())
    d["outputs"][0]["terms"][0]["factors"] = [["q1", 5]]
    (tmp_path / "edited.json").write_text(json.dumps(d))
    with pytest.raises(ModelFileError, match="does not match its content_sha256"):
        load_model(tmp_path / "edited.json")
    # an edit that also recomputes the checksum is still checked for consistency
    d["content_sha256"] = content_sha256(d)
    (tmp_path / "edited.json").write_text(json.dumps(d))
    with pytest.raises(ModelFileError, match="term name"):
        load_model(tmp_path / "edited.json")
    (tmp_path / "junk.json").write_text("{not json")
    with pytest.raises(ModelFileError, match="not a JSON"):
        load_model(tmp_path / "junk.json")
    back = load_model(p2)
    with pytest.raises(MissingColumnsError, match="T_"):
        back.predict(df.drop(columns=[c for c in df.columns if c.startswith("T_base")]))


def test_estimator_parameters_are_checked_once():
    from deltatwin.calibration.errors import CalibrationInputError
    with pytest.raises(CalibrationInputError, match="features"):
        DGM(features="force")
    with pytest.raises(CalibrationInputError, match="axis"):
        DGM(outputs=["w"])
    with pytest.raises(CalibrationInputError, match="penter"):
        DGM(penter=0.3, premove=0.1)
    with pytest.raises(CalibrationInputError, match="not fitted"):
        DGM().predict(None)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        DirectIGM(penter=0.01)
