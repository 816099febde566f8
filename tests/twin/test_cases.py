"""Generated discovery cases (deltatwin.twin.cases): seeded, loadable scenarios in the papers'
conditions whose hidden effects are missing from the baseline at the stated magnitude."""
import numpy as np
import pytest

from deltatwin.twin.cases import FRAME_ARM_M, MODEL, generate_cases
from deltatwin.twin.effects import LIBRARY
from deltatwin.twin.scenario import Scenario


def test_cases_are_seeded_loadable_and_hide_what_they_say(tmp_path):
    cases = generate_cases(np.random.default_rng(4), 12)
    again = generate_cases(np.random.default_rng(4), 12)
    assert [c.toml() for c in cases] == [c.toml() for c in again]
    assert any(not c.hidden for c in cases) and any(len(c.hidden) >= 2 for c in cases)
    for c in cases:
        path = tmp_path / f"{c.name}.toml"
        path.write_text(c.toml())
        sc = Scenario.load(path)
        on = {e.name: e for e in sc.effects}
        assert sc.hidden["effects"] == c.hidden_effects
        assert not set(c.hidden_effects) & set(c.baseline)
        assert set(c.baseline) | set(c.hidden_effects) == set(MODEL[c.kind]) | \
            set(c.hidden_effects)
        assert np.allclose(on["loop_drift"].frame_arm_m, FRAME_ARM_M)
        assert c.known == {"loop_drift": {"frame_arm_m": list(FRAME_ARM_M)}}
        assert "room_climate" in on and on["room_climate"].pressure_std_Pa == 80.0
        for e, m in c.hidden:
            if e == "gravity_sag":
                assert on[e].load_factor == pytest.approx(m * LIBRARY[e]().load_factor)


def test_bad_generator_input_is_named():
    with pytest.raises(ValueError, match="unknown campaign kind"):
        generate_cases(np.random.default_rng(0), 2, kinds=("vacuum",))
    with pytest.raises(ValueError, match="null_fraction"):
        generate_cases(np.random.default_rng(0), 2, null_fraction=2.0)
