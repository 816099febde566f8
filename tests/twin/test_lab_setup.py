"""The laboratory's setup a dataset carries (twin/lab_setup.py): a scenario's [hidden] known
constants and baseline in its metadata, a laboratory's setup file checked key by key, and the
constants merged, compared and stated on a command line."""
from pathlib import Path

import pytest

from deltatwin.twin.dataset import DatasetError, read_dataset, write_dataset
from deltatwin.twin.effects import make_effect
from deltatwin.twin.lab_setup import (
    SetupError,
    beyond_setup,
    check_known,
    fixed_constants,
    known_constants,
    load_setup,
    merged,
    overridden,
    set_options,
    used_constants,
    with_setup,
)
from deltatwin.twin.scenario import Scenario

EXAMPLE = Path(__file__).resolve().parents[2] / "docs" / "lab-setup.toml"
ARM = {"loop_drift": {"frame_arm_m": [-0.6, 0.0]}}


def test_a_hidden_scenario_s_metadata_carries_its_known_constants_and_baseline():
    sc = Scenario.load("hidden/loop-drift")
    meta = sc.metadata(sc.build(0.01)[0], 0.01)
    # and the set point of its Peltier-held supports, which the laboratory sets and so knows
    held = {"peltier_supports": {"setpoint_C": 25.0},
            "room_climate": {"air_support_share": 0.2222, "air_table_share": 0.037}}
    assert meta["setup"] == {"source": "scenario hidden/loop-drift", "known": {**ARM, **held},
                             "baseline": ["geometric_errors", "thermal_expansion",
                                          "sensor_contact"]}
    assert known_constants(meta) == {**ARM, **held}
    # a scenario without [hidden] states no baseline; its laboratory's geometry, where it is
    # not the library's (paper-thermal hangs its robot from a 0.6 m arm), it knows
    plain = Scenario.load("paper-thermal")
    assert plain.metadata(plain.build(0.01)[0], 0.01)["setup"] == {
        "source": "scenario paper-thermal", "known": {**ARM, **held}}


def test_the_setup_states_the_constants_a_model_never_fits_where_they_are_not_the_library_s():
    """fixed_constants: a parameter without a fit scale, away from its default, of an effect
    with a model form; a fitted parameter (the loop's expansion coefficients), a default value
    (its height) or an effect without a model form (the room's climate) is not stated."""
    effects = [make_effect("loop_drift", {"frame_arm_m": [-0.6, 0.0], "table_cte_per_K": 3e-5}),
               make_effect("room_climate", {"wander_std_C": 0.3}),
               make_effect("air_refraction")]
    assert fixed_constants(effects) == ARM
    assert fixed_constants([make_effect("loop_drift")]) == {}


def test_the_documented_example_setup_file_is_read_as_written():
    setup = load_setup(EXAMPLE)
    assert setup["known"] == {**ARM, "peltier_supports": {"setpoint_C": 25.0},
                              "room_climate": {"air_support_share": 0.22,
                                               "air_table_share": 0.037}}
    assert setup["baseline"] == ["geometric_errors", "thermal_expansion", "sensor_contact",
                                 "loop_drift"]
    assert setup["instruments"]["T_noise_C"] == 0.003
    assert setup["sensors"]["table"] == "table"


@pytest.mark.parametrize("text, words", [
    ("[known.loop_drift]\nframe_arm_mm = [-600, 0]", ["known.loop_drift", "'frame_arm_mm'",
                                                      "did you mean 'frame_arm_m'"]),
    ("[known.loop_drfit]\nframe_arm_m = [-0.6, 0]", ["known.loop_drfit", "unknown effect",
                                                     "did you mean 'loop_drift'"]),
    ("[known.loop_drift]\nframe_arm_m = -0.6", ["known.loop_drift.frame_arm_m",
                                                "expected shape (2,)"]),
    ("[known.loop_drift]\nframe_arm_m = ['-0.6 m', 0]", ["known.loop_drift.frame_arm_m",
                                                        "expected a number (m)"]),
    ("[known]\nloop_drift = 0.6", ["known.loop_drift", "a table of parameter = value"]),
    ("[instruments]\ninterferometer_noise_m = 5", ["instruments.interferometer_noise_m = 5",
                                                   "in m, 0 to 1e-06"]),
    ("[instruments]\nT_noise_mK = 3", ["instruments", "'T_noise_mK'", "did you mean"]),
    ("[instruments]\nT_noise_C = true", ["instruments.T_noise_C = True", "in K"]),
    ("baseline = ['geometric_error']", ["baseline", "did you mean 'geometric_errors'"]),
    ("baseline = 'geometric_errors'", ["baseline = 'geometric_errors'", "a list"]),
    ("baseline = ['loop_drift', 'loop_drift']", ["baseline", "'loop_drift' is named twice"]),
    ("", ["states nothing", "known"]),
    ("[sensors]\nbase = 'bse'", ["sensors.base = 'bse'", "unknown part", "'base'"]),
    ("[sensors]\n'T base' = 'base'", ["sensors.T base", "letters, digits and _"]),
    ("[know.loop_drift]\nframe_arm_m = [-0.6, 0]", ["unknown key 'know'", "'known'"]),
    ("format_version = 2", ["format_version = 2", "version 1"]),
    ("[known.loop_drift\n", ["not a TOML setup file"]),
])
def test_a_bad_setup_file_is_refused_naming_the_file_and_the_key(tmp_path, text, words):
    path = tmp_path / "lab.toml"
    path.write_text(text)
    with pytest.raises(SetupError) as exc:
        load_setup(path)
    message = str(exc.value)
    assert message.startswith(f"{path}: ") and "\n" not in message, message
    for w in words:
        assert w in message, message


def test_a_missing_setup_file_or_a_folder_is_named(tmp_path):
    for path, words in ((tmp_path / "none.toml", "no such setup file"),
                        (tmp_path, "is a folder")):
        with pytest.raises(SetupError, match=words):
            load_setup(path)


def test_a_setup_file_replaces_the_tables_it_gives_and_keeps_the_others():
    meta = {"setup": {"source": "scenario x", "known": ARM, "baseline": ["geometric_errors"]},
            "instruments": {"T_noise_C": 0.003, "kind": "sim"}, "sensors": {"base": "base"}}
    new = with_setup(meta, {"instruments": {"T_noise_C": 0.01},
                            "known": {"gravity_sag": {"load_factor": 2.0}}},
                     "lab.toml", ["T_base_C"])
    assert new["setup"] == {"source": "lab.toml", "known": {"gravity_sag": {"load_factor": 2.0}},
                            "baseline": ["geometric_errors"]}
    assert new["instruments"] == {"T_noise_C": 0.01, "kind": "sim"}
    assert new["sensors"] == {"base": "base"} and meta["setup"]["known"] == ARM   # a copy
    with pytest.raises(SetupError, match=r"lab.toml: sensors: \['frame'\] have no column "
                                         "T_frame_C"):
        with_setup(meta, {"sensors": {"frame": "frame"}}, "lab.toml", ["T_base_C"])


def test_a_damaged_setup_in_a_dataset_is_refused_when_read(tmp_path):
    sc = Scenario.load("hidden/loop-drift")
    df, meta = sc.simulate(0.01)
    meta["setup"]["known"] = {"loop_drift": {"frame_arm_m": "-0.6"}}
    write_dataset(df, meta, tmp_path / "d.parquet")
    with pytest.raises(DatasetError, match=r"d.parquet: metadata setup: known.loop_drift."
                                           "frame_arm_m: expected a number"):
        read_dataset(tmp_path / "d.parquet")


def test_constants_merge_parameter_by_parameter_and_only_overrides_are_stated():
    setup = {"loop_drift": {"frame_arm_m": [-0.6, 0.0], "frame_height_m": 0.35}}
    given = {"loop_drift": {"frame_arm_m": [-0.5, 0.0]}}
    assert merged(setup, given) == {"loop_drift": {"frame_arm_m": [-0.5, 0.0],
                                                   "frame_height_m": 0.35}}
    assert overridden(given, setup) == [("loop_drift.frame_arm_m", [-0.5, 0.0], [-0.6, 0.0])]
    assert overridden(setup, setup) == []
    # a model with the setup's arm needs no --set; another arm, or the default arm where the
    # setup gives one, does
    drift = make_effect("loop_drift", {"frame_arm_m": [-0.6, 0.0]})
    used = used_constants([drift], {}, setup)
    assert used == {"loop_drift": {"frame_arm_m": [-0.6, 0.0], "frame_height_m": 0.35}}
    assert beyond_setup(used, setup) == {}
    portal = used_constants([make_effect("loop_drift")], {}, setup)
    assert set_options(beyond_setup(portal, setup)) == " --set loop_drift.frame_arm_m=0.0,0.0"
    # without a setup the constants off the library's defaults are stated
    assert set_options(beyond_setup(used_constants([drift], {}, {}), {})) == \
        " --set loop_drift.frame_arm_m=-0.6,0.0"


@pytest.mark.parametrize("shares, words", [
    ({"air_support_share": 0.8, "air_table_share": 0.2}, "sum below 0.9"),
    ({"air_support_share": -0.1}, "not negative"),
])
def test_the_room_s_shares_of_the_beams_air_are_refused_where_no_room_is_left(shares, words):
    """A setup's shares of the beams' air temperature (room_climate air_support_share,
    air_table_share) that leave the room no share, or are negative, are refused by name: a
    room estimated from them would be meaningless."""
    with pytest.raises(SetupError, match=words):
        check_known({"room_climate": shares}, "lab.toml known")
