"""A fitted black-box model (DGM or direct IGM) on disk, as JSON: reading it back by kind."""
from __future__ import annotations

import json
from pathlib import Path

from deltatwin.calibration.blackbox.dgm import DGM
from deltatwin.calibration.blackbox.direct_igm import DirectIGM
from deltatwin.calibration.blackbox.estimator import MODEL_FORMAT, MODEL_FORMAT_VERSION
from deltatwin.calibration.errors import CalibrationInputError, ModelFileError, ModelMismatchError

_KINDS = {"DGM": DGM, "DirectIGM": DirectIGM}


def load_model(path, expect_kind: str | None = None, expect_features: str | None = None):
    """Load a model written by ``save()``; check the format and, if given, its kind and
    feature preset (``ModelMismatchError`` when they differ)."""
    path = Path(path)
    if not path.exists():
        raise ModelFileError(f"{path}: no such model file")
    try:
        d = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise ModelFileError(f"{path}: not a JSON model file ({exc})") from exc
    if not isinstance(d, dict) or d.get("format") != MODEL_FORMAT:
        raise ModelFileError(f"{path}: not a {MODEL_FORMAT} file")
    if d.get("format_version") != MODEL_FORMAT_VERSION:
        raise ModelFileError(f"{path}: model format version {d.get('format_version')} is not "
                             f"supported (this code reads {MODEL_FORMAT_VERSION})")
    kind = d.get("kind")
    if kind not in _KINDS:
        raise ModelFileError(f"{path}: unknown model kind {kind!r}")
    preset = (d.get("features") or {}).get("preset")
    if expect_features is not None and preset != expect_features:
        raise ModelMismatchError(f"{path}: is a {kind} fitted with the {preset!r} feature set, "
                                 f"but the {expect_features!r} features were asked for")
    if expect_kind is not None and kind != expect_kind:
        raise ModelMismatchError(f"{path}: holds a {kind} model, a {expect_kind} was expected")
    try:
        return _KINDS[kind]._from_dict(d)
    except (KeyError, TypeError) as exc:
        raise ModelFileError(f"{path}: malformed model ({type(exc).__name__}: {exc})") from exc
    except CalibrationInputError as exc:
        if isinstance(exc, (ModelFileError, ModelMismatchError)):
            raise type(exc)(f"{path}: {exc}") from exc
        raise ModelFileError(f"{path}: {exc}") from exc
