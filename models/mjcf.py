"""The robot as a MuJoCo model, built in code with ``mujoco.MjSpec`` from one parameter set.

Kinematic tree (the world frame is the base frame, z up, metres, radians):
  world -> arm{i} (hinge ``q{i}``: the actuator, qpos = motor coordinate) -> arm{i}_flex
  (three pseudo-rigid-body hinges: arm bending in and out of plane, torsion) -> rod{i}{j}
  (flexure hinge: two bending hinges ``rod{i}{j}_bx/by``, then axial slide ``rod{i}{j}_ax``)
  -> site ``rod{i}{j}_end``;  world -> platform (free joint) with sites ``plat{i}{j}``.
Six site-to-site connect equalities close the loops.  MuJoCo's soft constraints cannot hold a
statically loaded loop to nanometres, so static poses come from ``twin.statics``; this model
carries geometry, inertia and stiffness, and ``pose_model`` puts an exactly solved
configuration into it.  Joint stiffnesses are the element stiffnesses of models/stiffness.py
(the platform-side flexures and hinge torsion have no tree joint and live only in the statics).
"""
from __future__ import annotations

import xml.etree.ElementTree as ET

import mujoco
import numpy as np
from scipy.spatial.transform import Rotation

from deltatwin.models.geometry import Geometry, build_geometry
from deltatwin.models.layout import (  # noqa: F401  (re-exported: the model's layout)
    BEAM_RADIUS_M,
    COIL_HEIGHT_M,
    COIL_RADIUS_M,
    FOLD_MIRROR_HALF_M,
    FOLD_MIRROR_NORMAL,
    FOLD_MIRROR_Z,
    HEAD_HALF_M,
    INSTRUMENT_SITES,
    MAGNET_HALF_M,
    PLATE_THICKNESS_M,
    SPOKE_THICKNESS_M,
    SPOKE_WIDTH_M,
    STEM_RADIUS_M,
    magnet_positions,
)
from deltatwin.models.meshes import platform_plate
from deltatwin.models.params import RobotParams
from deltatwin.models.stiffness import element_stiffness

# bodies fixed in the room rather than parts of the robot (name prefixes)
ROOM_BODY_PREFIXES = ("coil", "interferometer_", "autocollimator_", "fold_mirror")


def is_room_body(name: str) -> bool:
    """True for the force simulator's coils and the metrology loop (heads, fold mirror)."""
    return name.startswith(ROOM_BODY_PREFIXES)


# Simulation (MuJoCo's dynamics, see README.md): the stiffest elements (drive, arm, rod axial)
# would need a timestep of ~10 us; armature (added inertia, k / w^2) caps every joint's own
# frequency at SIM_MAX_RAD_S and damping 2 zeta k / w damps it, so a 0.1 ms step is stable.
# Statics are unchanged (inertia and damping do not enter an equilibrium).
SIM_TIMESTEP_S = 1e-4
SIM_MAX_RAD_S = 2000.0
SIM_DAMPING_RATIO = 1.0
LOOP_SOLREF = (0.002, 1.0)   # connect constraints: time constant (s), damping ratio


def _quat_z_to(direction: np.ndarray) -> np.ndarray:
    """MuJoCo quaternion (w,x,y,z) of a frame whose z axis points along ``direction``."""
    d = direction / np.linalg.norm(direction)
    rot, _ = Rotation.align_vectors([d], [[0.0, 0.0, 1.0]])
    x, y, z, w = rot.as_quat()
    return np.array([w, x, y, z])


def _quat(rot: Rotation) -> np.ndarray:
    x, y, z, w = rot.as_quat()
    return np.array([w, x, y, z])


def rod_frames(geom: Geometry) -> np.ndarray:
    """Rotation (3,2,3,3) of each rod body in its arm body frame: z along the rod at home."""
    from deltatwin.models.kinematics import elbow_points, forward
    home = forward(geom, np.zeros((1, 3)), check=False)
    A = elbow_points(geom, geom.theta(np.zeros((1, 3))))[0]
    P = home.p[0] + np.einsum("ab,ijb->ija", home.R[0], geom.P0)
    frames = np.empty((3, 2, 3, 3))
    for i in range(3):
        arm0 = Rotation.from_rotvec(geom.axis[i] * geom.theta_zero[i])
        for j in range(2):
            d_local = arm0.inv().apply(P[i, j] - A[i, j])
            frames[i, j] = Rotation.align_vectors([d_local], [[0.0, 0.0, 1.0]])[0].as_matrix()
    return frames


def joint_dynamics(stiffness: float) -> tuple[float, float]:
    """(armature kg m^2 or kg, damping N m s/rad or N s/m) of a joint of ``stiffness`` (N m/rad
    or N/m): its own frequency capped at SIM_MAX_RAD_S and damped at SIM_DAMPING_RATIO."""
    armature = stiffness / SIM_MAX_RAD_S ** 2
    return armature, 2.0 * SIM_DAMPING_RATIO * stiffness / SIM_MAX_RAD_S


def _add_joint(body, stiffness: float, **kwargs) -> None:
    armature, damping = joint_dynamics(stiffness)
    body.add_joint(stiffness=stiffness, armature=armature, damping=damping, **kwargs)


def build_spec(params: RobotParams, geom: Geometry | None = None) -> mujoco.MjSpec:
    """The MjSpec of the robot, its metrology frame and its force simulator coils."""
    from deltatwin.models.kinematics import forward
    geom = geom or build_geometry(params)
    k = element_stiffness(params, geom)
    spec = mujoco.MjSpec()
    spec.modelname = params.name
    spec.compiler.degree = False
    spec.option.gravity = [0.0, 0.0, -9.80665]
    spec.option.timestep = SIM_TIMESTEP_S
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    rho = {part: params.material(part).density_kg_m3 for part in ("base", "arms", "rods", "platform")}
    home = forward(geom, np.zeros((1, 3)), check=False)
    cube_home = home.point(geom.cube_offset)[0]

    plate = platform_plate(geom.P0, PLATE_THICKNESS_M)
    spec.add_mesh(name="platform_plate", uservert=plate.vertices.ravel().tolist(),
                  userface=plate.faces.ravel().tolist())

    world = spec.worldbody
    table_top = cube_home[2] + FOLD_MIRROR_Z[2] - 0.03   # under the fold mirror
    world.add_geom(name="table", type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.3, 0.3, 0.02],
                   pos=[0.0, 0.0, table_top - 0.02], contype=0, conaffinity=0,
                   rgba=[0.4, 0.4, 0.45, 1])
    base = world.add_body(name="base")
    base.add_geom(name="base_plate", type=mujoco.mjtGeom.mjGEOM_CYLINDER,
                  size=[params.base_radius_m + 0.025, 0.01], pos=[0.0, 0.0, 0.03],
                  density=rho["base"], contype=0, conaffinity=0, rgba=[0.6, 0.6, 0.65, 1])
    frames = rod_frames(geom)
    for i in range(3):
        arm0 = Rotation.from_rotvec(geom.axis[i] * geom.theta_zero[i])
        arm = world.add_body(name=f"arm{i + 1}", pos=geom.B[i], quat=_quat(arm0))
        # the drive's stiffness is its position actuator's gain
        armature, damping = joint_dynamics(k.drive)
        arm.add_joint(name=f"q{i + 1}", type=mujoco.mjtJoint.mjJNT_HINGE, axis=geom.axis[i],
                      range=geom.stroke, limited=mujoco.mjtLimited.mjLIMITED_TRUE,
                      armature=armature, damping=damping)
        arm.add_geom(name=f"motor{i + 1}", type=mujoco.mjtGeom.mjGEOM_CYLINDER,
                     size=[0.02, 0.03], quat=_quat_z_to(geom.axis[i]), density=7800.0,
                     contype=0, conaffinity=0, rgba=[0.2, 0.2, 0.2, 1])
        elbow = geom.elbow_vec[i]
        a_dir = elbow / np.linalg.norm(elbow)
        e_n = np.cross(a_dir, geom.axis[i])
        pivot = (1.0 - params.prbm_gamma) * elbow
        flex = arm.add_body(name=f"arm{i + 1}_flex", pos=pivot)
        for name, ax, stiff in (("inplane", geom.axis[i], k.arm[0]), ("outplane", e_n, k.arm[1]),
                                ("torsion", a_dir, k.arm[2])):
            _add_joint(flex, stiff, name=f"arm{i + 1}_{name}", type=mujoco.mjtJoint.mjJNT_HINGE,
                       axis=ax)
        flex.add_geom(name=f"arm{i + 1}_beam", type=mujoco.mjtGeom.mjGEOM_BOX,
                      size=[np.linalg.norm(elbow) / 2, params.arm_width_m / 2, params.arm_thickness_m / 2],
                      pos=elbow / 2 - pivot, quat=_quat(Rotation.align_vectors(
                          [a_dir, geom.axis[i]], [[1, 0, 0], [0, 1, 0]])[0]),
                      density=rho["arms"], contype=0, conaffinity=0, rgba=[0.7, 0.7, 0.75, 1])
        for j in range(2):
            L = geom.L[i, j]
            rod = flex.add_body(name=f"rod{i + 1}{j + 1}", pos=geom.arm_vec[i, j] - pivot,
                                quat=_quat(Rotation.from_matrix(frames[i, j])))
            for axis_name, axis in (("bx", [1, 0, 0]), ("by", [0, 1, 0])):
                _add_joint(rod, k.hinge_bending, name=f"rod{i + 1}{j + 1}_{axis_name}",
                           type=mujoco.mjtJoint.mjJNT_HINGE, axis=axis)
            _add_joint(rod, k.rod_axial[i, j], name=f"rod{i + 1}{j + 1}_ax",
                       type=mujoco.mjtJoint.mjJNT_SLIDE, axis=[0, 0, 1])
            lf, lt, lw = (params.flexure_leaf_length_m, params.flexure_leaf_thickness_m,
                          params.flexure_leaf_width_m)
            # pos/size rather than fromto: the exported XML then carries the spec's own numbers
            rod.add_geom(name=f"rod{i + 1}{j + 1}_body", type=mujoco.mjtGeom.mjGEOM_CAPSULE,
                         pos=[0, 0, L / 2], size=[params.rod_diameter_m / 2, L / 2 - 2 * lf, 0],
                         density=rho["rods"], contype=0, conaffinity=0, rgba=[0.8, 0.8, 0.85, 1])
            for end, z0 in (("top", 0.0), ("bottom", L - 2 * lf)):
                for leaf, half in ((0, [lt / 2, lw / 2, lf / 2]), (1, [lw / 2, lt / 2, lf / 2])):
                    rod.add_geom(name=f"rod{i + 1}{j + 1}_flexure_{end}{leaf + 1}",
                                 type=mujoco.mjtGeom.mjGEOM_BOX, size=half,
                                 pos=[0, 0, z0 + lf * (leaf + 0.5)], density=rho["rods"],
                                 contype=0, conaffinity=0, rgba=[0.9, 0.6, 0.2, 1])
            rod.add_site(name=f"rod{i + 1}{j + 1}_end", pos=[0, 0, L])
        act = spec.add_actuator(name=f"drive{i + 1}", target=f"q{i + 1}",
                                trntype=mujoco.mjtTrn.mjTRN_JOINT)
        act.set_to_position(kp=k.drive)
        act.ctrlrange = geom.stroke
        act.ctrllimited = mujoco.mjtLimited.mjLIMITED_TRUE

    plat = world.add_body(name="platform", pos=home.p[0])
    plat.add_freejoint(name="platform_free")
    plat.add_geom(name="platform_plate", type=mujoco.mjtGeom.mjGEOM_MESH, meshname="platform_plate",
                  density=rho["platform"], contype=0, conaffinity=0, rgba=[0.6, 0.65, 0.7, 1])
    s = params.mirror_cube_size_m
    cube_top = geom.cube_offset[2] + s / 2
    hub_bottom = -PLATE_THICKNESS_M - SPOKE_THICKNESS_M
    if cube_top >= hub_bottom:
        raise ValueError(f"geometry.mirror_cube_offset_m {geom.cube_offset.tolist()}: the cube "
                         f"({s} m) must hang below the plate and flange (z < {hub_bottom} m)")
    plat.add_geom(name="cube_stem", type=mujoco.mjtGeom.mjGEOM_CYLINDER,
                  size=[STEM_RADIUS_M, (cube_top - hub_bottom) / -2, 0],
                  pos=[*geom.cube_offset[:2], (cube_top + hub_bottom) / 2],
                  density=rho["platform"], contype=0, conaffinity=0, rgba=[0.6, 0.65, 0.7, 1])
    plat.add_geom(name="mirror_cube", type=mujoco.mjtGeom.mjGEOM_BOX, size=[s / 2] * 3,
                  pos=geom.cube_offset, density=params.material("mirror_cube").density_kg_m3,
                  contype=0, conaffinity=0, rgba=[0.6, 0.8, 1.0, 0.7])
    plat.add_site(name="mirror_cube_centre", pos=geom.cube_offset)
    for i, m in enumerate(magnet_positions(params)):
        radial = m[:2] / np.linalg.norm(m[:2])
        spoke = np.linalg.norm(m[:2]) + MAGNET_HALF_M[0]     # hub to the magnet's outer edge
        plat.add_geom(name=f"flange_spoke{i + 1}", type=mujoco.mjtGeom.mjGEOM_BOX,
                      size=[spoke / 2, SPOKE_WIDTH_M / 2, SPOKE_THICKNESS_M / 2],
                      pos=[*(radial * spoke / 2), -PLATE_THICKNESS_M - SPOKE_THICKNESS_M / 2],
                      quat=_quat(Rotation.from_rotvec([0.0, 0.0, np.arctan2(m[1], m[0])])),
                      density=rho["platform"], contype=0, conaffinity=0, rgba=[0.6, 0.65, 0.7, 1])
        plat.add_geom(name=f"magnet{i + 1}", type=mujoco.mjtGeom.mjGEOM_BOX,
                      size=MAGNET_HALF_M, pos=m, density=7500.0,
                      contype=0, conaffinity=0, rgba=[0.75, 0.75, 0.7, 1])
        # coil below its magnet at the home pose, across the nominal gap
        coil_top = home.p[0] + m - [0.0, 0.0, MAGNET_HALF_M[2] + params.coil_gap_m]
        coil = world.add_body(name=f"coil{i + 1}", pos=coil_top - [0.0, 0.0, COIL_HEIGHT_M / 2])
        coil.add_geom(name=f"coil{i + 1}_winding", type=mujoco.mjtGeom.mjGEOM_CYLINDER,
                      size=[COIL_RADIUS_M, COIL_HEIGHT_M / 2], contype=0, conaffinity=0,
                      rgba=[0.72, 0.45, 0.2, 1])
        coil.add_site(name=f"coil{i + 1}_face", pos=[0.0, 0.0, COIL_HEIGHT_M / 2])
    for i in range(3):
        for j in range(2):
            plat.add_site(name=f"plat{i + 1}{j + 1}", pos=geom.P0[i, j])
            spec.add_equality(name=f"loop{i + 1}{j + 1}", type=mujoco.mjtEq.mjEQ_CONNECT,
                              objtype=mujoco.mjtObj.mjOBJ_SITE, name1=f"rod{i + 1}{j + 1}_end",
                              name2=f"plat{i + 1}{j + 1}", solref=list(LOOP_SOLREF))
    # metrology loop: one fixed body per instrument (its housing behind the beam's start, so a
    # ray cast from the site can exclude it) and the Z fold mirror (reflecting face through
    # its body origin, substrate behind)
    for name, (offset, direction) in INSTRUMENT_SITES.items():
        half = HEAD_HALF_M[name.split("_")[0]]
        head = world.add_body(name=f"{name}_head", pos=cube_home + offset,
                              quat=_quat_z_to(direction))
        head.add_geom(name=f"{name}_housing", type=mujoco.mjtGeom.mjGEOM_BOX, size=half,
                      pos=[0.0, 0.0, -half[2]], contype=0, conaffinity=0,
                      rgba=[0.25, 0.3, 0.45, 1])
        head.add_site(name=name, size=[0.004])
    fold = world.add_body(name="fold_mirror", pos=cube_home + FOLD_MIRROR_Z,
                          quat=_quat_z_to(FOLD_MIRROR_NORMAL))
    fold.add_geom(name="fold_mirror_z", type=mujoco.mjtGeom.mjGEOM_BOX, size=FOLD_MIRROR_HALF_M,
                  pos=[0.0, 0.0, -FOLD_MIRROR_HALF_M[2]], contype=0, conaffinity=0,
                  rgba=[0.8, 0.85, 0.9, 1])
    fold.add_site(name="fold_mirror_z", type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.008, 0.008, 0.001])
    return spec


# MJCF attribute -> MjSpec field where the names differ (integers such as faces are exact)
_XML_FIELDS = {"vertex": "uservert"}


def to_xml_full_precision(spec: mujoco.MjSpec) -> str:
    """MJCF of ``spec`` with every number of a named element (and the options) at full float64
    precision.  ``MjSpec.to_xml`` writes 6 significant digits (0.43 um errors on this robot);
    each numeric attribute is replaced by the spec's own value, written as the shortest string
    that reads back to the same double, after checking the 6-digit text is that value."""
    finders = {"body": spec.body, "geom": spec.geom, "site": spec.site, "joint": spec.joint,
               "mesh": spec.mesh, "general": spec.actuator, "connect": spec.equality}
    root = ET.fromstring(spec.to_xml())
    for element in root.iter():
        if element.tag == "option":
            source = spec.option
        elif element.tag in finders and "name" in element.attrib:
            source = finders[element.tag](element.get("name"))
        else:
            continue
        for attr, text in element.attrib.items():
            value = getattr(source, _XML_FIELDS.get(attr, attr), None)
            if value is None or isinstance(value, (str, bool, int)):
                continue   # names, flags, integer fields: written exactly
            # float32 fields (colours, mesh vertices) round-trip with float32's shortest text
            dtype = value.dtype if isinstance(value, np.ndarray) else (
                np.float64 if isinstance(value, float) else np.float32)
            try:
                written = np.array(text.split(), dtype=np.float64)
                full = np.array(list(np.atleast_1d(value)), dtype=dtype).ravel()[:written.size]
            except (TypeError, ValueError):
                continue   # enumerations
            if full.size != written.size or not np.allclose(written, full, rtol=1e-5, atol=1e-12):
                raise ValueError(f"MJCF export: <{element.tag} name={element.get('name')!r}> "
                                 f"{attr}={text!r} is not the spec's {full.tolist()}")
            element.set(attr, " ".join(str(v) if dtype == np.float32 else repr(float(v))
                                       for v in full))
    ET.indent(root)
    return ET.tostring(root, encoding="unicode") + "\n"


def build_model(params: RobotParams) -> tuple[mujoco.MjSpec, mujoco.MjModel]:
    spec = build_spec(params)
    return spec, spec.compile()


def update_model(model: mujoco.MjModel, params: RobotParams) -> None:
    """Write new geometry (errors, temperatures) into a compiled model without recompiling:
    actuator axis points and axes, elbow and platform hinge positions, rod lengths, the
    platform's home pose.  The coils and the metrology loop (``is_room_body``) stay where they
    are in the room."""
    geom = build_geometry(params)
    frames = rod_frames(geom)
    for i in range(3):
        arm = model.body(f"arm{i + 1}")
        model.body_pos[arm.id] = geom.B[i]
        model.body_quat[arm.id] = _quat(Rotation.from_rotvec(geom.axis[i] * geom.theta_zero[i]))
        model.jnt_axis[model.joint(f"q{i + 1}").id] = geom.axis[i]
        flex = model.body(f"arm{i + 1}_flex")
        pivot = (1.0 - params.prbm_gamma) * geom.elbow_vec[i]
        model.body_pos[flex.id] = pivot
        for j in range(2):
            rod = model.body(f"rod{i + 1}{j + 1}")
            model.body_pos[rod.id] = geom.arm_vec[i, j] - pivot
            model.body_quat[rod.id] = _quat(Rotation.from_matrix(frames[i, j]))
            model.site_pos[model.site(f"rod{i + 1}{j + 1}_end").id] = [0.0, 0.0, geom.L[i, j]]
            model.site_pos[model.site(f"plat{i + 1}{j + 1}").id] = geom.P0[i, j]
    model.site_pos[model.site("mirror_cube_centre").id] = geom.cube_offset
    from deltatwin.models.kinematics import forward
    home = forward(geom, np.zeros((1, 3)), check=False)
    plat = model.body("platform").id
    model.body_pos[plat] = home.p[0]
    adr = model.joint("platform_free").qposadr[0]
    model.qpos0[adr:adr + 3] = home.p[0]


def pose_model(model: mujoco.MjModel, data: mujoco.MjData, q: np.ndarray, p: np.ndarray,
               R: np.ndarray, arm_flex: np.ndarray | None = None) -> float:
    """Put one configuration into MuJoCo: motor coordinates q (3,) (plus drive deflection),
    platform pose (p, R), optional arm pseudo-rigid-body angles (3,3).  Rod joints are solved
    so each rod reaches its platform hinge.  Returns the largest rod stretch |slide| (m) and
    leaves ``data`` at the configuration (mj_kinematics done)."""
    data.qpos[:] = 0.0
    for i in range(3):
        data.qpos[model.joint(f"q{i + 1}").qposadr[0]] = q[i]
        if arm_flex is not None:
            for k, name in enumerate(("inplane", "outplane", "torsion")):
                data.qpos[model.joint(f"arm{i + 1}_{name}").qposadr[0]] = arm_flex[i, k]
    adr = model.joint("platform_free").qposadr[0]
    data.qpos[adr:adr + 3] = p
    data.qpos[adr + 3:adr + 7] = _quat(Rotation.from_matrix(R))
    mujoco.mj_kinematics(model, data)
    stretch = 0.0
    for i in range(3):
        for j in range(2):
            rod = model.body(f"rod{i + 1}{j + 1}")
            target = data.site(f"plat{i + 1}{j + 1}").xpos
            v = data.xmat[rod.id].reshape(3, 3).T @ (target - data.xpos[rod.id])
            length = np.linalg.norm(v)
            L = model.site_pos[model.site(f"rod{i + 1}{j + 1}_end").id][2]
            data.qpos[model.joint(f"rod{i + 1}{j + 1}_bx").qposadr[0]] = np.arctan2(-v[1], v[2])
            data.qpos[model.joint(f"rod{i + 1}{j + 1}_by").qposadr[0]] = np.arcsin(v[0] / length)
            data.qpos[model.joint(f"rod{i + 1}{j + 1}_ax").qposadr[0]] = length - L
            stretch = max(stretch, abs(length - L))
    mujoco.mj_kinematics(model, data)
    return stretch


def loop_closure(model: mujoco.MjModel, data: mujoco.MjData) -> float:
    """Largest distance (m) between a rod end and its platform hinge in ``data``."""
    return max(float(np.linalg.norm(data.site(f"rod{i}{j}_end").xpos - data.site(f"plat{i}{j}").xpos))
               for i in (1, 2, 3) for j in (1, 2))
