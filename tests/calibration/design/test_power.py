"""The linearised detection power: no signature, no power; the non-centrality grows with the
magnitude; the full rule is stricter than the F test and BIC
alone; the table and figure build from records."""
import numpy as np
import pandas as pd
import pytest

from deltatwin.calibration.design.power import (
    monte_carlo_power,
    power_figure,
    power_table,
    predicted_power_curve,
)
from deltatwin.calibration.design.sweep import SweepSpec

SPEC = """
[sweep]
seed = 3
[[study]]
scenario = "quiet/beam-misalignment"
effect = "beam_misalignment"
parameter = "abbe_offset_m"
magnitudes = [0.0]
[designs.small]
scale = 0.05
"""


def test_linearised_power_of_the_abbe_offsets(tmp_path):
    p = tmp_path / "spec.toml"
    p.write_text(SPEC)
    case = SweepSpec.load(p).cases[0]
    curve = predicted_power_curve([case], [0.0, 0.05, 0.1, 0.5], np.random.default_rng(1),
                                  n_draws=400).set_index("magnitude")
    assert curve.loc[0.0, "noncentrality"] == 0 and curve.loc[0.0, "power"] <= 0.01
    # the non-centrality grows faster than the magnitude (~ its square, less what the
    # candidate's start value and its undetermined directions leave out)
    lam = curve.noncentrality.to_numpy()
    assert np.all(np.diff(lam) > 0) and lam[2] / lam[1] > 3.0
    assert list(curve.power) == sorted(curve.power) and curve.loc[0.5, "power"] == 1.0
    assert np.all(curve.power <= curve.power_f_bic + 0.05)

    records = pd.DataFrame({"case_id": list("abcd"), "status": "ok", "scenario": "s",
                            "effect": "beam_misalignment", "design": "small",
                            "magnitude": [0.0, 0.0, 0.5, 0.5],
                            "significant": [False, False, True, False],
                            "named": [False, False, True, False]})
    t = power_table(curve.reset_index(), monte_carlo_power(records))
    assert t.set_index("magnitude").loc[0.5, "mc_significant"] == 0.5
    assert t.set_index("magnitude").loc[0.5, "difference"] == pytest.approx(-0.5)
    assert len(power_figure(t).axes) == 1
