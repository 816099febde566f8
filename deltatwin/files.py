"""Writing files the way every deltatwin output is written: atomically (a temporary file in the
same folder, renamed over the target only once complete, so a crash or a bad input never leaves
a half-written file), with the permissions a plain ``open`` would give; and TOML text for the
few TOML files the project writes (robot parameters, ports, fitted models). The ground floor:
every layer may import this module, and it imports nothing of the project."""
from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path


def atomic_write(path: str | os.PathLike, write: Callable[[str], None]) -> Path:
    """Call ``write(tmp_path)`` to fill a temporary file beside ``path``, then rename it to
    ``path``; on any error the temporary file is removed and ``path`` is untouched."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    try:
        write(tmp)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)          # mkstemp makes it private; open() would not
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return path


@contextmanager
def atomic_folder(path: str | os.PathLike) -> Iterator[Path]:
    """A temporary folder beside ``path`` to fill; once the block ends without error it takes
    ``path``'s place (a folder there before is replaced whole). On any error or interruption
    (KeyboardInterrupt too) the temporary folder is removed and ``path`` is untouched: a
    half-filled folder is never left under the name asked for."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.exists() and not path.is_dir():
        raise NotADirectoryError(f"{path}: is a file, not a folder")
    work = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent))
    try:
        yield work
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(work, 0o777 & ~umask)         # mkdtemp makes it private; mkdir would not
        if not path.exists():
            os.replace(work, path)
            return
        # a folder is not renamed over a full one: the old one steps aside first, and comes
        # back if the new one cannot take its place
        old = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".old", dir=path.parent))
        os.replace(path, old / path.name)
        try:
            os.replace(work, path)
        except BaseException:
            os.replace(old / path.name, path)
            shutil.rmtree(old)
            raise
        shutil.rmtree(old)
    except BaseException:
        shutil.rmtree(work, ignore_errors=True)
        raise


def check_writable(path: str | os.PathLike, folder: bool = False) -> Path:
    """Fail early (OSError naming the place) if ``path`` (a file, or with ``folder`` a folder to
    fill) cannot be written: a file in its nearest existing folder is made and removed, nothing
    else is created. Commands call it before computing, so an unwritable output costs a message,
    not the computation."""
    path = Path(path)
    if not folder and path.is_dir():
        raise IsADirectoryError(f"{path}: is a folder; give a file name")
    existing = path if folder else path.parent
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir():
        raise NotADirectoryError(f"{existing}: is a file, so {path} cannot be made")
    try:
        fd, probe = tempfile.mkstemp(prefix=".deltatwin-", suffix=".probe", dir=existing)
    except OSError as exc:
        raise OSError(f"{path}: cannot be written ({existing}: {exc.strerror or exc})") from exc
    os.close(fd)
    os.unlink(probe)
    return path


def atomic_write_text(path: str | os.PathLike, text: str) -> Path:
    return atomic_write(path, lambda tmp: Path(tmp).write_text(text))


def _plain(value):
    """numpy scalars and arrays, and tuples, as the Python values TOML writers take."""
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if hasattr(value, "tolist") and not isinstance(value, (str, bytes)):
        return _plain(value.tolist())
    return value


def toml_text(doc: dict, comment: str = "") -> str:
    """``doc`` as TOML text (tomli-w: strings with newlines, keys with spaces or dots, inf and
    nan written as TOML says; floats exactly), with ``comment`` as leading ``#`` lines."""
    import tomli_w

    head = "".join(f"# {line}\n" for line in comment.splitlines())
    return head + tomli_w.dumps(_plain(doc))


def unique_keys(pairs: list[tuple[str, object]]) -> dict:
    """``object_pairs_hook`` for ``json.loads``: a key repeated in one object is a ValueError
    (``json.loads`` alone keeps the last one silently)."""
    keys = [k for k, _ in pairs]
    repeated = sorted({k for k in keys if keys.count(k) > 1})
    if repeated:
        raise ValueError(f"key(s) {repeated} repeated in one object")
    return dict(pairs)


CONTENT_SHA256 = "content_sha256"


def content_sha256(doc: dict) -> str:
    """The SHA-256 of a document's content (every key but ``content_sha256``, keys sorted,
    numbers as their shortest exact text): the same for the document written as JSON or TOML and
    read back, different after any change of a key or a value. Files deltatwin writes for
    itself carry it, so that a file cut short, damaged or edited is refused, not half used."""
    import hashlib
    import json

    body = {k: v for k, v in _plain(doc).items() if k != CONTENT_SHA256}
    text = json.dumps(body, sort_keys=True, separators=(",", ":"), allow_nan=True)
    return hashlib.sha256(text.encode()).hexdigest()


def content_damage(doc: dict) -> str | None:
    """Why ``doc`` does not match the ``content_sha256`` it carries (None: it matches, or it
    carries none)."""
    expected = doc.get(CONTENT_SHA256)
    if expected is None:
        return None
    if not isinstance(expected, str) or expected != content_sha256(doc):
        return (f"its content does not match its {CONTENT_SHA256} (the file was cut short, "
                "damaged or edited)")
    return None
