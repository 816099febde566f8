"""The shipped hidden-effect scenarios (scenarios/hidden/) are the papers' conditions, written
from twin/cases.py (the one place those are defined), and a scenario's [hidden] table carries
the laboratory's known constants."""
import pytest

from deltatwin.twin.cases import (
    CLIMATE,
    FRAME_ARM_M,
    HIDDEN_SCENARIOS,
    PAPER_SENSORS,
    hidden_case,
)
from deltatwin.twin.scenario import SCENARIO_DIR, Scenario, ScenarioError


def test_shipped_hidden_scenarios_are_the_generated_ones():
    shipped = sorted(p.stem for p in (SCENARIO_DIR / "hidden").glob("*.toml"))
    assert shipped == sorted(HIDDEN_SCENARIOS)
    for name in HIDDEN_SCENARIOS:
        text = (SCENARIO_DIR / "hidden" / f"{name}.toml").read_text()
        assert text == hidden_case(name).toml(), (
            f"scenarios/hidden/{name}.toml is stale: python -c 'from deltatwin.twin.cases import "
            "write_hidden_scenarios as w; w(\"scenarios/hidden\")'")


@pytest.mark.parametrize("name", sorted(HIDDEN_SCENARIOS))
def test_hidden_scenarios_are_in_the_papers_conditions(name):
    sc = Scenario.load(f"hidden/{name}")
    kind = sc.campaign["kind"]
    effects = {e.name: e for e in sc.effects}
    assert tuple(sc.sensors) == PAPER_SENSORS[kind]                  # 11 / 13 sensors
    assert not sc.settings.barometer and not sc.settings.hygrometer  # pressure unrecorded
    assert effects["room_climate"].pressure_std_Pa == CLIMATE[kind]["pressure_std_Pa"] == 80.0
    if kind == "thermal":
        assert effects["room_climate"].ac_off_s == 1800.0            # AC off in the campaign
    else:
        assert effects["servo_settling"].angle_std_rad > 0
    assert "coil_heating" in effects or kind == "thermal"
    assert list(effects["loop_drift"].frame_arm_m) == list(FRAME_ARM_M)
    assert sc.hidden["known"] == {"loop_drift": {"frame_arm_m": list(FRAME_ARM_M)}}
    assert set(sc.hidden["effects"]).isdisjoint(sc.hidden["baseline"])


@pytest.mark.parametrize("known, words", [
    ("known = 3", "expected a table of effect"),
    ("known.loop_drift = { frame_arm = [-0.6, 0.0] }", "unknown parameter 'frame_arm'"),
    ("known.loop_drift = { frame_arm_m = -0.6 }", "expected shape (2,)"),
    ("known.no_such_effect = { x = 1 }", "no_such_effect")])
def test_bad_known_constants_are_refused_naming_the_key(tmp_path, known, words):
    text = (SCENARIO_DIR / "hidden" / "loop-drift.toml").read_text()
    head, tail = text.split("[hidden.known.loop_drift]")
    tail = tail.split("[effects]", 1)[1]
    path = tmp_path / "bad.toml"
    path.write_text(head.replace('[hidden]\n', f'[hidden]\n{known}\n', 1) + "[effects]" + tail)
    with pytest.raises(ScenarioError) as err:
        Scenario.load(path)
    assert "[hidden] known" in str(err.value) and words in str(err.value), str(err.value)
