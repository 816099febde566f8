"""What commands print: strict JSON for ``--json`` (RFC 8259: no NaN or Infinity; a figure that
does not exist is ``null``), numpy values as plain numbers and lists."""
from __future__ import annotations

import json
import math


def _plain(obj):
    if isinstance(obj, dict):
        return {str(k): _plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_plain(v) for v in obj]
    if hasattr(obj, "tolist") and not isinstance(obj, (str, bytes)):   # numpy scalar or array
        return _plain(obj.tolist())
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def strict_json(obj, indent: int | None = None) -> str:
    """``obj`` as strict JSON text: non-finite floats become null, numpy types plain values."""
    return json.dumps(_plain(obj), indent=indent, allow_nan=False)
