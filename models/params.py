"""The robot's parameter set: one TOML file <-> one typed, validated, immutable object.

Every quantity is SI (m, rad, Pa, kg); temperatures are degC and say so in their name.
``RobotParams.replace(**changes)`` returns a validated copy, which is how the physics varies
geometry errors and part temperatures.  Unknown keys, wrong shapes, negative or impossible
lengths are errors that name the file and the key.
"""
from __future__ import annotations

import copy
import dataclasses
import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from deltatwin.files import toml_text

FORMAT_VERSION = 1             # of the parameter TOML files this module writes and reads
DEFAULT_PARAMS_PATH = Path(__file__).with_name("delta_agietron") / "params.toml"


class ParameterError(ValueError):
    """A parameter file or value that is malformed or physically impossible."""


@dataclass(frozen=True)
class Material:
    youngs_modulus_Pa: float
    poisson: float
    cte_per_K: float
    density_kg_m3: float
    allowable_stress_Pa: float

    @property
    def shear_modulus_Pa(self) -> float:
        return self.youngs_modulus_Pa / (2.0 * (1.0 + self.poisson))


# (TOML section.key, attribute, shape, rule) ; rule: "pos" > 0, "nonneg" >= 0, "any", "str"
_SCHEMA: tuple[tuple[str, str, tuple, str], ...] = (
    ("meta.name", "name", (), "str"),
    ("meta.reference_temperature_C", "reference_temperature_C", (), "temp"),
    ("geometry.base_radius_m", "base_radius_m", (), "pos"),
    ("geometry.actuator_azimuth_deg", "actuator_azimuth_deg", (3,), "any"),
    ("geometry.arm_length_m", "arm_length_m", (), "pos"),
    ("geometry.elbow_half_width_m", "elbow_half_width_m", (), "pos"),
    ("geometry.rod_length_m", "rod_length_m", (), "pos"),
    ("geometry.platform_radius_m", "platform_radius_m", (), "pos"),
    ("geometry.platform_half_width_m", "platform_half_width_m", (), "pos"),
    ("geometry.home_angle_rad", "home_angle_rad", (), "any"),
    ("geometry.stroke_rad", "stroke_rad", (2,), "any"),
    ("geometry.mirror_cube_offset_m", "mirror_cube_offset_m", (3,), "any"),
    ("geometry.mirror_cube_size_m", "mirror_cube_size_m", (), "pos"),
    ("geometry.magnet_radius_m", "magnet_radius_m", (), "nonneg"),
    ("geometry.magnet_azimuth_deg", "magnet_azimuth_deg", (3,), "any"),
    ("geometry.coil_gap_m", "coil_gap_m", (), "pos"),
    ("deviations.rod_length_m", "d_rod_length_m", (3, 2), "any"),
    ("deviations.arm_length_m", "d_arm_length_m", (3,), "any"),
    ("deviations.base_joint_m", "d_base_joint_m", (3, 3), "any"),
    ("deviations.elbow_joint_m", "d_elbow_joint_m", (3, 2, 3), "any"),
    ("deviations.platform_joint_m", "d_platform_joint_m", (3, 2, 3), "any"),
    ("deviations.encoder_offset_rad", "encoder_offset_rad", (3,), "any"),
    ("deviations.actuator_axis_tilt_rad", "actuator_axis_tilt_rad", (3, 2), "any"),
    ("temperatures_C.base", "T_base_C", (), "temp"),
    ("temperatures_C.arms", "T_arms_C", (3,), "temp"),
    ("temperatures_C.rods", "T_rods_C", (3, 2), "temp"),
    ("temperatures_C.platform", "T_platform_C", (), "temp"),
    ("parts.base", "material_base", (), "str"),
    ("parts.arms", "material_arms", (), "str"),
    ("parts.rods", "material_rods", (), "str"),
    ("parts.platform", "material_platform", (), "str"),
    ("parts.mirror_cube", "material_mirror_cube", (), "str"),
    ("flexure.leaf_length_m", "flexure_leaf_length_m", (), "pos"),
    ("flexure.leaf_thickness_m", "flexure_leaf_thickness_m", (), "pos"),
    ("flexure.leaf_width_m", "flexure_leaf_width_m", (), "pos"),
    ("rod.diameter_m", "rod_diameter_m", (), "pos"),
    ("arm.width_m", "arm_width_m", (), "pos"),
    ("arm.thickness_m", "arm_thickness_m", (), "pos"),
    ("arm.prbm_gamma", "prbm_gamma", (), "pos"),
    ("arm.prbm_stiffness_coefficient", "prbm_stiffness_coefficient", (), "pos"),
    ("drive.torsional_stiffness_Nm_per_rad", "drive_stiffness_Nm_per_rad", (), "pos"),
    ("mass.platform_kg", "platform_mass_kg", (), "nonneg"),
)
_MATERIAL_KEYS = tuple(f.name for f in dataclasses.fields(Material))


@dataclass(frozen=True)
class RobotParams:
    """All parameters of the robot. Arrays are float64 and read-only."""
    name: str
    reference_temperature_C: float
    base_radius_m: float
    actuator_azimuth_deg: np.ndarray
    arm_length_m: float
    elbow_half_width_m: float
    rod_length_m: float
    platform_radius_m: float
    platform_half_width_m: float
    home_angle_rad: float
    stroke_rad: np.ndarray
    mirror_cube_offset_m: np.ndarray
    mirror_cube_size_m: float
    magnet_radius_m: float
    magnet_azimuth_deg: np.ndarray
    coil_gap_m: float
    d_rod_length_m: np.ndarray
    d_arm_length_m: np.ndarray
    d_base_joint_m: np.ndarray
    d_elbow_joint_m: np.ndarray
    d_platform_joint_m: np.ndarray
    encoder_offset_rad: np.ndarray
    actuator_axis_tilt_rad: np.ndarray
    T_base_C: float
    T_arms_C: np.ndarray
    T_rods_C: np.ndarray
    T_platform_C: float
    material_base: str
    material_arms: str
    material_rods: str
    material_platform: str
    material_mirror_cube: str
    flexure_leaf_length_m: float
    flexure_leaf_thickness_m: float
    flexure_leaf_width_m: float
    rod_diameter_m: float
    arm_width_m: float
    arm_thickness_m: float
    prbm_gamma: float
    prbm_stiffness_coefficient: float
    drive_stiffness_Nm_per_rad: float
    platform_mass_kg: float
    materials: dict = field(default_factory=dict)
    source: str = "<code>"

    def __post_init__(self):
        for key, attr, shape, rule in _SCHEMA:
            object.__setattr__(self, attr, _check(getattr(self, attr), shape, rule, self.source, key))
        _check_consistency(self)

    def material(self, part: str) -> Material:
        """Material of a part: base, arms, rods, platform, mirror_cube."""
        return self.materials[getattr(self, f"material_{part}")]

    def replace(self, **changes) -> RobotParams:
        """A validated copy with some attributes changed (the changed arrays are copied). Only
        the changed fields are checked again, and the whole set's consistency: the others were
        checked when this set was made and are read-only (a model evaluation replaces the
        geometric errors of a set of ~40 fields, re-validating all of them was ~0.2 ms)."""
        unknown = sorted(set(changes) - _FIELDS)
        if unknown:
            raise ParameterError(f"unknown robot parameter(s) {unknown}")
        out = copy.copy(self)
        source = changes.get("source", self.source)
        for attr, value in changes.items():
            if attr in _SCHEMA_OF:
                key, shape, rule = _SCHEMA_OF[attr]
                value = _check(value, shape, rule, source, key)
            object.__setattr__(out, attr, value)
        _check_consistency(out)
        return out

    def to_toml(self) -> str:
        """The parameter set as TOML text that ``load_params`` reads back identically."""
        doc: dict = {"format_version": FORMAT_VERSION}
        for key, attr, _, _rule in _SCHEMA:
            sec, name = key.split(".")
            doc.setdefault(sec, {})[name] = getattr(self, attr)
        doc["materials"] = {mname: {k: getattr(mat, k) for k in _MATERIAL_KEYS}
                            for mname, mat in self.materials.items()}
        return toml_text(doc)


_FIELDS = frozenset(f.name for f in dataclasses.fields(RobotParams))
_SCHEMA_OF = {attr: (key, shape, rule) for key, attr, shape, rule in _SCHEMA}


def _check(value, shape, rule, source, key):
    if rule == "str":
        if not isinstance(value, str) or not value:
            raise ParameterError(f"{source}: '{key}' must be a non-empty string, got {value!r}")
        return value
    try:
        arr = np.array(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ParameterError(f"{source}: '{key}' must be a number or array of numbers, "
                             f"got {value!r}") from None
    if arr.shape != shape:
        raise ParameterError(f"{source}: '{key}' must have shape {shape}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ParameterError(f"{source}: '{key}' must be finite, got {value!r}")
    if rule == "pos" and np.any(arr <= 0):
        raise ParameterError(f"{source}: '{key}' must be > 0, got {value!r}")
    if rule == "nonneg" and np.any(arr < 0):
        raise ParameterError(f"{source}: '{key}' must be >= 0, got {value!r}")
    if rule == "temp" and np.any((arr < -50) | (arr > 150)):
        raise ParameterError(f"{source}: '{key}' = {value!r} degC is outside -50..150 degC")
    if arr.ndim == 0:
        return float(arr)
    arr.setflags(write=False)
    return arr


def _check_consistency(p: RobotParams) -> None:
    src = p.source
    lo, hi = p.stroke_rad
    if not lo < hi:
        raise ParameterError(f"{src}: 'geometry.stroke_rad' must be [low, high] with low < high, "
                             f"got {p.stroke_rad}")
    for part in ("base", "arms", "rods", "platform", "mirror_cube"):
        m = getattr(p, f"material_{part}")
        if m not in p.materials:
            raise ParameterError(f"{src}: 'parts.{part}' names material '{m}', which has no "
                                 f"[materials.{m}] table (have {sorted(p.materials)})")
    rods = p.rod_length_m + p.d_rod_length_m
    if np.any(rods <= 0):
        raise ParameterError(f"{src}: rod length with 'deviations.rod_length_m' must be > 0, "
                             f"got {rods.tolist()}")
    arms = p.arm_length_m + p.d_arm_length_m
    if np.any(arms <= 0):
        raise ParameterError(f"{src}: arm length with 'deviations.arm_length_m' must be > 0, "
                             f"got {arms.tolist()}")
    if p.flexure_leaf_thickness_m >= p.flexure_leaf_width_m:
        raise ParameterError(f"{src}: 'flexure.leaf_thickness_m' ({p.flexure_leaf_thickness_m}) must be "
                             f"smaller than 'flexure.leaf_width_m' ({p.flexure_leaf_width_m})")
    if 2 * p.flexure_leaf_length_m >= 0.5 * p.rod_length_m:
        raise ParameterError(f"{src}: two flexures of 'flexure.leaf_length_m' = {p.flexure_leaf_length_m} m "
                             f"take more than half of the rod ({p.rod_length_m} m)")
    reach = p.base_radius_m + p.arm_length_m - p.platform_radius_m
    if p.rod_length_m <= abs(p.base_radius_m - p.platform_radius_m) - p.arm_length_m or \
            p.rod_length_m <= 0.2 * reach:
        raise ParameterError(f"{src}: 'geometry.rod_length_m' = {p.rod_length_m} m cannot close the "
                             f"loop with base/arm/platform radii (horizontal reach {reach:.4f} m)")
    if not 0 < p.prbm_gamma <= 1:
        raise ParameterError(f"{src}: 'arm.prbm_gamma' must be in (0, 1], got {p.prbm_gamma}")
    for name, m in p.materials.items():
        if not (m.youngs_modulus_Pa > 0 and 0 <= m.poisson < 0.5 and m.density_kg_m3 > 0
                and m.allowable_stress_Pa > 0 and math.isfinite(m.cte_per_K)):
            raise ParameterError(f"{src}: [materials.{name}] has an impossible value: {m}")


def params_from_dict(data: dict, source: str = "<dict>") -> RobotParams:
    """Build RobotParams from the nested TOML structure; every key is checked."""
    known = {k for k, *_ in _SCHEMA}
    data = dict(data)
    version = data.pop("format_version", FORMAT_VERSION)    # hand-written files may omit it
    if not isinstance(version, int) or isinstance(version, bool) or version > FORMAT_VERSION:
        raise ParameterError(f"{source}: format_version = {version!r}; this deltatwin reads "
                             f"parameter files up to version {FORMAT_VERSION}")
    kwargs = {}
    for sec, table in data.items():
        if sec == "materials":
            continue
        if not isinstance(table, dict):
            raise ParameterError(f"{source}: '{sec}' must be a table")
        for name in table:
            if f"{sec}.{name}" not in known:
                raise ParameterError(f"{source}: unknown key '{sec}.{name}'"
                                     + _suggest(f"{sec}.{name}", known))
    for key, attr, _, _ in _SCHEMA:
        sec, name = key.split(".")
        if sec not in data or name not in data[sec]:
            raise ParameterError(f"{source}: missing key '{key}'")
        kwargs[attr] = data[sec][name]
    materials = {}
    for mname, mt in data.get("materials", {}).items():
        missing = [k for k in _MATERIAL_KEYS if k not in mt]
        extra = [k for k in mt if k not in _MATERIAL_KEYS]
        if missing or extra:
            raise ParameterError(f"{source}: [materials.{mname}] missing {missing} / unknown {extra}")
        try:
            materials[mname] = Material(**{k: float(mt[k]) for k in _MATERIAL_KEYS})
        except (TypeError, ValueError):
            raise ParameterError(f"{source}: [materials.{mname}] values must be numbers") from None
    return RobotParams(**kwargs, materials=materials, source=source)


def _suggest(key: str, known) -> str:
    import difflib
    close = difflib.get_close_matches(key, sorted(known), n=1)
    return f" (did you mean '{close[0]}'?)" if close else ""


def load_params(path: str | Path | None = None) -> RobotParams:
    """Load a parameter TOML file (default: the nominal Agietron Micro-Nano set)."""
    path = Path(path) if path is not None else DEFAULT_PARAMS_PATH
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ParameterError(f"{path}: parameter file not found") from None
    except IsADirectoryError:
        raise ParameterError(f"{path}: is a folder, not a parameter file") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise ParameterError(f"{path}: malformed TOML ({exc})") from None
    return params_from_dict(data, str(path))
