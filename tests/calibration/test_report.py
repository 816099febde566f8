"""The report's words for the diagnosis loop: one formatter for a refit tried instead of a
rejected effect, plain (the demo's progress) and Markdown (report.md)."""
from deltatwin.calibration.diagnosis.report import tried_instead_line


def test_tried_instead_is_one_line_plain_or_markdown():
    kept = {"effect": "gravity_sag", "val_err90_nm": 12.345, "kept": True}
    dropped = {"effect": "loop_drift", "val_err90_nm": 40.0, "kept": False}
    assert tried_instead_line(kept) == "tried instead, also significant: gravity_sag (12.3 nm: kept)"
    assert tried_instead_line(dropped, markdown=True) == (
        "Tried instead, also significant: **loop_drift** (40.0 nm: not kept).")
    held = {"effect": "loop_drift", "val_err90_nm": 38.26, "kept": True, "held": "off"}
    assert tried_instead_line(held) == ("tried again held off (its free parameters at zero where "
                                        "the data do not determine them): loop_drift (38.3 nm: "
                                        "kept)")
    assert tried_instead_line(held, markdown=True).startswith("Tried again held off")
