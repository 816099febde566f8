"""The standards' test plans as campaigns (``twin.campaign.Plan``), one generator per test:

* ``iso9283_plan``: ISO 9283 pose accuracy and repeatability: the test cube inside the
  workspace, its five poses P1..P5 on the cube's diagonal plane, ``cycles`` (30) cycles in the
  standard's approach order;
* ``iso230_2_plan``: ISO 230-2 along each Cartesian axis through the workspace centre: target
  positions at non-uniform intervals, ``approaches`` (5) approaches in each direction with an
  overrun beyond the end targets (the standard's linear test cycle);
* ``iso230_3_plan``: ISO 230-3 ETVE: the robot at rest at one position, read over hours.

A target is an interferometer reading (m, per axis x, y, z) counted from the session's zero
at home, as everywhere in deltatwin. The plan's motor coordinates are the nominal robot's
inverse kinematics of the target (``nominal_q``): what a controller without a model commands,
the uncompensated robot. (A compensated test decides each point's motor coordinates in the loop
from the same targets: calibration.compensation.) Waiting times are the laboratory's
``wait_s`` after every move (the scenario's [instruments]), as for every campaign.

Each generator returns a ``StandardTest``: the plan and, per point, its target and what it is
in the test (pose or target index, direction, cycle, measured or only a move), which the
evaluation (calibration.standards) reads. Units: m, rad, s.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from deltatwin.models.geometry import build_geometry
from deltatwin.models.kinematics import forward, inverse
from deltatwin.twin.campaign import Plan

TESTS = ("iso9283", "iso230-2", "iso230-3")
POSE_NAMES = ("P1", "P2", "P3", "P4", "P5")
# ISO 9283 7.2: starting at P1, the robot moves successively to P5, P4, P3, P2, P1: one cycle
ISO9283_ORDER = ("P5", "P4", "P3", "P2", "P1")
ISO9283_CYCLES = 30
ISO9283_CORNER_FRACTION = 0.1    # P2..P5 at 10 % of the plane's diagonal from its corners
ISO230_2_APPROACHES = 5          # per direction
ISO230_2_TARGETS = 11            # the standard asks at least 5 (and 5 per metre)
ISO230_2_OVERRUN = 0.05          # of the travel, beyond each end target
ISO230_3_HOURS = 24.0
STROKE_FRACTION = 0.9            # the test's motor coordinates stay within this share of the stroke


@dataclass(frozen=True)
class StandardTest:
    """A test's plan and what each of its points is.

    ``targets_m`` (N, 3) the commanded reading per point; ``item`` (N,) the pose (ISO 9283:
    0..4 for P1..P5) or target (ISO 230-2: index into ``positions_m`` of its axis) of a
    point, -1 for a point that only moves (start, overrun); ``direction`` (N,) +1 up, -1 down
    (ISO 230-2), 0 otherwise; ``cycle`` (N,) the cycle or run; ``axis`` (N,) the axis tested
    (ISO 230-2), "" otherwise. ``positions_m`` {axis or "poses": (K, 3)} the distinct targets.
    """
    test: str
    plan: Plan
    targets_m: np.ndarray
    item: np.ndarray
    direction: np.ndarray
    cycle: np.ndarray
    axis: np.ndarray
    positions_m: dict
    parameters: dict = field(default_factory=dict)

    @property
    def measured(self) -> np.ndarray:
        return self.item >= 0


class Workspace:
    """The nominal robot's readings and motor coordinates: reading = platform position minus
    its position at home (q = 0), and the largest cube and axis spans inside ``fraction`` of the
    stroke about the workspace centre (the reading at the middle of the stroke cube)."""

    def __init__(self, params, fraction: float = STROKE_FRACTION):
        self.geom = build_geometry(params)
        lo, hi = (float(v) for v in params.stroke_rad)
        mid, half = 0.5 * (lo + hi), 0.5 * (hi - lo) * fraction
        self.q_lo, self.q_hi = mid - half, mid + half
        self.home_m = forward(self.geom, np.zeros((1, 3))).p[0]
        self.centre_m = forward(self.geom, np.full((1, 3), mid)).p[0] - self.home_m

    def nominal_q(self, targets_m) -> np.ndarray:
        """Motor coordinates (N, 3) rad of the nominal robot at the readings ``targets_m``."""
        return inverse(self.geom, self.home_m + np.atleast_2d(targets_m), check=False)[0]

    def reachable(self, targets_m) -> bool:
        try:
            q = self.nominal_q(targets_m)
        except ValueError:          # KinematicsError: no closure
            return False
        return bool(np.all(np.isfinite(q)) and np.all((q >= self.q_lo) & (q <= self.q_hi)))

    def largest(self, shape, hi: float = 0.05) -> float:
        """The largest size s (m) with ``shape(s)`` ((n, 3) readings) reachable, by bisection
        to 1 nm."""
        lo = 0.0
        while hi - lo > 1e-9:
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if self.reachable(shape(mid)) else (lo, mid)
        return lo


def _plan(sessions, session, item, q) -> Plan:
    n = len(q)
    return Plan(sessions=tuple(sessions), session=np.asarray(session, int),
                pos_id=np.asarray(item, np.int64), split=np.full(n, "val"), q=np.asarray(q),
                currents_A=np.zeros((n, 3)), F_N=np.zeros(n), readings=1)


def _check_int(name, value, low):
    if isinstance(value, bool) or int(value) != value or value < low:
        raise ValueError(f"{name} = {value!r}: expected an integer >= {low}")
    return int(value)


def iso9283_poses(ws: Workspace, corner_fraction: float = ISO9283_CORNER_FRACTION):
    """(poses (5, 3) m, cube side m): ISO 9283 6.8: the largest cube (edges along x, y, z)
    about the workspace centre; P1 at its centre, P2..P5 on its diagonal plane through the
    edges along x at (y-, z-) and (y+, z+), each at ``corner_fraction`` of the plane's
    diagonal from a corner (C1..C4 of the plane, in turn)."""
    signs = np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1], indexing="ij")).reshape(3, -1).T
    side = ws.largest(lambda s: ws.centre_m + 0.5 * s * signs)
    corners = ws.centre_m + 0.5 * side * np.array([[-1, -1, -1], [1, -1, -1], [1, 1, 1],
                                                   [-1, 1, 1]])
    # a corner to P_k along the diagonal: corner_fraction of the diagonal, whose half joins
    # the corner to the centre
    poses = corners + 2.0 * corner_fraction * (ws.centre_m - corners)
    return np.vstack([ws.centre_m, poses]), side


def iso9283_plan(params, cycles: int = ISO9283_CYCLES, order=ISO9283_ORDER,
                 corner_fraction: float = ISO9283_CORNER_FRACTION,
                 stroke_fraction: float = STROKE_FRACTION) -> StandardTest:
    """ISO 9283 pose test: a start at P1 (moved to, not counted), then ``cycles`` cycles
    visiting the poses in ``order`` (default P5, P4, P3, P2, P1), each approached from the
    pose before it, one session reading x, y, z."""
    cycles = _check_int("ISO 9283 cycles", cycles, 2)
    bad = [p for p in order if p not in POSE_NAMES]
    if bad or not order:
        raise ValueError(f"ISO 9283 order {list(order)}: poses are {list(POSE_NAMES)}")
    if not 0 < corner_fraction < 0.5:
        raise ValueError(f"ISO 9283 corner_fraction = {corner_fraction}: must be in (0, 0.5)")
    ws = Workspace(params, stroke_fraction)
    poses, side = iso9283_poses(ws, corner_fraction)
    idx = [POSE_NAMES.index(p) for p in order]
    item = np.array([-1] + idx * cycles)
    cycle = np.array([-1] + list(np.repeat(np.arange(cycles), len(idx))))
    which = np.where(item >= 0, item, 0)
    targets = poses[which]
    return StandardTest("iso9283", _plan([("iso9283", ("x", "y", "z"))], np.zeros(len(item)),
                                         item, ws.nominal_q(targets)),
                        targets, item, np.zeros(len(item), int), cycle,
                        np.full(len(item), ""), {"poses": poses},
                        {"cycles": cycles, "order": list(order), "cube_side_m": side,
                         "corner_fraction": corner_fraction, "stroke_fraction": stroke_fraction})


def iso230_2_targets(span_m: float, n: int, rng) -> np.ndarray:
    """``n`` target positions over ``span_m`` centred on 0: P_i = i p + r_i, the interior ones
    shifted by r_i uniform in +-p/4 so that the intervals differ (ISO 230-2: non-uniform
    intervals, so that periodic errors are sampled), the end targets at the ends."""
    p = span_m / (n - 1)
    r = rng.uniform(-0.25 * p, 0.25 * p, n)
    r[[0, -1]] = 0.0
    return -0.5 * span_m + np.arange(n) * p + r


def iso230_2_plan(params, rng, axes=("x", "y", "z"), targets: int = ISO230_2_TARGETS,
                  approaches: int = ISO230_2_APPROACHES, overrun: float = ISO230_2_OVERRUN,
                  stroke_fraction: float = STROKE_FRACTION) -> StandardTest:
    """ISO 230-2 along each axis of ``axes`` through the workspace centre, one session per
    axis reading that axis: the travel the largest symmetric span the stroke allows less the
    overrun; per run, from the overrun below the first target up through every target, to the
    overrun above the last and down through every target (the standard's linear cycle),
    ``approaches`` runs."""
    targets = _check_int("ISO 230-2 targets", targets, 2)
    approaches = _check_int("ISO 230-2 approaches", approaches, 2)
    if not 0 <= overrun <= 0.5:
        raise ValueError(f"ISO 230-2 overrun = {overrun}: a fraction of the travel in [0, 0.5]")
    bad = [a for a in axes if a not in ("x", "y", "z")]
    if bad or not axes or len(set(axes)) != len(axes):
        raise ValueError(f"ISO 230-2 axes {list(axes)}: expected some of x, y, z, each once")
    ws = Workspace(params, stroke_fraction)
    rows, sessions, positions, spans = [], [], {}, {}
    for k, a in enumerate(axes):
        e = np.eye(3)[("x", "y", "z").index(a)]
        half = ws.largest(lambda s, e=e: ws.centre_m + np.outer([-s, s], e))
        travel = 2 * half / (1 + 2 * overrun)
        pos = iso230_2_targets(travel, targets, rng)
        positions[a], spans[a] = ws.centre_m + np.outer(pos, e), travel
        below, above = pos[0] - overrun * travel, pos[-1] + overrun * travel
        for j in range(approaches):
            rows.append((k, -1, 0, j, below))
            rows += [(k, i, 1, j, pos[i]) for i in range(targets)]
            rows.append((k, -1, 0, j, above))
            rows += [(k, i, -1, j, pos[i]) for i in reversed(range(targets))]
        sessions.append((f"iso230-2 {a}", (a,)))
    sess, item, direction, cycle, along = (np.array(c) for c in zip(*rows))
    axis_of = np.array(axes)[sess]
    unit = np.eye(3)[[("x", "y", "z").index(a) for a in axis_of]]
    target_m = ws.centre_m + unit * along[:, None]
    return StandardTest("iso230-2", _plan(sessions, sess, item, ws.nominal_q(target_m)),
                        target_m, item, direction, cycle, axis_of, positions,
                        {"axes": list(axes), "targets": targets, "approaches": approaches,
                         "overrun": overrun, "travel_m": spans,
                         "stroke_fraction": stroke_fraction})


def point_time_at_rest(settings) -> float:
    """The time (s) a point at rest takes in the laboratory ``settings``: the settle of a null
    move, the wait, one reading window and the autocollimators, the overhead."""
    s = settings
    return s.move_base_s + s.wait_s + s.window_s + s.ac_read_s + s.overhead_s


def iso230_3_plan(params, settings, duration_h: float = ISO230_3_HOURS, position_m=None,
                  stroke_fraction: float = STROKE_FRACTION) -> StandardTest:
    """ISO 230-3 ETVE: the robot at rest at ``position_m`` (a reading, default the workspace
    centre) read in x, y, z as often as the laboratory's timing allows
    (``point_time_at_rest``; a longer interval: a longer ``overhead_s``) for ``duration_h``
    hours."""
    if not 0 < duration_h <= 24 * 30:
        raise ValueError(f"ISO 230-3 duration_h = {duration_h}: must be in (0, 720] hours")
    ws = Workspace(params, stroke_fraction)
    pos = ws.centre_m if position_m is None else np.asarray(position_m, dtype=np.float64)
    if pos.shape != (3,) or not ws.reachable(pos):
        raise ValueError(f"ISO 230-3 position {np.asarray(position_m).tolist()} m: not a "
                         "reachable reading (x, y, z) within the stroke")
    n = max(3, int(np.ceil(duration_h * 3600.0 / point_time_at_rest(settings))))
    targets = np.repeat(pos[None], n, axis=0)
    item = np.zeros(n, int)
    return StandardTest("iso230-3", _plan([("iso230-3", ("x", "y", "z"))], np.zeros(n), item,
                                          ws.nominal_q(targets)),
                        targets, item, np.zeros(n, int), np.arange(n), np.full(n, ""),
                        {"rest": pos[None]}, {"duration_h": duration_h,
                                              "stroke_fraction": stroke_fraction})
