"""The honest floor: what the complete, true model reaches when refitted on the same data.

The **noise floor** (``truth.noise_floor_nm``) is the readings' own noise: the twin's readings
against what a perfect instrument would have read on the same timeline, the interferometers'
noise and the servos' settling (most of it: a servo settles within microradians, which the
lever of a Delta robot turns into tens of nm). A model reads its conditions through
instruments too: thermometers (mK noise and resolution, smoothed causally) through long levers
(the frame's lift on Z, a frame arm on X), barometric pressure and humidity when the lab
records them (else the air index wanders unrecorded). No effect added to a model removes those
errors, so a model is *at the floor* when it reaches what the twin's own effects reach when
fitted to the same data, the **achievable floor**. ``achievable_floor`` fits that true model
(the data's model effects, their free parameters fitted from the library's starting values as
any model's are, and from the baseline's fit where the data declare one: what a researcher
could reach, never the twin's values) and gives its
validation error and a budget: the noise floor and what the other instruments add above it
(the quadrature difference).

``measured_floor_budget`` splits the floor per source, in nm per axis, for twin data: each
source alone is switched on in the twin with every other made perfect (same seed: the same
timeline and draws), the true model refitted, and the source's share is what its run adds in
quadrature to the run where every instrument is perfect. That last run's floor is itself a
line of the budget: what perfect instruments leave, the parts' temperatures the sensors do not
see (parts without a sensor, gradients, the model's smoothing of the readings). Each source
alone is measured rather than each switched off from the full set, because the latter's share
is a difference of two near-equal figures, each with its refit's scatter. The thermometers'
share is split per sensor to first order: the change of the model's prediction when that
sensor reads its true temperature, with the true model's refit (its identified directions and
each session's zero) taken out, 90 % over the validation rows.

``predicted_floor_budget`` gives the same lines for laboratory data from the instruments'
specifications and a fitted model's sensitivities (calibration/design/budget.py: the model's
derivative with respect to each measured input, GUM-style).
"""
from __future__ import annotations

import numpy as np

from deltatwin.calibration.physics.fit import PhysicsFit, fit_from_starts
from deltatwin.calibration.physics.measurements import measurements
from deltatwin.calibration.physics.model import model_effects, projected
from deltatwin.twin.effects import EffectError, effect_class
from deltatwin.twin.instruments.optics import AXES
from deltatwin.twin.lab_setup import baseline_of, known_constants, merged
from deltatwin.twin.noise import quantised_u
from deltatwin.twin.scenario import ERROR_SOURCES

# the floor's sources in the twin (twin/scenario.py ERROR_SOURCES), by their budget line's name
SOURCE_LINE = {"interferometers": "interferometer_noise_nm", "thermometers": "thermometers_nm",
               "air": "air_nm", "servo_settling": "servo_settling_nm"}
SOURCES = {SOURCE_LINE[k]: v for k, v in ERROR_SOURCES.items()}
REMAINDER = "thermal_state_nm"   # what perfect instruments leave
# the sum of the sources in quadrature is within this fraction of the achievable floor on the
# shipped papers' scenarios and the hidden ones (tests/calibration/test_floor_budget.py)
BUDGET_TOLERANCE = 0.25

# the ladder's fits may evaluate this many points (PhysicsFit's default: 20): a model lacking an
# effect is misspecified and slow to converge, and where a fit stops short its result depends
# on its start's path (a force case's refit with magnetic force stopped at the limit at 126.7
# or 58.8 nm validation error from the previous fit with and without loop drift's fitted
# expansion coefficients; with 40 evaluations the former converges, at 74.6 nm; 39 of 94
# ladder fits on six seeds stopped at 20, 9 of 93 at 40; a refit adding magnetic force at 10x
# stopped at 40 at 56.5 nm calibration rms, 478 nm validation, and converged at 80: 20.4 nm,
# 75.1 nm)
# The achievable floor's own fit has the same budget: the floor is what the complete model
# reaches with the search the loop's models get, not a shorter one.
LADDER_EVALUATIONS = 80


def _has_model_form(name: str) -> bool:
    """Whether the effect called ``name`` (a library effect, or a user effect this process has
    loaded: the twin that made the data ran it) has a model form; no code is run to tell."""
    try:
        return bool(effect_class(name, trust=False).model_stages())
    except EffectError:
        return False


def true_model(meta: dict) -> tuple[list[str], dict]:
    """The data's model effects (those of the twin's truth with a model form, a researcher's
    own included where this process has loaded it: the floor of data made by a twin with an
    effect outside the library is what the model with that effect reaches) and the twin's
    values of all their parameters: ({effect: {parameter: value}})."""
    truth = (meta or {}).get("truth") or {}
    forms = set(model_effects())
    effects = [e for e in truth.get("effects", [])
               if e["name"] in forms or _has_model_form(e["name"])]
    return ([e["name"] for e in effects],
            {e["name"]: {p: v["value"] for p, v in e["parameters"].items()} for e in effects})


def true_fit(df, meta: dict, noise_nm: float = 5.0) -> PhysicsFit:
    """The true model (``true_model``: the data's model effects) fitted to the data's
    calibration rows as a researcher would fit it: from the library's starting values, with
    the twin's fixed constants (those the fit does not estimate, e.g. a frame arm: the
    laboratory's known setup), never from the twin's values of the fitted parameters; and,
    where the data declare a baseline the model extends, also from the baseline's own fit
    (the start a researcher has who fitted it first): the lower calibration cost of the two
    (``fit_from_starts``). A force campaign's coil moment started at zero can stop in a
    shallow basin the baseline's values avoid."""
    effects, values = true_model(meta)
    # the twin's constants where the data's setup states none (where it does, the setup's: the
    # room's estimate from the beams' air is the laboratory's, not a twin's parameter)
    setup = known_constants(meta)
    fixed = {e: {p: v for p, v in vals.items()
                 if p not in {q.name for q in effect_class(e).free_parameters()}
                 and p not in setup.get(e, {})}
             for e, vals in values.items()}
    starts = {"library's starting values": {"start": fixed}}
    baseline = [e for e in baseline_of(meta) or [] if e in effects]
    if baseline and len(baseline) < len(effects):
        first = fit_from_starts(baseline, {"baseline": {"start": fixed}}, df, meta,
                                noise_nm=noise_nm, max_evaluations=LADDER_EVALUATIONS)
        starts["the baseline's fit"] = {"start": merged(fixed, first.model_.values())}
    return fit_from_starts(effects, starts, df, meta, noise_nm=noise_nm,
                           max_evaluations=LADDER_EVALUATIONS)


def _val_p90(fit: PhysicsFit) -> dict:
    return {a: fit.val_[a]["err_p90"] for a in (*AXES, "all") if a in fit.val_}


def achievable_floor(df, meta: dict, noise_nm: float = 5.0, fit: PhysicsFit | None = None) -> dict:
    """Fit the true model (``true_fit``, or take ``fit``, that fit) to the data's calibration
    rows: its validation error 90 % per axis and pooled (nm), the fit's status, and the noise
    floor's share of it and the rest's (nm)."""
    fit = fit or true_fit(df, meta, noise_nm)
    effects = fit.effects
    floor = _val_p90(fit)
    noise = ((meta or {}).get("truth") or {}).get("noise_floor_nm") or {}
    budget = {}
    for a in AXES:
        if a in floor and a in noise:
            rest = float(np.sqrt(max(floor[a] ** 2 - noise[a] ** 2, 0.0)))
            budget[a] = {"noise_floor_nm": noise[a], "above_noise_floor_nm": rest}
    return {"achievable_floor_nm": floor, "effects": effects, "converged": fit.converged_,
            "status": fit.status_, "budget_nm": budget,
            "start": getattr(fit, "start_label_", None),
            "calibration_rms_nm": getattr(fit, "start_costs_", {})}


def _refit_change(fit: PhysicsFit, delta: np.ndarray) -> np.ndarray:
    """(N,3) m: what a change ``delta`` (N,3) m of the model's prediction leaves once the fit
    has taken up what it can (its identified directions, each session's zero), to first order."""
    meas = fit.measurements_
    JV = (fit.jacobian_ * fit.model_.scales) @ fit.identified_directions_        # (N,3,k)
    d = np.where(meas.group >= 0, delta, 0.0)
    if JV.shape[2]:
        z = np.linalg.lstsq(projected(meas, meas.cal, JV), -projected(meas, meas.cal, d),
                            rcond=None)[0]
        d = d + JV @ z
    for g in range(len(meas.groups)):
        m = (meas.group == g)
        d[m] -= d[m & meas.cal[:, None]].mean()
    return np.where(meas.group >= 0, d, np.nan)


def _by_sensor(fit: PhysicsFit, df, meta: dict, perfect_df) -> dict:
    """{sensor column: {axis: nm}}: each thermometer's share of the floor, to first order (its
    reading replaced by the true one, ``perfect_df``'s, the refit taken out; 90 % over the
    validation rows)."""
    model, meas = fit.model_, fit.measurements_
    base = model.predict_path(meas)
    out = {}
    for c in (c for c in df.columns if c.startswith("T_") and c.endswith("_C")):
        true = df.copy()
        true[c] = perfect_df[c].to_numpy()
        delta = model.predict_path(measurements(true, meta, model.params)) - base
        r = _refit_change(fit, delta)
        out[c] = {a: float(np.quantile(np.abs(r[meas.val, k][np.isfinite(r[meas.val, k])]),
                                       0.9)) * 1e9
                  for k, a in enumerate(AXES) if np.isfinite(r[meas.val, k]).any()}
    return out


def measured_floor_budget(scenario, scale, df, meta: dict, full: PhysicsFit | None = None) -> dict:
    """The achievable floor of the twin's dataset ``df`` (``scenario`` at ``scale``) split per
    source (module docstring): ``{axis: {source_nm: nm, ..., "thermal_state_nm": nm,
    "quadrature_sum_nm": nm, "achievable_floor_nm": nm}, "thermometers_by_sensor_nm":
    {column: {axis: nm}}, "adds_up": {axis: the quadrature sum within BUDGET_TOLERANCE of the
    floor}, "sources": {source_nm: what it is}}``. ``full``: the true model's fit
    on ``df`` when already made."""
    full = full or true_fit(df, meta)
    present = scenario.sources()
    sources = [SOURCE_LINE[s] for s in present]
    floors = {}
    quiet_df = None
    for name, source in [(REMAINDER, None), *zip(sources, present)]:
        d, m = scenario.with_perfect([s for s in present if s != source]).simulate(scale)
        if not np.array_equal(d["t_s"].to_numpy(), df["t_s"].to_numpy()):
            raise RuntimeError(f"floor budget: the {name} run's timeline differs from the "
                               "dataset's (a source that is not a pure draw?)")
        floors[name] = _val_p90(true_fit(d, m))
        if name == REMAINDER:
            quiet_df = d
    floor = _val_p90(full)
    budget = {}
    for a in floor:
        rest = floors[REMAINDER].get(a, 0.0)
        line = {s: float(np.sqrt(max(floors[s][a] ** 2 - rest ** 2, 0.0))) for s in sources}
        line[REMAINDER] = rest
        line["quadrature_sum_nm"] = float(np.sqrt(sum(v ** 2 for v in line.values())))
        line["achievable_floor_nm"] = floor[a]
        budget[a] = line
    # each source alone is refitted on its own: where validation extrapolates (conditions past
    # the calibration range) a run with one quiet source can extrapolate worse than the whole,
    # and the lines no longer add up; said, not hidden
    budget["adds_up"] = {a: bool(abs(budget[a]["quadrature_sum_nm"] / budget[a][
        "achievable_floor_nm"] - 1) <= BUDGET_TOLERANCE) for a in floor if budget[a][
        "achievable_floor_nm"] > 0}
    budget["thermometers_by_sensor_nm"] = _by_sensor(full, df, meta, quiet_df)
    budget["sources"] = {s: SOURCES[s] for s in sources} | {
        REMAINDER: "what perfect instruments leave: the parts' temperatures the sensors do not "
                   "see (parts without a sensor, gradients, the model's smoothing)"}
    return budget


def predicted_floor_budget(fit: PhysicsFit, df, meta: dict, settings=None,
                           servo_u_rad: float = 0.0, climate: dict | None = None):
    """The floor's budget of laboratory data, predicted from the instruments' specifications
    (``settings``: twin.instruments.simulated.InstrumentSettings, the defaults' instruments
    unless given) through the fitted model's sensitivities to its measured inputs
    (calibration/design/budget.py): a table of the noise sources, 90 % per axis (nm). The
    thermometers' standard uncertainty is their noise and resolution (sigma^2 + step^2 / 12),
    propagated as white noise through the model's temperature levels and rates, and per sensor
    as an offset through each lever (an upper bound: the model's smoothing averages white
    noise). The air: the barometer's (hygrometer's) noise where the data record ``p_Pa``
    (``RH_pct``), else the wander the laboratory states (``climate``: room_climate's
    pressure_std_Pa, pressure_time_s, vapour_std_Pa, vapour_time_s; default the library's, the
    papers' 80 Pa over a day), over each reading's time since its session's zero."""
    from deltatwin.calibration.design.budget import thermometer_u_K, uncertainty_budget
    from deltatwin.twin.instruments.simulated import InstrumentSettings
    from deltatwin.twin.scenario import air_wander

    s = settings or InstrumentSettings()
    T_u = thermometer_u_K(s)
    air = air_wander(s, climate, "p_Pa" in df, "RH_pct" in df,
                     fit.model_.params.reference_temperature_C)
    reading_u = quantised_u(s.noise_floor_m, s.resolution_m)
    table = uncertainty_budget(fit, df, meta, reading_u, T_u, servo_u_rad, air,
                               np.random.default_rng(0), per_sensor=True)
    return table[table["kind"].isin(["noise", "thermometer"])].reset_index(drop=True)


def air_line_check(scenario: str, scale: float | None, seeds) -> dict:
    """The predicted budget's air line beside what the twin's own air does, pooled over the
    campaigns ``seeds`` of ``scenario`` at ``scale``, 90 % over the validation rows, nm per
    axis and pooled: {"budget": the line (calibration/design/budget.py air_line: the
    scenario's stated wander through the refitted true model's levers), "twin": the readings
    with the air's error alone switched on minus with every source perfect (same seed), up to
    the session zeros, "twin_refit": the true model refitted on both runs (from the twin's
    values), the difference of their residuals}. The wander is slow: one campaign sees one
    path of it, so the comparison needs several."""
    from deltatwin.calibration.design.budget import air_line, mixture_figures, quantile90, zero_centred
    from deltatwin.twin.scenario import Scenario

    lines = {"budget": [], "twin": [], "twin_refit": []}
    for seed in seeds:
        sc = Scenario.load(scenario, seed=seed)
        runs = [sc.with_perfect([s for s in sc.sources() if s != "air"]),
                sc.with_perfect(sc.sources())]
        (air_df, air_meta), (still_df, still_meta) = (r.simulate(scale) for r in runs)
        air_fit, still_fit = (true_fit(d, m)
                              for d, m in ((air_df, air_meta), (still_df, still_meta)))
        meas = air_fit.measurements_
        val = (meas.group >= 0) & meas.val[:, None]
        readings = np.stack([(air_df[f"{a}_nm"] - still_df[f"{a}_nm"]).to_numpy() * 1e-9
                             if f"{a}_nm" in air_df else np.full(len(air_df), np.nan)
                             for a in AXES], axis=1)
        lines["budget"].append(air_line(air_fit, sc.air_wander())[1])
        lines["twin"].append(zero_centred(meas, readings))
        lines["twin_refit"].append(air_fit.residual_ - still_fit.residual_)
        lines.setdefault("val", []).append(val)
    val = np.concatenate(lines.pop("val"))
    out = {}
    for name, per in lines.items():
        v = np.concatenate(per)
        if name == "budget":        # standard uncertainties: the mixture's 90 %
            out[name] = mixture_figures(np.where(val, v, np.nan), val)
        else:                       # errors: their 90 % quantile
            v = np.where(val, v, np.nan)
            out[name] = {a: quantile90(v[:, k]) * 1e9
                         for k, a in enumerate(AXES) if val[:, k].any()}
            out[name]["all"] = quantile90(v) * 1e9
    return out


def record_achievable_floor(df, meta: dict, scenario=None, scale=None) -> tuple[dict, PhysicsFit]:
    """Put the achievable floor, its budget and its fit's effects and status into the dataset's
    truth (``meta["truth"]``); returns the floor (nm by axis and pooled) and its fit (the other
    starts' fits in its ``start_fits_``, for a later fit of the same model to reuse). With the twin's
    ``scenario`` (and the ``scale`` it ran at) the budget is measured per source
    (``measured_floor_budget``), else it is the noise floor's share and the rest."""
    fit = true_fit(df, meta)
    floor = achievable_floor(df, meta, fit=fit)
    meta["truth"]["achievable_floor_nm"] = floor["achievable_floor_nm"]
    meta["truth"]["floor_budget_nm"] = (floor["budget_nm"] if scenario is None else
                                        measured_floor_budget(scenario, scale, df, meta, fit))
    meta["truth"]["achievable_floor_fit"] = {"effects": floor["effects"],
                                             "status": floor["status"]}
    return floor["achievable_floor_nm"], fit


def budget_lines(budget: dict | None) -> list[str]:
    """The floor's budget as text lines (nm per axis per source, the biggest thermometers'
    levers), for a command to print; [] without a budget."""
    axes = [a for a in (*AXES, "all") if isinstance((budget or {}).get(a), dict)]
    if not axes:
        return []
    sources = [k for k in budget[axes[0]] if k not in ("quadrature_sum_nm",
                                                       "achievable_floor_nm")]
    width = max(len(k) for k in [*sources, "quadrature_sum_nm"]) - 3
    lines = ["what sets the achievable floor, nm (90 %) per axis:"]
    lines.append(f"  {'source':<{width}}" + "".join(f"{a:>8}" for a in axes))
    for k in [*sources, "quadrature_sum_nm", "achievable_floor_nm"]:
        if all(k in budget[a] for a in axes):
            lines.append(f"  {k[:-3]:<{width}}" + "".join(f"{budget[a][k]:8.1f}" for a in axes))
    off = [a for a, ok in (budget.get("adds_up") or {}).items() if not ok]
    if off:
        lines.append(f"  the sources do not add up to the floor on {', '.join(off)} (beyond "
                     f"{BUDGET_TOLERANCE:.0%}): validation extrapolates past the calibration "
                     "conditions, where each source refitted alone extrapolates differently")
    by_sensor = budget.get("thermometers_by_sensor_nm") or {}
    top = sorted(by_sensor.items(), key=lambda kv: -max(kv[1].values(), default=0.0))[:4]
    if top:
        lines.append("  thermometers through their levers (first order), the largest: " + "; ".join(
            f"{c} " + "/".join(f"{v:.1f}" for v in d.values()) for c, d in top)
            + " nm (" + "/".join(next(iter(by_sensor.values())).keys()) + ")")
    return lines


def floor_of(meta: dict | None) -> tuple[dict | None, str]:
    """The floor a model is judged against, and its kind: the achievable floor when the data
    carry it, else the noise floor (the readings' own noise), else none."""
    truth = (meta or {}).get("truth") or {}
    if truth.get("achievable_floor_nm"):
        return truth["achievable_floor_nm"], "achievable"
    if truth.get("noise_floor_nm"):
        return truth["noise_floor_nm"], "noise"
    return None, "none"
