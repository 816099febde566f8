"""The uncertainty budget against hand values and the published sensitivities of the air's
index, and the ISO 14253-1 decision with its guard band."""
import math

import pytest

from deltatwin.calibration.standards.uncertainty import (
    MeasurementSpec,
    conformance,
    expanded,
    index_sensitivities,
    spec_from_scenario,
)
from deltatwin.twin.scenario import Scenario


def test_index_sensitivities_are_the_published_ones():
    # Edlén near 20 degC, 101325 Pa: -0.93 ppm/K, +2.7 ppm per 1000 Pa, -0.37 ppm per 1000 Pa
    # of water vapour (e.g. the rules of thumb of interferometer manuals: 1 ppm per K, per
    # 3.7 hPa, per 27 hPa of vapour)
    dT, dp, de = index_sensitivities()
    assert dT == pytest.approx(-0.93e-6, rel=0.03)
    assert dp == pytest.approx(2.68e-9, rel=0.03)
    assert de == pytest.approx(-3.7e-10, rel=0.05)


def test_budget_by_hand():
    spec = MeasurementSpec(resolution_m=1e-9, noise_m=4e-9, zero_noise_m=3e-9, air_T_u_C=0.02,
                           pressure_u_Pa=0.0, vapour_u_Pa=0.0, misalignment_rad=1e-3,
                           abbe_offset_m=0.0, dead_path_m=0.1, cte_per_K=1e-5,
                           cte_u_per_K=1e-6, material_T_u_C=0.1, material_dT_K=2.0)
    L, n = 0.004, 4
    b = spec.budget(L, n)
    dT = index_sensitivities()[0]
    assert b["resolution"] == pytest.approx(1e-9 / math.sqrt(6))
    assert b["noise"] == pytest.approx(math.sqrt((4e-9) ** 2 / 4 + (3e-9) ** 2))
    assert b["air refraction"] == pytest.approx(L * abs(dT) * 0.02)
    assert b["cosine/Abbe"] == pytest.approx(L * 1e-6 / (2 * math.sqrt(3)))
    assert b["dead path"] == pytest.approx(0.1 * abs(dT) * 0.02)
    assert b["material temperature"] == pytest.approx(L * math.hypot(1e-6, 2e-6))
    U, _ = expanded(spec, "position", L, n)
    assert U == pytest.approx(2 * math.sqrt(sum(v * v for v in b.values())))
    U, rand = expanded(spec, "difference", L, n)
    assert set(rand) == {"resolution", "noise"}
    U, _ = expanded(spec, "repeatability", multiplier=4.0)
    assert U == pytest.approx(4 * math.hypot(4e-9, 1e-9 / math.sqrt(12)))
    with pytest.raises(ValueError, match="uncertainty kind 'range'"):
        expanded(spec, "range")


@pytest.mark.parametrize("value, U, T, decision", [
    (400.0, 50.0, 500.0, "conforms"), (450.0, 50.0, 500.0, "conforms"),
    (460.0, 50.0, 500.0, "inconclusive"), (550.0, 50.0, 500.0, "inconclusive"),
    (551.0, 50.0, 500.0, "does not conform")])
def test_guard_band(value, U, T, decision):
    assert conformance(value, U, T) == decision


def test_a_source_the_world_lacks_is_left_out():
    full = spec_from_scenario(Scenario.load("paper-thermal"), "x")
    assert full.air_T_u_C > 0 and full.pressure_u_Pa > 0 and full.material_dT_K > 0
    text = ('[scenario]\nname = "quiet"\n[effects]\non = []\n[sensors]\nair_x = "air_x"\n'
            '[campaign]\nkind = "iso9283"\n')
    bare = spec_from_scenario(Scenario.from_text(text, "quiet.toml"), "x")
    b = bare.budget(0.004, 1)
    assert b["air refraction"] == b["dead path"] == b["material temperature"] == 0.0
    assert bare.zero_noise_m == 0.0            # the twin zeroes on the true path
