"""The assembly is physically possible: MuJoCo's own distance queries find no two parts
interpenetrating, and MuJoCo's ray casts find every beam reaching its cube face, at every pose
of a sample of the workspace (its hull: the faces of the stroke cube, and an interior grid)."""
import itertools

import mujoco
import numpy as np
import pytest

from deltatwin.models.geometry import build_geometry
from deltatwin.models.kinematics import forward
from deltatwin.models.mjcf import (
    BEAM_RADIUS_M,
    FOLD_MIRROR_NORMAL,
    INSTRUMENT_SITES,
    build_model,
    pose_model,
)
from deltatwin.models.params import load_params
from deltatwin.twin import workspace

# Parts that touch by design: the lower leaf of a rod's platform-side flexure is clamped in the
# plate (it is the hinge), the motors are bolted under the base plate.
MOUNTED = [(f"rod{i}{j}_flexure_bottom2", "platform_plate") for i in (1, 2, 3) for j in (1, 2)] + \
          [(f"motor{i}", "base_plate") for i in (1, 2, 3)]
MIN_CLEARANCE_M = 1e-3   # between parts not mounted together, at every sampled pose
# face each beam must reach (outward normal in the cube frame)
BEAM_FACES = {"interferometer_x": [-1, 0, 0], "interferometer_y": [0, -1, 0],
              "interferometer_z": [0, 0, -1], "autocollimator_1": [1, 0, 0],
              "autocollimator_2": [0, 1, 0]}


@pytest.fixture(scope="module")
def robot():
    params = load_params()
    geom = build_geometry(params)
    _, model = build_model(params)
    lo, hi = geom.stroke
    grid = np.array(list(itertools.product(np.linspace(lo, hi, 3), repeat=3)))
    q = np.vstack([workspace.boundary_motor_coordinates(geom, 5), grid])
    return params, geom, model, q, forward(geom, q)


def _checked_pairs(model):
    """Geom pairs of different bodies that are neither parent and child (joined by a flexure
    hinge) nor mounted together; the table (a drawing of the floor) is left out."""
    names = [model.geom(g).name for g in range(model.ngeom)]
    mounted = {frozenset(p) for p in MOUNTED}
    body, parent = model.geom_bodyid, model.body_parentid
    pairs = []
    for a, b in itertools.combinations(range(model.ngeom), 2):
        ba, bb = body[a], body[b]
        if ba == bb or parent[ba] == bb or parent[bb] == ba or "table" in (names[a], names[b]):
            continue
        if frozenset((names[a], names[b])) not in mounted:
            pairs.append((a, b))
    return names, pairs


def test_no_two_parts_interpenetrate_anywhere_in_the_workspace(robot):
    params, geom, model, q, pose = robot
    data = mujoco.MjData(model)
    names, pairs = _checked_pairs(model)
    assert len(pairs) > 1000
    closest = {}
    for k in range(len(q)):
        pose_model(model, data, q[k], pose.p[k], pose.R[k])
        for a, b in pairs:
            dist = mujoco.mj_geomDistance(model, data, a, b, 0.02, None)
            if dist < closest.get((a, b), np.inf):
                closest[(a, b)] = dist
    (a, b), worst = min(closest.items(), key=lambda item: item[1])
    assert worst > MIN_CLEARANCE_M, f"{names[a]} and {names[b]}: {worst * 1e3:.3f} mm"
    # the force simulator as the paper has it: the coils under their magnets, 10-15 mm at home
    data = mujoco.MjData(model)
    mujoco.mj_kinematics(model, data)
    for i in (1, 2, 3):
        gap = mujoco.mj_geomDistance(model, data, model.geom(f"magnet{i}").id,
                                     model.geom(f"coil{i}_winding").id, 1.0, None)
        assert 0.010 <= gap <= 0.015


def test_the_mounted_parts_do_touch(robot):
    """The exemption list is not a blanket: every mounted pair is in contact at home."""
    _, _, model, _, _ = robot
    data = mujoco.MjData(model)
    mujoco.mj_kinematics(model, data)
    for a, b in MOUNTED:
        assert mujoco.mj_geomDistance(model, data, model.geom(a).id, model.geom(b).id,
                                      1.0, None) < 1e-9, (a, b)


def _ray(model, data, origin, direction, exclude_body):
    geom_id = np.zeros(1, dtype=np.int32)
    dist = mujoco.mj_ray(model, data, origin, direction, None, 1, exclude_body, geom_id)
    return dist, int(geom_id[0])


def _rim_offsets(direction):
    """The beam's axis and four points on its rim (BEAM_RADIUS_M), across the beam."""
    u = np.cross(direction, [0.0, 0.0, 1.0] if abs(direction[2]) < 0.9 else [1.0, 0.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(direction, u)
    return [np.zeros(3)] + [BEAM_RADIUS_M * s * w for w in (u, v) for s in (1.0, -1.0)]


def test_every_beam_reaches_its_cube_face_unobstructed(robot):
    """mj_ray from each head (its housing excluded) along its beam: the first part hit is the
    mirror cube, on the face the instrument reads, for the beam's axis and rim, at every pose.
    The Z beam first meets the fold mirror, then (reflected) the cube's bottom face."""
    params, geom, model, q, pose = robot
    data = mujoco.MjData(model)
    cube, fold = model.geom("mirror_cube").id, model.geom("fold_mirror_z").id
    fold_body = model.body("fold_mirror").id
    half = params.mirror_cube_size_m / 2
    n_fold = FOLD_MIRROR_NORMAL
    for k in range(len(q)):
        pose_model(model, data, q[k], pose.p[k], pose.R[k])
        R_cube = data.geom_xmat[cube].reshape(3, 3)
        for name, face in BEAM_FACES.items():
            site = model.site(name)
            head_body = model.site_bodyid[site.id]
            start = data.site_xpos[site.id]
            d = data.site_xmat[site.id].reshape(3, 3)[:, 2].copy()
            assert np.allclose(d, INSTRUMENT_SITES[name][1], atol=1e-15)
            for offset in _rim_offsets(d):
                o, b, exclude = start + offset, d, head_body
                dist, hit = _ray(model, data, o, b, exclude)
                if name == "interferometer_z":
                    assert hit == fold, f"pose {q[k]}: Z beam hits {model.geom(hit).name}"
                    o = o + dist * b
                    b = b - 2.0 * (b @ n_fold) * n_fold
                    dist, hit = _ray(model, data, o, b, fold_body)
                assert hit == cube, (f"pose {q[k]}: {name} beam (rim {offset}) hits "
                                     f"{model.geom(hit).name if hit >= 0 else 'nothing'}")
                local = R_cube.T @ (o + dist * b - data.geom_xpos[cube])
                assert np.isclose(local @ face, half, rtol=0, atol=1e-12), (name, local)
