"""A fitted physics model exported for a real-time controller: a documented JSON file
(``deltatwin-physics-controller``) that calibration/physics/controller_evaluator.py, numpy only,
evaluates and inverts.

What the file holds (SI units throughout; docs/compensation.md lists every field):

* ``inputs``: what the controller gives per point (motor coordinates or a target, the part and
  air temperatures, the pressure, the coil currents) and per session (the same conditions at the
  zero), with units, and how its temperature loop derives the temperatures from the sensors
  (``temperature_loop``: the causal fit, the sensor-to-part map, the sensor contact model);
* ``geometry``: the fitted robot's joint arrays at the reference temperature, the stroke, the
  cube; ``thermal``: each part's effective CTE (0 when the model has no thermal expansion);
* ``statics``: the preload deflection and the compliance at q as tensor Chebyshev series (the
  twin's flexure statics depend on q only; interpolated at (d+1)^3 Chebyshev nodes, d raised
  until points between the nodes agree to ``STATICS_TOL_M`` / ``STATICS_TOL_REL``);
* ``load``: the weight and the coil-magnet dipoles; ``optics``: heads, beams, fold mirror and
  the model's optics steps in order;
* ``evaluation``: the steps in words.

Beside it, ``FILE.bin``: the same contents as the flat float64 block the portable C evaluator
(controller_evaluator.c) loads; controller_c.py defines its layout.

Only the library's model effects are exported; a model holding another effect (a researcher's
own) is refused with its name: its form is code the evaluator does not have.
"""
from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
from numpy.polynomial import chebyshev

from deltatwin.calibration.errors import FitError
from deltatwin.calibration.physics import controller_c
from deltatwin.calibration.physics import controller_evaluator as ce
from deltatwin.calibration.physics.measurements import TEMPERATURE_WINDOW_S, Measurements
from deltatwin.calibration.physics.model import PhysicsModel
from deltatwin.files import atomic_write, atomic_write_text
from deltatwin.models.geometry import PART_TEMPERATURES, build_geometry
from deltatwin.models.kinematics import forward
from deltatwin.models.layout import FOLD_MIRROR_Z, INSTRUMENT_SITES, magnet_positions
from deltatwin.twin.instruments.optics import AXES, FOLD_TURN
from deltatwin.twin.statics import GRAVITY_M_S2, Statics

EXPORTED = {"geometric_errors", "thermal_expansion", "gravity_sag", "magnetic_force",
            "loop_drift", "air_refraction", "beam_misalignment", "sensor_contact"}
# the statics series between their nodes: the preload deflection to 1e-13 m and rad (a rotation
# moves a reading by its lever, < 0.2 m: 2e-14 m), the compliance to 1e-9 of its largest entry
# (of a load deflection < 1 um): three orders below the 1e-11 m (0.01 nm) the export must match
STATICS_TOL_M = 1e-13
STATICS_TOL_REL = 1e-9
STATICS_DEGREES = range(4, 15, 2)

EVALUATION = [
    "1. geometry: each part's joint arrays (geometry.*_m at thermal.reference_C) times "
    "1 + thermal.cte_per_K[part] * (T_part - reference_C); rods of chain i at rod<i>",
    "2. kinematic pose: Newton on |p + R P0_ij - A_ij(q)|^2 = L_ij^2 (6 equations) for the "
    "platform position p and rotation R, A_ij = B_i + rotation of arm_vec_ij by "
    "q_i + theta_zero_i about axis_i",
    "3. load: y = preload(q) + compliance(q) w (statics.*: Chebyshev series on q_range_rad), "
    "w = gravity_N + the coil-magnet dipole wrench at (p, R); the pose becomes "
    "(p + y[:3], Rodrigues(y[3:]) R)",
    "4. optics: heads, directions and the fold mirror from optics.*, changed by optics.steps in "
    "order; path_k = n_air_k h_k cos(alpha_k) on cube face k (Z through the fold mirror's image)",
    "5. reading_k = (path_k - path_k at the session's zero) / n_comp_k",
]


def _statics_series(params) -> dict:
    """Preload deflection (6) and compliance (6,6) at q as tensor Chebyshev series."""
    st = Statics(params, build_geometry(params))
    lo, hi = (float(v) for v in params.stroke_rad)
    scaled = lambda x: 0.5 * (hi + lo) + 0.5 * (hi - lo) * x

    def values(q):
        return st.solve(q, gravity=False).deflection, st.compliance(q)

    # check points between the nodes of every degree tried (deterministic)
    x = np.linspace(-0.97, 0.97, 7)
    check = scaled(np.stack(np.meshgrid(x, x, x, indexing="ij"), -1).reshape(-1, 3))
    pre_c, C_c = values(check)
    for deg in STATICS_DEGREES:
        nodes = chebyshev.chebpts1(deg + 1)
        X = np.stack(np.meshgrid(nodes, nodes, nodes, indexing="ij"), -1).reshape(-1, 3)
        pre, C = values(scaled(X))
        V = chebyshev.chebvander3d(X[:, 0], X[:, 1], X[:, 2], [deg] * 3)
        coef = np.linalg.solve(V, np.concatenate([pre, C.reshape(-1, 36)], axis=1))
        coef = coef.reshape((deg + 1,) * 3 + (42,))
        got = ce.chebyshev3(coef, lo, hi, check)
        err_pre = np.abs(got[:, :6] - pre_c).max()
        err_C = np.abs(got[:, 6:] - C_c.reshape(-1, 36)).max() / np.abs(C_c).max()
        if err_pre <= STATICS_TOL_M and err_C <= STATICS_TOL_REL:
            break
    else:
        raise FitError(f"statics: no Chebyshev degree up to {deg} reaches {STATICS_TOL_M} m "
                       f"(got {err_pre:.3g} m, compliance {err_C:.3g} relative)")
    return {"q_range_rad": [lo, hi], "degree": deg,
            "preload_coef": coef[..., :6], "compliance_coef": coef[..., 6:].reshape(
                (deg + 1,) * 3 + (6, 6)),
            "check": {"points": int(check.shape[0]), "preload_max_error_m": float(err_pre),
                      "compliance_max_relative_error": float(err_C)}}


def controller_model(model: PhysicsModel, sensors: dict | None = None,
                     source: dict | None = None) -> dict:
    """The controller file's contents (JSON-ready) of a fitted ``model``; ``sensors``: the
    calibration data's sensor -> part map (the controller's temperature loop)."""
    other = [n for n in model.names if n not in EXPORTED]
    if other:
        raise FitError(f"the model holds effect(s) {other} whose form the controller evaluator "
                       f"does not have (it exports {sorted(EXPORTED)}): refit without them or "
                       "extend calibration/physics/controller_evaluator.py")
    eff = {e.name: e for e in model.effects}
    params, geom0, home = model._robot()
    T_ref = float(params.reference_temperature_C)
    if "thermal_expansion" in eff:
        at_ref = {"base": np.full(1, T_ref), "arms": np.full((1, 3), T_ref),
                  "rods": np.full((1, 3, 2), T_ref), "platform": np.full(1, T_ref)}
        g = build_geometry(params, at_ref)
        g = {k: getattr(g, k)[0] for k in ("B", "axis", "arm_vec", "P0", "L", "theta_zero",
                                             "cube_offset")}
        f = eff["thermal_expansion"].cte_factor
        cte = {part: float(params.material(part).cte_per_K * f[k])
               for k, part in enumerate(PART_TEMPERATURES)}
    else:       # the geometry at the robot file's own part temperatures, whatever the sensors
        g = {k: getattr(geom0, k) for k in ("B", "axis", "arm_vec", "P0", "L", "theta_zero",
                                              "cube_offset")}
        cte = dict.fromkeys(PART_TEMPERATURES, 0.0)
    cube_home = home + geom0.cube_offset
    assert np.allclose(forward(geom0, np.zeros((1, 3))).p[0], home, rtol=0, atol=1e-15)
    load = {"gravity_N": None, "magnetic": None}
    if "gravity_sag" in eff:
        load["gravity_N"] = [0.0, 0.0, -eff["gravity_sag"].load_factor
                             * params.platform_mass_kg * GRAVITY_M_S2]
    if "magnetic_force" in eff:
        m = eff["magnetic_force"]
        load["magnetic"] = {"magnet_moment_Am2": m.magnet_moment_Am2,
                            "coil_moment_per_A": m.coil_moment_per_A,
                            "magnets_platform_m": magnet_positions(params),
                            "coils_m": m.coil_dipoles(params, home)}
    steps = []
    for e in model.effects:
        if e.name in ("loop_drift", "air_refraction", "beam_misalignment"):
            steps.append({"kind": e.name, **e.values})
    nm = FOLD_TURN - INSTRUMENT_SITES["interferometer_z"][1]
    optics = {"heads_m": {a: cube_home + INSTRUMENT_SITES[f"interferometer_{a}"][0] for a in AXES},
              "directions": {a: INSTRUMENT_SITES[f"interferometer_{a}"][1]
                             / np.linalg.norm(INSTRUMENT_SITES[f"interferometer_{a}"][1])
                             for a in AXES},
              "fold_m": cube_home + FOLD_MIRROR_Z, "fold_normal": nm / np.linalg.norm(nm),
              "steps": steps}
    contact = eff.get("sensor_contact")
    doc = {
        "format": ce.FORMAT, "format_version": ce.FORMAT_VERSION,
        "source": {**(source or {}), "effects": list(model.names)},
        "units": "SI: m, rad, s, Pa, A, N; temperatures degC",
        "inputs": {
            "q_rad": "(3,) motor coordinates, rad (forward); or target_m (3,) readings x, y, z "
                     "counted from the session's zero, m (inverse)",
            "temperatures_C": {k: "degC" for k in ce.CONDITIONS},
            "temperatures_doc": "part temperatures as the model takes them: base, arm<i>, "
                                "rod<i>, platform (thermal expansion), table and frame (loop "
                                "drift), support (every instrument support: the table sensors' "
                                "level, without the sensor contact correction), air_<axis> by each beam, "
                                "comp_<axis> the interferometer's own air sensor, room = mean "
                                "of the three air_<axis> (air refraction); each the mean of the "
                                "sensors on its part (temperature_loop) or, without one, the "
                                "mean of its sensed siblings, else the reference",
            "pressure_Pa": "Pa (101325 when not measured)",
            "currents_A": "(3,) coil currents, A",
            "zero": "the same temperatures and pressure at the session's zero (home, coils off)",
        },
        "temperature_loop": {
            "sensors": dict(sensors or {}),
            "causal_fit_window_s": TEMPERATURE_WINDOW_S,
            "doc": "each sensor's stream smoothed causally: a straight line fitted to its scans "
                   "of the past window_s, level and rate at the present scan "
                   "(calibration/streams.py causal_fit, degree 1); with sensor_contact a "
                   "structure sensor stands for part = level + capacity / glue * rate + "
                   "leak / glue * (level - room), an air sensor for level + capacity / air_glue "
                   "* rate",
            "sensor_contact": None if contact is None else dict(contact.values),
        },
        "geometry": {"B_m": g["B"], "axis": g["axis"], "arm_vec_m": g["arm_vec"], "P0_m": g["P0"],
                     "L_m": g["L"], "theta_zero_rad": g["theta_zero"],
                     "cube_offset_m": g["cube_offset"],
                     "cube_size_m": float(params.mirror_cube_size_m),
                     "stroke_rad": params.stroke_rad, "home_m": home, "cube_home_m": cube_home},
        "thermal": {"reference_C": T_ref, "cte_per_K": cte},
        "statics": _statics_series(model.params),
        "load": load,
        "optics": optics,
        "evaluation": EVALUATION,
    }
    return _plain(doc)


def _plain(v):
    if isinstance(v, dict):
        return {k: _plain(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_plain(x) for x in v]
    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, np.generic):
        return v.item()
    return v


def write_controller_model(model: PhysicsModel, path, sensors=None, source_path=None) -> Path:
    """Write the controller file of ``model`` (atomically) and, beside it (``FILE.bin``), the
    same contents as the C evaluator's coefficient block (controller_c.py); ``source_path``:
    the fitted TOML it came from (named, with its sha256)."""
    block = controller_c.block_path(path)
    if block == Path(path):
        raise ValueError(f"{path}: a controller file must not end in .bin (its C coefficient "
                         "block is written beside it as NAME.bin)")
    source = {}
    if source_path is not None:
        source = {"model_file": str(source_path),
                  "sha256": hashlib.sha256(Path(source_path).read_bytes()).hexdigest()}
    doc = controller_model(model, sensors, source)
    atomic_write(block, lambda tmp: controller_c.coefficient_block(doc).tofile(tmp))
    return atomic_write_text(path, json.dumps(doc, separators=(",", ":")) + "\n")


def evaluator_conditions(model: PhysicsModel, meas: Measurements, rows) -> tuple[dict, dict]:
    """(conditions of ``rows``, conditions of their session zero) of a ``Measurements`` in the
    evaluator's names, as the model sees them (its sensor stage applied): what a controller's
    temperature loop gives the evaluator. All ``rows`` must share one session zero."""
    rows = np.asarray(rows, dtype=np.int64)
    zero = np.unique(meas.zero_row[rows])
    if zero.size != 1:
        raise FitError("evaluator_conditions: the rows belong to more than one session")
    pts = meas.points
    pts.params = model.params
    T = meas.part_temperatures(model.effects)

    def at(idx):
        out = {k: T[k][idx] for k in ce.CONDITIONS if k in T and not k.startswith("comp_")}
        out.update({f"comp_{a}": T[f"sensor:comp_{a}"][idx] for a in AXES})
        out["room"] = pts.room_C[idx]
        out["support"] = pts.support_C["x"][idx]
        out["pressure_Pa"] = pts.pressure_Pa[idx]
        out["currents_A"] = pts.currents_A[idx]
        return out
    return at(rows), at(zero)
