"""Whether validation rows lie inside the conditions the calibration rows covered: a model
checked outside its calibration range extrapolates, and a candidate effect judged there is
judged on extrapolation (with the air conditioning off, the force plan's validation grid
comes after its calibration grid, warmer)."""
from __future__ import annotations

import numpy as np
import pandas as pd

from deltatwin.twin.dataset import temperature_columns

OUTSIDE_FRACTION = 0.1   # flagged beyond 10 % of the calibration span past either end
CONDITIONS = ("F_N", "coil1_A", "coil2_A", "coil3_A", "p_Pa", "RH_pct")


def extrapolated_variables(df: pd.DataFrame) -> list[dict]:
    """Recorded conditions (temperatures, force, coil currents, pressure, humidity) whose
    validation values leave the calibration range by more than OUTSIDE_FRACTION of its span:
    [{variable, cal_range, val_range, beyond}] (the variable's own unit; ``beyond``: how far
    past the range, as a fraction of its span), worst first."""
    if "split" not in df:
        return []
    split = df["split"].astype(str).to_numpy()
    cal, val = split == "cal", split == "val"
    if not cal.any() or not val.any():
        return []
    out = []
    for c in [*temperature_columns(df), *(c for c in CONDITIONS if c in df)]:
        v = df[c].to_numpy(dtype=np.float64)
        vc, vv = v[cal & np.isfinite(v)], v[val & np.isfinite(v)]
        if not vc.size or not vv.size:
            continue
        lo, hi = float(vc.min()), float(vc.max())
        span = hi - lo
        past = max(lo - float(vv.min()), float(vv.max()) - hi, 0.0)
        if past > 0 and (span == 0 or past > OUTSIDE_FRACTION * span):
            out.append({"variable": c, "cal_range": [lo, hi],
                        "val_range": [float(vv.min()), float(vv.max())],
                        "beyond": past / span if span > 0 else float("inf")})
    return sorted(out, key=lambda d: -d["beyond"])


def extrapolation_message(items: list[dict]) -> str | None:
    """One sentence naming the variables whose validation values leave the calibration range."""
    if not items:
        return None
    parts = [f"{d['variable']} {d['val_range'][0]:.4g}..{d['val_range'][1]:.4g} "
             f"(calibration {d['cal_range'][0]:.4g}..{d['cal_range'][1]:.4g})" for d in items[:6]]
    return ("validation conditions leave the calibration range (the model extrapolates there; "
            "interleave calibration and validation points to avoid it): " + "; ".join(parts))
