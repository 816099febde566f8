"""Validation of black-box models: error figures per output on the validation rows, and the
papers' ladder (refits with growing feature sets)."""
from __future__ import annotations

import warnings

import numpy as np
import pandas as pd

from deltatwin.calibration.errors import NoValidationWarning
from deltatwin.calibration.metrics import error_figures

__all__ = ["evaluate", "ladder"]

SIGMA_90 = 1.645


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
    from deltatwin.calibration.blackbox.direct_igm import DirectIGM
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
    from deltatwin.calibration.blackbox.dgm import DGM
    from deltatwin.calibration.blackbox.direct_igm import DirectIGM
    from deltatwin.calibration.blackbox.estimator import thermal_sensors
    from deltatwin.calibration.blackbox.features import force_ladder, thermal_ladder
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
