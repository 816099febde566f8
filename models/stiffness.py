"""Element stiffness of the flexure-hinge Delta robot from part geometry and material.

Rod-end flexures are universal joints made of two crossed leaf springs in series (length l,
thickness h, width b), one bending about each axis perpendicular to the rod:
  bending  k_b = E b h^3 / (12 l)      [N m/rad]   per axis
  torsion  k_t = G b h^3 / (3 l)       [N m/rad]   thin strip, both leaves in series -> k_t / 2
  axial    c_a = l / (E b h)           [m/N]       per leaf, four leaves per rod in series
  stress   sigma = E h a / (2 l)       [Pa]        for a bending angle a
The arm is a rectangular Ti beam; its bending is lumped by the pseudo-rigid-body model (Howell):
a pivot at gamma*L from the free end with stiffness gamma * K_Theta * E I / L; its torsion is
G J / L with J = beta w h^3.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from deltatwin.models.geometry import Geometry
from deltatwin.models.params import RobotParams


@dataclass(frozen=True)
class Stiffness:
    rod_axial: np.ndarray      # (3,2) N/m, rod body + two necks in series
    hinge_bending: float       # N m/rad, each rod-end flexure, both bending axes
    hinge_torsion: float       # N m/rad, each flexure about the rod axis (its two leaves)
    drive: float               # N m/rad, encoder -> arm torsion
    arm: np.ndarray            # (3,) N m/rad: in-plane bending, out-of-plane bending, torsion
    stress_per_rad: float      # Pa/rad, flexure bending stress per bending angle


def element_stiffness(params: RobotParams, geom: Geometry) -> Stiffness:
    p = params
    rod_mat, arm_mat = p.material("rods"), p.material("arms")
    E, G = rod_mat.youngs_modulus_Pa, rod_mat.shear_modulus_Pa
    lf, lt, lw = p.flexure_leaf_length_m, p.flexure_leaf_thickness_m, p.flexure_leaf_width_m
    k_b = E * lw * lt ** 3 / (12.0 * lf)
    k_t = G * lw * lt ** 3 / (3.0 * lf) / 2.0
    leaf_axial = lf / (E * lw * lt)
    area = np.pi * p.rod_diameter_m ** 2 / 4.0
    rod_axial = 1.0 / ((geom.L - 4.0 * lf) / (E * area) + 4.0 * leaf_axial)

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
                     stress_per_rad=E * lt / (2.0 * lf))
