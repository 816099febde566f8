"""A standard test's campaign (``twin.standard_tests.StandardTest`` and its dataset, one row per
plan point, in plan order) evaluated by its standard."""
from __future__ import annotations

import numpy as np
import pandas as pd

from deltatwin.calibration.errors import CalibrationInputError
from deltatwin.calibration.standards import iso230_2, iso230_3, iso9283
from deltatwin.twin.instruments.optics import AXES
from deltatwin.twin.standard_tests import POSE_NAMES, StandardTest


def readings_m(df: pd.DataFrame, test: StandardTest) -> np.ndarray:
    """The readings (N, 3) m of the campaign's rows (NaN on an axis a session did not read)."""
    if len(df) != len(test.plan):
        raise CalibrationInputError(f"{test.test}: the dataset has {len(df)} rows, the test's "
                                    f"plan {len(test.plan)} points: not this test's campaign")
    return np.column_stack([df[f"{a}_nm"].to_numpy(dtype=np.float64) * 1e-9 if f"{a}_nm" in df
                            else np.full(len(df), np.nan) for a in AXES])


def evaluate_iso9283(test: StandardTest, df: pd.DataFrame, drift_block: int | None = None):
    """ISO 9283 figures of the campaign's measured points: attained = readings, command =
    target."""
    x = readings_m(df, test)
    poses = test.positions_m["poses"]
    used = [k for k in range(len(POSE_NAMES)) if np.any(test.item == k)]
    att = np.stack([x[test.item == k] for k in used])
    return iso9283.evaluate(poses[used], att, [POSE_NAMES[k] for k in used], drift_block)


def evaluate_iso230_2(test: StandardTest, df: pd.DataFrame) -> dict:
    """{axis: ISO 230-2 result} of the campaign: deviation = reading - target along the axis."""
    x = readings_m(df, test)
    out = {}
    for a in test.parameters["axes"]:
        k = AXES.index(a)
        rows = (test.axis == a) & test.measured
        dev = x[rows, k] - test.targets_m[rows, k]
        out[a] = iso230_2.from_readings(test.item[rows], test.direction[rows], dev,
                                        test.positions_m[a][:, k], a)
    return out


def evaluate_iso230_3(test: StandardTest, df: pd.DataFrame, reference: str | None = None):
    """ISO 230-3 ETVE of the campaign: displacement = reading - target per axis, against the
    scanned temperatures (``reference``: default the first sensor whose name starts with
    ``air``, else the first sensor)."""
    x = readings_m(df, test)
    sensors = [c[2:-2] for c in df.columns if c.startswith("T_") and c.endswith("_C")]
    if not sensors:
        raise CalibrationInputError("ISO 230-3: the dataset has no temperature column T_<name>_C")
    ref = reference or next((s for s in sensors if s.startswith("air")), sensors[0])
    disp = {a: x[:, k] - test.targets_m[:, k] for k, a in enumerate(AXES)
            if np.all(np.isfinite(x[:, k]))}
    return iso230_3.evaluate(df["t_s"].to_numpy(dtype=np.float64), disp,
                             {s: df[f"T_{s}_C"].to_numpy(dtype=np.float64) for s in sensors}, ref)


def evaluate_test(test: StandardTest, df: pd.DataFrame, drift_block: int | None = None):
    """The standard's result of the campaign (ISO 9283 result, with the drift between the
    first and last ``drift_block`` cycles if given; {axis: ISO 230-2 result}; or the ETVE
    result)."""
    if test.test == "iso9283":
        return evaluate_iso9283(test, df, drift_block)
    return {"iso230-2": evaluate_iso230_2, "iso230-3": evaluate_iso230_3}[test.test](test, df)
