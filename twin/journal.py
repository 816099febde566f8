"""The campaign journal: an append-only record of accepted points that survives a crash.

One JSON object per line (JSON lines). The first line is the header
``{"deltatwin_journal": 1, "header": {...}}`` (scenario name, seed, hash: whatever identifies the
campaign); every other line is one accepted point ``{"index": k, "point": {column: value}}``.
``append`` writes the line with a single ``write``, then flushes and ``os.fsync``s before it
returns, so a point the campaign moved on from is on disk.

A crash (``kill -9``, power loss) can at worst leave the last line incomplete: reading tolerates
exactly that (the incomplete line is not a point), and ``Journal.open`` cuts it off before
appending again. Anything else that does not parse (a damaged line in the middle, an index seen
twice) is an error naming the file and the line, never silently skipped.

    journal = Journal.open("run.journal", {"scenario": "thermal", "seed": 1, "hash": "..."})
    for k in range(n):
        if k in journal:            # done before the crash
            continue
        ...                         # take the point
        journal.append(k, row)      # on disk when this returns
    rows = journal.points()         # {index: row}, in index order

Values: numbers (NaN and infinities allowed), strings, booleans, None, lists; numpy scalars and
arrays are converted. Floats round-trip exactly.
"""
from __future__ import annotations

import json
import logging
import math
import os
import tempfile
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)
FORMAT_VERSION = 1


def journal_path(output, journal=None, resume: bool = False) -> Path:
    """The journal of a run writing ``output`` (``journal`` if given, else ``OUTPUT.journal``),
    checked against ``resume``: resuming needs it, a new run must not find one (JournalError)."""
    path = Path(journal) if journal else Path(output).with_name(Path(output).name + ".journal")
    if resume and not path.exists():
        raise JournalError(f"--resume: no journal {path} to resume (run without --resume to "
                           "start)")
    if not resume and path.exists():
        raise JournalError(f"{path} exists: continue that run with --resume, or remove the "
                           "journal (or choose another output) to start anew")
    return path


def _lock_exclusively(file) -> None:
    """An exclusive, non-blocking lock held while the file is open (OSError if another process
    holds it): flock on POSIX, msvcrt's byte-range lock on Windows."""
    try:
        import fcntl
    except ImportError:                                   # Windows
        import msvcrt
        msvcrt.locking(file.fileno(), msvcrt.LK_NBLCK, 1)
        return
    fcntl.flock(file.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)


class JournalError(ValueError):
    """A journal that cannot be used: mismatched header, damaged line, duplicate point, in use."""


def _plain(value):
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    raise TypeError(f"cannot journal a value of type {type(value).__name__}: {value!r}")


def canonical_json(obj) -> str:
    """The one-line JSON text of ``obj`` as the journal writes it (floats exact, NaN allowed):
    equal texts mean equal values."""
    return json.dumps(obj, default=_plain, separators=(",", ":"), allow_nan=True)


def _normalise(header: dict) -> dict:
    return json.loads(canonical_json(header))


def _same(a, b) -> bool:
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
        return True
    return a == b


def _parse(path: Path, data: bytes) -> tuple[dict, dict[int, dict], int]:
    """(header, {index: point}, length of the complete part in bytes). The last line may be
    incomplete (no newline): it is ignored."""
    complete = data[:data.rfind(b"\n") + 1]
    lines = complete.split(b"\n")[:-1]
    if not lines:
        raise JournalError(f"{path}: no complete header line (not a journal, or empty)")
    try:
        first = json.loads(lines[0])
        header = first["header"]
        version = first["deltatwin_journal"]
    except (ValueError, KeyError, TypeError) as exc:
        raise JournalError(f"{path}: line 1 is not a deltatwin journal header") from exc
    if version != FORMAT_VERSION:
        raise JournalError(f"{path}: journal format {version}, this version reads "
                           f"{FORMAT_VERSION}")
    points: dict[int, dict] = {}
    for lineno, line in enumerate(lines[1:], start=2):
        try:
            rec = json.loads(line)
            index, point = rec["index"], rec["point"]
            if not isinstance(index, int) or not isinstance(point, dict):
                raise TypeError("index must be an integer and point an object")
        except (ValueError, KeyError, TypeError) as exc:
            raise JournalError(f"{path}: line {lineno} is damaged ({exc}): {line[:80]!r}") from exc
        if index in points:
            raise JournalError(f"{path}: line {lineno}: point {index} recorded twice")
        points[index] = point
    return header, points, len(complete)


def read_journal(path: str | os.PathLike) -> tuple[dict, dict[int, dict]]:
    """(header, {index: point}) of a journal on disk, without changing it (an incomplete last
    line is ignored)."""
    path = Path(path)
    if not path.exists():
        raise JournalError(f"{path}: no such journal")
    header, points, _ = _parse(path, path.read_bytes())
    return header, points


def _fsync_dir(directory: Path) -> None:
    fd = os.open(directory, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


class Journal:
    """An open journal (use ``Journal.open``). Holds an exclusive lock on the file while open."""

    def __init__(self, path: Path, header: dict, points: dict[int, dict], file):
        self.path, self.header, self._file = path, header, file
        self._done = set(points)

    @classmethod
    def open(cls, path: str | os.PathLike, header: dict) -> Journal:
        """Create the journal with ``header``, or resume an existing one: its header must equal
        ``header`` (else ``JournalError`` naming the differing keys); an incomplete last line
        (crash mid-write) is cut off."""
        path = Path(path)
        header = _normalise(header)
        if not path.exists():
            cls._create(path, header)
        file = open(path, "r+b", buffering=0)
        try:
            try:
                _lock_exclusively(file)
            except OSError:
                raise JournalError(f"{path}: in use by another process") from None
            data = file.read()
            stored, points, good = _parse(path, data)
            differ = sorted(k for k in set(stored) | set(header)
                            if not _same(stored.get(k), header.get(k)))
            if differ:
                detail = "; ".join(f"{k}: journal {stored.get(k)!r}, now {header.get(k)!r}"
                                   for k in differ)
                raise JournalError(f"{path}: written for another campaign ({detail}); refusing "
                                   f"to resume -- use another output or remove the journal")
            if good < len(data):
                log.warning("%s: cut off an incomplete last line (%d bytes) left by a crash",
                            path, len(data) - good)
                file.truncate(good)
                os.fsync(file.fileno())
            file.seek(0, os.SEEK_END)
        except BaseException:
            file.close()
            raise
        if points:
            log.info("%s: resuming, %d point(s) already done", path, len(points))
        return cls(path, stored, points, file)

    @staticmethod
    def _create(path: Path, header: dict) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
        try:
            with os.fdopen(fd, "wb") as f:
                f.write((canonical_json({"deltatwin_journal": FORMAT_VERSION, "header": header})
                         + "\n").encode())
                f.flush()
                os.fsync(f.fileno())
            if path.exists():        # created meanwhile by someone else: theirs wins
                os.unlink(tmp)
                return
            os.replace(tmp, path)
            _fsync_dir(path.parent)
        except BaseException:
            if os.path.exists(tmp):
                os.unlink(tmp)
            raise

    def __contains__(self, index: int) -> bool:
        return index in self._done

    def done(self) -> set[int]:
        """Indices of the points on disk."""
        return set(self._done)

    def append(self, index: int, point: dict) -> None:
        """Record point ``index``; returns once the line is flushed and fsync'ed."""
        if self._file is None:
            raise JournalError(f"{self.path}: closed")
        if index in self._done:
            raise JournalError(f"{self.path}: point {index} is already recorded")
        if not isinstance(point, dict):
            raise TypeError(f"point must be a dict of column -> value, got {type(point).__name__}")
        line = memoryview((canonical_json({"index": int(index), "point": point}) + "\n").encode())
        while line:                          # unbuffered: one write, unless the OS splits it
            line = line[self._file.write(line):]
        os.fsync(self._file.fileno())
        self._done.add(int(index))

    def points(self) -> dict[int, dict]:
        """Every recorded point, {index: point} in index order (read back from disk)."""
        _, points, _ = _parse(self.path, self.path.read_bytes())
        return dict(sorted(points.items()))

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None

    def __enter__(self) -> Journal:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
