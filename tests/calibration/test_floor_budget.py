"""The achievable floor's budget: per source, nm per axis, measured in the twin by
switching each source alone on and refitting the true model; it adds up in quadrature to the
floor. For laboratory data, predicted from the instruments' specifications through a fitted
model's sensitivities."""
import pytest

from deltatwin.calibration.diagnosis.floor import (
    BUDGET_TOLERANCE,
    REMAINDER,
    air_line_check,
    budget_lines,
    measured_floor_budget,
    predicted_floor_budget,
    true_fit,
)
from deltatwin.twin.instruments.optics import nominal_dead_path
from deltatwin.twin.scenario import Scenario

SCALE = 0.02


@pytest.fixture(scope="module")
def thermal():
    sc = Scenario.load("paper-thermal")
    df, meta = sc.simulate(SCALE)
    fit = true_fit(df, meta)
    return sc, df, meta, fit


@pytest.fixture(scope="module")
def budget(thermal):
    sc, df, meta, fit = thermal
    return measured_floor_budget(sc, SCALE, df, meta, fit)


@pytest.mark.xfail(strict=True, reason=(
    "the floor fitted from the library's starting values only: on y the sources' quadrature "
    "sum, 19.8 nm, is 27 % above the floor's 15.6 nm (tolerance 25 %)"))
def test_the_sources_add_up_in_quadrature_to_the_achievable_floor(thermal, budget):
    """paper-thermal (reduced): interferometers, thermometers, the unrecorded air and what
    perfect instruments leave add up in quadrature to the true model's refitted floor within
    BUDGET_TOLERANCE, per axis and pooled."""
    _, _, _, fit = thermal
    for a in ("x", "y", "z", "all"):
        line = budget[a]
        assert line["achievable_floor_nm"] == pytest.approx(fit.val_[a]["err_p90"])
        assert set(line) >= {"interferometer_noise_nm", "thermometers_nm", "air_nm", REMAINDER}
        assert "servo_settling_nm" not in line           # no settling in the thermal campaign
        assert line["quadrature_sum_nm"] == pytest.approx(
            line["achievable_floor_nm"], rel=BUDGET_TOLERANCE), (a, line)
        assert budget["adds_up"][a]


@pytest.mark.xfail(strict=True, reason=(
    "the floor fitted from the library's starting values only: the z thermometer line, 29.4 nm, "
    "is 1.7x the y line (17.1 nm), not above 2x"))
def test_the_thermometers_set_the_floor_through_the_frame_arm(budget):
    """The robot hangs from a 0.6 m arm along x: the thermometers, through the frame's lift and
    that lever, are the largest of the floor's sources on Z (above the interferometers' noise)
    and reach X far more than Y; on X the frame's and the table's are the largest; a sensor on
    an arm (a short lever) is not. (Measured at this scale, true model in its deepest basin:
    z 24.3 vs 8.0 nm, thermometers x 7.2 vs y 2.3 nm.)"""
    assert budget["z"]["thermometers_nm"] > budget["z"]["interferometer_noise_nm"]
    assert budget["x"]["thermometers_nm"] > 2 * budget["y"]["thermometers_nm"]
    by_sensor = budget["thermometers_by_sensor_nm"]
    assert set(by_sensor) == {f"T_{s}_C" for s in Scenario.load("paper-thermal").sensors}
    biggest = max(by_sensor, key=lambda c: by_sensor[c]["x"])
    assert biggest in ("T_frame_C", "T_table_C")
    assert by_sensor["T_arm1_C"]["x"] < 0.1 * by_sensor[biggest]["x"]
    text = "\n".join(budget_lines(budget))
    assert "thermometers" in text and "achievable_floor" in text and biggest in text
    assert "do not add up" not in text
    assert "do not add up to the floor on x" in "\n".join(
        budget_lines({**budget, "adds_up": {**budget["adds_up"], "x": False}}))


def test_predicted_budget_of_laboratory_data(thermal):
    """Laboratory data (no truth): the budget from the instruments' specifications and the
    fitted model's sensitivities. Without a barometer the air line is the pressure's stated
    wander since each session's zero through the index's dn/dp (2.7e-9/Pa) over each beam's
    dead path: a white wander of 80 Pa gives 1.645 x 80 Pa x dn/dp x dead path (90 %); the
    papers' wander, 80 Pa over a day, moves little in a session and gives far less. The
    thermometers' line is there, one row per sensor with a lever."""
    sc, df, meta, fit = thermal
    white = predicted_floor_budget(fit, df, meta, sc.settings,
                                   climate={"pressure_time_s": 0.0}).set_index("source")
    air = white.loc["air (unrecorded pressure 80 Pa white)"]
    dead = nominal_dead_path(sc.params.mirror_cube_size_m)
    for a in ("x", "y"):
        assert air[f"{a}_p90_nm"] == pytest.approx(1.645 * 2.7e-9 * 80 * dead[a] * 1e9,
                                                   rel=0.05)
    table = predicted_floor_budget(fit, df, meta, sc.settings).set_index("source")
    slow = table.loc["air (unrecorded pressure 80 Pa wander over 24 h)"]
    assert 0 < slow["all_p90_nm"] < 0.5 * air["all_p90_nm"]
    assert any(s.startswith("thermometers (") for s in table.index)
    sensors = table[table["kind"] == "thermometer"]
    assert {s.split(" ")[0] for s in sensors.index} <= {c for c in df if c.startswith("T_")}
    assert len(sensors) >= 5


@pytest.mark.slow
def test_predicted_air_line_agrees_with_the_twins_refitted_air():
    """The predicted budget's air line (the scenario's stated wander, 80 Pa over 24 h, since
    each session's zero, through the refitted true model's levers and its first-order refit)
    against the twin's own air: the true model refitted on the twin with the air's error alone
    and with every source perfect, the difference of their validation residuals, pooled over 8
    campaigns (a slow wander: one path per campaign). Within 20 % (measured: 3.61 vs 3.60 nm;
    vs the readings up to the session zeros 3.43 nm)."""
    check = air_line_check("paper-force", 0.05, range(8))
    assert check["budget"]["all"] == pytest.approx(check["twin_refit"]["all"], rel=0.2)
    assert check["budget"]["all"] == pytest.approx(check["twin"]["all"], rel=0.2)
