"""A fitted black-box model (DGM or direct IGM) on disk, as JSON: reading it back by kind."""
from __future__ import annotations

import json
from pathlib import Path

from deltatwin.calibration.blackbox.dgm import DGM
from deltatwin.calibration.blackbox.direct_igm import DirectIGM
from deltatwin.calibration.blackbox.estimator import MODEL_FORMAT, MODEL_FORMAT_VERSION
from deltatwin.calibration.errors import CalibrationInputError, ModelFileError, ModelMismatchError
from deltatwin.files import CONTENT_SHA256, content_damage, unique_keys

_KINDS = {"DGM": DGM, "DirectIGM": DirectIGM}
READABLE_VERSIONS = tuple(range(1, MODEL_FORMAT_VERSION + 1))


def load_model(path, expect_kind: str | None = None, expect_features: str | None = None):
    """Load a model written by ``save()``; check the format and, if given, its kind and
    feature preset (``ModelMismatchError`` when they differ)."""
    path = Path(path)
    if not path.exists():
        raise ModelFileError(f"{path}: no such model file")
    if path.is_dir():
        raise ModelFileError(f"{path}: is a folder, not a model file")
    try:
        d = json.loads(path.read_text(encoding="utf-8"), object_pairs_hook=unique_keys)
    except (OSError, ValueError) as exc:
        raise ModelFileError(f"{path}: not a JSON model file ({exc})") from exc
    if not isinstance(d, dict) or d.get("format") != MODEL_FORMAT:
        raise ModelFileError(f"{path}: not a {MODEL_FORMAT} file (key 'format')")
    version = d.get("format_version")
    if isinstance(version, bool) or version not in READABLE_VERSIONS:
        raise ModelFileError(f"{path}: model format_version {version!r} is not supported (this "
                             f"code reads {', '.join(map(str, READABLE_VERSIONS))})")
    # from version 2 every file deltatwin writes carries its content's checksum
    if version >= 2 and CONTENT_SHA256 not in d:
        raise ModelFileError(f"{path}: no {CONTENT_SHA256}: the file is incomplete or edited")
    damage = content_damage(d)
    if damage:
        raise ModelFileError(f"{path}: {damage}; refit or restore it")
    kind = d.get("kind")
    if kind not in _KINDS:
        raise ModelFileError(f"{path}: unknown model kind {kind!r}")
    features = d.get("features")
    preset = features.get("preset") if isinstance(features, dict) else None
    if expect_features is not None and preset != expect_features:
        raise ModelMismatchError(f"{path}: is a {kind} fitted with the {preset!r} feature set, "
                                 f"but the {expect_features!r} features were asked for")
    if expect_kind is not None and kind != expect_kind:
        raise ModelMismatchError(f"{path}: holds a {kind} model, a {expect_kind} was expected")
    try:
        return _KINDS[kind]._from_dict(d)
    except CalibrationInputError as exc:
        if isinstance(exc, (ModelFileError, ModelMismatchError)):
            raise type(exc)(f"{path}: {exc}") from exc
        raise ModelFileError(f"{path}: {exc}") from exc
    except (KeyError, TypeError, AttributeError, IndexError, ValueError) as exc:
        # a version-1 file (no checksum) edited by hand
        raise ModelFileError(f"{path}: malformed model ({type(exc).__name__}: {exc})") from exc
