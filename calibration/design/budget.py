"""Uncertainty budget of a fitted physics model, in the spirit of the GUM: the error at the tool
point (nm, 90 % over the workspace) contributed by each effect's parameter uncertainty and by
each noise source, propagated to first order through the model.

The workspace is the dataset's points (calibration and validation rows, with their recorded
conditions). Per point and axis a source gives a standard uncertainty u (m); its figure is the
90 % error of the mixture over the points, x with mean_points P(|N(0, u_point)| <= x) = 0.9, so a
source that matters only in a corner of the workspace counts as much as it covers.

* Parameters: the fit's covariance of its identified directions (sigma of the calibration
  residual, as the fit reports it) and, on the directions the data leave undetermined, the
  prior (one fit scale), J_e C_ee J_e^T per effect; the line "all parameters (correlated)"
  uses the whole covariance (the effects' correlations included), so the effects' lines need
  not add up to it (its share is not added to theirs).

Every line is taken up to the session zeros: a reading is known relative to its session's
zero, and the fit refits the zeros, so what moves all of a session's readings alike is no
error at the tool point.
* Interferometer: the standard deviation of a point's reading (the validation readings carry
  it; a point that averages n readings has the single reading's over sqrt(n)).
* Thermometers: each sensor's white noise ``T_u_K`` per scan, independent sensors and scans,
  through the model's temperature levels *and rates* (causal fits over time): propagated by
  noise draws (GUM Supplement 1), since a constant shift of a column (a first-order lever)
  reaches the levels only and missed ~95 % of this line on the force campaign.
* Air: the air's pressure (and water vapour) at each reading off the one at its session's zero,
  through the index's change over each beam's dead path and displacement: an unrecorded
  wander as the laboratory states it (std and correlation time: a slow wander moves little
  between a session's zero and its readings), or a barometer's (hygrometer's) noise, white;
  its exact variance under the wander's covariance (``wander_u``), with, besides the session
  zeros, what the fit's identified directions take up of it on the calibration rows taken
  out to first order (``refit_map``): a slow wander looks partly like a slow drift the model
  fits, and where validation extrapolates that part returns amplified.
* Thermometers per sensor (``per_sensor``): each sensor's ``T_u_K`` as an offset through its
  lever (the model's prediction with that column shifted, a first-order difference), to show
  which sensor's lever matters.
* Servo settling: each motor's settled angle off by ``servo_u_rad``, independent motors.

``budget_monte_carlo`` checks every line against the spread of that source's error over many
simulated campaigns of one robot.
"""
from __future__ import annotations

import copy
import dataclasses

import numpy as np
import pandas as pd
from scipy import optimize, stats

from deltatwin.calibration.physics.air import air_levers
from deltatwin.calibration.physics.fit import PhysicsFit
from deltatwin.calibration.physics.measurements import measurements
from deltatwin.calibration.physics.model import PhysicsModel, projected, projected_transpose
from deltatwin.calibration.stats import exponential_kernel_sums
from deltatwin.twin.instruments.optics import AXES
from deltatwin.twin.noise import quantised_u


def mixture_p90(u: np.ndarray) -> float:
    """x (same unit as ``u``) with mean over the entries of P(|N(0, u)| <= x) = 0.9 (the 90 %
    error over the workspace of errors with standard uncertainties ``u``)."""
    u = np.asarray(u, float)
    u = u[np.isfinite(u)]
    if u.size == 0 or not np.any(u > 0):
        return 0.0
    coverage = lambda x: float(np.mean(2 * stats.norm.cdf(x / np.maximum(u, 1e-300)) - 1)) - 0.9
    return float(optimize.brentq(coverage, 0.0, 10 * u.max(), xtol=1e-6 * u.max()))


def mixture_figures(u: np.ndarray, read: np.ndarray) -> dict:
    """{axis: p90 nm, 'all': p90 nm} of standard uncertainties u (N,3) m on the read entries."""
    out = {a: mixture_p90(u[read[:, k], k]) * 1e9 for k, a in enumerate(AXES)
           if read[:, k].any()}
    out["all"] = mixture_p90(u[read]) * 1e9
    return out


def parameter_covariance(fit: PhysicsFit, prior: bool = True) -> np.ndarray:
    """(p, p) covariance (SI) of the fitted parameters: the fit's on its identified directions;
    on the directions the data cannot determine (held at their starting values), the prior's,
    each parameter's prior width (Parameter ``tolerance``) projected on them (``prior=False``:
    left out, the estimate's sampling covariance alone)."""
    meas, S, V = fit.measurements_, fit.model_.scales, fit.identified_directions_
    held = np.eye(S.size) - V @ V.T                        # unidentified subspace (scaled)
    width = fit.model_.tolerances / S
    C = ((S[:, None] * held * width ** 2) @ (held * S[None, :]) if prior
         else np.zeros((S.size, S.size)))
    if V.shape[1]:
        Jz = projected(meas, meas.cal, fit.jacobian_, scale=S) @ V
        sigma = fit.identifiability_["residual_sigma_nm"] * 1e-9
        SV = S[:, None] * V
        C = C + SV @ np.linalg.pinv(Jz.T @ Jz) @ SV.T * sigma ** 2
    return C


def _shifted(fit: PhysicsFit, df: pd.DataFrame, meta: dict, column: str, step: float,
             model: PhysicsModel | None = None) -> np.ndarray:
    """d prediction / d column (N,3) per unit of the column, by a first-order difference."""
    model = model or fit.model_
    base = model.predict_path(measurements(df, meta, model.params))
    moved = df.copy()
    moved[column] = moved[column] + step
    return (model.predict_path(measurements(moved, meta, model.params)) - base) / step


def parameter_lines(fit: PhysicsFit, C: np.ndarray) -> list:
    """[("parameters", name, u (N,3) m)]: per effect J_e C_ee J_e^T, then all parameters with
    the whole covariance ``C`` (correlations included), J taken up to the session zeros."""
    J = np.nan_to_num(zero_centred(fit.measurements_, fit.jacobian_))
    lines = []
    for e in fit.model_.effects:
        cols = np.concatenate([np.arange(f.sl.start, f.sl.stop) for f in fit.model_.free
                               if f.effect == e.name] or [np.zeros(0, int)])
        if cols.size:
            Je = J[:, :, cols]
            var = np.einsum("naj,jk,nak->na", Je, C[np.ix_(cols, cols)], Je)
            lines.append(("parameters", f"{e.name} ({cols.size} parameters)", np.sqrt(var)))
    var = np.einsum("naj,jk,nak->na", J, C, J)
    return lines + [("parameters", "all parameters (correlated)", np.sqrt(var))]


def zero_centred(meas, v: np.ndarray) -> np.ndarray:
    """v (N,3) or (N,3,D) minus each (session, axis) group's mean over its calibration rows
    (what the fitted session zero takes up: a reading is known up to its session's zero); NaN
    where the axis was not read."""
    out = np.full_like(v, np.nan)
    for g in range(len(meas.groups)):
        m = meas.group == g
        mc = m & meas.cal[:, None]
        if mc.any():
            out[m] = v[m] - v[mc].mean(axis=0)
    return out


def refit_map(fit: PhysicsFit) -> tuple[np.ndarray, np.ndarray] | None:
    """(G, W), each (N,3,k): the fit's first-order refit of a change d (N,3) of the readings
    (its identified directions and each session's zero take up what they can) leaves
    zero_centred(d) - G @ (sum over the entries of W * d); None without identified
    directions."""
    meas = fit.measurements_
    JV = np.nan_to_num((fit.jacobian_ * fit.model_.scales) @ fit.identified_directions_)
    if not JV.shape[2]:
        return None
    # the step z = -pinv(A) (the change's calibration part, each group's mean removed)
    solve_T = np.linalg.pinv(projected(meas, meas.cal, JV)).T
    return np.nan_to_num(zero_centred(meas, JV)), projected_transpose(meas, meas.cal, solve_T)


def wander_u(meas, row_lever: np.ndarray, zero_lever: np.ndarray, std: float,
             time_s: float, refit: tuple | None = None) -> np.ndarray:
    """(N,3) m: the standard uncertainty, up to the session zeros (``zero_centred``), of what a
    stationary Ornstein-Uhlenbeck wander of the air (``std``, correlation time ``time_s``; 0:
    white, a record's noise) puts on each reading through ``row_lever`` (its level at the
    reading) and ``zero_lever`` (at its session's zero), per unit: the exact variance of the
    linear combination under the covariance std^2 exp(-|dt| / time_s) (over a reading's time
    since its zero alone it would be std^2 2 (1 - exp(-dt / time_s)) on a constant lever).
    ``refit`` (``refit_map``): what the fit's identified directions take up of it taken out
    too, to first order (a slow wander looks partly like a slow drift the model fits).
    NaN where the axis was not read or its session has no calibration row."""
    t = meas.points.t_s
    kernel = (lambda dt: np.exp(-np.abs(dt) / time_s)) if time_s > 0 else (
        lambda dt: (dt == 0).astype(float))
    out = np.full(row_lever.shape, np.nan)
    for g, (_, axis) in enumerate(meas.groups):
        k = AXES.index(axis)
        rows = np.flatnonzero(meas.group[:, k] == g)
        cal = meas.cal[rows]
        if not cal.any():
            continue
        t0 = t[meas.zero_row[rows[0]]]
        a, b = row_lever[rows, k], zero_lever[rows, k]
        a_cal, n_cal = np.where(cal, a, 0.0), cal.sum()
        db = b - b[cal].mean()
        m = exponential_kernel_sums(np.append(t[rows], t0), np.append(a_cal, 0.0), time_s)
        # r_i = a_i p_i + b_i p_0 - mean over cal j of (a_j p_j + b_j p_0)
        var = (a ** 2 + db ** 2 + 2 * a * db * kernel(t[rows] - t0)
               - 2 * a * m[:-1] / n_cal - 2 * db * m[-1] / n_cal
               + a_cal @ m[:-1] / n_cal ** 2)
        out[rows, k] = std ** 2 * var
    if refit is not None:
        # r = Z d - G c with c = W . d: Var r = Var Zd - 2 G Cov(c, Zd) + G Cov(c) G
        G, W = refit
        read = meas.group >= 0
        a, b = np.where(read, row_lever, 0.0), np.where(read, zero_lever, 0.0)
        n = a.shape[0]
        at_times = np.zeros((t.size, W.shape[2]))
        at_times[:n] = np.einsum("na,nak->nk", a, W)
        np.add.at(at_times, meas.zero_row, np.einsum("na,nak->nk", b, W))
        K = std ** 2 * exponential_kernel_sums(t, at_times, time_s)
        cov_W = a[:, :, None] * K[:n, None, :] + b[:, :, None] * K[meas.zero_row][:, None, :]
        cov_c = np.einsum("nak,nal->kl", W, cov_W)
        out = (out - 2 * np.einsum("nak,nak->na", G, np.nan_to_num(zero_centred(meas, cov_W)))
               + np.einsum("nak,kl,nal->na", G, cov_c, G))
    return np.sqrt(np.maximum(out, 0.0))


def air_line(fit: PhysicsFit, air: dict) -> tuple[str, np.ndarray] | None:
    """("air (...)", u (N,3) m): the air's pressure and water vapour as the laboratory states
    them (``air``: {"pressure_Pa": (std, correlation time s), "vapour_Pa": (...)}, as
    twin.scenario.air_wander gives; time 0 is a record's white noise) through the fitted
    model's levers (physics ``air_levers``), up to the session zeros and the fit's first-order
    refit (``wander_u``, ``refit_map``); None without either."""
    parts, var, refit = [], 0.0, None
    recorded = fit.measurements_.df.columns
    for field, column, what in (("pressure_Pa", "p_Pa", "pressure"),
                                ("vapour_Pa", "RH_pct", "water vapour")):
        std, time_s = air.get(field, (0.0, 0.0))
        if std > 0:
            refit = refit_map(fit) if refit is None else refit     # the same for every field
            levers = air_levers(fit.model_, fit.measurements_, field)
            u = wander_u(fit.measurements_, *levers, std, time_s, refit)
            var = var + u ** 2
            parts.append(f"{'recorded' if column in recorded else 'unrecorded'} {what} "
                         f"{std:.3g} Pa " + (f"wander over {time_s / 3600:.3g} h" if time_s > 0
                                             else "white"))
    return (f"air ({', '.join(parts)})", np.sqrt(var)) if parts else None


def uncertainty_budget(fit: PhysicsFit, df: pd.DataFrame, meta: dict, reading_u_m: float,
                       T_u_K: float, servo_u_rad: float, air: dict,
                       rng: np.random.Generator, n_probe: int = 32,
                       per_sensor: bool = False) -> pd.DataFrame:
    """The budget table: one row per source (``kind``: parameters / noise), its standard
    uncertainty's 90 % figure over the workspace per axis and pooled (nm), and its share of the
    combined variance. ``df``/``meta``: the dataset ``fit`` was fitted to; ``reading_u_m``: the
    standard deviation of a point's reading (the mean of its repeated readings); ``T_u_K``: each
    thermometer's white noise per scan, propagated through the model's temperature levels and
    rates (its causal fits over time) with ``n_probe`` noise draws from ``rng`` (a Monte Carlo
    propagation, GUM Supplement 1: a constant shift of a column would miss the rates); ``air``:
    the air's wander or records' noise (``air_line``). Every line is taken up to the session
    zeros (``zero_centred``). ``per_sensor``:
    one thermometer row per sensor with a lever (``kind`` thermometer, first-order) besides
    their sum."""
    meas = fit.measurements_
    read = meas.group >= 0
    rows = parameter_lines(fit, parameter_covariance(fit))
    var_all = rows[-1][2] ** 2
    noise = [("noise", "interferometer reading", np.full(read.shape, reading_u_m))]
    sensors = [c for c in df.columns if c.startswith("T_") and c.endswith("_C")]
    if sensors and T_u_K > 0:
        model = fit.model_
        base = model.predict_path(meas)
        change = []
        for _ in range(n_probe):
            noisy = df.copy()
            noisy[sensors] = df[sensors].to_numpy() + T_u_K * rng.standard_normal(
                (len(df), len(sensors)))
            change.append(zero_centred(meas, model.predict_path(
                measurements(noisy, meta, model.params)) - base))
        u_T = np.sqrt(np.mean(np.square(change), axis=0))
        if np.nanmax(u_T) > 0:
            noise.append(("noise", f"thermometers ({len(sensors)}, {T_u_K * 1e3:g} mK white "
                          "noise each)", u_T))
    by_sensor = []
    if per_sensor:
        lever = {c: _shifted(fit, df, meta, c, 0.01) for c in sensors}
        by_sensor = [("thermometer", f"{c} ({T_u_K * 1e3:g} mK)", np.abs(lever[c]) * T_u_K)
                     for c in sensors if np.nanmax(np.abs(lever[c])) > 0]
    servo = np.sqrt(sum((_shifted(fit, df, meta, f"q{i}_rad", 1e-6) * servo_u_rad) ** 2
                        for i in (1, 2, 3)))
    noise.append(("noise", f"servo settling ({servo_u_rad:g} rad per motor)", servo))
    wander = air_line(fit, air)
    if wander:
        noise.append(("noise", *wander))
    combined = np.sqrt(var_all + sum(u ** 2 for _, _, u in noise))
    table = []
    total_var = float(np.nanmean(np.where(read, combined ** 2, np.nan)))
    everything = rows + noise + by_sensor + [("combined", "all parameters (correlated) and noise",
                                              combined)]
    for kind, name, u in everything:
        f = mixture_figures(np.where(read, u, np.nan), read)
        share = float(np.nanmean(np.where(read, u ** 2, np.nan))) / total_var
        table.append({"kind": kind, "source": name, **{f"{k}_p90_nm": v for k, v in f.items()},
                      "variance_share": share})
    return pd.DataFrame(table)


# ---------------------------------------------------------------------------------------------
# Monte Carlo check: many simulated campaigns, each source's error measured on the twin

NOISE_SOURCES = ("interferometer reading", "thermometers", "servo settling", "air")


def fixed_robot(sc, robot_seed: int):
    """The scenario with its robot drawn from ``robot_seed``'s robot stream whatever its own
    seed (twin/world.py STREAMS): the same robot in every campaign, the environment, noise and
    plan drawn from the campaign's seed. Call it before each simulation: the robot stream
    starts afresh."""

    from deltatwin.twin.effects.base import Effect
    from deltatwin.twin.world import random_streams

    stream = random_streams(robot_seed)["robot"]
    effects = []
    for e in sc.effects:
        if type(e).robot is not Effect.robot:       # an effect that draws the robot
            e = copy.copy(e)
            e.robot = lambda params, rng, draw=type(e).robot, e=e: draw(e, params, stream)
        effects.append(e)
    return dataclasses.replace(sc, effects=effects)


def without_random_errors(sc):
    """The scenario read without what no model predicts: the interferometers' reading noise
    and resolution and the servos' random settling switched off (every other draw where it was:
    the same campaign, for the truth a fitted model is judged against)."""
    return sc.with_perfect(["interferometers", "servo_settling"])


def thermometer_u_K(settings) -> float:
    """A thermometer's standard uncertainty per scan (K): its noise and its resolution's
    rounding, what Scenario.with_perfect(["thermometers"]) removes."""
    return quantised_u(settings.T_noise_C, settings.T_resolution_C)


# the noise lines the Monte Carlo measures on the twin: the scenario's error source switched
# perfect (twin/scenario.py ERROR_SOURCES) for each
SWITCHED = {"interferometer reading": "interferometers", "thermometers": "thermometers",
            "servo settling": "servo_settling", "air": "air"}


def _source_errors(sc, robot_seed, scale, df, meta, fit) -> dict:
    """{source: (N,3) m} the tool-point error each noise source put on this campaign, up to
    the session zeros: the reading with the source as it is minus the reading without it (the
    same seeds: for the air, the twin's own wander against air standing still), for the
    thermometers the fitted model's prediction from the recorded temperatures minus from
    noise-free ones. NaN where an axis was not read."""
    meas = fit.measurements_
    read = [f"{a}_nm" for a in AXES if f"{a}_nm" in df]
    out = {}
    for source in NOISE_SOURCES:
        if SWITCHED[source] not in sc.sources():
            continue
        df2, _ = fixed_robot(sc.with_perfect([SWITCHED[source]]), robot_seed).simulate(scale)
        if source == "thermometers":
            sensors = [c for c in df.columns if c.startswith("T_") and c.endswith("_C")]
            clean = df.copy()
            clean[sensors] = df2[sensors].to_numpy()
            model = fit.model_
            e = model.predict_path(meas) - model.predict_path(
                measurements(clean, meta, model.params))
        else:
            e = (df[read].to_numpy() - df2[read].to_numpy()) * 1e-9
        out[source] = zero_centred(meas, e)
    return out


def quantile90(e: np.ndarray) -> float:
    """The 90 % quantile of |e| over the finite entries (0 when none)."""
    e = np.abs(e[np.isfinite(e)])
    return float(np.quantile(e, 0.9)) if e.size else 0.0


def budget_monte_carlo(scenario, effects, campaigns: int, scale: float, seed: int,
                       tolerance: float = 0.1, n_boot: int = 2000,
                       progress=None) -> pd.DataFrame:
    """The budget of ``effects`` fitted to ``scenario``'s campaign (at ``scale``) beside the
    spread of each source's tool-point error over ``campaigns`` simulated campaigns of one
    robot (drawn from ``seed``; the campaigns' seeds, for environment, noise and plan, are
    children of ``SeedSequence(seed)``).

    Per campaign: simulated, fitted, its budget computed (the reading's standard deviation the
    scenario's noise floor over the square root of its readings per point; the thermometers',
    the servos' and the air's (``Scenario.air_wander``) the scenario's own settings); then

    * a parameter line's error is the fitted model's prediction on the campaign's points with
      that effect's parameters as this campaign fitted them, the others at their mean over
      the campaigns, minus the prediction at the mean (the combined line: all parameters as
      fitted): the sampling spread of the estimate, which the budget's covariance predicts;
    * a noise line's error is that source's part of the campaign's readings, measured on the
      twin by simulating the same seeds without it (``_source_errors``).

    All errors are taken up to the session zeros (the fit refits them). The Monte Carlo
    figure is the 90 % quantile of |error| over all points and campaigns (parameter lines:
    deviations from the mean scaled by sqrt(K/(K-1))). Its 95 % interval: for a noise line a
    bootstrap over the campaigns (``n_boot`` resamples; the campaigns are the independent
    units, each with hundreds of readings), for a parameter line the chi-square interval of a
    standard deviation on K - 1 degrees of freedom (one draw of the estimate per campaign).

    A parameter line is compared without the prior on the directions the data leave
    undetermined: those parameters are held at their starting values in every campaign, so
    the truth being one robot they do not scatter (their error is a bias the spread cannot
    show); ``with_prior_p90_nm`` gives the budget's line as the table prints it.

    A line agrees when the budget falls inside the Monte Carlo interval or within
    ``tolerance`` (relative) of the Monte Carlo figure: the budget is a first-order propagation
    through the fitted model's levers, not the twin's, and a planning budget that sizes each
    source within 10 % ranks the sources and sizes their variance shares within ~20 %, which is
    what it is for. Columns: source, kind, budget_p90_nm (mean over the campaigns' budgets),
    budget_spread_nm (their standard deviation), with_prior_p90_nm, mc_p90_nm, mc_low_nm,
    mc_high_nm, ratio (mc / budget), agrees."""
    from deltatwin.twin.scenario import Scenario

    if campaigns < 3:
        raise ValueError(f"campaigns = {campaigns}: a spread needs at least 3")
    seeds = [int(s.generate_state(1, np.uint64)[0] >> np.uint64(1))
             for s in np.random.SeedSequence(seed).spawn(campaigns)]
    rng = np.random.default_rng(seed)
    budgets, thetas, noise, fits = [], [], [], []
    for k, s in enumerate(seeds):
        sc = Scenario.load(scenario, seed=s)
        df, meta = fixed_robot(sc, seed).simulate(scale)
        fit = PhysicsFit(list(effects), noise_nm=sc.settings.noise_floor_m * 1e9).fit(df, meta)
        servo = next((float(e.values["angle_std_rad"]) for e in sc.effects
                      if e.name == "servo_settling"), 0.0)
        readings = sc.campaign.get("readings", 1) if sc.campaign["kind"] == "force" else 1
        b = uncertainty_budget(fit, df, meta, sc.settings.noise_floor_m / np.sqrt(readings),
                               thermometer_u_K(sc.settings), servo, sc.air_wander(), rng)
        read = fit.measurements_.group >= 0
        sampling = {name: mixture_figures(np.where(read, u, np.nan), read)["all"]
                    for _, name, u in parameter_lines(fit, parameter_covariance(fit, False))}
        b["sampling_p90_nm"] = b.source.map(sampling).fillna(b.all_p90_nm)
        budgets.append(b)
        noise.append(_source_errors(sc, seed, scale, df, meta, fit))
        thetas.append(fit.model_.theta())
        fits.append(fit)
        if progress:
            progress(k + 1, campaigns)
    thetas = np.array(thetas)
    mean = thetas.mean(axis=0)
    inflate = np.sqrt(campaigns / (campaigns - 1))
    model = fits[0].model_
    groups = {f"{e.name} (": np.concatenate([np.arange(f.sl.start, f.sl.stop)
                                             for f in model.free if f.effect == e.name])
              for e in model.effects if any(f.effect == e.name for f in model.free)}
    errors = {}                                   # line -> list over campaigns of (N,3) m
    for k, fit in enumerate(fits):
        meas = fit.measurements_
        base = model.predict_path(meas, mean)
        for prefix, cols in list(groups.items()) + [("all parameters", None)]:
            theta = mean.copy()
            if cols is None:
                theta = thetas[k].copy()
            else:
                theta[cols] = thetas[k][cols]
            dev = zero_centred(meas, model.predict_path(meas, theta) - base) * inflate
            errors.setdefault(prefix, []).append(dev)
        for source, e in noise[k].items():
            errors.setdefault(source, []).append(e)
    boot = rng.integers(0, campaigns, (n_boot, campaigns))
    rows = []
    for key, per in errors.items():
        named = [b.set_index("source") for b in budgets]
        source = next((x for x in named[0].index if x.startswith(key)), None)
        if source is None:         # a source the budget has no line for (no lever)
            continue
        predicted = np.array([b.loc[source, "sampling_p90_nm"] for b in named])
        flat = [np.abs(p[np.isfinite(p)]) for p in per]
        mc = quantile90(np.concatenate(flat)) * 1e9
        kind = named[0].loc[source, "kind"]
        if kind == "parameters":
            # K campaigns are K - 1 independent draws of the estimate's scatter (about their
            # mean): the chi-square interval of a standard deviation on K - 1 degrees of
            # freedom (the bootstrap of so few units is too narrow)
            low, high = mc * np.sqrt((campaigns - 1)
                                     / stats.chi2.ppf([0.975, 0.025], campaigns - 1))
        else:
            resampled = [quantile90(np.concatenate([flat[i] for i in idx])) * 1e9
                         for idx in boot]
            low, high = np.quantile(resampled, [0.025, 0.975])
        b = float(np.mean(predicted))
        rows.append({"source": source, "kind": kind,
                     "budget_p90_nm": b, "budget_spread_nm": float(np.std(predicted)),
                     "with_prior_p90_nm": float(np.mean([b_.loc[source, "all_p90_nm"]
                                                         for b_ in named])),
                     "mc_p90_nm": mc, "mc_low_nm": float(low), "mc_high_nm": float(high),
                     "ratio": mc / b if b > 0 else np.nan,
                     "agrees": bool(low <= b <= high or abs(b / mc - 1) <= tolerance
                                    if mc > 0 else b == 0)})
    return pd.DataFrame(rows)
