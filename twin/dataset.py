"""The one measurement data format (see docs/data-format.md): read, validate, write.

A dataset is a pandas DataFrame with units in the column names plus a metadata dict.
Parquet keeps the metadata in the schema under the key ``deltatwin``; CSV keeps it in a
``<name>.meta.json`` sidecar.  Writes are atomic: temporary file in the same folder, then rename.
"""
from __future__ import annotations

import hashlib
import io
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
_UNIT_SUFFIX = re.compile(r"_(s|rad|nm|arcsec|C|A|N|m|K|Pa|pct)$")
# numeric columns of the format (docs/data-format.md): checked for numbers, plausible sizes
_NUMERIC = re.compile(r"^([xyz]_nm|T_\w+_C|coil\d+_A|F_N|ac\d+_r[xyz]_arcsec|p_Pa|RH_pct|"
                      r"std_[xyz]_nm|t_s|q[123]_rad)$")
_AXIS_LIKE = re.compile(r"^[xyz]_(?!nm$)[A-Za-z]+$")     # x_um, y_mm: a reading in another unit
PLAUSIBLE_ABS = {"nm": 1e9, "C": 1000.0, "A": 100.0, "N": 1e4, "arcsec": 1e6, "rad": 10.0,
                 "Pa": 1e7, "s": 1e10, "pct": 100.0}    # |value| above: not a measurement
# the laboratory air's records: a barometric pressure (absolute, Pa) and a relative humidity (%)
AIR_RANGES = {"p_Pa": (50e3, 120e3, "an absolute barometric pressure in pascal (hPa x 100)"),
              "RH_pct": (0.0, 100.0, "a relative humidity in percent")}


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
    odd = [c for c in df.columns if _AXIS_LIKE.match(str(c))]
    if odd:
        raise DatasetError(f"{where}: column(s) {odd}: interferometer readings are x_nm, y_nm, "
                           "z_nm (nanometres); convert and rename them")
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
    for c in df.columns:
        if not _NUMERIC.match(str(c)):
            continue
        raw = df[c]
        col = pd.to_numeric(raw, errors="coerce").to_numpy(dtype=float)
        text = np.flatnonzero(np.isnan(col) & raw.notna().to_numpy())
        if text.size:
            raise DatasetError(f"{where}: column '{c}' holds text at row(s) "
                               f"{text[:10].tolist()} (e.g. {raw.iloc[text[0]]!r}); expected "
                               "numbers (an empty cell means not measured)")
        unit = _UNIT_SUFFIX.search(str(c)).group(1)
        limit = PLAUSIBLE_ABS.get(unit)
        bad = np.flatnonzero(np.isinf(col) | (np.abs(col) > limit)) if limit else \
            np.flatnonzero(np.isinf(col))
        if bad.size:
            raise DatasetError(f"{where}: column '{c}' at row(s) {bad[:10].tolist()}: "
                               f"{col[bad[0]]!r} is not a plausible value in {unit} (|value| <= "
                               f"{limit:g}; an empty cell means not measured)")
    for c, (lo, hi, what) in AIR_RANGES.items():
        if c in df.columns:
            col = pd.to_numeric(df[c], errors="coerce").to_numpy(dtype=float)
            bad = np.flatnonzero(np.isfinite(col) & ((col < lo) | (col > hi)))
            if bad.size:
                raise DatasetError(f"{where}: column '{c}' at row(s) {bad[:10].tolist()}: "
                                   f"{col[bad[0]]!r} is not {what} ({lo:g} .. {hi:g})")
    dup = df.duplicated()
    if dup.any():
        rows = np.flatnonzero(dup.to_numpy())
        raise DatasetError(f"{where}: row(s) {rows[:10].tolist()} repeat an earlier row exactly "
                           "(a file appended twice?); each reading must appear once")
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
        # the pair cannot be renamed at once: the sidecar carries the CSV's checksum, so a CSV
        # beside another version's sidecar (a full disk between the two renames) is detected
        text = df.to_csv(index=False, float_format="%.10g", lineterminator="\n").encode()
        meta["csv_sha256"] = hashlib.sha256(text).hexdigest()
        atomic_write(path.with_suffix(".meta.json"),
                     lambda tmp: Path(tmp).write_text(json.dumps(meta, indent=1, default=str)))
        atomic_write(path, lambda tmp: Path(tmp).write_bytes(text))
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
    if path.is_dir():
        raise DatasetError(f"{path}: is a folder, not a dataset file")
    try:
        if path.suffix == ".csv":
            data = path.read_bytes()
            if data and not data.endswith(b"\n"):
                raise DatasetError(f"{path}: the last line is incomplete (the file was cut "
                                   "short?); refusing a partial row")
            df = pd.read_csv(io.BytesIO(data))
            meta = _sidecar(path, data)
        else:
            table = pq.read_table(path)
            raw = (table.schema.metadata or {}).get(METADATA_KEY)
            meta = json.loads(raw) if raw else {"source": "lab"}
            df = table.to_pandas()
    except (OSError, ValueError, pa.ArrowException) as exc:
        if isinstance(exc, DatasetError):
            raise
        raise DatasetError(f"{path}: cannot be read as a dataset ({exc})") from exc
    if not isinstance(meta, dict):
        raise DatasetError(f"{path}: its metadata is a {type(meta).__name__}, not a JSON object")
    version = meta.get("format_version", FORMAT_VERSION)
    if not isinstance(version, int) or version > FORMAT_VERSION:
        raise DatasetError(f"{path}: format_version {version!r}; this deltatwin reads up to "
                           f"{FORMAT_VERSION}")
    validate(df, str(path))
    return df, meta


def _sidecar(path: Path, data: bytes) -> dict:
    """The CSV's metadata from ``<name>.meta.json`` (a laboratory's CSV may have none)."""
    side = path.with_suffix(".meta.json")
    if not side.exists():
        return {"source": "lab"}
    try:
        meta = json.loads(side.read_text(encoding="utf-8"))
    except (ValueError, UnicodeDecodeError) as exc:
        raise DatasetError(f"{side}: not valid JSON ({exc})") from exc
    if not isinstance(meta, dict):
        raise DatasetError(f"{side}: holds a JSON {type(meta).__name__}, not an object")
    expected = meta.get("csv_sha256")
    if expected is not None and expected != hashlib.sha256(data).hexdigest():
        raise DatasetError(f"{side}: written for another version of {path.name} (checksum "
                           "differs): the pair was not written together; rewrite both")
    return meta
