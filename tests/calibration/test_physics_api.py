"""PhysicsFit in scikit-learn's and statsmodels' conventions: ``summary()`` a table object
(text, HTML, JSON), ``predict`` the readings, ``score`` minus the validation error 90 %,
``save``/``load`` the file ``deltatwin fit -o`` writes; the parameter table's columns."""
import json
import math
import tomllib

import numpy as np
import pytest
from scipy import stats

from deltatwin.calibration.errors import FitError
from deltatwin.calibration.physics.fit import PhysicsFit
from deltatwin.calibration.physics.table import Z95
from deltatwin.cli import main
from deltatwin.twin.dataset import write_dataset


@pytest.fixture(scope="module")
def fitted(force_data):
    df, meta = force_data
    return df, meta, PhysicsFit(["geometric_errors", "magnetic_force"]).fit(df, meta)


def _strict(text: str):
    def refuse(name):
        raise ValueError(f"non-strict JSON constant {name}")
    return json.loads(text, parse_constant=refuse)


def test_the_summary_is_a_table_object_with_text_html_and_json(fitted):
    _, _, fit = fitted
    s = fit.summary()
    text = str(s)
    assert "validation error 90 % (nm)" in text
    labels = fit.model_.labels
    assert all(label in text for label in labels)
    html = s._repr_html_()
    assert html.count("<tr>") == len(labels) + 1 + len(s.header_lines())   # + heading row
    d = _strict(s.to_json())
    assert d["val_err90_nm"] == pytest.approx(fit.val_["all"]["err_p90"])
    assert d["parameters"] == fit.parameters_ and len(d["parameter_table"]) == len(labels)
    assert s["status"] == fit.status_                      # the dict form's entries


def test_the_parameter_table_says_value_interval_prior_and_identified(fitted):
    _, _, fit = fitted
    assert Z95 == pytest.approx(stats.norm.ppf(0.975), rel=1e-15)
    rows = fit.summary().table.as_dict()
    scales = fit.model_.scales
    undetermined = set(fit.identifiability_["not_identifiable"])
    for row, p, scale in zip(rows, fit.parameters_, scales):
        assert row["parameter"] == p["label"] and row["unit"] == p["unit"]
        half = (row["ci95_high"] - row["ci95_low"]) / 2       # 1.96 sigma either side
        assert half == pytest.approx(1.96 * p["uncertainty"], rel=1e-3)
        assert (row["ci95_high"] + row["ci95_low"]) / 2 == pytest.approx(p["value"], abs=1e-9 * half)
        assert (row["prior"], row["prior_uncertainty"]) == (p["start"], scale)
        assert row["identified"] == (p["label"] not in undetermined)
    assert any(r["identified"] for r in rows) and not all(r["identified"] for r in rows)
    # the diagonal of the covariance is the table's uncertainty
    np.testing.assert_allclose(np.sqrt(np.diag(fit.covariance_)),
                               [r["uncertainty"] for r in rows], rtol=1e-12)


def test_predict_gives_the_readings_and_score_minus_the_validation_error(fitted):
    df, meta, fit = fitted
    shuffled = df.set_axis(df.index + 1000)                 # predict keeps the caller's index
    pred = fit.predict(shuffled, meta)
    assert list(pred.columns) == ["x_m", "y_m", "z_m"] and (pred.index == shuffled.index).all()
    np.testing.assert_allclose(pred.to_numpy(), fit.reading_m_, rtol=0, atol=1e-15)
    # score by hand: |reading - prediction| on the validation readings, 90th percentile, m
    val = (df["split"] == "val").to_numpy()
    error = np.abs(df[["x_nm", "y_nm", "z_nm"]].to_numpy()[val] * 1e-9 - pred.to_numpy()[val])
    assert fit.score(df, meta) == pytest.approx(-np.percentile(error[np.isfinite(error)], 90),
                                                rel=1e-12)
    assert fit.score(df, meta) == pytest.approx(-fit.val_["all"]["err_p90"] * 1e-9, rel=1e-9)


def test_save_and_load_are_the_cli_files_and_give_back_the_same_model(fitted, tmp_path):
    df, meta, fit = fitted
    fit.save(tmp_path / "api.toml", data="force.parquet")
    loaded = PhysicsFit.load(tmp_path / "api.toml")
    assert "read from" in repr(loaded) and "73 parameters" in repr(loaded)
    np.testing.assert_array_equal(loaded.predict(df, meta).to_numpy(),
                                  fit.predict(df, meta).to_numpy())
    assert loaded.score(df) == fit.score(df, meta)          # the file's sensor map
    assert [p["uncertainty"] for p in loaded.parameters_] == [
        p["uncertainty"] for p in fit.parameters_]
    # the correlations are kept to 4 decimals
    sigma = np.sqrt(np.diag(fit.covariance_))
    assert np.max(np.abs((loaded.covariance_ - fit.covariance_) / np.outer(sigma, sigma))) <= 5e-5
    loaded.save(tmp_path / "again.toml")
    first, again = (tomllib.loads((tmp_path / n).read_text()) for n in ("api.toml", "again.toml"))
    assert first["content_sha256"] == again["content_sha256"]
    # the command line's file is read by the same loader and written back the same
    write_dataset(df, meta, tmp_path / "force.parquet")
    assert main(["fit", str(tmp_path / "force.parquet"), "--effects", "geometric_errors", "-q",
                 "--json", "-o", str(tmp_path / "cli.toml")]) == 0
    cli = PhysicsFit.load(tmp_path / "cli.toml")
    cli.save(tmp_path / "cli-again.toml")
    assert (tomllib.loads((tmp_path / "cli.toml").read_text())["content_sha256"]
            == tomllib.loads((tmp_path / "cli-again.toml").read_text())["content_sha256"])
    assert len(cli.summary().table) == cli.model_.n_free


def test_a_file_without_uncertainties_loads_and_a_damaged_table_is_refused(fitted, tmp_path):
    _, _, fit = fitted
    fit.save(tmp_path / "m.toml")
    text = (tmp_path / "m.toml").read_text()
    # hand-edited files carry no checksum: the layout checks apply
    bare = "\n".join(line for line in text.splitlines() if not line.startswith("content_sha256"))
    head, _, rest = bare.partition("[uncertainty]")
    tail = rest[rest.index("\n["):] if "\n[" in rest else ""
    (tmp_path / "old.toml").write_text(head + tail)
    old = PhysicsFit.load(tmp_path / "old.toml")
    assert old.parameters_ is None and "holds no uncertainties" in str(old.summary())
    damaged = bare.replace("standard_uncertainty = [\n", "standard_uncertainty = [\n    -1.0,\n", 1)
    (tmp_path / "bad.toml").write_text(damaged)
    with pytest.raises(FitError, match=r"bad.toml: \[uncertainty\] standard_uncertainty must be "
                                       r"73 finite numbers"):
        PhysicsFit.load(tmp_path / "bad.toml")


def test_the_repr_says_what_the_fit_is():
    assert repr(PhysicsFit(["geometric_errors"])) == (
        "PhysicsFit([geometric_errors], noise_nm=5, identifiable_ratio=0.3) (not fitted)")


def test_summary_json_is_strict_where_a_figure_does_not_exist(fitted):
    _, _, fit = fitted
    s = fit.summary()
    s.header["val_err90_nm"] = math.nan
    assert _strict(s.to_json())["val_err90_nm"] is None
