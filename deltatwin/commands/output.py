"""What commands print: strict JSON for ``--json`` (RFC 8259: no NaN or Infinity; a figure that
does not exist is ``null``), numpy values as plain numbers and lists."""
from __future__ import annotations

from deltatwin.calibration.tables import strict_json

__all__ = ["strict_json"]
