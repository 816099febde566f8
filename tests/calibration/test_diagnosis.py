"""The diagnosis loop on data with hidden effects (scenarios/quiet/, reduced scale): the true
effect is ranked first, adding it lowers the validation error >= 3x to within 1.5x the noise
floor; two hidden effects are found one after the other; an effect outside the library is not
claimed, and the variable it depends on is named."""
import json
import re
import subprocess
import sys
import tomllib

import numpy as np
import pytest

from deltatwin.calibration.diagnosis.diagnose import diagnose, effect_ladder
from deltatwin.calibration.errors import FitError
from deltatwin.calibration.physics.fit import PhysicsFit, fit_from_starts
from deltatwin.calibration.physics.model import PhysicsModel
from deltatwin.calibration.physics.model_file import fitted_toml, load_fitted
from deltatwin.twin.effects import Effect, Parameter
from deltatwin.twin.scenario import SCENARIO_DIR, Scenario, ScenarioError

HIDDEN = sorted(p.stem for p in (SCENARIO_DIR / "quiet").glob("*.toml"))
SINGLE = [n for n in HIDDEN if len(Scenario.load(f"quiet/{n}").hidden["effects"]) == 1]


def _floor(meta) -> float:
    return max(meta["truth"]["noise_floor_nm"].values())


def test_at_least_six_different_hidden_effects_are_shipped():
    hidden = {Scenario.load(f"quiet/{n}").hidden["effects"][0] for n in SINGLE}
    assert len(hidden) >= 6, hidden


@pytest.mark.slow
@pytest.mark.parametrize("name", SINGLE)
def test_hidden_effect_is_ranked_first_and_adding_it_reaches_the_noise_floor(name):
    sc = Scenario.load(f"quiet/{name}")
    df, meta = sc.simulate(sc.reduced_scale)
    hidden = sc.hidden["effects"][0]
    base = PhysicsFit(sc.hidden["baseline"]).fit(df, meta)
    d = diagnose(base)
    assert d["ranking"][0]["effect"] == hidden, [(c["effect"], c["significant"]) for c in d["ranking"]]
    assert d["ranking"][0]["significant"] and d["missing_effect"] == hidden
    assert hidden in d["next_command"]
    full = PhysicsFit(sc.hidden["baseline"] + [hidden], start=base.model_.values()).fit(df, meta)
    before, after = base.val_["all"]["err_p90"], full.val_["all"]["err_p90"]
    assert before >= 3 * after, (before, after)
    assert after <= 1.5 * _floor(meta), (after, meta["truth"]["noise_floor_nm"])


@pytest.mark.slow
def test_two_hidden_effects_are_found_one_after_the_other():
    sc = Scenario.load("quiet/thermal-and-loop")
    df, meta = sc.simulate(sc.reduced_scale)
    ladder, diagnoses, _ = effect_ladder(df, meta, sc.hidden["baseline"])
    found = [d["missing_effect"] for d in diagnoses if d["missing_effect"]]
    assert sorted(found) == sorted(sc.hidden["effects"]), found
    assert diagnoses[-1]["missing_effect"] is None
    errors = [row["val_err90_nm"] for row in ladder]
    assert errors[0] > errors[1] > errors[2] and errors[2] <= 1.5 * _floor(meta), errors


class DraughtOnTheBeams(Effect):
    """Outside the library: a draught (a door, a duct) cycles the air along the beams where no
    sensor sees it, so the air index of the whole path, dead path included, drifts with time."""
    name = "draught_on_the_beams"
    summary = "relative air index change A sin(2 pi t / P) along every beam"
    parameters = (Parameter("amplitude", "-", 3e-7, "relative index amplitude (~0.3 K of air)"),
                  Parameter("period_s", "s", 20000.0, "period of the draught"))

    def optics(self, points, optics):
        f = 1.0 + self.amplitude * np.sin(2 * np.pi * points.t_s / self.period_s)
        for a in optics.n_air:
            optics.n_air[a] = optics.n_air[a] * f


def test_effect_outside_the_library_is_not_claimed_and_time_is_named():
    sc = Scenario.load("quiet/gravity-sag")
    sc.effects.append(DraughtOnTheBeams())
    sc.hidden = None
    df, meta = sc.simulate(sc.reduced_scale)
    fit = PhysicsFit(["gravity_sag"]).fit(df, meta)
    assert fit.val_["all"]["err_p90"] > 2 * _floor(meta)      # the drift is there to be found
    d = diagnose(fit)
    assert d["missing_effect"] is None
    assert not any(c["significant"] for c in d["ranking"]), d["ranking"]
    depends = [x["variable"] for x in d["unexplained"]["depends_on"]]
    assert depends and depends[0] == "t_s", depends
    assert "t_s" in d["unexplained"]["message"]


@pytest.mark.slow
def test_identifiability_names_what_the_data_cannot_separate():
    sc = Scenario.load("quiet/geometric-errors")
    df, meta = sc.simulate(sc.reduced_scale)
    fit = PhysicsFit(["geometric_errors"]).fit(df, meta)
    ident = fit.identifiability_
    assert ident["n_parameters"] == 63
    assert 15 < ident["n_identified_directions"] < 63
    assert ident["not_identifiable"] and ident["unidentified_groups"]
    # a rod pair's two lengths: only their mean moves the platform's position at first order
    labels = {p["label"]: p for p in fit.parameters_}
    assert labels["geometric_errors.rod_length_error_m[0,0]"]["identified_fraction"] < 0.9
    for p in fit.parameters_:
        if p["identified_fraction"] < 0.5:
            assert p["label"] in ident["not_identifiable"]
    assert fit.val_["all"]["err_p90"] <= 1.5 * _floor(meta)


def test_fitted_model_file_round_trips(tmp_path):
    sc = Scenario.load("quiet/gravity-sag")
    df, meta = sc.simulate(sc.reduced_scale)
    fit = PhysicsFit(["gravity_sag"]).fit(df, meta)
    path = tmp_path / "fitted.toml"
    path.write_text(fitted_toml(fit, "data.parquet"))
    model, doc = load_fitted(path)
    assert model.names == ["gravity_sag"]
    np.testing.assert_array_equal(model.theta(), fit.model_.theta())
    assert abs(doc["fit"]["val_err90_nm"] - fit.val_["all"]["err_p90"]) < 1e-9
    assert doc["model"]["sensors"] == meta["sensors"]          # where the temperatures came from
    # the fitted load factor is the hidden scenario's
    truth = next(e for e in meta["truth"]["effects"] if e["name"] == "gravity_sag")
    assert abs(model.theta()[0] - truth["parameters"]["load_factor"]["value"]) < 0.1
    # the identified directions, edited (the checksum line removed), are refused by name
    text = "\n".join(line for line in path.read_text().splitlines()
                     if not line.startswith("content_sha256"))
    for bad, match in ((text.replace('"gravity_sag.load_factor"', '"load_factor"'),
                        r"\[identification\] parameters"),
                       (text.replace("directions = [", "directions = [[0.5, 1.0], "),
                        r"\[identification\] directions must be a list"),
                       (text.replace("directions = [", "directions = [[0.0], "),
                        r"\[identification\] directions must be orthonormal"),
                       (text.replace('data_sha256 = "', 'data_sha256 = "x'),
                        r"\[model\] data_sha256 .*SHA-256"),
                       (re.sub(r"thermometer_corrected = \w+", 'thermometer_corrected = "yes"',
                               text),
                        r"\[model\] thermometer_corrected must be true or false")):
        path.write_text(bad)
        with pytest.raises(FitError, match=match):
            load_fitted(path)


def _diagnosed_from_its_file(tmp_path, monkeypatch, fit, df, meta):
    """Write the data and the fitted model, run ``deltatwin diagnose DATA --model FILE``:
    (the fits handed to the diagnosis, list; the data's path; the model file's path)."""
    from deltatwin.calibration.diagnosis import diagnose as diagnose_module
    from deltatwin.cli import main
    from deltatwin.twin.dataset import write_dataset

    data, path = tmp_path / "data.parquet", tmp_path / "fitted.toml"
    write_dataset(df, meta, data)
    path.write_text(fitted_toml(fit, str(data)))
    seen = []
    monkeypatch.setattr(diagnose_module, "diagnose",
                        lambda f, data, **kw: seen.append(f) or diagnose(f, data, **kw))
    assert main(["diagnose", str(data), "--model", str(path), "--json", "--trust-effects"]) == 0
    return seen, data, path


def test_a_saved_converged_model_is_kept_in_the_directions_it_was_fitted_in(tmp_path,
                                                                              monkeypatch):
    """fit, save, ``deltatwin diagnose``: the file's values are kept with one Jacobian and
    diagnosed as the fit would be. On this case the directions identified at the fitted values
    (not the fit's, which were identified at its start) leave a step above the convergence limit:
    judged in them, the model was refitted on reloading."""
    from deltatwin.calibration.physics.model_file import saved_directions

    sc = Scenario.load("quiet/magnetic-force")
    df, meta = sc.simulate(sc.reduced_scale)
    effects = ["geometric_errors", "magnetic_force"]
    fit = PhysicsFit(effects).fit(df, meta)
    assert fit.converged_
    seen, data, path = _diagnosed_from_its_file(tmp_path, monkeypatch, fit, df, meta)
    model, doc = load_fitted(path)
    np.testing.assert_array_equal(saved_directions(doc), fit.identified_directions_)
    (kept,) = seen
    assert "kept" in kept.solver_message_ and kept.n_jacobians_ == 1
    assert kept.n_evaluations_ == kept.model_.n_free + 1
    np.testing.assert_array_equal(kept.theta_, fit.theta_)
    np.testing.assert_array_equal(kept.identified_directions_, fit.identified_directions_)
    assert kept.identifiability_["n_identified_directions"] == \
        fit.identifiability_["n_identified_directions"]
    ours, theirs = diagnose(kept), diagnose(fit)
    assert [c["effect"] for c in ours["ranking"]] == [c["effect"] for c in theirs["ranking"]]
    for a, b in zip(ours["ranking"], theirs["ranking"]):
        np.testing.assert_allclose([a["explained_fraction"], a["val_err90_after_nm"]],
                                   [b["explained_fraction"], b["val_err90_after_nm"]],
                                   rtol=1e-6)
    # values moved by a few uncertainties along the fitted directions are refined, not kept
    u = np.array([q["uncertainty"] for q in fit.parameters_])
    moved = PhysicsModel(effects, values=fit.model_.values())
    moved.set_theta(fit.model_.theta() + 3 * u)
    refined = PhysicsFit(effects, start=moved.values()).fit(
        df, meta, keep_converged_start=True, start_directions=saved_directions(doc))
    assert "kept" not in refined.solver_message_ and refined.n_jacobians_ > 1
    assert refined.converged_
    with pytest.raises(FitError, match="orthonormal"):
        PhysicsFit(effects, start=fit.model_.values()).fit(
            df, meta, keep_converged_start=True, start_directions=2 * saved_directions(doc))


def test_a_saved_unconverged_model_is_diagnosed_as_fitted_on_its_own_data(tmp_path,
                                                                           monkeypatch, caplog):
    """``deltatwin diagnose`` of a model that stopped short of converging: on the very data it
    was fitted on (the file's data_sha256) its values are kept as fitted (one Jacobian; its
    status still says not converged), so the diagnosis is of the file's model; on other data
    (another campaign of the same laboratory) they are refined as before."""
    from deltatwin.cli import main
    from deltatwin.twin.dataset import write_dataset

    sc = Scenario.load("quiet/magnetic-force")
    df, meta = sc.simulate(sc.reduced_scale)
    effects = ["geometric_errors", "magnetic_force"]
    fit = PhysicsFit(effects, max_evaluations=2).fit(df, meta)
    assert not fit.converged_
    caplog.clear()
    seen, data, path = _diagnosed_from_its_file(tmp_path, monkeypatch, fit, df, meta)
    (kept,) = seen
    assert "kept as fitted" in kept.solver_message_ and kept.n_jacobians_ == 1
    # its warning says the saved model is not converged, not that a fit ran out of evaluations
    warned = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert any("kept as fitted on these data, is not converged" in w for w in warned), warned
    assert not any("did not converge after" in w for w in warned), warned
    np.testing.assert_array_equal(kept.theta_, fit.theta_)
    assert not kept.converged_
    np.testing.assert_allclose(kept.residual_, fit.residual_, rtol=0, atol=1e-15)
    other = tmp_path / "other.parquet"
    write_dataset(*Scenario.load("quiet/magnetic-force", seed=sc.seed + 1).simulate(
        sc.reduced_scale), other)
    assert main(["diagnose", str(other), "--model", str(path), "--json"]) == 0
    refined = seen[-1]
    assert "kept" not in refined.solver_message_ and refined.n_jacobians_ > 1
    # the same rows read through another sensor map (a corrected .meta.json) are other data
    sensors = dict(meta["sensors"])
    a, b = sorted(s for s in sensors if sensors[s] != sensors[sorted(sensors)[0]])[:1] + \
        sorted(sensors)[:1]
    sensors[a], sensors[b] = sensors[b], sensors[a]
    moved = PhysicsFit(effects, start=fit.model_.values()).fit(
        df, {**meta, "sensors": sensors}, keep_converged_start=True,
        start_directions=fit.identified_directions_, fitted_on=fit.data_sha256_)
    assert "kept" not in moved.solver_message_


RIPPLE = """
import numpy as np
from deltatwin.twin.effects import Effect, Parameter, shift_reading


class Ripple(Effect):
    name = "ripple_code"
    summary = "X reads a ripple in q1"
    parameters = (Parameter("amplitude_m", "m", 0.0, "amplitude", fit_scale=10e-9),)

    def optics(self, points, optics):
        shift_reading(optics, "x", {scale} * self.amplitude_m * np.sin(points.q[:, 0] / 2e-3))
"""


def test_a_saved_model_whose_effect_code_changed_is_refined_not_kept(tmp_path, monkeypatch):
    """The file keeps a fingerprint of the effects' code (deltatwin's version, each effect's
    source file): a researcher's effect edited since the fit makes its saved values a fit of
    other code, so ``deltatwin diagnose`` on the very same data refines them instead of keeping
    them as fitted."""
    sc = Scenario.load("quiet/magnetic-force")
    df, meta = sc.simulate(sc.reduced_scale)
    user = tmp_path / "lab_ripple.py"
    user.write_text(RIPPLE.format(scale="1.0"))
    effects = ["geometric_errors", f"{user}:Ripple"]
    fit = PhysicsFit(effects, max_evaluations=2).fit(df, meta)
    seen, data, path = _diagnosed_from_its_file(tmp_path, monkeypatch, fit, df, meta)
    assert "kept as fitted" in seen[-1].solver_message_
    doc = tomllib.loads(path.read_text())
    user.write_text(RIPPLE.format(scale="2.0"))       # the researcher doubles the term
    from deltatwin.cli import main

    assert main(["diagnose", str(data), "--model", str(path), "--json", "--trust-effects"]) == 0
    assert "kept" not in seen[-1].solver_message_ and seen[-1].n_jacobians_ > 1
    # a hand-edited file (its content_sha256 line removed) with a bad fingerprint: refused by name
    bad = tmp_path / "bad.toml"
    bad.write_text("\n".join(line for line in path.read_text().splitlines()
                             if not line.startswith("content_sha256")).replace(
        doc["model"]["code_sha256"], "nothex"))
    with pytest.raises(FitError, match=r"code_sha256.*SHA-256"):
        load_fitted(bad, trust_effects=True)


def test_a_start_already_fitted_is_reused_not_refitted(monkeypatch):
    """fit_from_starts(made=...): a start whose problem (effects, starting values, prior,
    options) another call already solved on the same rows is taken from there (the demo's
    floor and last rung); any difference is fitted."""
    sc = Scenario.load("hidden/gravity-sag")
    df, meta = sc.simulate(sc.reduced_scale)
    first = fit_from_starts(["gravity_sag"], {"library": {}}, df, meta)
    calls = []
    fit = PhysicsFit.fit
    monkeypatch.setattr(PhysicsFit, "fit", lambda self, *a, **k: calls.append(self.start)
                        or fit(self, *a, **k))
    moved = {"gravity_sag": {"load_factor": 0.5}}
    second = fit_from_starts(["gravity_sag"], {"priors": {}, "moved": {"start": moved},
                                               "noisier": {"noise_nm": 6.0}}, df, meta,
                             made=list(first.start_fits_.values()))
    assert calls == [moved, None]                     # "priors" was not fitted again
    reused = second.start_fits_["priors"]
    np.testing.assert_array_equal(reused.theta_, first.theta_)
    # a copy: labelling the second call's best leaves the first call's fit as it was
    assert reused is not first and first.start_label_ == "library"
    assert set(second.start_costs_) == {"priors", "moved", "noisier"}


def test_bad_input_is_named(tmp_path):
    sc = Scenario.load("quiet/gravity-sag")
    df, meta = sc.simulate(0.05)
    with pytest.raises(ValueError, match="unknown effect 'gravity_sagg'.*did you mean 'gravity_sag'"):
        PhysicsFit(["gravity_sagg"])
    with pytest.raises(FitError, match="room_climate.*thermal network"):
        PhysicsFit(["room_climate"])
    with pytest.raises(ValueError, match="cannot identify"):
        PhysicsFit(["geometric_errors"]).fit(df.iloc[:20], meta)
    bad = dict(meta, sensors={**meta["sensors"], "ghost": "base"})
    with pytest.raises(ValueError, match="'ghost'.*T_ghost_C"):
        PhysicsFit(["thermal_expansion"]).fit(df, bad)
    with pytest.raises(ValueError, match="missing column"):
        PhysicsFit(["gravity_sag"]).fit(df.drop(columns=["q2_rad"]), meta)
    with pytest.raises(ValueError, match="not a fitted physics model"):
        (tmp_path / "x.toml").write_text("[scenario]\nname = 'x'\n")
        load_fitted(tmp_path / "x.toml")
    bad_scenario = tmp_path / "h.toml"
    bad_scenario.write_text((SCENARIO_DIR / "quiet" / "gravity-sag.toml").read_text()
                            .replace('effects = ["gravity_sag"]', 'effects = ["beam_misalignment"]'))
    with pytest.raises(ScenarioError, match=r"\[hidden\].*not in \[effects\] on"):
        Scenario.load(bad_scenario)


def test_cli_fit_and_diagnose_and_nothing_partial_on_error(tmp_path):
    sc = Scenario.load("quiet/gravity-sag")
    from deltatwin.twin.dataset import write_dataset
    df, meta = sc.simulate(sc.reduced_scale)
    data = tmp_path / "data.parquet"
    write_dataset(df, meta, data)
    run = lambda *a: subprocess.run([sys.executable, "-m", "deltatwin.cli", *map(str, a)],
                                    capture_output=True, text=True, cwd=tmp_path)
    r = run("fit", data, "--effects", "none", "--json", "-o", tmp_path / "base.toml")
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["n_parameters"] == 0
    r = run("diagnose", data, "--model", tmp_path / "base.toml", "--json")
    assert r.returncode == 0, r.stderr
    d = json.loads(r.stdout)
    assert d["ranking"][0]["effect"] == "gravity_sag" and d["ranking"][0]["significant"]
    assert set(d) >= {"val_err90_nm", "ranking", "unexplained"}
    assert set(d["ranking"][0]) >= {"effect", "explained_fraction", "val_err90_after_nm",
                                    "significant"}
    ghost = tmp_path / "ghost.parquet"
    write_dataset(df, dict(meta, sensors={**meta["sensors"], "ghost": "base"}), ghost)
    r = run("fit", ghost, "--effects", "thermal_expansion", "-o", tmp_path / "g.toml")
    assert r.returncode == 2 and str(ghost) in r.stderr and "T_ghost_C" in r.stderr
    assert not (tmp_path / "g.toml").exists()
    unmapped = tmp_path / "unmapped.csv"        # a lab CSV whose sidecar maps no sensor
    write_dataset(df, dict(meta, sensors={}), unmapped)
    r = run("fit", unmapped, "--effects", "loop_drift", "-o", tmp_path / "u.toml")
    assert r.returncode == 2 and "names no temperature sensor" in r.stderr, r.stderr
    assert ".meta.json" in r.stderr and not (tmp_path / "u.toml").exists()
    (tmp_path / "not_a_model.toml").write_text("[scenario]\nname = 'x'\n")
    r = run("diagnose", data, "--model", tmp_path / "not_a_model.toml")
    assert r.returncode == 2 and "not a fitted physics model" in r.stderr
    r = run("fit", data, "--effects", "geometric_errors,nope", "-o", tmp_path / "bad.toml")
    assert r.returncode == 2 and "unknown effect 'nope'" in r.stderr
    assert not (tmp_path / "bad.toml").exists()
    # known constants of the laboratory: --set EFFECT.PARAM=VALUE
    r = run("fit", data, "--effects", "gravity_sag", "--set", "gravity_sag.load_factor=2",
            "--set", "gravity_sag.load_factor=abc", "-o", tmp_path / "bad.toml")
    assert r.returncode == 2 and "'abc' is not a number" in r.stderr
    # a constant of an effect outside the model is kept for the candidates a diagnosis adds
    r = run("fit", data, "--effects", "gravity_sag", "--set", "loop_drift.frame_arm_m=-0.6,0",
            "-o", tmp_path / "known.toml")
    assert r.returncode == 0, r.stderr
    known = tomllib.loads((tmp_path / "known.toml").read_text())["known"]
    # beside what the data's setup states (simulate: the beams' air's shares of the room)
    assert known["loop_drift"] == {"frame_arm_m": [-0.6, 0.0]}
    assert set(known) == {"loop_drift", "room_climate"}
    r = run("fit", data, "--effects", "gravity_sag", "--set", "loop_drift.frame_arms_m=-0.6,0",
            "-o", tmp_path / "bad.toml")
    assert r.returncode == 2 and "frame_arms_m" in r.stderr and "'frame_arm_m'" in r.stderr
    assert not (tmp_path / "bad.toml").exists()


def test_stepwise_residual_is_traced_to_its_feature_family(tmp_path):
    """The black-box view: a geometric-only DGM on thermal data misses the temperatures; the
    complete DGM leaves no family to blame; the CLI gives the same on a model.json."""
    from deltatwin.calibration.blackbox.dgm import DGM
    from deltatwin.calibration.blackbox.estimator import thermal_sensors
    from deltatwin.calibration.blackbox.features import thermal_ladder
    from deltatwin.calibration.diagnosis.diagnose import diagnose_families
    from deltatwin.twin.dataset import write_dataset

    sc = Scenario.load("paper-thermal")
    df, meta = sc.simulate(0.1)
    rungs = dict(thermal_ladder(thermal_sensors(df, meta)))
    geometric = DGM(features=rungs["geometric only"]).fit(df, meta)
    d = diagnose_families(df, meta, geometric)
    top = d["ranking"][0]
    assert d["correlated_family"] == "temperatures" == top["family"]
    assert top["significant"] and not top["in_model"] and top["explained_fraction"] > 0.9, top
    assert top["val_err90_after_nm"] < 0.2 * d["val_err90_nm"]
    geometric_row = next(c for c in d["ranking"] if c["family"] == "geometric")
    assert geometric_row["in_model"] and not geometric_row["significant"]

    complete = DGM(features=rungs["C: complete (+ derivatives)"]).fit(df, meta)
    data, model = tmp_path / "th.parquet", tmp_path / "dgm.json"
    write_dataset(df, meta, data)
    complete.save(model)
    out = subprocess.run([sys.executable, "-m", "deltatwin.cli", "diagnose", str(data), "--model",
                          str(model), "--json"], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    d = json.loads(out.stdout)
    assert d["model"] == "DGM" and d["correlated_family"] is None
    assert all(c["in_model"] and not c["significant"] for c in d["ranking"])


def test_a_converged_fitted_model_is_kept_without_the_solver():
    """``diagnose`` of a model fitted on the same data: the fitted values are kept with one
    Jacobian (no refit); a start that is not converged is still refined."""
    sc = Scenario.load("hidden/gravity-sag")
    df, meta = sc.simulate(sc.reduced_scale)
    fit = PhysicsFit(["gravity_sag"]).fit(df, meta)
    assert fit.converged_
    kept = PhysicsFit(["gravity_sag"], start=fit.model_.values()).fit(
        df, meta, keep_converged_start=True)
    np.testing.assert_array_equal(kept.theta_, fit.theta_)
    assert kept.n_evaluations_ == kept.model_.n_free + 1 and kept.converged_
    assert "kept" in kept.solver_message_
    np.testing.assert_allclose(kept.residual_, fit.residual_, rtol=0, atol=1e-15)
    assert [c["effect"] for c in diagnose(kept)["ranking"]] == \
        [c["effect"] for c in diagnose(fit)["ranking"]]
    # from the nominal start (not converged on these data) the solver runs
    fresh = PhysicsFit(["gravity_sag"]).fit(df, meta, keep_converged_start=True)
    assert "kept" not in fresh.solver_message_ and fresh.n_evaluations_ > fresh.model_.n_free + 1
    np.testing.assert_allclose(fresh.theta_, fit.theta_, rtol=1e-12)


def test_the_attribution_in_a_second_process_gives_the_same_diagnosis(monkeypatch):
    """diagnose's attribution beside the candidates (models.batched.in_background): forked or
    computed in the process, the diagnosis is the same to the last bit."""
    from deltatwin.models import batched

    sc = Scenario.load("quiet/gravity-sag")
    sc.effects.append(DraughtOnTheBeams())
    sc.hidden = None
    df, meta = sc.simulate(sc.reduced_scale)
    fit = PhysicsFit(["gravity_sag"]).fit(df, meta)
    diagnoses = []
    for background in (False, True):
        monkeypatch.setattr(batched, "BACKGROUND", background)
        diagnoses.append(json.dumps(diagnose(fit), sort_keys=True, default=str))
    assert diagnoses[0] == diagnoses[1]
    assert '"depends_on": [{' in diagnoses[1]          # the attribution named a variable
    # the laboratory variables made beforehand (as `deltatwin diagnose` does, in a second
    # process): the same diagnosis; variables made from other data are refused by name
    from deltatwin.calibration.diagnosis.attribution import laboratory_variables

    given = json.dumps(diagnose(fit, variables=laboratory_variables(df)), sort_keys=True,
                       default=str)
    assert given == diagnoses[0]
    with pytest.raises(ValueError, match=r"variables \['t_s', .* one value per row"):
        diagnose(fit, variables=laboratory_variables(df.iloc[:10]))


def test_at_the_floor_nothing_is_proposed():
    """A model at its achievable floor with no library effect significant: the diagnosis says
    so and proposes neither a variable nor a form (what they would fit is the floor's noise)."""
    from deltatwin.calibration.diagnosis.floor import record_achievable_floor

    sc = Scenario.load("quiet/thermal-and-loop")
    df, meta = sc.simulate(0.05)
    record_achievable_floor(df, meta)                  # as `deltatwin simulate` does
    fit = PhysicsFit(["geometric_errors", "thermal_expansion", "loop_drift"],
                     max_evaluations=80).fit(df, meta)
    d = diagnose(fit)
    assert d["missing_effect"] is None and d["at_floor"]
    assert d["unexplained"]["depends_on"] == [] and "form" not in d["unexplained"]
    assert d["unexplained"]["message"].endswith("nothing is proposed")


def test_the_diagnosis_is_a_typed_result_with_json():
    """diagnose returns a Diagnosis: attributes for what a researcher reads, its rows
    Candidates, strict JSON equal to the mapping (NaN as null), and a repr that says what was
    found."""
    from deltatwin.calibration.diagnosis.results import Candidate, Diagnosis

    sc = Scenario.load("quiet/gravity-sag")
    df, meta = sc.simulate(sc.reduced_scale)
    d = diagnose(PhysicsFit(["geometric_errors"]).fit(df, meta))
    assert isinstance(d, Diagnosis) and all(isinstance(c, Candidate) for c in d.ranking)
    assert d.missing_effect == d["missing_effect"] and d.effects == ["geometric_errors"]
    assert json.loads(d.to_json())["val_err90_nm"] == pytest.approx(d.val_err90_nm)
    assert "NaN" not in d.to_json()
    top = d.ranking[0]
    assert top.significant == bool(top["significant"]) and top.effect in repr(top)
    assert repr(d).startswith("Diagnosis(geometric_errors: validation error 90 %")
    assert (f"missing {d.missing_effect}" in repr(d)) if d.missing_effect else \
        "no library effect" in repr(d)


@pytest.mark.slow
@pytest.mark.parametrize("name", ["hidden/magnetic-force", "hidden/loop-drift",
                                  "hidden/thermal-expansion"])
def test_every_rows_verdict_follows_from_the_figures_the_table_prints(name):
    """On shipped hidden scenarios of both campaign kinds (reduced scale, the data's baseline
    and setup, the floor recorded as `simulate` records it), each ranking row's "significant"
    is the rule applied to the figures the table prints for it (``Candidate.table_figures``:
    a refit's where the refit decided) with its test level ``alpha``: by the calibration rows
    (p < alpha, the BIC falls, explains MIN_EXPLAINED or closes GAP_CLOSED of the gap to the
    floor, the model not within AT_FLOOR of it), by the calibration and validation rows
    combined (p_combined < alpha, closes GAP_CLOSED), or by the refit's tests; and a row
    called not significant satisfies neither of the first two on its printed figures unless a
    refit or the generic terms judged it."""
    from deltatwin.calibration.diagnosis.floor import record_achievable_floor
    from deltatwin.calibration.stats import ALPHA, AT_FLOOR, GAP_CLOSED, MIN_EXPLAINED
    from deltatwin.twin.lab_setup import baseline_of, known_constants

    sc = Scenario.load(name)
    df, meta = sc.simulate(sc.reduced_scale)
    record_achievable_floor(df, meta)
    fit = PhysicsFit(baseline_of(meta), start=known_constants(meta),
                     max_evaluations=80).fit(df, meta)
    d = diagnose(fit)
    floor = d["floor_nm"]["all"]
    above = d["val_err90_nm"] > AT_FLOOR * floor
    seen = set()
    for c in d["ranking"]:
        if "failed" in c:
            assert not c["significant"]
            continue
        explained, _, p, d_bic = c.table_figures()
        how = c.decided_by()
        seen.add(how)
        by_calibration = (p < c["alpha"] and d_bic < 0 and above
                          and (explained >= MIN_EXPLAINED or c["gap_closed"] >= GAP_CLOSED))
        by_both = c["gap_closed"] >= GAP_CLOSED and c["p_combined"] < c["alpha"]
        if how == "calibration":
            assert by_calibration, c
        elif how == "validation":
            assert by_both and not by_calibration, c
        elif how == "refit":
            assert (c["refit_p_value"] < ALPHA and c["refit_delta_bic"] < 0) or (
                c["refit_gap_closed"] >= GAP_CLOSED and c["refit_p_combined"] < ALPHA), c
        elif "refit_explained_fraction" not in c and not c.get("matched_by_generic"):
            assert not (by_calibration or by_both), c
    assert seen & {"calibration", "validation", "refit"}, "no row was significant"
