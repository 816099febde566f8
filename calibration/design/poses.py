"""Pose selection: which of a candidate set of measurement points identify a physics model's
parameters best for a given number of points (greedy Bayesian D-optimal design, the way
robot-calibration tools such as FIGAROH pick poses for serial robots).

A candidate is one planned point (motor coordinates, load, the conditions the campaign records);
its information is its Jacobian block J_i (readings x parameters) of the physics model at the
parameters' starting values, in units of each parameter's typical size (fit scale) and of the
readings' noise. Each session axis's zero is a parameter too (a column of ones on that axis,
typical size ``zero_scale_m``), so a selection pays for the zeros it needs. The prior is each
parameter known to +-1 typical size: M_0 = I. The greedy step adds the candidate that raises
log det(M) most,

    log det(M + J_i^T J_i) - log det(M) = log det(I + J_i M^-1 J_i^T),

evaluated for all candidates at once (a (readings x readings) determinant each), and updates
M^-1 by the Woodbury identity. No readings are needed: the selection is made before the lab,
from the plan's conditions.
"""
from __future__ import annotations

import dataclasses
import itertools

import numpy as np
import pandas as pd

from deltatwin.calibration.errors import FitError, TooFewPointsError
from deltatwin.calibration.physics.measurements import Measurements
from deltatwin.calibration.physics.model import PhysicsModel

ZERO_SCALE_M = 1e-3        # a session zero is unknown to ~1 mm before its reading


def information_blocks(model: PhysicsModel, meas: Measurements, sigma_m: float,
                       rows: np.ndarray, zero_scale_m: float = ZERO_SCALE_M) -> np.ndarray:
    """(n_rows, 3, p + zeros) Jacobian blocks of ``rows`` (indices into ``meas``) at the
    model's current values, scaled by the parameters' fit scales and divided by ``sigma_m``;
    the last columns are the (session, axis) zeros; axes not read are zero rows."""
    _, J = model.jacobian(meas, model.theta())
    J = J[rows] * model.scales / sigma_m
    group = meas.group[rows]                                   # (n, 3), -1 where not read
    Z = np.zeros(group.shape + (len(meas.groups),))
    n, a = np.nonzero(group >= 0)
    Z[n, a, group[n, a]] = zero_scale_m / sigma_m
    blocks = np.concatenate([J, Z], axis=2)
    return np.where((group >= 0)[:, :, None], blocks, 0.0)


def greedy_selection(blocks: np.ndarray, n_select: int, criterion: str = "D",
                     region: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Indices of ``n_select`` candidates (in the order chosen) and the criterion after each
    choice. ``blocks``: (n, r, p) information blocks. ``criterion``:

    * ``"D"``: maximise log det of the information M = I + sum J_i^T J_i (all parameters);
    * ``"I"``: minimise the mean prediction variance over ``region`` ((m, r, p) blocks of the
      points where the model will be used, zeros' columns zero), trace(W M^-1) / m with
      W = sum over the region of J^T J: the parameters only as far as they move predictions.
    """
    n, r, p = blocks.shape
    if not 0 < n_select <= n:
        raise ValueError(f"n_select = {n_select}: expected 1 .. {n} (the candidates)")
    if criterion not in ("D", "I"):
        raise ValueError(f"criterion = {criterion!r}: expected 'D' or 'I'")
    if criterion == "I":
        if region is None:
            raise ValueError("criterion 'I' needs the region's blocks")
        W = np.einsum("mrp,mrq->pq", region, region) / region.shape[0]
    M_inv = np.eye(p)
    chosen = np.zeros(n, bool)
    order, value = [], []
    total = 0.0 if criterion == "D" else float(np.trace(W))
    eye_r = np.eye(r)
    for _ in range(n_select):
        B = blocks @ M_inv                                     # (n, r, p) = J_i M^-1
        S = eye_r + B @ np.swapaxes(blocks, 1, 2)              # I + J_i M^-1 J_i^T
        if criterion == "D":
            gain = np.linalg.slogdet(S)[1]
        else:      # the fall of trace(W M^-1): trace(S^-1 J_i M^-1 W M^-1 J_i^T)
            gain = np.trace(np.linalg.solve(S, B @ W @ np.swapaxes(B, 1, 2)), axis1=1, axis2=2)
        gain[chosen] = -np.inf
        i = int(np.argmax(gain))
        chosen[i] = True
        order.append(i)
        total += float(gain[i]) if criterion == "D" else -float(gain[i])
        value.append(total)
        # Woodbury: (M + J^T J)^-1 = M^-1 - M^-1 J^T (I + J M^-1 J^T)^-1 J M^-1
        M_inv = M_inv - B[i].T @ np.linalg.solve(S[i], B[i])
        M_inv = 0.5 * (M_inv + M_inv.T)
    return np.asarray(order), np.asarray(value)


def mean_prediction_variance(blocks: np.ndarray, region: np.ndarray) -> float:
    """trace(W M^-1) / m of a set of candidates over a region (units: the noise's variance)."""
    p = blocks.shape[2]
    M = np.eye(p) + np.einsum("nrp,nrq->pq", blocks, blocks)
    W = np.einsum("mrp,mrq->pq", region, region) / region.shape[0]
    return float(np.trace(np.linalg.solve(M, W)))


def log_det_information(blocks: np.ndarray) -> float:
    """log det(I + sum J_i^T J_i) of a set of candidates (to compare selections)."""
    p = blocks.shape[2]
    M = np.eye(p) + np.einsum("nrp,nrq->pq", blocks, blocks)
    return float(np.linalg.slogdet(M)[1])


def _subset(df, cal_rows: np.ndarray, rows: np.ndarray):
    """``df`` with only the calibration rows ``rows`` (a subset of ``cal_rows``) and every
    validation row."""
    keep = np.ones(len(df), bool)
    keep[cal_rows] = False
    keep[rows] = True
    return df.iloc[np.flatnonzero(keep)]


def _fitted(df, meta, effects, sigma_m: float, where: str, clean=None) -> dict:
    """val_err90_nm, identified_directions and status of ``effects`` fitted to ``df``; with
    ``clean`` (the same rows read without the interferometers' noise) also truth_err90_nm, the
    fitted model's error against those readings on the validation rows: the estimation error
    a selection can change, without the reading noise every selection shares. A design with
    too few readings for the model is a result (NaN, and the reason as the status)."""
    from deltatwin.calibration.physics.fit import PhysicsFit
    from deltatwin.calibration.physics.measurements import measurements
    from deltatwin.calibration.physics.model import figures_nm

    out = {"val_err90_nm": np.nan, "truth_err90_nm": np.nan} if clean is not None \
        else {"val_err90_nm": np.nan}
    try:
        fit = PhysicsFit(effects, noise_nm=sigma_m * 1e9).fit(df, meta, where=where)
    except (FitError, TooFewPointsError) as exc:
        return {**out, "identified_directions": 0, "status": str(exc)}
    out["val_err90_nm"] = fit.val_["all"]["err_p90"]
    if clean is not None:
        meas = fit.measurements_
        y = measurements(clean, meta, fit.model_.params, where).y
        out["truth_err90_nm"] = figures_nm(fit.residual_ + (y - meas.y), meas.val)["all"][
            "err_p90"]
    return {**out, "identified_directions": fit.identifiability_["n_identified_directions"],
            "status": "ok" if fit.converged_ else fit.status_}


def _plan_blocks(df, meta, effects, sigma_m: float, where: str):
    """(model, measurements, calibration rows, information blocks of every row, region): the
    region is the planned points' blocks with the zeros' columns cleared (a zero is a
    nuisance, not a prediction)."""
    from deltatwin.calibration.physics.measurements import measurements

    model = PhysicsModel(effects)
    meas = measurements(df, meta, model.params, where)
    blocks = information_blocks(model, meas, sigma_m, np.arange(meas.n))
    region = blocks.copy()
    region[:, :, model.n_free:] = 0.0
    return model, meas, np.flatnonzero(meas.cal), blocks, region


def selection_study(df, meta, effects, n_select: int, sigma_m: float, rng: np.random.Generator,
                    where: str = "data") -> dict:
    """The validation error (90 %, nm) of ``effects`` fitted to all calibration rows of a
    campaign, to ``n_select`` of them chosen D- and I-optimally (from the plan's conditions
    alone; the I criterion's region is the campaign's planned points), and to ``n_select`` drawn
    at random by ``rng``; the validation rows are the same for all. Each entry also gives the
    mean prediction variance over the region (in units of the noise's variance).
    ``sigma_m``: the readings' noise (m) the selection weighs the information with."""
    model, meas, cal_rows, blocks, region = _plan_blocks(df, meta, effects, sigma_m, where)
    picks = {"all": cal_rows}
    gains = {}
    for crit in ("D", "I"):
        order, value = greedy_selection(blocks[cal_rows], n_select, crit, region)
        picks[f"{crit}_optimal"] = cal_rows[order]
        gains[f"{crit}_optimal"] = float(value[-1])
    picks["random"] = np.sort(rng.choice(cal_rows, n_select, replace=False))
    out = {"n_candidates": int(cal_rows.size), "n_selected": int(n_select),
           "n_validation": int(meas.val.sum())}
    for name, rows in picks.items():
        sub = _subset(df, cal_rows, rows)
        out[name] = {**_fitted(sub, meta, effects, sigma_m, where),
                     "cal_points": int(rows.size),
                     "forces_N": sorted(set(np.round(sub["F_N"].to_numpy()[
                         (sub["split"] == "cal").to_numpy()], 3).tolist())) if "F_N" in sub else []}
    for name, rows in picks.items():
        out[name]["mean_prediction_variance"] = mean_prediction_variance(blocks[rows], region)
    out["selected_rows"] = {k: picks[k].tolist() for k in gains}
    return out


def fraction_study(df, meta, effects, fractions, sigma_m: float, rng: np.random.Generator,
                   n_random: int = 8, where: str = "data", clean=None) -> pd.DataFrame:
    """Where the selection matters: per fraction of the calibration points, the D- and
    I-optimal subsets against ``n_random`` random subsets of the same size (drawn by ``rng``),
    each fitted and validated on every validation row (``clean``: the same campaign read
    without the interferometers' noise, for ``truth_err90_nm``, see ``_fitted``). One row per
    fitted subset: fraction, selection ("all", "D_optimal", "I_optimal", "random"), draw,
    points, mean_prediction_variance (over the planned points, noise variances), log_det (of
    the information), val_err90_nm, [truth_err90_nm], identified_directions, status ("ok" or
    why the fit stopped or could not start)."""
    model, meas, cal_rows, blocks, region = _plan_blocks(df, meta, effects, sigma_m, where)
    rows_out = []

    def record(fraction, selection, draw, rows):
        rows_out.append({"fraction": fraction, "selection": selection, "draw": draw,
                         "points": int(rows.size),
                         "mean_prediction_variance": mean_prediction_variance(blocks[rows],
                                                                              region),
                         "log_det": log_det_information(blocks[rows]),
                         **_fitted(_subset(df, cal_rows, rows), meta, effects, sigma_m, where,
                                   None if clean is None else _subset(clean, cal_rows, rows))})

    record(1.0, "all", 0, cal_rows)
    for fraction in fractions:
        n = max(int(round(fraction * cal_rows.size)), 1)
        for crit in ("D", "I"):
            order, _ = greedy_selection(blocks[cal_rows], n, crit, region)
            record(fraction, f"{crit}_optimal", 0, cal_rows[order])
        for k in range(n_random):
            record(fraction, "random", k, np.sort(rng.choice(cal_rows, n, replace=False)))
    return pd.DataFrame(rows_out)


def fraction_summary(study: pd.DataFrame, error: str = "val_err90_nm") -> pd.DataFrame:
    """Per fraction and optimal criterion: its subset's ``error`` (a column of the study) and
    prediction variance beside the random subsets' median and range (of those that could be
    fitted), and the share of random subsets that did worse (better than every random draw:
    1.0; a random subset the model cannot be fitted to counts as worse)."""
    full = float(study.loc[study.selection == "all", error].iloc[0])
    out = []
    for fraction, g in study[study.selection != "all"].groupby("fraction", sort=False):
        r = g[g.selection == "random"]
        for _, d in g[g.selection.str.endswith("_optimal")].iterrows():
            out.append({"fraction": fraction, "selection": d.selection, "points": int(d.points),
                        "error_nm": d[error], "x_full": d[error] / full,
                        "random_median_nm": float(r[error].median()),
                        "random_min_nm": float(r[error].min()),
                        "random_max_nm": float(r[error].max()),
                        "random_median_x_full": float(r[error].median()) / full,
                        "random_worse_share": float(np.mean(~(r[error] <= d[error]))),
                        "random_failed": int(r[error].isna().sum()),
                        "prediction_variance": d.mean_prediction_variance,
                        "random_prediction_variance_median":
                            float(r.mean_prediction_variance.median()),
                        "random_draws": len(r)})
    return pd.DataFrame(out)


def load_level_study(df, meta, effects, n_levels: int, sigma_m: float, where: str = "data",
                     clean=None) -> pd.DataFrame:
    """Which load levels: every subset of ``n_levels`` of the campaign's force levels (all its
    calibration positions at those levels), ranked by the D criterion (log det of the
    information, from the plan alone), each fitted and validated on every validation row (all
    levels), beside the campaign's own levels (``clean``: see ``fraction_study``). Columns:
    levels_N, points, log_det, mean_prediction_variance, val_err90_nm, [truth_err90_nm],
    identified_directions, status."""
    model, meas, cal_rows, blocks, region = _plan_blocks(df, meta, effects, sigma_m, where)
    if "F_N" not in df:
        raise ValueError(f"{where}: no F_N column: a load-level study needs a force campaign")
    F = np.round(df["F_N"].to_numpy()[cal_rows], 6)
    levels = sorted(set(F.tolist()))
    if not 0 < n_levels <= len(levels):
        raise ValueError(f"n_levels = {n_levels}: the campaign has {len(levels)} load levels")
    out = []
    subsets = list(itertools.combinations(levels, n_levels))
    if n_levels < len(levels):
        subsets.append(tuple(levels))
    for subset in subsets:
        rows = cal_rows[np.isin(F, subset)]
        out.append({"levels_N": list(subset), "points": int(rows.size),
                    "log_det": log_det_information(blocks[rows]),
                    "mean_prediction_variance": mean_prediction_variance(blocks[rows], region),
                    **_fitted(_subset(df, cal_rows, rows), meta, effects, sigma_m, where,
                              None if clean is None else _subset(clean, cal_rows, rows))})
    return pd.DataFrame(out).sort_values("log_det", ascending=False, ignore_index=True)


def order_study(scenario, effect_sets: dict, scale: float, seeds,
                sigma_m: float) -> pd.DataFrame:
    """Order and interleaving of a force campaign: the papers' order (the calibration grid,
    then the validation grid) against the two merged in proportion, per seed and per fitted
    model (``effect_sets``: {label: effects}). Per case the validation error, the error
    against the same campaign read without random errors (truth_err90_nm, see ``_fitted``),
    and from the plan's conditions alone the mean prediction variance over the validation
    points (what the order changes: the conditions, times and temperatures, validation meets
    relative to those calibration saw). Columns: order, model, seed,
    validation_prediction_variance, val_err90_nm, truth_err90_nm, identified_directions,
    status."""
    from deltatwin.calibration.design.budget import without_random_errors
    from deltatwin.twin.scenario import Scenario

    out = []
    for seed in seeds:
        base = Scenario.load(scenario, seed=int(seed))
        if base.campaign.get("kind") != "force":
            raise ValueError(f"{scenario}: the order study needs a force campaign "
                             f"([campaign] kind = 'force')")
        for order in ("papers", "interleaved"):
            sc = dataclasses.replace(base, campaign={**base.campaign, "order": order})
            df, meta = sc.simulate(scale)
            clean = without_random_errors(sc).simulate(scale)[0]
            for label, effects in effect_sets.items():
                _, meas, cal_rows, blocks, region = _plan_blocks(df, meta, effects, sigma_m,
                                                                 "data")
                out.append({"order": order, "model": label, "seed": int(seed),
                            "validation_prediction_variance": mean_prediction_variance(
                                blocks[cal_rows], region[np.flatnonzero(meas.val)]),
                            **_fitted(df, meta, effects, sigma_m, "data", clean)})
    return pd.DataFrame(out)
