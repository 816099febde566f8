"""``deltatwin demo``: the main job on the embedded twin.

Until the diagnosis loop lands, it shows what exists: the model and its key figures, the
workspace, and a short simulated sweep (kinematics, parasitic rotations from a rod-length
error, gravity sag and the deflection under the force simulator's ~2 N)."""
from __future__ import annotations

import json

import numpy as np
from tqdm import tqdm

ARCSEC_PER_RAD = 180.0 / np.pi * 3600.0


def register(sub) -> None:
    p = sub.add_parser("demo", help="run the main job on the embedded twin")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--points", type=int, default=9, help="points of the sweep along each motor")
    p.set_defaults(func=run)


def run(args) -> int:
    from models.cli import model_info
    from models.geometry import build_geometry
    from models.params import load_params
    from twin.statics import Statics

    if args.points < 2:
        raise ValueError(f"--points must be >= 2, got {args.points}")
    steps = tqdm(total=3, desc="demo", disable=args.json)
    info = model_info()
    steps.update()
    params = load_params()
    ideal = Statics(params, build_geometry(params))
    dev = np.zeros((3, 2))
    dev[0, 0] = 10e-6                                     # rod 1 of chain 1 is 10 um long
    flawed_params = params.replace(d_rod_length_m=dev)
    flawed = Statics(flawed_params, build_geometry(flawed_params))
    lo, hi = ideal.geom.stroke
    line = np.linspace(lo, hi, args.points)
    q = np.column_stack([line, -line, np.zeros_like(line)])
    coil = np.array([0.0, 0.0, 2.0, 0.0, 0.0, 0.0])
    base = ideal.solve(q, gravity=False)
    sag = ideal.solve(q, gravity=True)
    loaded = ideal.solve(q, wrench=coil, gravity=True)
    tilted = flawed.solve(q, gravity=True)
    steps.update()
    rows = []
    for k in range(len(q)):
        rows.append({
            "q_rad": q[k].tolist(),
            "p_mm": (base.kinematic_pose.p[k] * 1e3).tolist(),
            "gravity_sag_nm": ((sag.pose.p[k] - base.pose.p[k]) * 1e9).tolist(),
            "coil_2N_nm": ((loaded.pose.p[k] - sag.pose.p[k]) * 1e9).tolist(),
            "rod_error_rotation_arcsec": (tilted.pose.rotvec[k] * ARCSEC_PER_RAD).tolist(),
        })
    steps.update()
    steps.close()
    if args.json:
        print(json.dumps({"model": info, "sweep": rows}, indent=1))
        return 0
    print(f"\ndeltatwin demo: {params.name} ({info['parameter_file']})")
    print(f"  workspace {info['workspace_cm3']:.3f} cm^3, extent "
          f"{np.round(info['workspace_extent_mm'], 1).tolist()} mm; envelope "
          f"{np.round(info['envelope_mm'], 0).tolist()} mm")
    C = np.array(info["compliance_nm_per_N"])
    print(f"  compliance at the centre: {np.round(np.diag(C), 1).tolist()} nm/N (X, Y, Z); flexures "
          f"bend up to {info['flexure_max_angle_deg']:.2f} deg ({info['flexure_max_stress_MPa']:.0f} MPa)")
    print("\n  sweep q = (s, -s, 0): platform position, gravity sag, +2 N up (coils), rotation with "
          "rod 1.1 +10 um")
    print(f"  {'q1 mrad':>8} {'x mm':>8} {'y mm':>8} {'z mm':>9} {'sag z nm':>9} "
          f"{'2N x,y,z nm':>22} {'rot x,y,z arcsec':>24}")
    for r in rows:
        f = r["coil_2N_nm"]
        rot = r["rod_error_rotation_arcsec"]
        print(f"  {r['q_rad'][0] * 1e3:8.1f} {r['p_mm'][0]:8.3f} {r['p_mm'][1]:8.3f} {r['p_mm'][2]:9.3f} "
              f"{r['gravity_sag_nm'][2]:9.1f} {f[0]:7.1f},{f[1]:7.1f},{f[2]:6.1f} "
              f"{rot[0]:7.2f},{rot[1]:7.2f},{rot[2]:7.2f}")
    return 0
