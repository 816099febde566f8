"""``deltatwin calibrate`` on small Parquet / CSV files written in the dataset format."""
import json

import numpy as np
import pytest

from deltatwin.calibration.blackbox.model_file import load_model
from deltatwin.cli import main
from deltatwin.twin.dataset import write_dataset


@pytest.fixture(scope="module")
def files(tmp_path_factory, thermal_data, force_data):
    """The twin's thermal and force campaigns (conftest.py) as dataset files."""
    d = tmp_path_factory.mktemp("cal")
    df, meta = thermal_data
    write_dataset(df, meta, d / "thermal.parquet")
    write_dataset(*force_data, d / "force.parquet")
    return d, df, meta


def run(capsys, *argv):
    code = main(list(map(str, argv)))
    out, err = capsys.readouterr()
    return code, out, err


def test_thermal_json_schema_and_model_file(files, capsys):
    d, df, meta = files
    floor = meta["truth"]["noise_floor_nm"]
    code, out, err = run(capsys, "calibrate", d / "thermal.parquet", "--features", "thermal",
                         "--json", "-o", d / "model.json")
    assert code == 0, err
    rep = json.loads(out)
    assert rep["features"] == "thermal" and rep["n_candidates"] == 217
    assert set(rep["axes"]) == {"x", "y", "z"}
    for ax, r in rep["axes"].items():
        assert isinstance(r["terms_kept"], int) and r["terms_kept"] > 0
        # the bound of test_models.py::test_dgm_fits_the_twins_thermal_campaign
        assert 0 < r["cal_err90_nm"] < 25 * floor[ax]
        assert floor[ax] < r["val_err90_nm"] < 25 * floor[ax]
        assert r["n_val"] > 0 and "ladder" not in r
    m = load_model(d / "model.json", expect_features="thermal")
    assert m.terms_kept_ == {ax: r["terms_kept"] for ax, r in rep["axes"].items()}
    # evaluating the saved model gives the same figures
    code, out2, err = run(capsys, "calibrate", d / "thermal.parquet", "--features", "thermal",
                          "--json", "--model", d / "model.json")
    assert code == 0, err
    rep2 = json.loads(out2)
    for ax in rep["axes"]:
        assert rep2["axes"][ax]["val_err90_nm"] == pytest.approx(rep["axes"][ax]["val_err90_nm"],
                                                                 rel=1e-12)


def test_thermal_ladder_json_and_text(files, capsys):
    from deltatwin.commands.calibrate import format_report
    d, _, _ = files
    code, out, err = run(capsys, "calibrate", d / "thermal.parquet", "--features", "thermal",
                         "--ladder", "--json", "--sensors", "base,arm1,rod1")
    assert code == 0, err
    rep = json.loads(out)
    assert rep["n_candidates"] == 19 + 3 + 57 + 3 + 3
    for ax, r in rep["axes"].items():
        lad = r["ladder"]
        assert [x["name"][:1] for x in lad] == ["g", "A", "B", "C"]
        assert all(set(x) >= {"name", "terms_kept", "val_err90_nm"} for x in lad)
        assert lad[0]["val_err90_nm"] > 5 * lad[-1]["val_err90_nm"], ax
        assert lad[-1]["terms_kept"] == r["terms_kept"]
    text = format_report(rep)
    assert "DGM (thermal features, 85 candidate terms)" in text
    assert "val p90" in text and "1.645s" in text and "geometric only" in text


def test_force_json(files, capsys):
    d, _, _ = files
    code, out, err = run(capsys, "calibrate", d / "force.parquet", "--features", "force",
                         "--json", "--ladder")
    assert code == 0, err
    rep = json.loads(out)
    assert rep["n_candidates"] == 79 and set(rep["axes"]) == {"q1", "q2", "q3"}
    for r in rep["axes"].values():
        assert r["val_err90_nm"] > 0 and r["val_err90_urad"] > 0
        assert [x["name"] for x in r["ladder"]] == ["geometric only", "with force terms"]
    assert set(rep["position"]) == {"x", "y", "z"}
    for r in rep["axes"].values():       # the kept terms as stepwisefit lists them
        assert len(r["terms"]) == r["terms_kept"]
        assert all(t["se"] > 0 and 0 <= t["p_value"] <= 1 and t["unit"].startswith("rad/")
                   for t in r["terms"])


def test_the_text_lists_each_outputs_terms_with_standard_errors_and_p_values(files, capsys):
    d, _, _ = files
    code, out, err = run(capsys, "calibrate", d / "force.parquet", "--features", "force")
    assert code == 0, err
    for motor in ("q1", "q2", "q3"):
        assert f"DirectIGM output {motor} (rad): " in out
    assert out.count("coefficient") == 3 and "std. error" in out and "p-value" in out


def test_bad_inputs_exit_2_with_a_clear_message(files, capsys, tmp_path):
    d, df, meta = files
    code, _, err = run(capsys, "calibrate", tmp_path / "none.parquet", "--features", "thermal")
    assert code == 2 and "no such file" in err
    # missing temperature columns
    write_dataset(df.drop(columns=[c for c in df.columns if c.startswith("T_")]), meta,
                  tmp_path / "notemp.parquet")
    code, _, err = run(capsys, "calibrate", tmp_path / "notemp.parquet", "--features",
                       "thermal")
    assert code == 2 and "temperature" in err
    code, _, err = run(capsys, "calibrate", d / "thermal.parquet", "--features", "thermal",
                       "--sensors", "base,ghost")
    assert code == 2 and "T_ghost_C" in err
    # force features on data without F_N, or without the three readings in a row
    code, _, err = run(capsys, "calibrate", tmp_path / "notemp.parquet", "--features", "force")
    assert code == 2 and "NaN in ['X', 'Y', 'Z']" in err
    write_dataset(df.drop(columns=["F_N"]), meta, tmp_path / "noforce.parquet")
    code, _, err = run(capsys, "calibrate", tmp_path / "noforce.parquet", "--features", "force")
    assert code == 2 and "F_N" in err
    # too few points for the terms asked
    write_dataset(df.iloc[:120], meta, tmp_path / "small.parquet")
    code, _, err = run(capsys, "calibrate", tmp_path / "small.parquet", "--features", "thermal")
    assert code == 2 and "candidate terms" in err
    # validation positions that are calibration positions: same id (CSV, not checked on write)
    bad = df.copy()
    bad.loc[bad.index[bad.split == "val"][:3], "pos_id"] = int(bad.loc[bad.split == "cal",
                                                                       "pos_id"].iloc[0])
    bad.to_csv(tmp_path / "overlap.csv", index=False)
    code, _, err = run(capsys, "calibrate", tmp_path / "overlap.csv", "--features", "thermal")
    assert code == 2 and "both 'cal' and 'val'" in err
    # ... or same coordinates under another id
    bad = df.copy()
    vi, ci = bad.index[bad.split == "val"][0], bad.index[bad.split == "cal"][0]
    for c in ("q1_rad", "q2_rad", "q3_rad"):
        bad.loc[vi, c] = bad.loc[ci, c]
    write_dataset(bad, meta, tmp_path / "overlap2.parquet")
    code, _, err = run(capsys, "calibrate", tmp_path / "overlap2.parquet", "--features",
                       "thermal")
    assert code == 2 and "same coordinates" in err
    # a model file from another feature set
    code, _, err = run(capsys, "calibrate", d / "force.parquet", "--features", "force",
                       "-o", tmp_path / "force_model.json")
    assert code == 0, err
    code, _, err = run(capsys, "calibrate", d / "thermal.parquet", "--features", "thermal",
                       "--model", tmp_path / "force_model.json")
    assert code == 2 and "'force' feature set" in err


def test_nan_rows_give_a_named_warning_in_the_report(files, capsys, tmp_path):
    _, df, meta = files
    bad = df.copy()
    bad.loc[bad.index[:5], "T_arm2_C"] = np.nan
    write_dataset(bad, meta, tmp_path / "nan.parquet")
    code, out, err = run(capsys, "calibrate", tmp_path / "nan.parquet", "--features",
                         "thermal", "--json")
    assert code == 0, err
    rep = json.loads(out)
    assert any(w.startswith("DroppedRowsWarning") for w in rep["warnings"])
    assert "DroppedRowsWarning" in err
