"""Validation: error figures per output, disjointness of the splits, and the papers' ladder.

Two 90 % figures are reported, labelled as such, because the papers equate them and real
errors need not be normal:

* ``err_1645sigma``: 1.645 x the sample standard deviation (ddof = 1) of the error — the
  papers' "90 % (1.645 sigma)";
* ``err_p90``: the empirical 90th percentile of |error|.

The mean error is reported too (1.645 sigma ignores a bias, the percentile does not).
"""
from __future__ import annotations

import math
import warnings

import numpy as np
import pandas as pd

from .errors import NoValidationWarning, ValidationOverlapError

__all__ = ["error_figures", "check_disjoint", "evaluate", "ladder", "SIGMA_90"]

SIGMA_90 = 1.645


def error_figures(err, scale: float = 1e9) -> dict:
    """Figures of an error sample (SI) in the unit ``scale`` converts to (default nm)."""
    e = np.asarray(err, dtype=float).ravel()
    e = e[np.isfinite(e)] * scale
    n = int(e.size)
    if n == 0:
        return {"n": 0, "mean": None, "sigma": None, "err_1645sigma": None, "err_p90": None,
                "max_abs": None}
    sigma = float(np.std(e, ddof=1)) if n > 1 else math.nan
    return {"n": n, "mean": float(e.mean()), "sigma": sigma,
            "err_1645sigma": SIGMA_90 * sigma, "err_p90": float(np.percentile(np.abs(e), 90)),
            "max_abs": float(np.abs(e).max())}


def check_disjoint(df: pd.DataFrame, coord_cols=("q1_rad", "q2_rad", "q3_rad"),
                   resolution: float = 1e-10) -> None:
    """Raise :class:`ValidationOverlapError` if a validation position is also a calibration
    position: the same ``pos_id`` in both splits, or the same coordinates (to ``resolution``,
    in the columns' unit) under different ids."""
    if "split" not in df.columns:
        return
    split = df["split"].astype(str).to_numpy()
    cal, val = split == "cal", split == "val"
    if not val.any() or not cal.any():
        return
    if "pos_id" in df.columns:
        both = np.intersect1d(df["pos_id"].to_numpy()[cal], df["pos_id"].to_numpy()[val])
        if both.size:
            raise ValidationOverlapError(
                f"{both.size} position id(s) appear in both 'cal' and 'val' (e.g. "
                f"{both[:5].tolist()}): validation positions must be disjoint from calibration")
    if all(c in df.columns for c in coord_cols):
        key = np.round(df[list(coord_cols)].to_numpy(dtype=float) / resolution)
        kc = {tuple(r) for r in key[cal] if np.all(np.isfinite(r))}
        common = [tuple(r) for r in key[val] if tuple(r) in kc]
        if common:
            ex = [tuple(float(v) * resolution for v in r) for r in common[:3]]
            raise ValidationOverlapError(
                f"{len(set(common))} validation position(s) have the same coordinates "
                f"{list(coord_cols)} as calibration positions (e.g. {ex}): validation "
                "positions must be disjoint from calibration")


def _splits(df):
    if "split" not in df.columns:
        return {"cal": np.ones(len(df), bool)}
    s = df["split"].astype(str).to_numpy()
    return {"cal": s == "cal", "val": s == "val"}


def evaluate(model, df: pd.DataFrame) -> dict:
    """Error figures of a fitted model on the cal and val rows of ``df``.

    DGM: per axis, error = prediction - reading (nm).  DirectIGM: per motor, the error in
    µrad and expressed at the end-effector in nm (|dq_i| x ||column i of (dq/dX)^-1||), and
    per Cartesian axis the end-effector error J^-1 (q_pred - q_meas) in nm.
    """
    from .models import DirectIGM
    model._check_fitted()
    masks = _splits(df)
    if "val" not in masks or not masks["val"].any():
        warnings.warn("no validation rows ('split' == 'val'): validation figures are None",
                      NoValidationWarning, stacklevel=2)
    out = {"kind": model.kind, "features": model.features_.name,
           "n_candidates": len(model.features_), "outputs": {}}
    pred = model.predict(df)
    targ = model.targets(df)
    if isinstance(model, DirectIGM):
        at_eff = model.motor_error_at_effector(df)
        pos_err = model.position_error(df) if model.output_names_ == ["q1", "q2", "q3"] \
            else None
    for i, om in enumerate(model.outputs_):
        err = pred[:, i] - targ[:, i]
        rec = {"terms_kept": om.terms_kept}
        for name in ("cal", "val"):
            m = masks.get(name, np.zeros(len(df), bool)) & np.isfinite(err)
            if isinstance(model, DirectIGM):
                rec[name] = error_figures(at_eff[m, i], 1e9)
                rec[name + "_urad"] = error_figures(err[m], 1e6)
            else:
                rec[name] = error_figures(err[m], 1e9)
        rec["unit"] = "nm"
        out["outputs"][om.output] = rec
    if isinstance(model, DirectIGM) and pos_err is not None:
        out["position"] = {}
        for j, ax in enumerate("xyz"):
            out["position"][ax] = {
                name: error_figures(pos_err[masks.get(name, np.zeros(len(df), bool)), j], 1e9)
                for name in ("cal", "val")}
    return out


def ladder(df: pd.DataFrame, meta: dict | None, kind: str = "thermal", **model_kw) -> list:
    """The papers' ladder: refit with growing feature sets and report, per output, the terms
    kept and the errors.  ``kind``: ``"thermal"`` (geometric only; Set A: + temperatures;
    Set B: + temperature x geometric; Set C: complete) or ``"force"`` (geometric only; with
    force terms).  ``model_kw`` go to the model's constructor (sensors, penter, ...)."""
    from .features import force_ladder, thermal_ladder
    from .models import DGM, DirectIGM, thermal_sensors
    if kind == "thermal":
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")   # the full fit already warned about metadata
            sensors = thermal_sensors(df, meta, model_kw.pop("sensors", None))
        rungs = thermal_ladder(sensors)
        cls = DGM
    elif kind == "force":
        rungs = force_ladder()
        model_kw.pop("sensors", None)
        cls = DirectIGM
    else:
        raise ValueError(f"ladder: kind {kind!r} must be 'thermal' or 'force'")
    result = []
    for name, fs in rungs:
        model = cls(features=fs, **model_kw).fit(df, meta)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", NoValidationWarning)
            ev = evaluate(model, df)
        result.append({"name": name, "n_candidates": len(fs), "outputs": ev["outputs"],
                       "position": ev.get("position")})
    return result
