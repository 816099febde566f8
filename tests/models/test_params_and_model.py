"""Parameter file validation, MJCF building/export, in-place model updates, model CLI."""
import dataclasses
import json

import mujoco
import numpy as np
import pytest

from deltatwin.cli import main
from deltatwin.models.geometry import build_geometry
from deltatwin.models.mjcf import build_model, is_room_body, update_model
from deltatwin.models.params import (
    DEFAULT_PARAMS_PATH,
    ParameterError,
    RobotParams,
    load_params,
)


def _write(tmp_path, text):
    f = tmp_path / "p.toml"
    f.write_text(text)
    return f


def test_round_trip_to_toml(tmp_path):
    p = load_params()
    q = load_params(_write(tmp_path, p.to_toml()))
    assert np.array_equal(q.T_rods_C, p.T_rods_C) and q.rod_length_m == p.rod_length_m


@pytest.mark.parametrize("old,new,match", [
    ("rod_length_m = 0.110", "rod_length_m = -0.110", "geometry.rod_length_m' must be > 0"),
    ("leaf_width_m = 0.005", "leaf_widht_m = 0.005", "unknown key 'flexure.leaf_widht_m'.*leaf_width_m"),
    ("encoder_offset_rad = [0.0, 0.0, 0.0]", "encoder_offset_rad = [0.0, 0.0]", "shape"),
    ("[geometry]", "[geometry", "malformed TOML"),
    ("rods = \"titanium\"", "rods = \"unobtainium\"", "unobtainium"),
])
def test_bad_parameter_files_name_the_key(tmp_path, old, new, match):
    text = DEFAULT_PARAMS_PATH.read_text()
    assert old in text
    with pytest.raises(ParameterError, match=match):
        load_params(_write(tmp_path, text.replace(old, new, 1)))


def test_impossible_deviation_is_rejected():
    p = load_params()
    with pytest.raises(ParameterError, match="rod length"):
        p.replace(d_rod_length_m=np.full((3, 2), -0.2))


def test_temperature_scales_parts_by_their_cte():
    p = load_params()
    hot = p.replace(T_rods_C=np.full((3, 2), 30.0), T_base_C=25.0)
    g0, g1 = build_geometry(p), build_geometry(hot)
    assert np.allclose(g1.L / g0.L, 1 + 8.6e-6 * 10, rtol=0, atol=1e-15)
    assert np.allclose(g1.B, g0.B * (1 + 8.6e-6 * 5), rtol=0, atol=1e-15)


def test_update_model_matches_a_fresh_compile():
    p = load_params()
    spec, m = build_model(p)
    dev = np.zeros((3, 2))
    dev[1, 0] = 20e-6
    changed = p.replace(d_rod_length_m=dev, T_base_C=23.0, encoder_offset_rad=np.array([1e-4, 0, 0]),
                        d_base_joint_m=np.array([[1e-5, 0, 0], [0, 0, 0], [0, 0, 2e-5]]))
    update_model(m, changed)
    _, fresh = build_model(changed)
    robot = [b for b in range(m.nbody) if not is_room_body(m.body(b).name)]
    for attr in ("body_pos", "body_quat"):
        assert np.allclose(getattr(m, attr)[robot], getattr(fresh, attr)[robot], rtol=0, atol=1e-15), attr
    sites = [s for s in range(m.nsite) if m.site_bodyid[s] in robot]
    assert np.allclose(m.site_pos[sites], fresh.site_pos[sites], rtol=0, atol=1e-15)
    for attr in ("jnt_axis", "qpos0"):
        assert np.allclose(getattr(m, attr), getattr(fresh, attr), rtol=0, atol=1e-15), attr
    assert not np.allclose(m.site_pos, build_model(p)[1].site_pos, rtol=0, atol=1e-9)


def test_model_export_loads_in_mujoco(tmp_path, capsys):
    out = tmp_path / "robot.xml"
    assert main(["model", "export", "-o", str(out)]) == 0
    m = mujoco.MjModel.from_xml_path(str(out))
    assert m.neq == 6 and m.nu == 3
    names = {m.site(i).name for i in range(m.nsite)}
    assert {"interferometer_x", "interferometer_y", "interferometer_z", "autocollimator_1",
            "mirror_cube_centre", "coil1_face"} <= names


def test_model_info_json(capsys):
    assert main(["model", "info", "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert 0.5 < info["workspace_cm3"] < 2.0
    assert abs(info["workspace_hull_cm3"] - info["workspace_cm3"]) < 0.15 * info["workspace_cm3"]
    env = info["envelope_mm"]
    assert len(env) == 3 and all(150 < e < 300 for e in env)
    C = np.array(info["compliance_nm_per_N"])
    assert C.shape == (3, 3) and np.all(np.diag(C) > 0)
    assert info["flexure_max_stress_MPa"] < info["flexure_allowable_stress_MPa"]
    assert info["actuator_strokes"] == [[-0.065, 0.065]] * 3


def test_model_cli_bad_file_is_a_clear_error(tmp_path, capsys):
    bad = _write(tmp_path, "[geometry]\nrod_length_m = 'long'\n")
    assert main(["model", "info", "--params", str(bad)]) == 2
    assert "p.toml" in capsys.readouterr().err
    out = tmp_path / "x.xml"
    assert main(["model", "export", "-o", str(out), "--params", str(bad)]) == 2
    assert not out.exists()


def test_parameter_files_carry_a_format_version(tmp_path):
    from deltatwin.models.params import ParameterError, load_params
    text = load_params().to_toml()
    assert text.startswith("format_version = 1\n")
    path = tmp_path / "p.toml"
    path.write_text(text.replace("format_version = 1", "format_version = 2"))
    with pytest.raises(ParameterError, match="format_version = 2"):
        load_params(path)
    with pytest.raises(ParameterError, match="is a folder"):
        load_params(tmp_path)


def test_replace_checks_what_changed_and_equals_a_full_validation():
    """``replace`` re-checks only the changed fields (and the set's consistency): the copy
    equals one validated field by field from scratch, and a bad change is still named."""
    p = load_params()
    changed = p.replace(d_rod_length_m=np.full((3, 2), 1e-6), T_base_C=25)
    fresh = RobotParams(**{f.name: getattr(changed, f.name) for f in dataclasses.fields(p)})
    for f in dataclasses.fields(p):
        assert type(getattr(changed, f.name)) is type(getattr(fresh, f.name)), f.name
        np.testing.assert_array_equal(getattr(changed, f.name), getattr(fresh, f.name))
    assert not changed.d_rod_length_m.flags.writeable
    assert np.all(p.d_rod_length_m == 0) and p.T_base_C != 25
    with pytest.raises(ParameterError, match=r"temperatures_C.arms' must have shape \(3,\)"):
        p.replace(T_arms_C=np.zeros(2))
    with pytest.raises(ParameterError, match="must be finite"):
        p.replace(T_base_C=np.nan)
    with pytest.raises(ParameterError, match="unknown robot parameter"):
        p.replace(T_nowhere_C=20.0)
