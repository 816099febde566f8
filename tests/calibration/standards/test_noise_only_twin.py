"""The standards' figures on the twin with Gaussian reading noise only (the nominal robot, no
effect): RP and R_i against their predictions, and the AP components' expanded uncertainty
against the value a perfect instrument reads on the same timeline. Two tests of each; the
benchmark (benchmarks/iso_noise_only.py) runs 20."""
import numpy as np
import pytest

from deltatwin.calibration.standards.campaign import evaluate_test
from deltatwin.calibration.standards.gaussian import r_gaussian, rp_gaussian
from deltatwin.calibration.standards.report import figure_rows
from deltatwin.calibration.standards.uncertainty import spec_from_scenario
from deltatwin.twin.campaign import simulate_campaign
from deltatwin.twin.scenario import Scenario
from deltatwin.twin.world import random_streams

SIGMA_M = 5e-9
TEXT = """[scenario]
name = "noise-only"
seed = {seed}
[effects]
on = []
[sensors]
air_x = "air_x"
[instruments]
noise_floor_m = 5e-9
sample_noise_m = 0.0
resolution_m = 0.0
cosine_correction = false
[campaign]
{campaign}
"""


def run(seed, campaign):
    sc = Scenario.from_text(TEXT.format(seed=seed, campaign=campaign), "noise-only.toml")
    test = sc.standard_test(random_streams(sc.seed)["campaign"])
    twin, plan = sc.build()
    df, clean = simulate_campaign(plan, twin, sc.settings, sc.cosine, sc.dead_path(),
                                  noise_free=True)
    specs = {a: spec_from_scenario(sc, a) for a in "xyz"}
    result = evaluate_test(test, df)
    return test, result, evaluate_test(test, clean), figure_rows(test, "", result, specs)


@pytest.mark.parametrize("seed", [1, 2])
def test_noise_only_rp_r_and_ap_coverage(seed):
    test, r, truth, rows = run(seed, 'kind = "iso9283"\ncycles = 30')
    rp = np.mean([p.RP for p in r.poses])
    assert rp == pytest.approx(rp_gaussian(SIGMA_M, 30), rel=0.10)
    U = {row["figure"]: row["U_nm"] * 1e-9 for row in rows}
    err = [abs(getattr(p, k) - getattr(t, k)) / U[f"{k} {p.name}"]
           for p, t in zip(r.poses, truth.poses) for k in ("APx", "APy", "APz")]
    assert max(err) < 1.6          # U is 2 sigma: 15 draws, none beyond 3.2 sigma
    assert np.mean(np.array(err) <= 1) >= 0.8
    _, r2, _, _ = run(seed, 'kind = "iso230-2"\ntargets = 21\napproaches = 5')
    r_i = np.mean(np.concatenate([np.r_[a.R_up_i, a.R_down_i] for a in r2.values()]))
    assert r_i == pytest.approx(r_gaussian(SIGMA_M, 5), rel=0.10)
