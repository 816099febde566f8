"""The twin's world: one robot with its effects in its laboratory, evaluated at any instants.

Stages, in the order data flows (each effect joins the stages it overrides, twin/effects/):
1. robot: the robot parameters (nominal + the file's deviations) -> ``robot`` hooks (geometric
   errors drawn from the seeded stream);
2. environment: room air, pressure, support temperatures on the thermal grid (``environment``);
3. heat: motor and coil powers from what the campaign did (``heat_sources`` over the Schedule);
4. thermal network (twin/thermal.py): the sensors' contact with their parts (``thermometers``),
   node and sensor temperatures, integrated up to any time;
5. geometry: per-point part temperatures (``part_temperatures``) and where the motors truly
   sit (``motor_angles``: encoder errors, backlash) -> exact kinematics;
6. load: the wrench (``wrench``: gravity, coils) through the statics -> the platform's pose;
7. optics: beams, fold mirror and air index (``optics``) -> optical paths and the index the
   instruments divide by; autocollimator tilts.
The simulated instruments (twin/instruments/simulated.py) add zeroing, noise, resolution and
timing; the fast path (twin/campaign.py) evaluates whole campaigns at once through the same
functions.  Units: m, rad, s, N, degC.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from deltatwin.models.geometry import build_geometry
from deltatwin.models.kinematics import Pose, forward
from deltatwin.models.params import RobotParams
from deltatwin.twin.effects import Effect
from deltatwin.twin.instruments.optics import (
    AXES,
    Optics,
    autocollimator_angles,
    optical_path,
    saturation_vapour_pressure,
)
from deltatwin.twin.noise import NoiseBank
from deltatwin.twin.statics import Statics, deflected_pose
from deltatwin.twin.thermal import GRID_S, SUPPORTS, Inputs, ThermalNetwork, sensor_set

# a new stream goes at the end: a child's draws depend only on its position
STREAMS = ("robot", "environment", "interferometers", "autocollimators", "thermometers",
           "campaign", "servo", "air_sensors")
STANDARD_VAPOUR_PA = 1000.0    # the air's water vapour when no climate sets it (43 % RH at 20 degC)
COMPENSATION_SENSORS = {f"comp_{a}": f"air_{a}" for a in AXES}


# the streams drawn per event (a motor settling, an interferometer window, an autocollimator
# read), counted from the world's start; the others make the robot, its climate and the
# campaign's plan, or are indexed by campaign time (the thermometer and air-sensor scans)
EVENT_STREAMS = ("interferometers", "autocollimators", "servo")


def random_streams(seed: int, session: tuple[int, ...] | None = None
                   ) -> dict[str, np.random.Generator]:
    """One independent generator per purpose, all from ``seed`` (same seed, same data).
    ``session``: the world is a later session of the same robot in the same laboratory (a
    compensated campaign): its ``EVENT_STREAMS`` are drawn from ``(seed, *session)`` instead,
    so that its settles and reading windows are new draws, not those the calibration campaign's
    world (and every other session) counts from its start."""
    children = np.random.SeedSequence(seed).spawn(len(STREAMS))
    streams = {name: np.random.default_rng(s) for name, s in zip(STREAMS, children)}
    if session is not None:
        fresh = np.random.SeedSequence([seed, *session]).spawn(len(EVENT_STREAMS))
        streams.update({name: np.random.default_rng(s) for name, s in zip(EVENT_STREAMS, fresh)})
    return streams


class Schedule:
    """What the campaign did, as it happened: moves and coil current settings (campaign time)."""

    def __init__(self):
        self.moves: list[tuple[float, float, np.ndarray]] = []   # (start, end, dq / max|dq| (3,))
        self.current_t: list[float] = [-np.inf]
        self.current_I: list[np.ndarray] = [np.zeros(3)]

    def add_move(self, t_start: float, t_end: float, dq: np.ndarray) -> None:
        dq = np.asarray(dq, dtype=np.float64)
        top = np.abs(dq).max()
        self.moves.append((float(t_start), float(t_end), dq / top if top > 0 else dq))

    def set_currents(self, t: float, currents_A) -> None:
        self.current_t.append(float(t))
        self.current_I.append(np.asarray(currents_A, dtype=np.float64).copy())

    def speed_fraction(self, t: np.ndarray) -> np.ndarray:
        """(n,3): each motor's share of full speed at times t (0 at rest)."""
        out = np.zeros((t.size, 3))
        if not self.moves:
            return out
        start = np.array([m[0] for m in self.moves])
        end = np.array([m[1] for m in self.moves])
        share = np.abs([m[2] for m in self.moves])
        k = np.searchsorted(start, t, side="right") - 1
        inside = (k >= 0) & (t < end[np.maximum(k, 0)])
        out[inside] = share[k[inside]]
        return out

    def settling_events(self, t: np.ndarray) -> np.ndarray:
        """(n,) how many times the position controller has settled by times t: at the end of
        every move and at every change of the coil currents (the load)."""
        ends = np.sort([m[1] for m in self.moves])
        changes = np.sort(self.current_t[1:])
        return (np.searchsorted(ends, t, side="right")
                + np.searchsorted(changes, t, side="right")).astype(np.int64)

    def move_direction(self, t: np.ndarray) -> np.ndarray:
        """(n,3) the sign of each motor's last move begun by times t (0 before its first)."""
        t = np.asarray(t, dtype=np.float64)
        out = np.zeros((t.size, 3))
        if not self.moves:
            return out
        start = np.array([m[0] for m in self.moves])
        sign = np.sign([m[2] for m in self.moves])
        for i in range(3):
            moved = np.flatnonzero(sign[:, i] != 0)
            if moved.size:
                k = np.searchsorted(start[moved], t, side="right") - 1
                out[:, i] = np.where(k >= 0, sign[moved[np.maximum(k, 0)], i], 0.0)
        return out

    def currents(self, t: np.ndarray) -> np.ndarray:
        """(n,3) coil currents (A) in force at times t."""
        k = np.searchsorted(np.array(self.current_t), t, side="right") - 1
        return np.array(self.current_I)[k]


@dataclass
class Points:
    """Conditions at N instants (arrays with a leading axis N)."""
    t_s: np.ndarray
    q: np.ndarray
    currents_A: np.ndarray
    node_T: dict
    room_C: np.ndarray
    pressure_Pa: np.ndarray
    support_C: dict
    params: RobotParams
    home_p: np.ndarray
    pose: Pose | None = None     # kinematic pose, set by the twin before the load stage
    # a model fitted to measurements: sensor name -> (part, smoothed reading degC, rate K/s)
    sensor_readings: dict | None = None
    # the air's water-vapour partial pressure (Pa); None in a model without a humidity record
    # (the air is then taken at the humidity the interferometers assume)
    vapour_Pa: np.ndarray | None = None
    _unique_q: tuple | None = field(default=None, repr=False)

    def unique_q(self) -> tuple[np.ndarray, np.ndarray]:
        """The distinct motor coordinates (M,3) and each point's index among them (N,):
        computed once per ``q`` array (a model evaluated many times on the same points, a
        twin's kinematics and statics on the same instants)."""
        if self._unique_q is None or self._unique_q[0] is not self.q:
            qu, inv = np.unique(self.q, axis=0, return_inverse=True)
            self._unique_q = (self.q, qu, inv.reshape(-1))
        return self._unique_q[1:]
    # (N,3) sign of each motor's last move (+1, -1; 0 before its first): what a hysteresis
    # depends on
    move_direction: np.ndarray | None = None


@dataclass
class Truth:
    """What the instruments look at, at N instants."""
    pose: Pose                     # the platform's true (deflected) pose
    kinematic_pose: Pose
    wrench: np.ndarray             # (N,6)
    optical_path_m: dict           # axis -> (N,) n * s
    n_comp: dict                   # axis -> (N,)
    angles_rad: dict               # autocollimator channel -> (N,)
    optics: Optics = field(repr=False, default=None)
    deflection: np.ndarray = field(repr=False, default=None)   # (N,6) y of ``pose``


class Twin:
    """One robot, its effects and its laboratory, for one scenario and seed (``session``: a
    later session's own event noise, ``random_streams``)."""

    def __init__(self, params: RobotParams, effects: list[Effect], sensors: dict[str, str],
                 seed: int, horizon_s: float, warmup_s: float = 7200.0,
                 session: tuple[int, ...] | None = None):
        self.effects = list(effects)
        self.names = {e.name for e in self.effects}
        self.rng = random_streams(seed, session)
        for e in self.effects:
            params = e.robot(params, self.rng["robot"])
        self.params = params
        self.geom = build_geometry(params)
        self.statics = Statics(params, self.geom)
        self.home_p = forward(self.geom, np.zeros((1, 3))).p[0]
        self.cube_home = self.home_p + self.geom.cube_offset
        settling = [e for e in self.effects
                    if type(e).motor_settling is not Effect.motor_settling]
        # the motors' settled angle errors, row k after the k-th settling event
        self.settling = NoiseBank(self.rng["servo"], lambda g, n: sum(
            e.motor_settling(g, n) for e in settling)) if settling else None
        self.schedule = Schedule()                         # what the campaign did so far
        self.sensors = dict(sensors)
        thermometers = sensor_set({**self.sensors, **COMPENSATION_SENSORS})
        for e in self.effects:
            thermometers = e.thermometers(thermometers)
        self.network = ThermalNetwork(thermometers,
                                      supports_on="peltier_supports" in self.names)
        # campaign-independent environment on the whole grid
        t_grid = -warmup_s + GRID_S * np.arange(int(np.ceil((horizon_s + warmup_s) / GRID_S)) + 2)
        T_ref = params.reference_temperature_C
        self.env = Inputs(t_grid=t_grid, room_C=np.full(t_grid.size, T_ref),
                          supports_C={s: np.full(t_grid.size, T_ref) for s in SUPPORTS},
                          pressure_Pa=np.full(t_grid.size, 101325.0),
                          vapour_Pa=np.full(t_grid.size, STANDARD_VAPOUR_PA))
        for e in self.effects:
            e.environment(self.env, self.rng["environment"])
        self.t_grid = t_grid
        self._U_env = self.network.input_matrix(self.env)
        self._state = self.network.start(self._U_env[0])
        self._T = np.empty((t_grid.size, len(self.network.nodes)))
        self._T[0] = self.network.steady_state(self._U_env[0])
        self._done = 0                                   # grid index integrated up to

    # -- thermal ------------------------------------------------------------------------------
    def advance(self, t_s: float, schedule: Schedule) -> None:
        """Integrate the thermal network far enough to know temperatures at time ``t_s``.
        Inputs at a grid time depend only on events before it, so integrating in pieces as a
        campaign goes gives the same temperatures as integrating its whole schedule at once."""
        # the first grid point at or after t_s, found on the grid itself: (t_s + warmup) / GRID_S
        # rounds onto a grid point when t_s is a few ulp above it, and ceil would then stop one
        # step short of t_s
        k = int(np.searchsorted(self.t_grid, t_s, side="left"))
        if k >= self.t_grid.size:
            raise ValueError(f"time {t_s:.6g} s is beyond the twin's time horizon "
                             f"({self.t_grid[-1]:.6g} s, the longest campaign its scenario, "
                             "scale and seed plan for)")
        self.schedule = schedule
        if k <= self._done:
            return
        steps = slice(self._done, k)
        U = self._U_env[steps].copy()
        t = self.t_grid[steps]
        for e in self.effects:
            for node, P in e.heat_sources(t, schedule, self.params).items():
                U[:, self.network.inputs.index(node)] += P
        self._T[self._done + 1:k + 1] = self._state.advance(U)
        self._done = k

    def node_temperatures(self, t_s: np.ndarray) -> dict[str, np.ndarray]:
        """Temperatures (degC) of every node at times ``t_s`` (linear between grid points)."""
        t_s = np.asarray(t_s, dtype=np.float64)
        if t_s.size and t_s.max() > self.t_grid[self._done]:
            raise ValueError("temperatures asked beyond the integrated time; call advance()")
        # the interval t_grid[i] < t_s <= t_grid[i + 1], located on the grid itself (not by
        # rounding (t_s - t0) / GRID_S), so it never reaches past the integrated point
        i = np.clip(np.searchsorted(self.t_grid, t_s, side="left") - 1, 0, self.t_grid.size - 2)
        f = ((t_s - self.t_grid[i]) / (self.t_grid[i + 1] - self.t_grid[i]))[:, None]
        # f == 0 only at the grid's first point, whose successor may not be integrated yet
        T = np.where(f > 0, self._T[i] * (1 - f) + self._T[i + 1] * f, self._T[i])
        out = {name: T[:, j] for j, name in enumerate(self.network.nodes)}
        out.update({alias: out[part] for alias, part in self.network.aliases.items()})
        return out

    def points(self, t_s, q, currents_A, settled: bool = True) -> Points:
        """Conditions at times ``t_s`` with the motors commanded to ``q`` (n,3) rad and the
        coils at ``currents_A``; with a settling effect the motors sit where their controller
        settled after the schedule's last event (``settled=False``: at ``q`` exactly)."""
        t_s = np.atleast_1d(np.asarray(t_s, dtype=np.float64))
        q = np.atleast_2d(np.asarray(q, dtype=np.float64))
        if self.settling is not None and settled:
            k = self.schedule.settling_events(t_s)
            q = q + self.settling.take(0, int(k.max()) + 1)[k]
        node_T = self.node_temperatures(t_s)
        env = lambda arr: np.interp(t_s, self.t_grid, arr)
        peltier = "peltier_supports" in self.names
        support_C = {a: env(self.env.supports_C[f"support_{a}"]) if peltier else node_T["table"]
                     for a in AXES}
        return Points(t_s=t_s, q=q,
                      currents_A=np.atleast_2d(currents_A).astype(np.float64), node_T=node_T,
                      room_C=env(self.env.room_C), pressure_Pa=env(self.env.pressure_Pa),
                      support_C=support_C, params=self.params, home_p=self.home_p,
                      move_direction=self.schedule.move_direction(t_s),
                      vapour_Pa=env(self.env.vapour_Pa))

    def air(self, t_s) -> dict[str, np.ndarray]:
        """The laboratory air at times ``t_s``: barometric pressure (Pa), water-vapour partial
        pressure (Pa) and the relative humidity (%) it makes at the beams' mean air temperature
        (where a hygrometer by the beams measures it)."""
        t_s = np.atleast_1d(np.asarray(t_s, dtype=np.float64))
        env = lambda arr: np.interp(t_s, self.t_grid, arr)
        T = self.node_temperatures(t_s)
        beams_C = np.mean([T[f"air_{a}"] for a in AXES], axis=0)
        vapour = env(self.env.vapour_Pa)
        return {"pressure_Pa": env(self.env.pressure_Pa), "vapour_Pa": vapour,
                "humidity_pct": 100.0 * vapour / saturation_vapour_pressure(beams_C)}

    # -- geometry, load, optics ---------------------------------------------------------------
    def truth(self, pts: Points) -> Truth:
        geom, kin = kinematic_pose(self.params, self.geom, self.effects, pts)
        qu, inv = pts.unique_q()
        # statics are linear in the load: preload deflection + compliance * wrench, per position
        preload = self.statics.solve(qu, gravity=False).deflection[inv]
        return observe(geom, kin, self.effects, pts, preload, self.statics.compliance(qu)[inv],
                       self.cube_home, self.params.mirror_cube_size_m)


def geometry_temperatures(effects: list[Effect], pts: Points) -> dict:
    """Per-point part temperatures the effects give the geometry ({"base": (N,), "arms": (N,3),
    ...}, degC); empty when none does (the robot parameters' own temperatures hold)."""
    temps = {}
    for e in effects:
        temps.update(e.part_temperatures(pts) or {})
    return temps


def point_geometry(params: RobotParams, geom, effects: list[Effect], pts: Points):
    """The geometry at the points: scaled per point by the effects' part temperatures (a
    batched Geometry), else ``geom`` (one robot state, built from ``params``)."""
    temps = geometry_temperatures(effects, pts)
    return build_geometry(params, temps) if temps else geom


def motor_positions(effects: list[Effect], pts: Points) -> np.ndarray:
    """Where the motors truly sit (N,3) rad: the encoders' reading ``pts.q`` plus the effects'
    angle errors (``pts.q`` itself when no effect has any)."""
    errors = [d for d in (e.motor_angles(pts) for e in effects) if d is not None]
    return pts.q + sum(errors) if errors else pts.q


def kinematic_pose(params: RobotParams, geom, effects: list[Effect], pts: Points):
    """Geometry and kinematic pose at the points: the effects' part temperatures scale the
    geometry per point and their motor angle errors move the motors (exact kinematics per
    point), otherwise one geometry for all (FK per unique q)."""
    geom = point_geometry(params, geom, effects, pts)
    q = motor_positions(effects, pts)
    if geom.batched or q is not pts.q:
        return geom, forward(geom, q)
    qu, inv = pts.unique_q()
    ku = forward(geom, qu)
    return geom, Pose(ku.p[inv], ku.R[inv])


def platform_wrench(effects: list[Effect], pts: Points) -> np.ndarray:
    """The effects' wrench (N,6) on the platform at the kinematic pose ``pts.pose`` (N, N*m)."""
    wrench = np.zeros((pts.t_s.shape[0], 6))
    for e in effects:
        w = e.wrench(pts)
        if w is not None:
            wrench += w
    return wrench


def deflection(preload: np.ndarray, compliance: np.ndarray, wrench: np.ndarray) -> np.ndarray:
    """The platform's small displacement (N,6: position, rotation vector) under the wrench: the
    preload deflection plus C w, in one pass over C (a batched 6x6 product pays per item, and
    C's columns one at a time stride through it six times: 3.4x slower at 29,000 rows)."""
    return preload + np.einsum("nij,nj->ni", compliance, wrench)


def instrument_optics(effects: list[Effect], pts: Points, cube_home: np.ndarray,
                      start: Optics | None = None) -> Optics:
    """The effects' optics (heads, beams, fold mirror, air indices) at the points, on the
    nominal instruments aligned on ``cube_home`` or on a copy of ``start`` (the optics earlier
    effects made: a model's derivative in one effect's parameter re-uses them)."""
    optics = (Optics.nominal(cube_home, pts.t_s.shape[0], n_nominal=1.0) if start is None
              else start.copy())
    for e in effects:
        e.optics(pts, optics)
    return optics


def observe(geom, kin: Pose, effects: list[Effect], pts: Points, preload: np.ndarray,
            compliance: np.ndarray, cube_home: np.ndarray, cube_size_m: float,
            wrench: np.ndarray | None = None) -> Truth:
    """Load and optics stages: the effects' wrench through the compliance (N,6,6) on top of the
    preload deflection (N,6) moves the platform; the effects' optics give what the
    instruments look at. ``wrench``: the effects' wrench at ``kin`` when the caller has it
    already (a model's derivative in an optics parameter re-uses it), else computed here."""
    pts.pose = kin
    if wrench is None:
        wrench = platform_wrench(effects, pts)
    y = deflection(preload, compliance, wrench)
    pose = deflected_pose(kin, y)
    optics = instrument_optics(effects, pts, cube_home)
    paths = {a: optical_path(pose, geom.cube_offset, cube_size_m, optics, a) for a in AXES}
    return Truth(pose=pose, kinematic_pose=kin, wrench=wrench, optical_path_m=paths,
                 n_comp=dict(optics.n_comp), angles_rad=autocollimator_angles(pose.R),
                 optics=optics, deflection=y)
