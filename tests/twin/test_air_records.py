"""The laboratory's air records: a barometer and a hygrometer as instruments of the
common interface, their columns (p_Pa, RH_pct) in the dataset, the same through the interface as
through the fast path, and the physics model reading them."""
import dataclasses

import numpy as np
import pandas as pd
import pytest

from deltatwin.calibration.errors import CalibrationInputError
from deltatwin.calibration.physics.measurements import measurements
from deltatwin.twin.scenario import SCENARIO_DIR, Scenario, ScenarioError

AIR = """
[instruments]
noise_floor_m = 5e-9
cosine_correction = true
barometer = true
hygrometer = true
"""


def _scenario(tmp_path, instruments=AIR, climate="vapour_std_Pa = 50.0\n"):
    """paper-thermal with the lab's air recorded (or as ``instruments`` says)."""
    text = (SCENARIO_DIR / "paper-thermal.toml").read_text()
    head, tail = text.split("[instruments]")
    tail = tail.split("[campaign]")[1]
    text = head.replace("daily_amplitude_C = 1.4", "daily_amplitude_C = 1.4\n" + climate) \
        + instruments + "\n[campaign]" + tail
    path = tmp_path / "air.toml"
    path.write_text(text)
    return Scenario.load(path)


def test_barometer_and_hygrometer_columns_same_through_interface_and_fast_path(tmp_path):
    """The records agree exactly between the vectorised campaign and the one run call by call
    through the instruments; their noise is the instrument's (1.5 Pa, 0.2 %RH std, against the
    twin's air at the scan times) and they sit on the resolution's grid (0.1 Pa, 0.1 %RH)."""
    sc = _scenario(tmp_path)
    df, _ = sc.simulate(0.01)
    df_i, _ = sc.run(0.01, progress=False)
    assert {"p_Pa", "RH_pct"} <= set(df.columns)
    np.testing.assert_array_equal(df[["p_Pa", "RH_pct"]], df_i[["p_Pa", "RH_pct"]])
    twin, plan = sc.build(0.01)
    big, _ = sc.simulate(0.2)
    twin, _ = sc.build(0.2)
    twin.advance(float(big["t_s"].max()), twin.schedule)
    # the twin's air at each row's scan: the noise-free record
    k = np.floor(big["t_s"].to_numpy() / sc.settings.scan_period_s)
    air = twin.air(k * sc.settings.scan_period_s)
    dp = big["p_Pa"].to_numpy() - air["pressure_Pa"]
    drh = big["RH_pct"].to_numpy() - air["humidity_pct"]
    # one record per scan: rows sharing a scan share a draw
    _, first = np.unique(k, return_index=True)
    assert np.std(dp[first]) == pytest.approx(np.hypot(1.5, 0.1 / np.sqrt(12)), rel=0.15)
    assert np.std(drh[first]) == pytest.approx(np.hypot(0.2, 0.1 / np.sqrt(12)), rel=0.15)
    assert np.allclose(big["p_Pa"] / 0.1, np.round(big["p_Pa"] / 0.1), atol=1e-6)
    # the pressure wanders (80 Pa std) and the humidity with the vapour and the temperature
    assert np.ptp(air["pressure_Pa"]) > 20 and np.ptp(air["humidity_pct"]) > 1


def test_a_lab_without_barometer_records_no_air_and_other_columns_do_not_change(tmp_path):
    """No barometer, no hygrometer (the papers' lab): no columns; every other column is what
    it is with them (their noise has its own stream)."""
    with_air, _ = _scenario(tmp_path).simulate(0.01)
    without, _ = _scenario(tmp_path, instruments="[instruments]\nnoise_floor_m = 5e-9\n"
                           ).simulate(0.01)
    assert "p_Pa" not in without and "RH_pct" not in without
    pd.testing.assert_frame_equal(with_air.drop(columns=["p_Pa", "RH_pct"]), without)


@pytest.mark.parametrize("value, words", [("\"yes\"", "expected true"),
                                          ("1", "expected true")])
def test_barometer_switch_must_be_a_boolean(tmp_path, value, words):
    with pytest.raises(ScenarioError, match=f"barometer = .*{words}"):
        _scenario(tmp_path, instruments=f"[instruments]\nbarometer = {value}\n")


def test_the_model_reads_the_recorded_pressure_and_humidity(tmp_path):
    """measurements(): the air's pressure is the barometer's record and its water vapour the
    hygrometer's relative humidity times the saturation pressure at the beams' air: within the
    instruments' noise of the twin's true air (vapour: 0.2 %RH of ~2.7 kPa, 5.5 Pa std, the
    thermometers' reading of the beams' air adding less); without a record, the assumed
    constants."""
    sc = _scenario(tmp_path)
    df, meta = sc.simulate(0.05)
    twin, _ = sc.build(0.05)
    twin.advance(float(df["t_s"].max()), twin.schedule)
    k = np.floor(df["t_s"].to_numpy() / sc.settings.scan_period_s)
    air = twin.air(k * sc.settings.scan_period_s)
    pts = measurements(df, meta, sc.params).points
    n = len(df)
    assert np.abs(pts.pressure_Pa[:n] - air["pressure_Pa"]).max() < 5 * 1.5
    dv = pts.vapour_Pa[:n] - air["vapour_Pa"]
    assert np.std(dv) < 7.0 and np.abs(dv).max() < 5 * 5.5
    bare = measurements(df.drop(columns=["p_Pa", "RH_pct"]), meta, sc.params).points
    assert bare.vapour_Pa is None and np.all(bare.pressure_Pa == 101325.0)
    with pytest.raises(CalibrationInputError, match="'p_Pa' is empty at row"):
        measurements(df.assign(p_Pa=df["p_Pa"].where(df.index != 3)), meta, sc.params)


def test_recorded_air_brings_the_true_models_floor_down(tmp_path):
    """With air refraction in the truth and 80 Pa of pressure wander, the twin's complete model
    refitted on the data (the achievable floor) is lower when it reads the barometer and
    hygrometer than when the same data lack the columns (the wander is then part of the floor).
    The wander's correlation time is cut to 1 h (a short campaign at this scale would see little
    of a day's) and the other instruments made quiet, so that the air is what the floor is."""
    from deltatwin.calibration.diagnosis.floor import achievable_floor

    sc = _scenario(tmp_path, climate="vapour_std_Pa = 50.0\npressure_time_s = 3600.0\n")
    sc = dataclasses.replace(sc, settings=dataclasses.replace(
        sc.settings, T_noise_C=0.0, T_resolution_C=0.0, noise_floor_m=1e-9))
    df, meta = sc.simulate(0.03)
    recorded = achievable_floor(df, meta)["achievable_floor_nm"]
    unrecorded = achievable_floor(df.drop(columns=["p_Pa", "RH_pct"]), meta)["achievable_floor_nm"]
    print("recorded", recorded, "unrecorded", unrecorded)
    assert recorded["all"] < 0.8 * unrecorded["all"]


def test_the_air_a_reading_sees_as_the_laboratory_states_it():
    """Scenario.air_wander: without a barometer the room's wander (room_climate's std and
    correlation time), with one the record's noise and resolution, white; none where the air
    does not reach the readings."""
    sc = Scenario.load("paper-thermal")
    assert sc.air_wander()["pressure_Pa"] == (80.0, 86400.0)
    recorded = dataclasses.replace(sc, settings=dataclasses.replace(sc.settings, barometer=True))
    std, time_s = recorded.air_wander()["pressure_Pa"]
    assert time_s == 0.0 and std == np.hypot(sc.settings.barometer_noise_Pa,
                                             sc.settings.barometer_resolution_Pa / np.sqrt(12))
    still = dataclasses.replace(sc, effects=[e for e in sc.effects if e.name != "air_refraction"])
    assert still.air_wander()["pressure_Pa"] == (0.0, 0.0)
