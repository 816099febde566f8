"""Error figures of a sample of errors and the disjointness of calibration and validation
points, shared by the black-box and the physics paths.

Two 90 % figures are reported, labelled as such, because the papers equate them and real
errors need not be normal:

* ``err_1645sigma``: 1.645 x the sample standard deviation (ddof = 1) of the error — the
  papers' "90 % (1.645 sigma)";
* ``err_p90``: the empirical 90th percentile of |error|.

The mean error is reported too (1.645 sigma ignores a bias, the percentile does not).
"""
from __future__ import annotations

import math

import numpy as np
import pandas as pd

from deltatwin.calibration.errors import ValidationOverlapError

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


