"""The find-the-missing-effect loop: a fit that always returns, effects the baseline absorbs
reported as absorbed, a candidate that fails named in its row, the achievable floor, and
extrapolation flagged (small simulated campaigns)."""
import functools
import logging
from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest

from deltatwin.calibration.diagnosis import diagnose as diagnosis
from deltatwin.calibration.diagnosis.conditions import extrapolated_variables
from deltatwin.calibration.diagnosis.floor import achievable_floor, true_fit, true_model
from deltatwin.calibration.errors import FitError
from deltatwin.calibration.physics.fit import PhysicsFit, fit_from_starts
from deltatwin.calibration.physics.measurements import Measurements
from deltatwin.calibration.physics.model import PhysicsModel
from deltatwin.calibration.stats import ABSORBED, ALPHA, GAP_CLOSED, GENERIC_SHARE, DecisionRule
from deltatwin.models.kinematics import KinematicsError
from deltatwin.twin.cases import KNOWN, MODEL, Case, generate_cases
from deltatwin.twin.lab_setup import merged
from deltatwin.twin.scenario import Scenario
from tests.calibration.series import ar1

RULE = DecisionRule()   # the rule's defaults, as the diagnosis runs by default

BASELINE = ["geometric_errors", "thermal_expansion", "sensor_contact"]


@pytest.fixture(scope="module")
def loop_drift():
    return Scenario.load("quiet/loop-drift").simulate(0.05)


@pytest.fixture(scope="module")
def baseline_fit(loop_drift):
    # the loop drift is missing: the residual is ~40x the noise, the model misspecified
    return PhysicsFit(BASELINE, max_evaluations=3).fit(*loop_drift)


def test_a_misspecified_fit_returns_its_best_fit_with_a_status(loop_drift, caplog):
    # stopped after one step (the fit re-uses its Jacobian, so three evaluations converge here)
    with caplog.at_level(logging.WARNING):
        fit = PhysicsFit(BASELINE, max_evaluations=2).fit(*loop_drift)
    start = PhysicsFit(BASELINE, max_evaluations=1).fit(*loop_drift)
    assert not fit.converged_
    assert fit.status_.startswith("not converged") and "uncertainty" in fit.status_
    assert any("did not converge" in r.message for r in caplog.records)
    assert np.isfinite(fit.val_["all"]["err_p90"])
    assert fit.cal_["all"]["err_p90"] < start.cal_["all"]["err_p90"]
    assert fit.summary()["status"] == fit.status_


def test_absorbed_candidates_are_reported_as_absorbed_not_absent(baseline_fit):
    d = diagnosis.diagnose(baseline_fit)
    rows = {c["effect"]: c for c in d["ranking"]}
    sag = rows["gravity_sag"]
    # a uniform load on the platform moves it as a change of geometry would
    assert sag["absorbed_fraction"] > 0.9 and sag["absorbed_by"] == "geometric_errors"
    assert not sag["significant"] and "absorbed by geometric_errors" in sag["verdict"]
    assert any(v.startswith("gravity_sag:") for v in d["absorbed"])
    # the coils never carry current in a thermal campaign: no signature, not "absorbed"
    assert rows["magnetic_force"]["signature_nm"] == 0
    assert "no signature" in rows["magnetic_force"]["verdict"]
    assert d["missing_effect"] == "loop_drift"


def test_a_candidate_that_fails_says_so_in_its_row(baseline_fit, monkeypatch):
    real = diagnosis._candidate

    def failing(fit, name, *args):
        if name == "beam_misalignment":
            raise KinematicsError("pose 3: the rods cannot reach the platform")
        return real(fit, name, *args)

    monkeypatch.setattr(diagnosis, "_candidate", failing)
    d = diagnosis.diagnose(baseline_fit)
    row = next(c for c in d["ranking"] if c["effect"] == "beam_misalignment")
    assert "rods cannot reach" in row["failed"] and not row["significant"]
    assert d["missing_effect"] == "loop_drift"
    assert any("beam_misalignment: could not be evaluated" in v for v in d["failed_candidates"])


def test_achievable_floor_refits_the_true_model(loop_drift):
    df, meta = loop_drift
    effects, values = true_model(meta)
    assert set(effects) == {"geometric_errors", "thermal_expansion", "loop_drift",
                            "sensor_contact"}
    floor = achievable_floor(df, meta)
    instrument = meta["truth"]["noise_floor_nm"]
    for a in "xyz":
        budget = floor["budget_nm"][a]
        assert budget["noise_floor_nm"] == instrument[a]
        assert np.hypot(budget["noise_floor_nm"], budget["above_noise_floor_nm"]) \
            == pytest.approx(max(floor["achievable_floor_nm"][a], instrument[a]))
    assert floor["converged"], floor["status"]
    # the twin's complete model, refitted, reaches near the interferometers' floor here (every
    # part carries a sensor, the pressure holds still)
    assert floor["achievable_floor_nm"]["all"] < 1.5 * max(instrument.values())


def test_extrapolation_names_the_variables_that_leave_the_calibration_range():
    split = np.array(["cal"] * 50 + ["val"] * 50)
    t = np.linspace(0, 1, 100)
    df = pd.DataFrame({"split": split, "T_coil1_C": 20 + 10 * t,          # val is warmer
                       "T_base_C": 20 + 0.01 * np.sin(40 * t),            # same range
                       "F_N": np.tile([0.0, 1.0, 2.0, 0.5], 25)})
    out = extrapolated_variables(df)
    assert [d["variable"] for d in out] == ["T_coil1_C"]
    assert out[0]["val_range"][1] == pytest.approx(30.0)


def test_force_plans_can_interleave_calibration_and_validation(tmp_path):
    text = Scenario.load("paper-force").path.read_text()
    plans = {}
    for order in ("papers", "interleaved"):
        p = tmp_path / f"{order}.toml"
        p.write_text(text.replace('kind = "force"', f'kind = "force"\norder = "{order}"'))
        plans[order] = Scenario.load(p).plan(np.random.default_rng(0), 0.05)
    papers, mixed = plans["papers"].split, plans["interleaved"].split
    assert sorted(papers) == sorted(mixed)
    half = len(papers) // 2
    assert (papers[:half] == "val").sum() == 0                   # the val grid comes last
    assert 0.3 < (mixed[:half] == "val").mean() / (mixed == "val").mean() * 0.5 < 0.7
    bad = tmp_path / "bad.toml"
    bad.write_text(text.replace('kind = "force"', 'kind = "force"\norder = "random"'))
    with pytest.raises(ValueError, match="order = 'random'"):
        Scenario.load(bad).plan(np.random.default_rng(0), 0.05)


@pytest.fixture(scope="module")
def two_basins(tmp_path_factory):
    """A generated thermal case (air_refraction x1/3 and gravity_sag hidden from the papers'
    model): its true model has two basins, and the twin's values lie in the shallower one."""
    case = generate_cases(np.random.default_rng(2611), 7)[6]
    assert case.hidden_effects == ["air_refraction", "gravity_sag"]
    path = tmp_path_factory.mktemp("two_basins") / "case.toml"
    path.write_text(case.toml())
    return case, *Scenario.load(path).simulate(0.02)


@pytest.mark.xfail(strict=True, reason=(
    "fitted from the library's starting values only, the complete model stops at 12.23 nm "
    "calibration rms against the baseline's 11.99: the floor needs a researcher's second start "
    "(the baseline's fit), not the twin's values"))
def test_the_achievable_floor_fits_at_least_as_well_as_a_model_with_fewer_effects(two_basins):
    # the true model holds the baseline's effects and more: fitted as a researcher would (from
    # the library's starting values, never the twin's values) it fits the calibration rows at
    # least as well (from the twin's values it stopped in a shallower basin: 13.0 nm rms
    # against the baseline's 7.9, and a floor of 26 nm above the baseline's 14 nm)
    case, df, meta = two_basins
    floor = achievable_floor(df, meta)
    base = fit_from_starts(list(case.baseline), {"priors": {"start": case.known}}, df, meta)
    assert set(floor["calibration_rms_nm"]) == {"library's starting values"}
    kept = floor["calibration_rms_nm"][floor["start"]]
    assert kept <= base.start_costs_["priors"] * 1.001, (floor["calibration_rms_nm"],
                                                          base.start_costs_)
    assert floor["achievable_floor_nm"]["all"] <= 1.1 * base.val_["all"]["err_p90"]


@pytest.mark.xfail(strict=True, reason=(
    "with directions counted beyond the thermometers' own information, the priors' start no "
    "longer stops in the shallower basin: both starts reach 16.18 nm, the case shows no second "
    "basin"))
def test_the_ladder_keeps_the_deeper_basin_of_two_starts(tmp_path):
    # a generated loop-drift case: from the library's starting values the complete model stops,
    # converged, in a second basin (sensor_contact's leak negative, 12.2 nm calibration rms);
    # from the baseline's fitted values it reaches 8.5 nm (the twin's true model: 8.4 nm)
    case = generate_cases(np.random.default_rng(2611), 5)[4]
    assert case.hidden_effects == ["loop_drift"]
    path = tmp_path / "case.toml"
    path.write_text(case.toml())
    df, meta = Scenario.load(path).simulate(0.02)
    base = PhysicsFit(list(case.baseline), start=case.known).fit(df, meta)
    starts = {"priors": {"start": case.known},
              "previous fit": {"start": {**base.model_.values(), **case.known}}}
    fit = fit_from_starts(list(case.baseline) + ["loop_drift"], starts, df, meta)
    costs = fit.start_costs_
    assert fit.start_label_ == "previous fit" and costs["previous fit"] < 0.8 * costs["priors"]
    leak = fit.model_.values()["sensor_contact"]["leak_W_per_K"]
    assert leak > 0, leak


def test_known_constants_replace_only_their_own_parameters_of_a_previous_fit():
    # the ladder's "previous fit" start: a known frame arm must not reset the loop drift's
    # fitted expansion coefficients beside it (a whole-effect merge did)
    values = {"loop_drift": {"table_cte_per_K": 4.1e-6, "frame_arm_m": [0.0, 0.0]},
              "sensor_contact": {"leak_W_per_K": 0.0021}}
    start = merged(values, {"loop_drift": {"frame_arm_m": [-0.6, 0.0]},
                            "gravity_sag": {"load_factor": 1.0}})
    assert start == {"loop_drift": {"table_cte_per_K": 4.1e-6, "frame_arm_m": [-0.6, 0.0]},
                     "sensor_contact": {"leak_W_per_K": 0.0021},
                     "gravity_sag": {"load_factor": 1.0}}
    assert merged(values, None) == values


@pytest.mark.xfail(strict=True, reason=(
    "with directions counted beyond the thermometers' own information the smaller models' start "
    "gains 4 % (14.48 against 15.11 nm), not the 10 % the case showed"))
def test_the_baseline_is_also_fitted_from_its_own_smaller_models(tmp_path):
    # a generated null thermal case (seed 5077, case 7): the baseline is the twin's model, yet
    # from the priors alone its fit stopped, converged, in the basin of a negative
    # sensor_contact leak (-0.0075 W/K, 10.2 nm calibration rms, validation 15.5 nm against an
    # achievable floor of 13.2: 1.17x); fitted also from the baseline without each of its later
    # effects it leaves that basin
    case = generate_cases(np.random.default_rng(5077), 8)[7]
    assert not case.hidden and case.kind == "thermal"
    path = tmp_path / "case.toml"
    path.write_text(case.toml())
    df, meta = Scenario.load(path).simulate(0.02)
    floor = achievable_floor(df, meta)
    meta["truth"]["achievable_floor_nm"] = floor["achievable_floor_nm"]
    ladder, _, fits = diagnosis.effect_ladder(df, meta, list(case.baseline), max_added=0,
                                              known=case.known)
    base = fits[0]
    assert set(base.start_costs_) == {"priors"} | {f"without {e}" for e in case.baseline[1:]}
    assert base.start_label_ != "priors"
    assert base.start_costs_[base.start_label_] < 0.9 * base.start_costs_["priors"]
    assert base.model_.values()["sensor_contact"]["leak_W_per_K"] > 0
    assert ladder[0]["val_err90_nm"] <= 1.1 * floor["achievable_floor_nm"]["all"]


def test_a_later_start_is_kept_only_when_it_lowers_the_cost_beyond_chance():
    sc = Scenario.load("hidden/gravity-sag")
    df, meta = sc.simulate(sc.reduced_scale)
    effects = ["geometric_errors", "gravity_sag"]
    starts = {"priors": {}, "near": {"start": {"gravity_sag": {"load_factor": 0.9}}}}
    plain = fit_from_starts(effects, starts, df, meta)
    costs = plain.start_costs_
    # both starts end in the same minimum: their costs differ by round-off only (which one is
    # lower is chance)
    assert abs(costs["near"] - costs["priors"]) < 1e-6 * costs["priors"]
    chosen = fit_from_starts(effects, starts, df, meta, chance_alpha=1e-3)
    assert chosen.start_label_ == "priors"
    # a first start stopped far from the minimum is replaced by one that reaches it
    far = {"gravity_sag": {"load_factor": 5.0}}
    better = fit_from_starts(effects, {"stopped": {"start": far, "max_evaluations": 1},
                                       "priors": {}}, df, meta, chance_alpha=1e-3)
    assert better.start_label_ == "priors"
    assert better.start_costs_["priors"] < 0.5 * better.start_costs_["stopped"]
    with pytest.raises(FitError, match="chance_alpha = 0"):
        fit_from_starts(effects, starts, df, meta, chance_alpha=0)


def _validation_rows(n: int) -> SimpleNamespace:
    """The measurements' layout of n validation rows read on x, y and z in one session (a
    group per axis, rows in time order)."""
    return SimpleNamespace(val=np.ones(n, bool), group=np.tile(np.arange(3), (n, 1)),
                           df=pd.DataFrame({"t_s": np.arange(n, dtype=float),
                                            "session": np.zeros(n, int)}))


def test_a_candidate_the_calibration_rows_barely_see_is_claimed_when_validation_confirms_it():
    """Calibration F test p = 0.0025 and the BIC rising (2 directions): not enough alone. When
    the change closes the gap to the floor on the validation rows and leaves noise there, the
    two tests combined claim it; with the model already at the floor (no gap), or a change
    that leaves the residual as it was, nothing is claimed."""
    rng = np.random.default_rng(17)
    t = np.linspace(0, 1, 300)
    change = np.column_stack([t ** 2, 0.3 * t, np.sin(2 * t)]) * 1e-7
    noise = rng.standard_normal((300, 3)) * 1e-8
    val = np.ones(300, bool)
    meas = _validation_rows(300)
    floor_nm = diagnosis.figures_nm(noise, val)["all"]["err_p90"]
    args = (3002.0, 2990.0, 2, 3000, 2990)
    v = diagnosis._verdict(meas, *args, change + noise, noise, floor_nm, RULE)
    assert 1e-3 < v["p_value"] < 1e-2 and v["delta_bic"] > 0
    assert v["gap_closed"] > 0.9 and v["p_combined"] < 1e-3 and v["significant"]
    assert not diagnosis._verdict(meas, *args, change + noise, noise, None, RULE)["significant"]
    at_floor = diagnosis._verdict(meas, *args, noise, noise - 0.1 * change, floor_nm, RULE)
    assert at_floor["gap_closed"] == 0 and not at_floor["significant"]
    useless = diagnosis._verdict(meas, *args, change + noise, change + noise, floor_nm, RULE)
    assert not useless["significant"]


def test_nothing_is_claimed_from_a_model_at_the_achievable_floor():
    """A change that explains over 10 % of the validation residual, calibration p far below
    ALPHA, is claimed without a floor; with the model within 1.1x the achievable floor it is
    the floor's own error and is not."""
    rng = np.random.default_rng(23)
    t = np.linspace(0, 1, 300)
    shape = np.column_stack([t ** 2, 0.3 * t, np.sin(2 * t)])
    change = shape / np.sqrt(np.mean(shape ** 2)) * 0.4e-8
    noise = rng.standard_normal((300, 3)) * 1e-8
    val = np.ones(300, bool)
    meas = _validation_rows(300)
    floor_nm = diagnosis.figures_nm(noise, val)["all"]["err_p90"]
    args = (3100.0, 2990.0, 1, 3000, 2990)
    free = diagnosis._verdict(meas, *args, change + noise, noise, None, RULE)
    assert free["explained_fraction"] > 0.1 and free["p_value"] < 1e-6 and free["significant"]
    assert diagnosis.figures_nm(change + noise, val)["all"]["err_p90"] <= 1.1 * floor_nm
    assert not diagnosis._verdict(meas, *args, change + noise, noise, floor_nm, RULE)["significant"]


def test_a_candidate_held_at_the_librarys_start_does_not_make_the_calibration_worse(tmp_path):
    """Loop drift hidden at a third of the library's CTEs: its combination the data do not
    determine one typical size at a time, held at the library's start, made the calibration
    residual worse than the model without it (p = 1, BIC +356 on a generated case); held off
    where the calibration rows prefer it, the candidate's row is a test of what the data
    determine."""
    case = Case(name="loop-third", kind="thermal", seed=808, hidden=(("loop_drift", 1 / 3),),
                baseline=tuple(e for e in MODEL["thermal"] if e != "loop_drift"), known=KNOWN)
    path = tmp_path / "case.toml"
    path.write_text(case.toml())
    df, meta = Scenario.load(path).simulate(0.02)
    fit = PhysicsFit(list(case.baseline), start=KNOWN).fit(df, meta)
    row = next(c for c in diagnosis.diagnose(fit)["ranking"] if c["effect"] == "loop_drift")
    assert row["new_directions"] >= 1 and row["held_at"] == "off"
    assert row["p_value"] < 1.0 and row["delta_bic"] < 0, row


class _Fit:
    """What effect_ladder reads of a fit, with a given validation error (nm)."""
    def __init__(self, effects, val_nm):
        self.effects = list(effects)
        self.model_ = type("M", (), {"n_free": 1, "values": lambda self: {}})()
        self.identifiability_ = {"n_identified_directions": 1}
        self.val_ = {"all": {"err_p90": val_nm}}
        self.start_label_ = "priors"
        # unconverged: fitted_again_where_it_ended returns it as it is
        self.status_, self.converged_, self.fitted_again_ = "not converged", False, False


def test_the_ladder_keeps_an_effect_only_if_its_refit_predicts_validation_better(monkeypatch):
    errors = iter([45.0, 69.0])
    monkeypatch.setattr(diagnosis, "fit_from_starts",
                        lambda effects, *a, **k: _Fit(effects, next(errors)))
    monkeypatch.setattr(diagnosis, "diagnose", lambda fit, data, **kw: {
        "missing_effect": "loop_drift", "ranking": [], "extrapolation": {
            "variables": [{"variable": "T_table_C"}]}})
    ladder, diagnoses, fits = diagnosis.effect_ladder(pd.DataFrame(), None, ["geometric_errors"])
    assert [r["val_err90_nm"] for r in ladder] == [45.0] and len(fits) == len(diagnoses) == 1
    rejected = diagnoses[-1]["refit_rejected"]
    assert rejected["effect"] == "loop_drift" and rejected["val_err90_nm"] == 69.0
    assert "not kept" in rejected["message"] and "T_table_C" in rejected["message"]
    errors = iter([45.0, 30.0])
    ladder, _, _ = diagnosis.effect_ladder(pd.DataFrame(), None, ["geometric_errors"],
                                           max_added=1)
    assert [r["val_err90_nm"] for r in ladder] == [45.0, 30.0]


def test_the_ladder_fits_again_where_they_ended_only_the_rungs_that_added_an_effect(
        monkeypatch):
    """The baseline's fit is diagnosed where it ended (its candidates linearised there); a
    rung that added an effect is fitted again from where it ended (fitted_again_where_it_ended),
    the fit it returns the rung's, said in its ladder row."""
    named = iter(["magnetic_force", "loop_drift", None])
    monkeypatch.setattr(diagnosis, "diagnose", lambda fit, data, **kw: {
        "missing_effect": next(named), "ranking": [], "extrapolation": {}})
    errors = iter([297.0, 120.0, 100.0, 80.0, 70.0])
    monkeypatch.setattr(diagnosis, "fit_from_starts",
                        lambda effects, *a, **k: _Fit(effects, next(errors)))
    again = []

    def fitted_again(fit):
        again.append(list(fit.effects))
        out = _Fit(fit.effects, next(errors))
        out.fitted_again_ = True
        return out
    monkeypatch.setattr(diagnosis, "fitted_again_where_it_ended", fitted_again)
    ladder, _, fits = diagnosis.effect_ladder(pd.DataFrame(), None, ["geometric_errors"])
    assert again == [["geometric_errors", "magnetic_force"],
                     ["geometric_errors", "magnetic_force", "loop_drift"]]
    assert [r["val_err90_nm"] for r in ladder] == [297.0, 100.0, 70.0]
    assert [r["fitted_again"] for r in ladder] == [False, True, True]
    assert all(f.fitted_again_ for f in fits[1:])


def test_the_ladder_tries_the_next_significant_effect_when_a_refit_is_rejected(monkeypatch):
    """Two effects significant, the first named: its refit predicts validation worse and is not
    kept; the second is refitted in its place and kept when it predicts better (each try
    recorded). A not-significant candidate is never tried, and when every significant one is
    rejected the ladder ends at the previous model."""
    ranking = [{"effect": "magnetic_force", "significant": True},
               {"effect": "air_refraction", "significant": False},
               {"effect": "loop_drift", "significant": True}]
    named = iter(["magnetic_force", None])
    monkeypatch.setattr(diagnosis, "diagnose", lambda fit, data, **kw: {
        "missing_effect": next(named), "ranking": ranking, "extrapolation": {}})
    errors = iter([297.0, 299.0, 240.0])
    fitted = []

    def fake_fit(effects, *a, **k):
        fitted.append(list(effects))
        return _Fit(effects, next(errors))
    monkeypatch.setattr(diagnosis, "fit_from_starts", fake_fit)
    ladder, diagnoses, fits = diagnosis.effect_ladder(pd.DataFrame(), None, ["geometric_errors"])
    assert fitted == [["geometric_errors"], ["geometric_errors", "magnetic_force"],
                      ["geometric_errors", "loop_drift"]]
    assert [r["added"] for r in ladder] == [None, "loop_drift"] and len(diagnoses) == 2
    assert diagnoses[0]["refit_rejected"]["effect"] == "magnetic_force"
    assert diagnoses[0]["tried_instead"] == [{"effect": "loop_drift", "kept": True,
                                              "val_err90_nm": 240.0}]
    named, errors, fitted[:] = iter(["magnetic_force"]), iter([297.0, 299.0, 301.0]), []
    ladder, diagnoses, _ = diagnosis.effect_ladder(pd.DataFrame(), None, ["geometric_errors"])
    assert len(fitted) == 3 and [r["added"] for r in ladder] == [None]
    assert diagnoses[0]["tried_instead"] == [{"effect": "loop_drift", "kept": False,
                                              "val_err90_nm": 301.0}]


@pytest.mark.parametrize("held_at", ["off", "start"])
def test_a_rejected_effect_significant_held_off_is_refitted_held_off(monkeypatch, held_at):
    """Loop drift named, significant held off (its start's undetermined rest switched off):
    its refit at the library's start predicts validation worse, so it is refitted once more
    held off (free parameters started and held at zero) before the next significant effect,
    and kept when that predicts better. A rejected effect significant at its start is not."""
    ranking = [{"effect": "loop_drift", "significant": True, "held_at": held_at},
               {"effect": "magnetic_force", "significant": True, "held_at": None}]
    named = iter(["loop_drift", None])
    monkeypatch.setattr(diagnosis, "diagnose", lambda fit, data, **kw: {
        "missing_effect": next(named), "ranking": ranking, "extrapolation": {}})
    errors = iter([45.0, 69.0, 40.0])
    fitted = []

    def fake_fit(effects, starts, *a, **k):
        fitted.append((list(effects), starts))
        return _Fit(effects, next(errors))
    monkeypatch.setattr(diagnosis, "fit_from_starts", fake_fit)
    monkeypatch.setattr(diagnosis, "_switches_off", lambda fit, effect: True)
    ladder, diagnoses, _ = diagnosis.effect_ladder(pd.DataFrame(), None, ["geometric_errors"],
                                                   known=KNOWN)
    assert diagnoses[0]["refit_rejected"]["effect"] == "loop_drift"
    if held_at == "start":
        assert [e for e, _ in fitted][-1] == ["geometric_errors", "magnetic_force"]
        assert diagnoses[0]["tried_instead"] == [{"effect": "magnetic_force", "kept": True,
                                                  "val_err90_nm": 40.0}]
    else:
        effects, starts = fitted[-1]
        assert effects == ["geometric_errors", "loop_drift"] and len(starts) == 1
        (start,) = starts.values()
        off = {"table_cte_per_K": 0.0, "frame_cte_per_K": 0.0, "support_cte_per_K": 0.0}
        assert start["prior"] == {"loop_drift": off}
        assert start["start"]["loop_drift"] == {**off, **KNOWN["loop_drift"]}
        assert [r["added"] for r in ladder] == [None, "loop_drift"]
        assert diagnoses[0]["tried_instead"] == [{"effect": "loop_drift", "kept": True,
                                                  "val_err90_nm": 40.0, "held": "off"}]


def test_an_effect_held_off_changes_no_prediction(baseline_fit):
    """``_held_off``'s values switch loop drift, gravity sag and a coil without current off:
    the model with the effect added there predicts what the model without it does; air
    refraction at zero room fraction and offset still changes them (its beam and sensor air
    differ), so it is not refitted held off."""
    meas, values = baseline_fit.measurements_, baseline_fit.model_.values()
    without = PhysicsModel(BASELINE, baseline_fit.params, values).predict_path(meas)
    for effect in ("loop_drift", "gravity_sag", "magnetic_force", "air_refraction"):
        held = diagnosis._held_off(values, effect, KNOWN)
        assert held["prior"] == {effect: diagnosis._off(effect)}
        # a fit keeps the start of its own effects (the rest are the laboratory's constants)
        added = PhysicsModel(BASELINE + [effect], baseline_fit.params,
                             {e: v for e, v in held["start"].items()
                              if e in BASELINE + [effect]}).predict_path(meas)
        off = effect != "air_refraction"
        assert (np.nanmax(np.abs(added - without)) < 1e-15) == off, effect
        assert diagnosis._switches_off(baseline_fit, effect) == off, effect
    # at the library's start loop drift does change them (the comparison can fail)
    start = PhysicsModel(BASELINE + ["loop_drift"], baseline_fit.params,
                         {**values, "loop_drift": KNOWN["loop_drift"]}).predict_path(meas)
    assert np.nanmax(np.abs(start - without)) > 1e-9


def test_a_candidate_is_compared_with_what_generic_terms_explain_above_the_floor():
    """Generic functions of the laboratory variables also fit the floor's own error: a
    candidate adding nothing beyond them, explaining 18 % where they explain 41 %, is a
    correlate without a floor, but not when only 32 % of the validation power lies above the
    achievable floor (13.1 nm against 10.84)."""
    rng = np.random.default_rng(5)
    G = rng.standard_normal((400, 3))
    r = G @ np.array([1.0, -0.5, 0.2]) + 0.1 * rng.standard_normal(400)
    Xc, Jm = G[:, :1], np.zeros((400, 0))
    above = diagnosis._above_floor_share(13.1, 10.84)
    assert above == pytest.approx(1 - (10.84 / 13.1) ** 2) and 0.3 < above < 0.33
    assert diagnosis._above_floor_share(10.0, 10.84) == diagnosis._above_floor_share(10, None) == 1
    meas = _one_group(400)
    without = diagnosis._beyond_generic(meas, r, Xc, Jm, diagnosis._generic(Jm, G, 0.41, r, 1.0),
                                        1, 400, 0.18, RULE)
    assert without["p_beyond_generic"] >= ALPHA and without["matched_by_generic"]
    with_floor = diagnosis._beyond_generic(meas, r, Xc, Jm,
                                           diagnosis._generic(Jm, G, 0.41, r, above), 1, 400,
                                           0.18, RULE)
    assert not with_floor["matched_by_generic"]


def _ladder_on(tmp_path, case, scale: float, hidden: bool = True, **ladder_options):
    """(metadata with the achievable floor, ladder, diagnoses, fits) of ``effect_ladder`` on
    generated ``case`` simulated at ``scale``, or on the same case with nothing hidden."""
    if not hidden:
        case = Case(name="null", kind=case.kind, seed=case.seed, hidden=(),
                    baseline=case.baseline, known=case.known)
    path = tmp_path / "case.toml"
    path.write_text(case.toml())
    df, meta = Scenario.load(path).simulate(scale)
    meta["truth"]["achievable_floor_nm"] = achievable_floor(df, meta)["achievable_floor_nm"]
    return meta, *diagnosis.effect_ladder(df, meta, list(case.baseline), known=case.known,
                                          **ladder_options)


def _loop_drift_x1(tmp_path, seed: int, index: int, kind: str, scale: float):
    """(metadata, the first diagnosis of the ladder, loop drift's row in it) of generated case
    ``index`` of ``seed``, a ``kind`` case hiding loop drift at the library's strength."""
    case = generate_cases(np.random.default_rng(seed), 12)[index]
    assert case.hidden == (("loop_drift", 1.0),) and case.kind == kind
    meta, _, diagnoses, _ = _ladder_on(tmp_path, case, scale, max_added=0)
    return meta, diagnoses, next(c for c in diagnoses[0]["ranking"]
                                 if c["effect"] == "loop_drift")


@pytest.mark.xfail(strict=True, reason=(
    "the candidate is no longer refitted on this case (no refit_explained_fraction): the "
    "diagnosis' special rules are to be rebuilt on the one rule"))
def test_a_candidate_matched_by_generic_terms_is_judged_again_refitted(tmp_path):
    """A generated thermal case hiding loop drift at the library's strength (seed 6502, its
    fifth case): the baseline's thermal parameters took part of the drift's place, and loop
    drift linearised at the baseline's fit explains 13 % of the validation residual, less than
    half of what generic functions of the laboratory variables explain above the floor: a
    correlate, by the linear test. Refitted with the model it explains more than that share,
    and it is named."""
    meta, diagnoses, row = _loop_drift_x1(tmp_path, 6502, 4, "thermal", 0.02)
    above = diagnosis._above_floor_share(diagnoses[0]["val_err90_nm"],
                                         meta["truth"]["achievable_floor_nm"]["all"])
    needed = GENERIC_SHARE * min(row["generic_explained_fraction"], above)
    assert row["explained_fraction"] < needed <= row["refit_explained_fraction"], row
    assert row["significant"] and not row["matched_by_generic"]
    assert diagnoses[0]["missing_effect"] == "loop_drift" and "refitted" in row["verdict"]


@pytest.mark.slow
def test_a_refit_that_determines_nothing_new_is_not_named_on_the_validation_rows_alone(tmp_path):
    """A generated force case hiding loop drift at the library's strength (seed 2222, its
    second case): the calibration grid barely moves the temperatures and the linearised change
    closes a fifth of the gap to the floor. On the validation rows it is mostly an offset per
    (session, axis), which the offset-immune block test does not count (the per-reading test
    it replaced gave p = 2e-57), so nothing confirms it and it is not refitted. It is not
    named; its row says that most of its signature is absorbed by the model's geometry."""
    _, diagnoses, row = _loop_drift_x1(tmp_path, 2222, 1, "force", 0.3)
    assert row["p_validation_any"] >= ALPHA and row["gap_closed"] < GAP_CLOSED
    assert "refit_p_combined" not in row
    assert not row["significant"] and "absorbed by geometric_errors" in row["verdict"], row
    assert not any(c["significant"] for c in diagnoses[0]["ranking"])


def _one_group(n: int) -> SimpleNamespace:
    """The measurements' grouping of n calibration readings of one (session, axis) group, with
    the measurements' own degrees of freedom (``Measurements.residual_dof``)."""
    grouping = SimpleNamespace(group=np.column_stack([np.zeros(n, int), np.full((n, 2), -1)]),
                               groups=[(0, "x")], cal=np.ones(n, bool))
    grouping.residual_dof = functools.partial(Measurements.residual_dof, grouping)
    grouping.reading_counts = functools.partial(Measurements.reading_counts, grouping)
    return grouping


def test_the_test_beyond_generic_terms_holds_its_level_on_correlated_rows():
    """Under the null (a slow candidate column unrelated to a slow residual, AR(1) rho = 0.95,
    with generic columns fitted first that hold none of either) the F test of what the
    candidate adds beyond the generic terms is below ALPHA far more often than ALPHA on
    independent rows' terms; with the rows' serial-correlation factor (as the calibration
    test's) it comes near its level. A candidate that is the residual's slow structure still
    adds beyond the generic terms at any level."""
    rng = np.random.default_rng(41)
    n = 400
    meas, Jm = _one_group(n), np.zeros((n, 0))
    p = []
    for _ in range(200):
        e, x = ar1(rng, n, 0.95), ar1(rng, n, 0.95)
        G = rng.standard_normal((n, 2))
        generic = diagnosis._generic(Jm, G, 0.5, e - e.mean(), 1.0)
        p.append(diagnosis._beyond_generic(meas, e - e.mean(), (x - x.mean())[:, None], Jm,
                                           generic, 1, n, 0.0, RULE)["p_beyond_generic"])
    p = np.array(p)
    assert np.mean(p < 0.01) <= 0.07 and np.mean(p < ALPHA) <= 0.03
    # the naive F test on these draws: below 0.01 in a third or more (the test above)
    x = ar1(rng, n, 0.95)
    r = x + 0.2 * rng.standard_normal(n)
    found = diagnosis._beyond_generic(meas, r - r.mean(), (x - x.mean())[:, None], Jm,
                                      diagnosis._generic(Jm, rng.standard_normal((n, 2)), 0.5,
                                                        r - r.mean(), 1.0),
                                      1, n, 0.0, RULE)
    assert found["p_beyond_generic"] < 1e-6


def test_the_benchmark_refuses_an_only_prefix_that_selects_no_case():
    """benchmarks/discovery.py --only: a prefix no generated case of the seed has is named (exit 2,
    the seed's cases listed), not silently a run of nothing."""
    import subprocess
    import sys
    from pathlib import Path

    script = Path(__file__).resolve().parents[2] / "benchmarks" / "discovery.py"
    run = subprocess.run([sys.executable, str(script), "--cases", "3", "--seed", "1234",
                          "--skip-full", "--only", "case001,case077"], capture_output=True,
                         text=True, timeout=120)
    assert run.returncode == 2, run.stderr
    assert "--only case077: no case of seed 1234" in run.stderr and "case001-" in run.stderr
    assert "Traceback" not in run.stderr


def test_the_benchmark_pools_several_seeds_and_refuses_a_bad_range(tmp_path):
    """benchmarks/discovery.py --seeds: the cases of every seed, run in worker processes
    (--jobs), each case's row naming its seed, a line per seed and the pooled scores with
    their 95 % intervals; a range given backwards, a seed that is no integer >= 0 or no worker
    is named (exit 2) before any case runs, no traceback; an --only that one seed lacks writes
    no dump folder for any."""
    import subprocess
    import sys
    from pathlib import Path

    script = Path(__file__).resolve().parents[2] / "benchmarks" / "discovery.py"
    for args, said in ((["--seeds", "9-7"], "'9-7': give seeds"),
                       (["--seeds", "x"], "'x': give seeds"),
                       (["--seeds", "-3"], "'-3': give seeds"),
                       (["--jobs", "0"], "--jobs 0: need at least 1")):
        bad = subprocess.run([sys.executable, str(script), *args, "--skip-full"],
                             capture_output=True, text=True, timeout=120)
        assert bad.returncode == 2 and said in bad.stderr, (args, bad.stderr)
        assert "Traceback" not in bad.stderr and not bad.stdout, args
    # seed 2's first case is a force campaign, seed 1's a thermal one: refused at seed 1,
    # with no dump folder written for seed 2 either
    refused = subprocess.run([sys.executable, str(script), "--cases", "1", "--seeds", "2,1",
                              "--only", "case000-force", "--dump", str(tmp_path / "refused"),
                              "--skip-full"], capture_output=True, text=True, timeout=120)
    assert refused.returncode == 2 and "no case of seed 1 starts so" in refused.stderr
    assert not (tmp_path / "refused").exists()
    run = subprocess.run([sys.executable, str(script), "--cases", "1", "--seeds", "3,4",
                          "--jobs", "2", "--skip-full", "--dump", str(tmp_path)],
                         capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr
    lines = run.stdout.splitlines()
    for seed in (3, 4):
        case = generate_cases(np.random.default_rng(seed), 1)[0]
        assert any(f"seed {seed}, case {case.name.split('-')[0]}" in s for s in lines)
        assert any(s.startswith(f"  {seed}: named ") for s in lines)
        assert (tmp_path / str(seed) / f"{case.name}.pkl").is_file()
    assert "2 cases (seed(s) 3,4" in run.stdout and "(2 job(s))" in run.stdout
    assert "final error within 1.1x the achievable floor: " in run.stdout
    assert "95 % interval" in run.stdout


def test_a_direction_counts_at_its_estimated_size_only_where_the_data_know_it():
    """``_determined``: the fit's rule (a change above noise / identifiable_ratio per typical
    size), or, for a candidate with no direction determined so, a change of at least the
    noise per typical size whose estimate (the residual's component along it) exceeds that
    threshold; never a direction the data know worse than its typical size, whatever the
    residual holds along it."""
    fit = SimpleNamespace(noise_nm=5.0, identifiable_ratio=0.3)
    threshold = 5e-9 / 0.3
    U = np.eye(4)
    s = threshold * np.array([2.0, 0.5, 0.5, 0.1])      # the last: below the noise (0.3)
    r = threshold * np.array([0.0, 3.0, 0.5, 30.0])
    determined, sized = diagnosis._determined(fit, U, s, r)
    assert determined.tolist() == [True, False, False, False]
    # a candidate with a determined direction is held along the rest (``_held_at``)
    assert not sized.any()
    determined, sized = diagnosis._determined(fit, U[:, 1:], s[1:], r)
    assert not determined.any() and sized.tolist() == [True, False, False]


@pytest.mark.parametrize("hidden", [True, False])
def test_an_absorbed_effect_far_beyond_its_typical_size_is_named_and_refitted(tmp_path, hidden):
    """A generated thermal case hiding beam misalignment at ten times the library's angles and
    offsets (seed 3737, its eleventh case): at one typical size 99.9 % of its signature lies
    in geometric_errors' span and no direction beyond it is determined by the fit's rule, but
    the calibration rows put 5-10 typical sizes on its directions beyond the span. Determined
    at that size, it is named; the ladder refits it from the calibration rows' estimate and
    the validation error falls to the floor (held at the library's start, zero, the refit
    stopped at 17.2 nm against 16.5). The same case with nothing hidden names nothing."""
    case = generate_cases(np.random.default_rng(3737), 12)[10]
    assert case.hidden == (("beam_misalignment", 10.0),) and case.kind == "thermal"
    meta, ladder, diagnoses, _ = _ladder_on(tmp_path, case, 0.02, hidden, max_added=1)
    floor = meta["truth"]["achievable_floor_nm"]
    if not hidden:
        assert all(d["missing_effect"] is None for d in diagnoses), diagnoses[0]["ranking"]
        return
    row = next(c for c in diagnoses[0]["ranking"] if c["effect"] == "beam_misalignment")
    assert row["new_directions"] == 0 and row["absorbed_fraction"] >= ABSORBED
    assert row["sized_directions"] >= 1 and row["significant"], row
    assert diagnoses[0]["missing_effect"] == "beam_misalignment" and "estimate" in row
    assert ladder[-1]["added"] == "beam_misalignment" and "estimate" in ladder[-1]["fit_start"]
    assert ladder[0]["val_err90_nm"] > 1.1 * floor["all"] >= ladder[-1]["val_err90_nm"], ladder


@pytest.mark.parametrize("hidden", [pytest.param(True, marks=pytest.mark.xfail(
    strict=True, reason="the pair rule is not reached on this case any more (no 'pair'): the "
    "diagnosis' special rules are to be rebuilt on the one rule")), False])
def test_two_effects_too_small_alone_are_added_together_and_reach_the_floor(tmp_path, hidden):
    """A generated thermal case hiding beam misalignment x3 with loop drift and air refraction
    at a third of the library's strength (seed 6363, its fourth case): the baseline is 1.3x
    the achievable floor and its diagnosis names no effect (loop drift refitted closes a
    tenth of the gap, air refraction alone makes the calibration worse). The ladder refits
    loop drift with each other candidate (``_pair``); loop drift with air refraction is
    significant against the baseline (``_joint_verdict``) and the two, one rung, reach the
    floor; the pairs that are not (loop drift with gravity sag: calibration p tiny, but 8 % of
    the validation residual and no gap closed) are recorded, not added. The same case with
    nothing hidden names nothing."""
    case = generate_cases(np.random.default_rng(6363), 12)[3]
    assert case.kind == "thermal" and [e for e, _ in case.hidden] == [
        "beam_misalignment", "loop_drift", "air_refraction"]
    meta, ladder, diagnoses, fits = _ladder_on(tmp_path, case, 0.02, hidden)
    floor = meta["truth"]["achievable_floor_nm"]
    if not hidden:
        assert all(d["missing_effect"] is None and "pair" not in d for d in diagnoses)
        return
    first = diagnoses[0]
    assert not any(c["significant"] for c in first["ranking"]), first["ranking"]
    assert first["pair"]["effects"] == ["loop_drift", "air_refraction"], first["pairs_tried"]
    assert first["pair"]["significant"] and first["missing_effect"] == "loop_drift"
    assert any(not p["significant"] for p in first["pairs_tried"])
    assert ladder[1]["added"] == "loop_drift + air_refraction"
    assert "loop_drift,air_refraction" in first["next_command"]
    assert fits[1].effects[-2:] == ["loop_drift", "air_refraction"]
    assert ladder[0]["val_err90_nm"] > 1.2 * floor["all"], ladder
    assert ladder[-1]["val_err90_nm"] <= 1.1 * floor["all"], ladder


@pytest.mark.xfail(strict=True, reason="the validation rows' evidence for loop drift here was "
                   "its drift offset, which the offset-immune block test does not count (p = "
                   "0.08): in the papers' order only an interleaved plan shows it")
def test_a_candidate_closing_half_the_gap_but_not_confirmed_linearised_is_judged_refitted(
        tmp_path):
    """A generated force campaign in the papers' order hiding loop drift x3 beside beam
    misalignment x10 and air refraction at a third (seed 9292, its sixth case): loop drift's
    change linearised at the baseline's fit closes more than half the gap to the floor, but
    the calibration rows barely see it (p = 0.17) and the try with the lower BIC (held at the
    library's start) has validation p = 0.007: combined 0.009, not significant, though the
    other try (held off) has validation p = 2e-7. Such a candidate was not refitted (only
    those closing less than GAP_CLOSED were) and nothing was named, 1.38x the floor. Judged
    again refitted, it is named, the verdict gives the refit's figures, and the ladder's
    refit reaches 1.1x the floor."""
    case = generate_cases(np.random.default_rng(9292), 12)[5]
    assert case.kind == "force" and dict(case.hidden) == {
        "beam_misalignment": 10.0, "air_refraction": 1 / 3, "loop_drift": 3.0}
    meta, ladder, diagnoses, _ = _ladder_on(tmp_path, case, 0.3, max_added=1)
    floor = meta["truth"]["achievable_floor_nm"]
    row = next(c for c in diagnoses[0]["ranking"] if c["effect"] == "loop_drift")
    # linearised: half the gap closed, the combined test not below ALPHA
    assert row["gap_closed"] >= GAP_CLOSED and row["p_combined"] >= ALPHA
    assert row["p_validation_any"] < ALPHA and row["new_directions"] >= 1, row
    # refitted: confirmed
    assert row["refit_gap_closed"] >= GAP_CLOSED, row
    assert row["refit_p_combined"] < ALPHA and row["significant"], row
    assert diagnoses[0]["missing_effect"] == "loop_drift"
    assert "refitted with the model" in row["verdict"], row["verdict"]
    assert f"calibration p = {row['refit_p_value']:.2g}" in row["verdict"]
    assert ladder[-1]["added"] == "loop_drift"
    assert ladder[0]["val_err90_nm"] > 1.1 * floor["all"] >= ladder[-1]["val_err90_nm"], ladder


@pytest.mark.parametrize("seed, index, shown", [(4646, 0, True), (4646, 11, False)])
def test_the_benchmark_counts_the_rounds_whose_data_show_the_complete_model(tmp_path, seed,
                                                                             index, shown):
    """benchmarks/discovery.py's ``shown_by_data``: a thermal case hiding loop drift x1 (seed
    4646, its first case): the complete model fits the calibration rows far better than the
    baseline, shown. A force campaign in the papers' order hiding loop drift x1 and air
    refraction x3 (its twelfth case, the baseline 1.13x the floor): the complete model fitted
    on the same rows leaves the calibration residual *larger* than the baseline's and its
    change is not confirmed on the validation rows at ALPHA either: no rule on these rows could
    name it, not shown. A model against itself is never shown."""
    import importlib.util
    from pathlib import Path

    script = Path(__file__).resolve().parents[2] / "benchmarks" / "discovery.py"
    spec = importlib.util.spec_from_file_location("discovery_benchmark", script)
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    case = generate_cases(np.random.default_rng(seed), 12)[index]
    path = tmp_path / "case.toml"
    path.write_text(case.toml())
    df, meta = Scenario.load(path).simulate(bench.SCALE[case.kind])
    complete = true_fit(df, meta)
    _, _, fits = diagnosis.effect_ladder(df, meta, list(case.baseline), max_added=0,
                                         known=case.known)
    data = bench.shown_by_data(fits[0], complete)
    assert data["shown"] is shown, data
    if not shown:
        assert data["p_calibration"] == 1.0 and data["p_validation"] >= ALPHA, data
    assert not bench.shown_by_data(complete, complete)["shown"]
