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

import numpy as np

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


def selection_study(df, meta, effects, n_select: int, sigma_m: float, rng: np.random.Generator,
                    where: str = "data") -> dict:
    """The validation error (90 %, nm) of ``effects`` fitted to all calibration rows of a
    campaign, to ``n_select`` of them chosen D- and I-optimally (from the plan's conditions
    alone; the I criterion's region is the campaign's planned points), and to ``n_select`` drawn
    at random by ``rng``; the validation rows are the same for all. Each entry also gives the
    mean prediction variance over the region (in units of the noise's variance).
    ``sigma_m``: the readings' noise (m) the selection weighs the information with."""
    from deltatwin.calibration.physics.fit import PhysicsFit
    from deltatwin.calibration.physics.measurements import measurements

    model = PhysicsModel(effects)
    meas = measurements(df, meta, model.params, where)
    cal_rows = np.flatnonzero(meas.cal)
    blocks = information_blocks(model, meas, sigma_m, np.arange(meas.n))
    # the region the model serves: the planned points themselves, zeros left out (a zero is a
    # nuisance, not a prediction)
    region = blocks.copy()
    region[:, :, model.n_free:] = 0.0
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
        keep = np.ones(len(df), bool)
        keep[cal_rows] = False
        keep[rows] = True
        sub = df.iloc[np.flatnonzero(keep)]
        fit = PhysicsFit(effects, noise_nm=sigma_m * 1e9).fit(sub, meta, where=where)
        out[name] = {"val_err90_nm": fit.val_["all"]["err_p90"],
                     "cal_points": int(rows.size),
                     "identified_directions": fit.identifiability_["n_identified_directions"],
                     "forces_N": sorted(set(np.round(sub["F_N"].to_numpy()[
                         (sub["split"] == "cal").to_numpy()], 3).tolist())) if "F_N" in sub else []}
    for name, rows in picks.items():
        out[name]["mean_prediction_variance"] = mean_prediction_variance(blocks[rows], region)
    out["selected_rows"] = {k: picks[k].tolist() for k in gains}
    return out
