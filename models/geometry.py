"""Effective joint geometry of the robot: nominal values + deviations, scaled by part temperatures.

Frames: the base frame is the world frame, origin at the base centre, z up; the robot hangs
below the base (platform at negative z). Chain i has its actuator axis through ``B[i]`` along
``axis[i]``; the arm angle ``theta`` is the right-hand rotation about that axis, positive down.
Rod j of chain i joins elbow point ``A[i, j]`` to platform point ``P0[i, j]`` (platform frame).

A geometry is either one robot state (arrays shaped as documented in ``Geometry``) or a batch
of states, one per measurement point, with a leading axis N on every joint array: that is how
per-point part temperatures enter the exact kinematics (``build_geometry(params, temperatures)``).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from deltatwin.models.params import RobotParams

ROD_SIDES = np.array([+1.0, -1.0])  # rod j sits at +/- half width along the actuator axis


@dataclass(frozen=True)
class Geometry:
    """Joint geometry at the parts' temperatures (all m / rad, float64)."""
    B: np.ndarray          # (3,3) actuator axis point, base frame
    axis: np.ndarray       # (3,3) unit actuator axis
    radial: np.ndarray     # (3,3) unit radial direction of each chain (nominal)
    arm_vec: np.ndarray    # (3,2,3) B -> elbow hinge of each rod, arm at theta = 0
    elbow_vec: np.ndarray  # (3,3) B -> elbow centre, arm at theta = 0
    P0: np.ndarray         # (3,2,3) platform hinge of each rod, platform frame
    L: np.ndarray          # (3,2) rod lengths, hinge centre to hinge centre
    theta_zero: np.ndarray  # (3,) arm angle at motor coordinate 0 (home + encoder offset)
    stroke: np.ndarray     # (2,) motor coordinate limits
    cube_offset: np.ndarray  # (3,) mirror cube centre, platform frame

    @property
    def batched(self) -> bool:
        """True when every joint array carries a leading per-point axis."""
        return self.B.ndim == 3

    def theta(self, q: np.ndarray) -> np.ndarray:
        """Arm angles (rad) for motor coordinates ``q`` (..., 3)."""
        return np.asarray(q, dtype=np.float64) + self.theta_zero


def part_scale(params: RobotParams, part: str, T_C) -> np.ndarray:
    """Thermal scale factor 1 + CTE * (T - T_ref) of a part at temperature(s) ``T_C``."""
    cte = params.material(part).cte_per_K
    return 1.0 + cte * (np.asarray(T_C, dtype=np.float64) - params.reference_temperature_C)


PART_TEMPERATURES = ("base", "arms", "rods", "platform")


def part_scales(params: RobotParams, temperatures: dict | None = None) -> tuple:
    """Thermal scale factors of (base, arms, rods, platform): at the parameters' own part
    temperatures or, when ``temperatures`` is given, per point (as ``build_geometry``). Every
    joint array of the base, of an arm, of a rod or of the platform is its value at the
    reference temperature times its part's factor."""
    p = params
    T = {"base": p.T_base_C, "arms": p.T_arms_C, "rods": p.T_rods_C, "platform": p.T_platform_C}
    if temperatures is not None:
        unknown = sorted(set(temperatures) - set(PART_TEMPERATURES))
        if unknown:
            raise ValueError(f"unknown part temperature(s) {unknown}; parts: {PART_TEMPERATURES}")
        n = {np.shape(v)[0] for v in temperatures.values()}
        if len(n) != 1:
            raise ValueError(f"per-point temperatures of different lengths {sorted(n)}")
        n_pts = n.pop()
        for part in PART_TEMPERATURES:
            value = np.asarray(temperatures.get(part, T[part]), dtype=np.float64)
            T[part] = np.broadcast_to(value, (n_pts,) + np.shape(T[part]))
    return tuple(part_scale(params, part, T[part]) for part in PART_TEMPERATURES)


def build_geometry(params: RobotParams, temperatures: dict | None = None) -> Geometry:
    """Joint geometry of ``params``; part temperatures (degC) from the parameters or, when
    ``temperatures`` is given, per point: ``{"base": (N,), "arms": (N,3), "rods": (N,3,2),
    "platform": (N,)}`` (missing parts keep the parameters' value) -> a batched Geometry."""
    p = params
    az = np.deg2rad(p.actuator_azimuth_deg)
    radial = np.stack([np.cos(az), np.sin(az), np.zeros(3)], axis=1)
    tangent = np.stack([-np.sin(az), np.cos(az), np.zeros(3)], axis=1)
    up = np.array([0.0, 0.0, 1.0])
    # actuator axes: nominal tangent tilted towards radial and vertical by small angles
    axis = tangent + p.actuator_axis_tilt_rad[:, :1] * radial + p.actuator_axis_tilt_rad[:, 1:] * up
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)

    # scale factors with trailing axes matching each joint array ((N,) + shape when batched)
    s_base, s_arm, s_rod, s_plat = part_scales(p, temperatures)
    s_base, s_arm, s_plat = s_base[..., None, None], s_arm[..., None], s_plat[..., None, None]

    B = s_base * (p.base_radius_m * radial + p.d_base_joint_m)
    arm_len = (p.arm_length_m + p.d_arm_length_m)[:, None]
    elbow_vec = s_arm * arm_len * radial
    side = ROD_SIDES[None, :, None]
    arm_vec = s_arm[..., None] * ((arm_len * radial)[:, None, :]
                                  + side * p.elbow_half_width_m * tangent[:, None, :]
                                  + p.d_elbow_joint_m)
    P0 = s_plat[..., None] * ((p.platform_radius_m * radial)[:, None, :]
                              + side * p.platform_half_width_m * tangent[:, None, :]
                              + p.d_platform_joint_m)
    L = s_rod * (p.rod_length_m + p.d_rod_length_m)
    cube = s_plat[..., 0] * p.mirror_cube_offset_m
    theta_zero = p.home_angle_rad + p.encoder_offset_rad
    if temperatures is not None:
        n_pts = L.shape[0]
        axis = np.broadcast_to(axis, (n_pts, 3, 3))
        theta_zero = np.broadcast_to(theta_zero, (n_pts, 3))
    return Geometry(B=B, axis=axis, radial=radial, arm_vec=arm_vec, elbow_vec=elbow_vec, P0=P0, L=L,
                    theta_zero=theta_zero, stroke=p.stroke_rad.copy(), cube_offset=cube)
