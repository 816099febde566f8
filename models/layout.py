"""Where things sit around the robot: the instruments' beams, the Z fold mirror, the force
simulator's magnets and coils (m, platform or world frame as each says).  Plain numbers and
numpy, no MuJoCo: the twin's optics and effects read them on every evaluation, and the MuJoCo
model (models/mjcf.py) builds its bodies from them."""
from __future__ import annotations

import numpy as np

from deltatwin.models.params import RobotParams

INSTRUMENT_SITES = {
    # name: (origin offset from the cube centre in the world frame at home, beam direction).
    # The interferometers X and Y look at the cube's -x and -y faces through their centres; Z runs
    # horizontally to a 45 deg fold mirror under the cube (``FOLD_MIRROR_Z``) and up to the cube's
    # bottom face (longer path).  Each autocollimator looks at the face opposite an interferometer
    # (+x, +y): a face's tilt is the cube's, and two beams on one 25 mm face would leave the face
    # as the platform moves ~+-8 mm (see ``beam_origins`` and tests/models/test_assembly.py).
    "interferometer_x": (np.array([-0.10, 0.0, 0.0]), np.array([1.0, 0.0, 0.0])),
    "interferometer_y": (np.array([0.0, -0.10, 0.0]), np.array([0.0, 1.0, 0.0])),
    "interferometer_z": (np.array([0.0, 0.10, -0.06]), np.array([0.0, -1.0, 0.0])),
    "autocollimator_1": (np.array([0.12, 0.0, 0.0]), np.array([-1.0, 0.0, 0.0])),
    "autocollimator_2": (np.array([0.0, 0.12, 0.0]), np.array([0.0, -1.0, 0.0])),
}
FOLD_MIRROR_Z = np.array([0.0, 0.0, -0.06])   # fold mirror centre, offset from the cube centre
FOLD_MIRROR_NORMAL = np.array([0.0, 1.0, 1.0]) / np.sqrt(2.0)   # bisects -y in and +z out
FOLD_MIRROR_HALF_M = (0.012, 0.015, 0.003)   # reflecting face 24 x 30 mm, 6 mm thick substrate
# instrument housings (half sizes: across, across, along the beam), behind the beam's start
HEAD_HALF_M = {"interferometer": (0.020, 0.020, 0.030), "autocollimator": (0.025, 0.025, 0.040)}
# Beam radius used for the obstruction check: an assumption (neither paper gives it): rays on
# the beam's rim, this far from its axis, must reach the same cube face as the axis ray.
BEAM_RADIUS_M = 0.001

# The force simulator (paper 2): magnets under the plate, coils 10-15 mm below them.
PLATE_THICKNESS_M = 0.006
MAGNET_HALF_M = (0.0075, 0.0075, 0.0015)       # 15 x 15 x 3 mm
COIL_RADIUS_M = 0.012                          # winding and the conductive tube around it
COIL_HEIGHT_M = 0.030
# The magnets sit under the ends of a three-spoke flange below the plate (the plate, the hull of
# the rod hinges, is too small to put the coils out of the beams); the cube hangs from its hub.
SPOKE_WIDTH_M = 0.016
SPOKE_THICKNESS_M = 0.003
STEM_RADIUS_M = 0.005


def magnet_positions(params: RobotParams) -> np.ndarray:
    """Magnet centres (3,3) in the platform frame, under the flange's spokes."""
    az = np.deg2rad(params.magnet_azimuth_deg)
    r = params.magnet_radius_m
    return np.stack([r * np.cos(az), r * np.sin(az),
                     np.full(3, -PLATE_THICKNESS_M - SPOKE_THICKNESS_M - MAGNET_HALF_M[2])], axis=1)
