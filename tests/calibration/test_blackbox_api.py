"""The black-box estimators in scikit-learn's conventions (``score``, ``load``, a useful
``repr``) and their coefficient table as MATLAB's stepwisefit shows it: coefficients, standard
errors and p-values, checked against statsmodels' OLS on the kept terms, kept in the saved
model."""
import json

import numpy as np
import pandas as pd
import pytest
import statsmodels.api as sm

from deltatwin.calibration.blackbox.dgm import DGM
from deltatwin.calibration.blackbox.direct_igm import DirectIGM
from deltatwin.calibration.blackbox.estimator import base_variables, coefficient_unit
from deltatwin.calibration.blackbox.features import FeatureSet, Monomials, Term
from deltatwin.calibration.blackbox.model_file import load_model
from deltatwin.calibration.errors import ModelFileError, ModelMismatchError


def test_standard_errors_and_p_values_are_statsmodels_ols_on_the_kept_terms(force_igm,
                                                                              force_data):
    df, _ = force_data
    values = base_variables(df, force_igm.features_.variables, [], force_igm.T_ref_K,
                            force_igm.window_s)
    cal = (df["split"] == "cal").to_numpy()
    for o in force_igm.outputs_:
        names = [t.name for t in o.terms]
        X = force_igm.features_.matrix(values)[:, [force_igm.features_.names.index(n)
                                                   for n in names]]
        y = df[o.column].to_numpy(dtype=float)
        rows = cal & np.isfinite(y) & np.all(np.isfinite(X), axis=1)
        # standardised columns: OLS's own solve is then well conditioned; se scale back
        scale = X[rows].std(axis=0)
        ols = sm.OLS(y[rows], sm.add_constant(X[rows] / scale)).fit()
        np.testing.assert_allclose(o.coef, ols.params[1:] / scale, rtol=1e-6)
        np.testing.assert_allclose(o.se, ols.bse[1:] / scale, rtol=1e-6)
        big = ols.pvalues[1:] > 1e-250          # below, both are round-off of zero
        np.testing.assert_allclose(o.p_value[big], ols.pvalues[1:][big], rtol=1e-5)
        assert o.dfe == int(ols.df_resid)


def test_the_saved_model_keeps_the_uncertainties_and_loads_by_kind(force_igm, tmp_path):
    force_igm.save(tmp_path / "igm.json")
    doc = json.loads((tmp_path / "igm.json").read_text())
    assert len(doc["outputs"][0]["se"]) == force_igm.outputs_[0].terms_kept
    loaded = DirectIGM.load(tmp_path / "igm.json")
    for a, b in zip(loaded.outputs_, force_igm.outputs_):
        np.testing.assert_array_equal(a.se, b.se)
        np.testing.assert_array_equal(a.p_value, b.p_value)
    assert loaded.coefficient_table("q1").as_dict() == force_igm.coefficient_table("q1").as_dict()
    from deltatwin.calibration.blackbox.dgm import DGM
    with pytest.raises(ModelMismatchError, match="holds a DirectIGM model, a DGM was expected"):
        DGM.load(tmp_path / "igm.json")
    # a model saved before the uncertainties were kept still loads; its table shows '-'
    for o in doc["outputs"]:
        del o["se"], o["p_value"], o["dfe"]
    doc.pop("content_sha256")
    doc["format_version"] = 1                   # files without a checksum: version 1
    (tmp_path / "old.json").write_text(json.dumps(doc))
    old = load_model(tmp_path / "old.json")
    assert old.outputs_[0].se is None
    row = old.coefficient_table("q1").rows()[0]
    assert row[3:] == ["-", "-", "-"]


def test_score_is_minus_the_validation_error_90_at_the_end_effector(force_igm, force_data):
    df, _ = force_data
    at_effector = force_igm.motor_error_at_effector(df)
    val = (df["split"] == "val").to_numpy()
    e = np.abs(at_effector[val])
    assert force_igm.score(df) == pytest.approx(-np.percentile(e[np.isfinite(e)], 90), rel=1e-12)
    assert -force_igm.score(df) < 1e-6                      # metres: well under a micrometre


def test_the_repr_says_what_the_estimator_is(force_igm):
    assert repr(DirectIGM()) == "DirectIGM(features='force', penter=0.05, premove=0.1) (not fitted)"
    kept = ", ".join(f"{o.output} {o.terms_kept}" for o in force_igm.outputs_)
    assert repr(force_igm) == (f"DirectIGM(features='force', sensors=[]: 79 candidate terms; "
                               f"terms kept {kept})")


def test_a_coefficients_unit_is_the_outputs_over_the_terms():
    assert coefficient_unit("rad", Term((("X", 1),))) == "rad/m"
    assert coefficient_unit("rad", Term((("X", 1), ("Y", 2), ("F", 1)))) == "rad/(m^3*N)"
    assert coefficient_unit("m", Term((("dT_base", 2),))) == "m/(K/s)^2"


def test_an_igm_says_which_dgm_it_inverts():
    from deltatwin.calibration.blackbox.dgm import DGM
    from deltatwin.calibration.blackbox.estimator import OutputModel
    from deltatwin.calibration.blackbox.features import FeatureSet, geometric
    from deltatwin.calibration.blackbox.igm import IGM

    outputs = [OutputModel(a, "m", f"{a}_nm", 1e-9, [Term(((q, 1),))], np.array([0.1]), 0.0,
                           np.zeros(1), np.ones(1), 0.0, 1.0)
               for a, q in zip("xyz", ("q1", "q2", "q3"))]
    text = repr(IGM(DGM.from_outputs(FeatureSet([geometric()]), outputs)))
    assert text.startswith("IGM(DGM(features=") and "terms kept x 1, y 1, z 1" in text
    assert "tol_m=1e-12, max_iter=30" in text


def _drifting_regression(rng, n=1000, rho=0.9):
    """A DGM's data with a known truth: x = 1e-4 q1 - 2e-4 q2 + 5e-5 q3 (m, q in rad) plus an
    AR(1) misfit of 20 nm (a thermal model's slow residual), one reading per 10 s; q2 drifts
    slowly, as a temperature does (its score is then serially correlated too)."""
    q = rng.uniform(-0.05, 0.05, (n, 3))
    q[:, 1] = 0.05 * np.sin(2 * np.pi * (np.arange(n) / n * rng.uniform(1.5, 3)
                                         + rng.uniform()))
    e = np.empty(n)
    e[0] = rng.standard_normal()
    for i in range(1, n):
        e[i] = rho * e[i - 1] + np.sqrt(1 - rho ** 2) * rng.standard_normal()
    x = q @ np.array([1e-4, -2e-4, 5e-5]) + 20e-9 * e
    return pd.DataFrame({"t_s": 10.0 * np.arange(n), "pos_id": np.arange(n), "split": "cal",
                         "session": "s", "q1_rad": q[:, 0], "q2_rad": q[:, 1],
                         "q3_rad": q[:, 2], "x_nm": x * 1e9})


def test_a_dgm_s_coefficient_covariance_covers_the_truth_with_a_drifting_residual():
    """The covariance a DGM keeps for its band counts the residual's serial correlation: over
    120 regressions with a known truth and an AR(1) residual (rho 0.9, 1000 rows), the 95 %
    intervals from its diagonal cover the true coefficients about as often as they claim
    (measured 92 %; the drifting term's 88 %: its batch means see some 30 independent
    blocks), where stepwisefit's standard errors (independent residuals) cover the drifting
    term's in less than half the fits."""
    features = FeatureSet([Monomials(orders=(1,))], name="linear")
    truth = {"q1": 1e-4, "q2": -2e-4, "q3": 5e-5}
    rng = np.random.default_rng(20261129)
    covered = {"covariance": 0, "se q2": 0}
    n = 0
    for _ in range(120):
        model = DGM(features=features, sensors=[], penter=0.5, premove=0.6).fit(
            _drifting_regression(rng), {})
        out = model.output("x")
        u = np.sqrt(np.diag(out.covariance))
        for k, term in enumerate(out.terms):
            error = abs(out.coef[k] - truth[term.name])
            covered["covariance"] += error <= 1.96 * u[k]
            covered["se q2"] += term.name == "q2" and error <= 1.96 * out.se[k]
            n += 1
    assert n == 360
    assert 0.90 <= covered["covariance"] / n <= 0.99, covered
    assert covered["se q2"] / 120 < 0.5, covered


@pytest.mark.parametrize("fixture", ["thermal_dgm", "force_igm"])
def test_a_model_file_keeps_its_covariance(fixture, request, tmp_path):
    """Exactly, symmetric to the last digit (a file whose covariance is not is refused), and
    positive definite: computed in standardised columns (a cubic term's column and a
    temperature's are decades apart; in raw units the sandwich's inverse left a direct IGM's
    covariance asymmetric by 5 % of its largest entry)."""
    model = request.getfixturevalue(fixture)
    again = load_model(model.save(tmp_path / "model.json"))
    for name in model.output_names_:
        before, after = model.output(name).covariance, again.output(name).covariance
        assert before.shape == (len(model.output(name).terms),) * 2
        np.testing.assert_array_equal(before, after)
        np.testing.assert_array_equal(before, before.T)
        assert np.linalg.eigvalsh(before / np.sqrt(np.outer(np.diag(before),
                                                            np.diag(before)))).min() > 0


def _asymmetric(covariance):
    covariance[0][1] *= 1.001
    return covariance


@pytest.mark.parametrize("damage, words", [
    (_asymmetric, "covariance is not a finite symmetric"),
    (lambda c: c[:2], "output entry is malformed"),          # the wrong size
    (lambda c: "text", "output entry is malformed")])
def test_a_model_file_with_a_bad_covariance_is_refused(thermal_dgm, tmp_path, damage, words):
    path = thermal_dgm.save(tmp_path / "model.json")
    doc = json.loads(path.read_text())
    doc.pop("content_sha256")
    doc["format_version"] = 1                   # files without a checksum: version 1
    doc["outputs"][0]["covariance"] = damage(doc["outputs"][0]["covariance"])
    path.write_text(json.dumps(doc))
    with pytest.raises(ModelFileError, match=words):
        load_model(path)
