"""``deltatwin model export | info``: the robot model as MJCF, and its key figures."""
from __future__ import annotations

from pathlib import Path

from deltatwin.commands.output import strict_json


def register(sub) -> None:
    model = sub.add_parser("model", help="the robot model: export MJCF, print key figures")
    msub = model.add_subparsers(dest="model_command", required=True, metavar="ACTION")
    exp = msub.add_parser("export", help="write the MuJoCo model as MJCF XML",
                          description="Write the MuJoCo model as MJCF XML (MuJoCo loads it back "
                                      "before the file is put in place).")
    exp.add_argument("-o", "--output", required=True, help="output .xml path")
    exp.add_argument("--params", default=None,
                     help="parameter TOML (default: the shipped models/delta_agietron/params.toml)")
    exp.set_defaults(func=run_export)
    info = msub.add_parser("info", help="workspace, envelope, compliance, strokes",
                           description="Key figures of the robot: workspace volume, envelope, "
                                       "compliance at the workspace centre, strokes, flexures.")
    info.add_argument("--params", default=None, help="parameter TOML")
    info.add_argument("--json", action="store_true", help="print one JSON object")
    info.set_defaults(func=run_info)


def run_export(args) -> int:
    import mujoco

    from deltatwin.files import atomic_write
    from deltatwin.models.mjcf import build_spec, to_xml_full_precision
    from deltatwin.models.params import load_params

    params = load_params(args.params)
    xml = to_xml_full_precision(build_spec(params))
    out = Path(args.output)

    def write(tmp):
        Path(tmp).write_text(xml)
        mujoco.MjModel.from_xml_path(tmp)   # what we write, MuJoCo must load

    atomic_write(out, write)
    print(f"wrote {out} ({len(xml)} bytes)")
    return 0


def model_info(params_path=None) -> dict:
    """Key figures of a parameter set (see ``deltatwin model info``)."""
    import mujoco
    import numpy as np

    from deltatwin.models.geometry import build_geometry
    from deltatwin.models.mjcf import build_spec, is_room_body
    from deltatwin.models.params import DEFAULT_PARAMS_PATH, load_params
    from deltatwin.twin import workspace
    from deltatwin.twin.statics import Statics
    params = load_params(params_path)
    geom = build_geometry(params)
    spec = build_spec(params, geom)
    m = spec.compile()
    d = mujoco.MjData(m)
    mujoco.mj_kinematics(m, d)
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    for g in range(m.ngeom):   # the robot's envelope: not the table, coils or instruments
        body = m.geom_bodyid[g]
        if body == 0 or is_room_body(m.body(body).name):
            continue
        R = d.geom_xmat[g].reshape(3, 3)
        c = d.geom_xpos[g] + R @ m.geom_aabb[g, :3]
        h = np.abs(R) @ m.geom_aabb[g, 3:]
        lo, hi = np.minimum(lo, c - h), np.maximum(hi, c + h)
    statics = Statics(params, geom)
    C = statics.compliance(np.zeros((1, 3)))[0]
    boundary = workspace.boundary_motor_coordinates(geom, 7)
    angles = workspace.flexure_angles(geom, boundary)
    hull = workspace.hull(geom)
    return {
        "parameter_file": str(Path(params_path).resolve() if params_path else DEFAULT_PARAMS_PATH),
        "workspace_cm3": workspace.volume(geom) * 1e6,
        "workspace_hull_cm3": float(hull.volume) * 1e6,
        "workspace_extent_mm": ((hull.bounds[1] - hull.bounds[0]) * 1e3).tolist(),
        "envelope_mm": ((hi - lo) * 1e3).tolist(),
        "actuator_strokes": [geom.stroke.tolist()] * 3,
        "actuator_strokes_unit": "rad",
        "compliance_nm_per_N": (C[:3, :3] * 1e9).tolist(),
        "rotational_compliance_urad_per_Nm": (C[3:, 3:] * 1e6).tolist(),
        "flexure_max_angle_deg": float(np.degrees(angles.max())),
        "flexure_max_stress_MPa": float(angles.max() * statics.k.stress_per_rad / 1e6),
        "flexure_allowable_stress_MPa": params.material("rods").allowable_stress_Pa / 1e6,
        "flexure_bending_stiffness_Nm_per_rad": statics.k.hinge_bending,
        "mujoco": {"nbody": m.nbody, "njnt": m.njnt, "neq": m.neq, "version": mujoco.__version__},
    }


def run_info(args) -> int:
    import numpy as np

    info = model_info(args.params)
    if args.json:
        print(strict_json(info, indent=1))
        return 0
    C = np.array(info["compliance_nm_per_N"])
    print(f"parameters      {info['parameter_file']}")
    print(f"workspace       {info['workspace_cm3']:.3f} cm^3 (hull {info['workspace_hull_cm3']:.3f}), "
          f"extent {np.round(info['workspace_extent_mm'], 2).tolist()} mm")
    print(f"envelope        {np.round(info['envelope_mm'], 1).tolist()} mm")
    print(f"strokes         {info['actuator_strokes'][0]} rad")
    print(f"compliance      diag {np.round(np.diag(C), 1).tolist()} nm/N at the workspace centre")
    print(f"flexures        max {info['flexure_max_angle_deg']:.2f} deg, "
          f"{info['flexure_max_stress_MPa']:.0f} MPa (allowable {info['flexure_allowable_stress_MPa']:.0f})")
    return 0
