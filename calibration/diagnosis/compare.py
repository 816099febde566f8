"""Compare a model with measurements and see where it fails (``deltatwin compare``).

The model is a physics model (``calibration.physics.model.PhysicsModel``, e.g. from a fitted-model
TOML via ``load_fitted``) or a stepwise DGM (``calibration.blackbox.dgm.DGM``, a ``model.json``).
Readings are relative to each session's zero and a new campaign has new zeros, so every
(session, axis) zero is re-estimated on the dataset's calibration rows (``physics.readings.
session_zeros``); a session without calibration readings takes its zero from its own
(validation) rows, and the output says so.

Sign convention (as ``deltatwin view``'s arrows): **residual = model minus measurement**, the
model's reading (prediction + re-estimated zero) minus the measured reading.

``compare`` returns, JSON-ready, the residual statistics per axis (calibration and validation
splits), and on the chosen rows (default: the validation split) the error broken down by
workspace region (octants of the platform's nominal kinematic position about the centre of
the positions' bounding box), time window (equal windows of ``t_s`` over those rows' span),
force level (``F_N``)
and each recorded variable (temperatures, their causal rates, motor coordinates, coil
currents, autocollimator angles, pressure: quantile bins, or one bin per value when a variable
takes few values), with the worst regions and time windows listed. Units: SI inside, nm (and
the variables' units, named) in the output.
"""
from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from deltatwin.calibration.blackbox.features import temperature_variables
from deltatwin.calibration.diagnosis.conditions import (
    extrapolated_variables,
    extrapolation_message,
)
from deltatwin.calibration.diagnosis.floor import floor_of
from deltatwin.calibration.errors import CalibrationInputError
from deltatwin.calibration.physics.band import prediction_band
from deltatwin.calibration.physics.measurements import Measurements, check_sensors, measurements
from deltatwin.calibration.physics.model import PhysicsModel, figures_nm, residuals
from deltatwin.calibration.physics.model_file import load_fitted, saved_uncertainty
from deltatwin.calibration.physics.readings import session_zeros
from deltatwin.calibration.stats import AT_FLOOR
from deltatwin.calibration.streams import DEFAULT_WINDOW_S
from deltatwin.models.geometry import build_geometry
from deltatwin.models.kinematics import forward
from deltatwin.models.params import RobotParams, load_params
from deltatwin.twin.dataset import AXES, temperature_columns

__all__ = ["ModelEvaluation", "evaluate", "compare", "load_model_file",
           "load_model_and_covariance", "dgm_reading_m",
           "RESIDUAL_SIGN"]

RESIDUAL_SIGN = "model minus measurement"
NM_PER_M = 1e9
RATE_K_PER_H = 3600.0                     # K/s -> K/h
RATE_WINDOW_S = DEFAULT_WINDOW_S          # causal linear fit over the past 600 s
_RECORDED = re.compile(r"^(q[123]_rad|coil\d+_A|ac\d+_r[xyz]_arcsec|p_Pa)$")


@dataclass
class ModelEvaluation:
    """A model on a dataset, with the session zeros re-estimated on the dataset.

    ``reading_m`` (N,3): the model's reading in the dataset's zeroed frame (prediction + the
    (session, axis) zero), NaN where no measured reading or no prediction. ``residual_m``
    (N,3): ``reading_m`` minus the measured reading (m). ``offsets_m``: zero per
    ``meas.groups`` entry; ``zero_rows``: the rows each zero was estimated on (``"cal"``, or
    ``"own rows"`` for a session without calibration readings). ``position_m`` (N,3): the
    platform's nominal kinematic position (base frame) at each row's motor coordinates."""
    description: dict
    meas: Measurements
    reading_m: np.ndarray
    residual_m: np.ndarray
    offsets_m: np.ndarray
    zero_rows: list
    position_m: np.ndarray


def _at_floor(axes: dict, floor: dict | None, kind: str) -> dict | None:
    """Per axis: whether the error 90 % is within AT_FLOOR of the floor ({axis: bool}, with the
    floor's kind), None without a floor."""
    if not floor:
        return None
    out = {a: bool(r["err_p90_nm"] <= AT_FLOOR * floor[a]) for a, r in axes.items()
           if a in floor and r.get("err_p90_nm") is not None}
    return {"kind": kind, "factor": AT_FLOOR, "axes": out}


# ---------------------------------------------------------------------------------------------
# models

def load_model_file(path, trust_effects=False):
    """A model from a file: a fitted physics model (``.toml``, ``deltatwin fit -o``) or a DGM
    (``.json``, ``deltatwin calibrate -o``). Raises ValueError naming the file otherwise. The
    user effects a physics model names run only with ``trust_effects`` (``load_fitted``)."""
    from deltatwin.calibration.blackbox.dgm import DGM
    from deltatwin.calibration.blackbox.model_file import load_model
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in (".toml", ".json"):
        raise CalibrationInputError(f"{path}: unknown model file type {path.suffix!r}; expected "
                                    "a fitted physics model (.toml) or a DGM (.json)")
    if not path.is_file():
        raise CalibrationInputError(f"{path}: no such model file")
    if suffix == ".toml":
        return load_fitted(path, trust_effects)[0]
    model = load_model(path)
    if not isinstance(model, DGM):
        raise CalibrationInputError(f"{path}: holds a {model.kind}, which predicts motor "
                                    "coordinates, not readings; compare takes a fitted physics "
                                    "model (.toml) or a DGM (.json)")
    return model


def load_model_and_covariance(path, trust_effects=False):
    """(model, covariance): ``load_model_file``'s model and, for a fitted physics model whose
    file holds its [uncertainty], its parameters' covariance (p, p; SI), else None."""
    if Path(path).suffix.lower() != ".toml" or not Path(path).is_file():
        return load_model_file(path, trust_effects), None
    model, doc = load_fitted(path, trust_effects)
    return model, saved_uncertainty(doc, model)[1]


def dgm_reading_m(model, df: pd.DataFrame) -> np.ndarray:
    """(N,3) a DGM's predicted readings (m) for x, y, z; NaN on axes it has no output for and on
    rows with a missing input."""
    reading = np.full((len(df), 3), np.nan)
    pred = model.predict(df)
    for k, out in enumerate(model.output_names_):
        reading[:, AXES.index(out)] = pred[:, k]
    return reading


def evaluate(df: pd.DataFrame, meta: dict | None, model, params=None) -> ModelEvaluation:
    """Evaluate ``model`` (PhysicsModel or DGM) on a dataset and re-estimate the zeros.

    ``params``: robot parameters (RobotParams or file) for a DGM's kinematic positions
    (default: nominal; a physics model uses its own)."""
    from deltatwin.calibration.blackbox.dgm import DGM
    df = df.reset_index(drop=True)
    if isinstance(model, PhysicsModel):
        meas = measurements(df, meta, model.params)
        check_sensors(model.names, meas)
        pred = model.predict_path(meas)
        robot = model.params
        desc = {"kind": "physics", "effects": list(model.names), "n_parameters": model.n_free,
                "sensors": dict(meas.sensors)}
    elif isinstance(model, DGM):
        robot = params if isinstance(params, RobotParams) else load_params(params)
        # the DGM reads its own temperature columns; the physics sensor map is not needed
        meas = measurements(df, {**(meta or {}), "sensors": {}}, robot)
        pred = dgm_reading_m(model, df)
        desc = {"kind": "DGM", "features": model.features_.preset or model.features_.name,
                "outputs": list(model.output_names_), "sensors": list(model.sensors_),
                "n_candidate_terms": len(model.features_)}
    else:
        raise CalibrationInputError(f"compare: a {type(model).__name__} is not a model to "
                                    "compare (a PhysicsModel or a DGM)")
    # every (session, axis) zero on the calibration rows; a group without any there, on its own
    offsets, on_cal = session_zeros(meas, pred)
    residual = -residuals(meas, pred, offsets)              # model minus measurement
    reading = meas.y + residual
    position = forward(build_geometry(robot), meas.points.q[:meas.n]).p
    return ModelEvaluation(description=desc, meas=meas, reading_m=reading,
                           residual_m=residual, offsets_m=offsets,
                           zero_rows=["cal" if c else "own rows" for c in on_cal],
                           position_m=position)


# ---------------------------------------------------------------------------------------------
# statistics

def _num(v):
    """JSON-ready float (None for NaN / inf)."""
    v = float(v)
    return v if np.isfinite(v) else None


def _figures(fig: dict) -> dict:
    return {"n": fig["n"], "mean_nm": fig["mean"], "sigma_nm": fig["sigma"],
            "err_p90_nm": fig["err_p90"], "err_1645sigma_nm": fig["err_1645sigma"],
            "max_abs_nm": fig["max_abs"]}


def _long(residual_nm: np.ndarray, rows: np.ndarray) -> pd.DataFrame:
    """One line per finite (row, axis) residual of the selected rows: row, axis, res, abs."""
    idx = np.flatnonzero(rows)
    r = residual_nm[idx]
    ok = np.isfinite(r)
    ri, ai = np.nonzero(ok)
    return pd.DataFrame({"row": idx[ri], "axis": np.asarray(AXES)[ai], "res": r[ok],
                         "abs": np.abs(r[ok])})


def _by_bin(long: pd.DataFrame, codes: np.ndarray, labels: list[dict]) -> list[dict]:
    """Statistics per bin (``codes`` per dataset row, -1 = no bin): n readings, err_p90 and
    mean pooled over the axes, and per axis."""
    g = long.assign(bin=codes[long["row"].to_numpy()])
    g = g[g["bin"] >= 0]
    by_bin = g.groupby("bin")["abs"]
    pooled = pd.DataFrame({"n": by_bin.size(), "err_p90_nm": by_bin.quantile(0.9)})
    by_axis = g.groupby(["bin", "axis"])
    per = pd.DataFrame({"n": by_axis.size(), "err_p90_nm": by_axis["abs"].quantile(0.9),
                        "mean_nm": by_axis["res"].mean()})
    out = []
    for b, lab in enumerate(labels):
        entry = dict(lab)
        entry["n"] = int(pooled["n"].get(b, 0))
        entry["err_p90_nm"] = _num(pooled["err_p90_nm"].get(b, np.nan))
        entry["by_axis"] = {a: {"n": int(per.loc[(b, a), "n"]),
                                "err_p90_nm": _num(per.loc[(b, a), "err_p90_nm"]),
                                "mean_nm": _num(per.loc[(b, a), "mean_nm"])}
                            for a in AXES if (b, a) in per.index}
        out.append(entry)
    return out


def _value_bins(values: np.ndarray, rows: np.ndarray, n_bins: int):
    """Bins of a variable over the selected rows: one per value if it takes at most
    ``n_bins`` values there, else ``n_bins`` quantile bins (fewer where quantiles coincide;
    intervals (lo, hi], the first closed). Returns (codes per row, labels),
    or None if the variable has fewer than two distinct finite values on those rows."""
    v = np.asarray(values, dtype=np.float64)
    finite = rows & np.isfinite(v)
    distinct = np.unique(v[finite])
    codes = np.full(v.size, -1)
    if distinct.size < 2:
        return None
    if distinct.size <= n_bins:
        codes[finite] = np.searchsorted(distinct, v[finite])
        return codes, [{"value": float(x)} for x in distinct]
    edges = np.unique(np.quantile(v[finite], np.linspace(0.0, 1.0, n_bins + 1)))
    # intervals (lo, hi], the first one closed on the left
    codes[finite] = np.clip(np.searchsorted(edges, v[finite], side="left") - 1, 0,
                            edges.size - 2)
    return codes, [{"lo": float(lo), "hi": float(hi)} for lo, hi in zip(edges[:-1], edges[1:])]


def _octants(position_m: np.ndarray, rows: np.ndarray):
    """Octant of each row's platform position about the centre of the bounding box of the
    selected rows' positions: codes and labels such as ``x+y-z+``."""
    p = position_m[rows]
    centre = (p.min(axis=0) + p.max(axis=0)) / 2.0
    bits = (position_m > centre).astype(int)
    codes = np.where(rows, bits @ np.array([4, 2, 1]), -1)
    labels = [{"region": "".join(f"{a}{'+' if (o >> (2 - k)) & 1 else '-'}"
                                 for k, a in enumerate(AXES))} for o in range(8)]
    return codes, labels, centre


def _time_windows(t_s: np.ndarray, rows: np.ndarray, n_windows: int):
    """Equal windows of time over the selected rows' span: codes and labels."""
    edges = np.linspace(t_s[rows].min(), t_s[rows].max(), n_windows + 1)
    codes = np.clip(np.searchsorted(edges, t_s, side="right") - 1, 0, n_windows - 1)
    labels = [{"window": k, "t_from_s": float(edges[k]), "t_to_s": float(edges[k + 1])}
              for k in range(n_windows)]
    return np.where(rows, codes, -1), labels


def recorded_variables(df: pd.DataFrame, window_s: float = RATE_WINDOW_S) -> dict:
    """The recorded conditions a residual can depend on, name (unit in it) -> (N,) values:
    every ``T_<s>_C``, its causal rate ``dT_<s>_K_per_h`` (local linear fit over the past
    ``window_s`` of the same session, ``features.temperature_variables``), motor coordinates,
    coil currents, autocollimator angles and pressure when recorded."""
    out = {}
    tcols = temperature_columns(df)
    sensors = [c[2:-2] for c in tcols]
    rates = temperature_variables(df, sensors, {f"dT_{s}" for s in sensors}, 293.15,
                                  window_s, degree=1) if sensors else {}
    for c, s in zip(tcols, sensors):
        out[c] = df[c].to_numpy(dtype=np.float64)
        out[f"dT_{s}_K_per_h"] = rates[f"dT_{s}"] * RATE_K_PER_H
    for c in df.columns:
        if _RECORDED.match(c):
            out[c] = pd.to_numeric(df[c], errors="coerce").to_numpy(dtype=np.float64)
    return out


def _worst(bins: list[dict], key: str, overall: float | None, n_worst: int,
           min_readings: int) -> list[dict]:
    ok = [b for b in bins if b["n"] >= min_readings and b["err_p90_nm"] is not None]
    ok.sort(key=lambda b: -b["err_p90_nm"])
    return [{key: b[key], "err_p90_nm": b["err_p90_nm"], "n": b["n"],
             "times_overall": _num(b["err_p90_nm"] / overall) if overall else None,
             **({k: b[k] for k in ("t_from_s", "t_to_s") if k in b})}
            for b in ok[:n_worst]]


def _by_variable(df: pd.DataFrame, long, rows: np.ndarray, n_bins: int,
                 min_readings: int) -> tuple[dict, list]:
    """({variable: {bins, p90_ratio_max_min}}, [the variables constant on ``rows``]): the
    residual ``long`` (``_long``) in ``n_bins`` quantile bins of each recorded variable, and
    the ratio of its largest to its smallest bin's 90 % error over bins of at least
    ``min_readings`` readings."""
    variables, constant = {}, []
    for name, values in recorded_variables(df).items():
        binned = _value_bins(values, rows, n_bins)
        if binned is None:
            constant.append(name)
            continue
        bins = _by_bin(long, *binned)
        p90 = [b["err_p90_nm"] for b in bins if b["n"] >= min_readings and b["err_p90_nm"]]
        variables[name] = {"bins": bins,
                           "p90_ratio_max_min": _num(max(p90) / min(p90)) if len(p90) > 1
                           else None}
    return variables, constant


def _validation_band(ev: ModelEvaluation, model, covariance: np.ndarray | None,
                     rng: np.random.Generator | None = None) -> dict | None:
    """{axis or "all": {"low", "high", "within"}} (nm): the 95 % band the validation error 90 %
    of a physics ``model`` of parameter ``covariance`` falls in on the evaluated data ``ev``
    if the model is right (calibration/physics/band.py ``prediction_band``: the parameters'
    uncertainty through the model's Jacobian on these data, the readings' noise as these
    data's calibration residual under the model shows it), and whether the validation error
    lies within it; None for a DGM, without a covariance or without validation rows."""
    if covariance is None or not isinstance(model, PhysicsModel) or not ev.meas.val.any():
        return None
    covariance = np.asarray(covariance, dtype=float)
    if covariance.shape != (model.n_free, model.n_free):
        raise CalibrationInputError(f"covariance {covariance.shape}: expected "
                                    f"({model.n_free}, {model.n_free}), one row per parameter")
    J = model.jacobian(ev.meas, model.theta())[1]
    rng = rng if rng is not None else np.random.default_rng(0)
    # the fit's residual convention (measurement minus model): the fit's own band, draw for draw
    band = prediction_band(ev.meas, J, covariance, -ev.residual_m, rng)
    val = figures_nm(ev.residual_m, ev.meas.val)
    out = {}
    for a, (lo, hi) in band.items():
        err = (val.get(a) or {}).get("err_p90")
        out[a] = {"low": lo, "high": hi,
                  "within": None if err is None else bool(lo <= err <= hi)}
    return out


def _floors_and_conditions(df: pd.DataFrame, meta: dict | None, ev: ModelEvaluation,
                           judged_axes: dict) -> dict:
    """What compare says beside the residual: the twin's floors and their budget, whether the
    error figures ``judged_axes`` are at the floor, the conditions the validation rows
    extrapolate to, and the temperature columns the model does not use."""
    truth = (meta or {}).get("truth") or {}
    judged, kind = floor_of(meta)
    extrapolated = extrapolated_variables(df)
    used_T = set(ev.description["sensors"])
    return {"noise_floor_nm": truth.get("noise_floor_nm"),
            "achievable_floor_nm": truth.get("achievable_floor_nm"),
            "floor_budget_nm": truth.get("floor_budget_nm"),
            "at_floor": _at_floor(judged_axes, judged, kind),
            "extrapolation": {"variables": extrapolated,
                              "message": extrapolation_message(extrapolated)},
            "unused_temperature_columns": [c for c in temperature_columns(df)
                                           if c[2:-2] not in used_T]}


def compare(df: pd.DataFrame, meta: dict | None, model, *, split: str = "val",
            n_time_windows: int = 8, n_bins: int = 5, n_worst: int = 3,
            min_readings: int = 10, params=None, covariance: np.ndarray | None = None,
            rng: np.random.Generator | None = None) -> dict:
    """Where ``model`` fails on a dataset: JSON-ready dict (see the module docstring).

    ``split``: the rows the breakdowns use, ``"val"`` (default), ``"cal"`` or ``"all"``.
    ``n_time_windows``: equal windows of ``t_s``. ``n_bins``: quantile bins per variable.
    ``n_worst``: length of the worst lists, over bins with at least ``min_readings``
    (row, axis) readings. ``params``: robot parameters for a DGM's positions (default nominal).
    ``covariance`` (p, p; SI): a physics model's parameter covariance (a fitted model file's
    [uncertainty]): the validation error's 95 % band is drawn with ``rng`` (default seeded 0)
    on these data (``_validation_band``).
    """
    if split not in ("val", "cal", "all"):
        raise CalibrationInputError(f"split {split!r}: expected 'val', 'cal' or 'all'")
    if n_time_windows < 1 or n_bins < 2:
        raise CalibrationInputError(f"n_time_windows = {n_time_windows} must be >= 1 and "
                                    f"n_bins = {n_bins} >= 2")
    df = df.reset_index(drop=True)
    ev = evaluate(df, meta, model, params)
    meas = ev.meas
    rows = {"val": meas.val, "cal": meas.cal, "all": np.ones(meas.n, bool)}[split]
    res_nm = ev.residual_m * NM_PER_M
    if not np.isfinite(res_nm[rows]).any():
        raise CalibrationInputError(f"compare: no {split!r} row has both a reading and a "
                                    "prediction" + (" (use split 'all' for data without "
                                                    "validation rows)" if split == "val" else ""))
    long = _long(res_nm, rows)
    splits = {"cal": meas.cal, "val": meas.val, **({"all": rows} if split == "all" else {})}
    axes = {s: {k: _figures(v) for k, v in figures_nm(ev.residual_m, r).items()}
            for s, r in splits.items() if r.any()}
    overall = axes[split]["all"]["err_p90_nm"]

    codes, labels, centre = _octants(ev.position_m, rows)
    regions = _by_bin(long, codes, labels)
    codes, labels = _time_windows(meas.points.t_s[:meas.n], rows, n_time_windows)
    windows = _by_bin(long, codes, labels)
    force = None
    if "F_N" in df.columns:
        binned = _value_bins(df["F_N"].to_numpy(dtype=np.float64), rows, 12)
        force = _by_bin(long, *binned) if binned else None
    variables, constant = _by_variable(df, long, rows, n_bins, min_readings)
    spread = sorted((v["p90_ratio_max_min"], k) for k, v in variables.items()
                    if v["p90_ratio_max_min"] is not None)[::-1]
    return {
        "model": ev.description,
        "residual": f"{RESIDUAL_SIGN} (nm): the model's reading, with each (session, axis) zero "
                    "re-estimated on this dataset, minus the measured reading",
        "zeros": {"note": "a new campaign has new zeros: each (session, axis) zero offset was "
                          "re-estimated on this dataset's calibration rows",
                  "offsets_nm": {f"{s}.{a}": _num(o * NM_PER_M)
                                 for (s, a), o in zip(meas.groups, ev.offsets_m)},
                  "estimated_on": {f"{s}.{a}": w for (s, a), w in zip(meas.groups, ev.zero_rows)}},
        "rows": split,
        **_floors_and_conditions(df, meta, ev, axes.get("val") or axes.get(split) or {}),
        "axes": axes,
        "validation_band_95_nm": _validation_band(ev, model, covariance, rng),
        "regions": {"scheme": "octants of the platform's nominal kinematic position about the "
                              "centre of the bounding box of the rows' positions",
                    "centre_mm": [float(c * 1e3) for c in centre], "bins": regions},
        "time_windows": {"n": n_time_windows, "bins": windows},
        "force": {"column": "F_N", "bins": force} if force is not None else None,
        "variables": variables,
        "constant_variables": constant,
        "worst": {"regions": _worst(regions, "region", overall, n_worst, min_readings),
                  "time_windows": _worst(windows, "window", overall, n_worst, min_readings),
                  "variables": [{"variable": k, "p90_ratio_max_min": r}
                                for r, k in spread[:n_worst]]},
    }
