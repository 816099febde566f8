"""The one measurement data format (see docs/data-format.md): read, validate, write.

A dataset is a pandas DataFrame with units in the column names plus a metadata dict.
Parquet keeps the metadata in the schema under the key ``deltatwin``; CSV keeps it in a
``<name>.meta.json`` sidecar.  Writes are atomic: temporary file in the same folder, then rename.
"""
from __future__ import annotations

import csv
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

from deltatwin.files import atomic_write, unique_keys
from deltatwin.twin.lab_setup import SETUP_KEY, setup_problem

FORMAT_VERSION = 1
METADATA_KEY = b"deltatwin"
REQUIRED_COLUMNS = ("t_s", "pos_id", "split", "q1_rad", "q2_rad", "q3_rad")
AXES = ("x", "y", "z")
SPLITS = ("cal", "val")
_UNIT_SUFFIX = re.compile(r"_(s|rad|nm|arcsec|C|A|N|m|K|Pa|pct)$")
# numeric columns of the format (docs/data-format.md): checked for numbers, plausible sizes
_NUMERIC = re.compile(r"^([xyz]_nm|T_\w+_C|coil\d+_A|F_N|ac\d+_r[xyz]_arcsec|p_Pa|RH_pct|"
                      r"std_[xyz]_nm|[xyz]_(repeat_)?std_nm|t_s|q[123]_rad)$")
_AXIS_LIKE = re.compile(r"^[xyz]_(?!nm$)[A-Za-z]+$")     # x_um, y_mm: a reading in another unit
PLAUSIBLE_ABS = {"nm": 1e9, "C": 1000.0, "A": 100.0, "N": 1e4, "arcsec": 1e6, "rad": 10.0,
                 "Pa": 1e7, "s": 1e10, "pct": 100.0}    # |value| above: not a measurement
# the laboratory air's records: a barometric pressure (absolute, Pa) and a relative humidity (%)
AIR_RANGES = {"p_Pa": (50e3, 120e3, "an absolute barometric pressure in pascal (hPa x 100)"),
              "RH_pct": (0.0, 100.0, "a relative humidity in percent")}


# how a flag column (cosine_corrected) may be written, case-insensitive
FLAG_TEXTS = ("true", "false", "1", "0", "1.0", "0.0")


def _text_map(v) -> str | None:
    if not isinstance(v, dict):
        return "not a JSON object"
    return next((f"{k} = {u!r} is not text" for k, u in v.items() if not isinstance(u, str)), None)


def _lengths_m(v) -> str | None:
    if not isinstance(v, dict):
        return "not a JSON object"
    return next((f"{k} = {u!r} is not a length in m (|value| < 10)" for k, u in v.items()
                 if isinstance(u, bool) or not isinstance(u, (int, float))
                 or not np.isfinite(u) or abs(u) >= 10.0), None)


def _scalar(ok, what):
    return lambda v: None if ok(v) else f"{v!r} is not {what}"


# sidecar / schema metadata keys the readers use -> what is wrong with the value (None: fine);
# the other keys are provenance, kept unread
_META_CHECKS = {
    "units": _text_map,
    "sensors": _text_map,
    "cosine_dead_path_m": _lengths_m,
    "csv_sha256": _scalar(lambda v: isinstance(v, str) and re.fullmatch(r"[0-9a-f]{64}", v)
                          is not None, "a SHA-256 in hex"),
    "seed": _scalar(lambda v: isinstance(v, int) and not isinstance(v, bool) and v >= 0,
                    "an integer >= 0"),
    SETUP_KEY: setup_problem,
    "scale": _scalar(lambda v: isinstance(v, (int, float)) and not isinstance(v, bool)
                     and 0 < v <= 1, "a number in (0, 1]"),
}


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
    pos = pd.to_numeric(df["pos_id"], errors="coerce").to_numpy(dtype=float)
    bad = np.flatnonzero(~np.isfinite(pos) | (pos != np.round(pos)) | (np.abs(pos) > 2.0**53))
    if bad.size:
        raise DatasetError(f"{where}: column 'pos_id' is not an integer at row(s) "
                           f"{bad[:10].tolist()} (e.g. {df['pos_id'].iloc[bad[0]]!r})")
    if "session" in df.columns:
        bad = np.flatnonzero(df["session"].isna().to_numpy()
                             | (df["session"].astype(str).str.strip() == "").to_numpy())
        if bad.size:
            raise DatasetError(f"{where}: column 'session' is empty at row(s) {bad[:10].tolist()}")
    if "cosine_corrected" in df.columns:
        flags = df["cosine_corrected"].astype(str).str.strip().str.lower()
        bad = np.flatnonzero(~flags.isin(FLAG_TEXTS).to_numpy())
        if bad.size:
            raise DatasetError(f"{where}: column 'cosine_corrected' holds "
                               f"{df['cosine_corrected'].iloc[bad[0]]!r} at row(s) "
                               f"{bad[:10].tolist()}; expected True or False")
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


DATASET_SUFFIXES = (".parquet", ".csv")


def check_dataset_path(path: str | os.PathLike, where: str = "dataset") -> Path:
    """``path`` if its suffix says how to write a dataset (``DATASET_SUFFIXES``), else a
    DatasetError naming ``where`` (a command line passes its option): ``out.txt`` is not
    written as Parquet under a name that says text."""
    path = Path(path)
    if path.suffix not in DATASET_SUFFIXES:
        raise DatasetError(f"{where} {path}: unknown dataset file type {path.suffix or '(none)'!r}"
                           f"; write {' or '.join(DATASET_SUFFIXES)}")
    return path


def write_dataset(df: pd.DataFrame, meta: dict, path: str | os.PathLike) -> Path:
    """Write ``df`` with ``meta`` to Parquet (or CSV + sidecar) by suffix, atomically; another
    suffix raises DatasetError."""
    path = check_dataset_path(path)
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
            meta = _sidecar(path, data)
            meta_where = path.with_suffix(".meta.json") if meta is not None else path
            _unique_header(path, data)
            df = pd.read_csv(io.BytesIO(data))
            meta = meta if meta is not None else {"source": "lab"}
        else:
            table = pq.read_table(path)
            meta_where = path
            raw = (table.schema.metadata or {}).get(METADATA_KEY)
            meta = json.loads(raw) if raw else {"source": "lab"}
            df = table.to_pandas()
    except (OSError, ValueError, pa.ArrowException) as exc:
        if isinstance(exc, DatasetError):
            raise
        raise DatasetError(f"{path}: cannot be read as a dataset ({exc})") from exc
    if not isinstance(meta, dict):
        raise DatasetError(f"{meta_where}: its metadata is a {type(meta).__name__}, not a JSON "
                           "object")
    version = meta.get("format_version", FORMAT_VERSION)
    if not isinstance(version, int) or isinstance(version, bool) \
            or not 1 <= version <= FORMAT_VERSION:
        raise DatasetError(f"{meta_where}: format_version {version!r}; this deltatwin reads "
                           f"1 to {FORMAT_VERSION}")
    for key, check in _META_CHECKS.items():
        wrong = check(meta[key]) if key in meta else None
        if wrong:
            raise DatasetError(f"{meta_where}: metadata {key}: {wrong[:200]} "
                               "(docs/data-format.md)")
    validate(df, str(path))
    return df, meta


def _unique_header(path: Path, data: bytes) -> None:
    """A column named twice (pandas would rename the second ``x_nm.1`` and drop it silently)."""
    header = next(csv.reader([data.split(b"\n", 1)[0].decode("utf-8", "replace")]), [])
    repeated = sorted({c for c in header if header.count(c) > 1})
    if repeated:
        raise DatasetError(f"{path}: column(s) {repeated} appear more than once in the header")


def _sidecar(path: Path, data: bytes) -> dict | None:
    """The CSV's metadata from ``<name>.meta.json`` (None: a laboratory's CSV may have none)."""
    side = path.with_suffix(".meta.json")
    if not side.exists():
        return None
    if side.is_dir():
        raise DatasetError(f"{side}: is a folder, not the dataset's metadata")
    try:
        meta = json.loads(side.read_text(encoding="utf-8"), object_pairs_hook=unique_keys)
    except (ValueError, UnicodeDecodeError) as exc:
        raise DatasetError(f"{side}: not valid JSON ({exc})") from exc
    if not isinstance(meta, dict):
        raise DatasetError(f"{side}: holds a JSON {type(meta).__name__}, not an object")
    expected = meta.get("csv_sha256")
    if expected is not None and _META_CHECKS["csv_sha256"](expected):
        raise DatasetError(f"{side}: csv_sha256 = {str(expected)[:80]!r} is not a SHA-256 in hex")
    if expected is not None and expected != hashlib.sha256(data).hexdigest():
        raise DatasetError(f"{side}: written for another version of {path.name} (checksum "
                           "differs): the pair was not written together; rewrite both")
    return meta
