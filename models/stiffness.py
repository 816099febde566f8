"""Element stiffness of the flexure-hinge Delta robot from part geometry and material.

Rod-end flexures are rotationally symmetric circular-notch hinges (neck diameter t, notch radius
R).  With the thin-hinge profile d(x) = t + x^2/R integrated over the notch:
  bending  k_b = E t^3.5 / (20 sqrt(R))          [N m/rad]   (integral of dx / (E I(x)))
  torsion  k_t = G t^3.5 / (10 sqrt(R))          [N m/rad]
  axial    c_a = 2 sqrt(R) / (E t^1.5)           [m/N]       (compliance of one neck)
(the rectangular-section analogue of the bending formula is Paros & Weisbord's
2 E b t^2.5 / (9 pi sqrt(R))).  The arm is a rectangular Ti beam; its bending is lumped by the
pseudo-rigid-body model (Howell): a pivot at gamma*L from the free end with stiffness
gamma * K_Theta * E I / L; its torsion is G J / L with J = beta w h^3.
Maximum flexure stress for a bending angle a: sigma = k_b a (t/2) / I_neck.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .geometry import Geometry
from .params import RobotParams


@dataclass(frozen=True)
class Stiffness:
    rod_axial: np.ndarray      # (3,2) N/m, rod body + two necks in series
    hinge_bending: float       # N m/rad, each rod-end flexure, both bending axes
    hinge_torsion: float       # N m/rad, each flexure about the rod axis
    drive: float               # N m/rad, encoder -> arm torsion
    arm: np.ndarray            # (3,) N m/rad: in-plane bending, out-of-plane bending, torsion
    neck_second_moment: float  # m^4, I of the flexure neck (for stresses)


def element_stiffness(params: RobotParams, geom: Geometry) -> Stiffness:
    p = params
    rod_mat, arm_mat = p.material("rods"), p.material("arms")
    E, G = rod_mat.youngs_modulus_Pa, rod_mat.shear_modulus_Pa
    t, R = p.flexure_neck_diameter_m, p.flexure_notch_radius_m
    k_b = E * t ** 3.5 / (20.0 * np.sqrt(R))
    k_t = G * t ** 3.5 / (10.0 * np.sqrt(R))
    neck_axial = 2.0 * np.sqrt(R) / (E * t ** 1.5)
    area = np.pi * p.rod_diameter_m ** 2 / 4.0
    rod_axial = 1.0 / (geom.L / (E * area) + 2.0 * neck_axial)

    Ea, Ga = arm_mat.youngs_modulus_Pa, arm_mat.shear_modulus_Pa
    w, h = p.arm_width_m, p.arm_thickness_m     # w along the actuator axis, h in the motion plane
    La = p.arm_length_m
    prbm = p.prbm_gamma * p.prbm_stiffness_coefficient
    I_in_plane = w * h ** 3 / 12.0              # bending about the actuator axis
    I_out_plane = h * w ** 3 / 12.0
    long, short = max(w, h), min(w, h)
    J = (1.0 / 3.0) * (1.0 - 0.63 * short / long) * long * short ** 3
    arm = np.array([prbm * Ea * I_in_plane / La, prbm * Ea * I_out_plane / La, Ga * J / La])
    return Stiffness(rod_axial=rod_axial, hinge_bending=k_b, hinge_torsion=k_t,
                     drive=p.drive_stiffness_Nm_per_rad, arm=arm,
                     neck_second_moment=np.pi * t ** 4 / 64.0)
