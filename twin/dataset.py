"""The one measurement data format (see docs/data-format.md): read, validate, write.

A dataset is a pandas DataFrame with units in the column names plus a metadata dict.
Parquet keeps the metadata in the schema under the key ``deltatwin``; CSV keeps it in a
``<name>.meta.json`` sidecar.  Writes are atomic: temporary file in the same folder, then rename.
"""
from __future__ import annotations

import json
import os
import re
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from deltatwin.files import atomic_write

FORMAT_VERSION = 1
METADATA_KEY = b"deltatwin"
REQUIRED_COLUMNS = ("t_s", "pos_id", "split", "q1_rad", "q2_rad", "q3_rad")
AXES = ("x", "y", "z")
SPLITS = ("cal", "val")
_UNIT_SUFFIX = re.compile(r"_(s|rad|nm|arcsec|C|A|N|m|K)$")


class DatasetError(ValueError):
    """A dataset file or table that does not follow docs/data-format.md."""


def temperature_columns(df: pd.DataFrame) -> list[str]:
    """Temperature sensor columns (``T_<name>_C``), in table order."""
    return [c for c in df.columns if c.startswith("T_") and c.endswith("_C")]


def axis_columns(df: pd.DataFrame) -> list[str]:
    """Interferometer reading columns present (``x_nm``, ``y_nm``, ``z_nm``)."""
    return [f"{a}_nm" for a in AXES if f"{a}_nm" in df.columns]


def units_from_columns(columns) -> dict[str, str]:
    units = {}
    for c in columns:
        m = _UNIT_SUFFIX.search(c)
        units[c] = m.group(1) if m else "-"
    return units


def validate(df: pd.DataFrame, where: str = "dataset") -> None:
    """Raise DatasetError naming the file and the problem if ``df`` breaks the format."""
    missing = [c for c in REQUIRED_COLUMNS if c not in df.columns]
    if missing:
        raise DatasetError(f"{where}: missing required column(s) {missing}; "
                           f"columns present: {list(df.columns)}")
    if len(df) == 0:
        raise DatasetError(f"{where}: no rows")
    bad_split = sorted(set(df["split"].astype(str)) - set(SPLITS))
    if bad_split:
        raise DatasetError(f"{where}: column 'split' holds {bad_split}; allowed: {list(SPLITS)}")
    for c in ("t_s", "q1_rad", "q2_rad", "q3_rad"):
        col = pd.to_numeric(df[c], errors="coerce")
        bad = np.flatnonzero(~np.isfinite(col.to_numpy(dtype=float)))
        if bad.size:
            raise DatasetError(f"{where}: column '{c}' is not a finite number at row(s) "
                               f"{bad[:10].tolist()}{' ...' if bad.size > 10 else ''}")
    both = (df.groupby("pos_id")["split"].nunique() > 1)
    if both.any():
        ids = both[both].index[:10].tolist()
        raise DatasetError(f"{where}: position(s) {ids} appear in both 'cal' and 'val': "
                           "the validation positions must be disjoint from calibration")


def write_dataset(df: pd.DataFrame, meta: dict, path: str | os.PathLike) -> Path:
    """Write ``df`` with ``meta`` to Parquet (or CSV + sidecar by suffix), atomically."""
    path = Path(path)
    validate(df, str(path))
    meta = {"format_version": FORMAT_VERSION, "units": units_from_columns(df.columns), **meta}
    if path.suffix == ".csv":
        atomic_write(path, lambda tmp: df.to_csv(tmp, index=False, float_format="%.10g"))
        atomic_write(path.with_suffix(".meta.json"),
                      lambda tmp: Path(tmp).write_text(json.dumps(meta, indent=1, default=str)))
        return path
    table = pa.Table.from_pandas(df, preserve_index=False)
    schema_meta = dict(table.schema.metadata or {})
    schema_meta[METADATA_KEY] = json.dumps(meta, default=str).encode()
    table = table.replace_schema_metadata(schema_meta)
    atomic_write(path, lambda tmp: pq.write_table(table, tmp))
    return path


def read_dataset(path: str | os.PathLike) -> tuple[pd.DataFrame, dict]:
    """Read a dataset (Parquet, or CSV with optional ``.meta.json``); validate it."""
    path = Path(path)
    if not path.exists():
        raise DatasetError(f"{path}: no such file")
    try:
        if path.suffix == ".csv":
            df = pd.read_csv(path)
            side = path.with_suffix(".meta.json")
            meta = json.loads(side.read_text()) if side.exists() else {"source": "lab"}
        else:
            table = pq.read_table(path)
            raw = (table.schema.metadata or {}).get(METADATA_KEY)
            meta = json.loads(raw) if raw else {"source": "lab"}
            df = table.to_pandas()
    except (OSError, ValueError, pa.ArrowException) as exc:
        if isinstance(exc, DatasetError):
            raise
        raise DatasetError(f"{path}: cannot be read as a dataset ({exc})") from exc
    validate(df, str(path))
    return df, meta
