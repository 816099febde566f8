"""What a physics model is evaluated on: the conditions a dataset recorded (motor coordinates, coil
currents, part temperatures from the sensors, air), gathered from a dataset table and its metadata."""
from __future__ import annotations

import dataclasses
import hashlib
from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from deltatwin.calibration.errors import CalibrationInputError, MissingColumnsError
from deltatwin.calibration.streams import causal_fit
from deltatwin.models.geometry import build_geometry
from deltatwin.models.params import RobotParams
from deltatwin.twin.dataset import temperature_columns
from deltatwin.twin.effects import effect_class
from deltatwin.twin.instruments.optics import (
    AXES,
    COSINE_ANGLES,
    cosine_correction,
    cosine_factor,
    nominal_dead_path,
    vapour_pressure,
)
from deltatwin.twin.lab_setup import known_constants
from deltatwin.twin.statics import Statics
from deltatwin.twin.thermal import PART_NODES
from deltatwin.twin.world import Points

SIBLINGS = {"arm": ("arm1", "arm2", "arm3"), "rod": ("rod1", "rod2", "rod3"),
            "motor": ("motor1", "motor2", "motor3"), "coil": ("coil1", "coil2", "coil3"),
            "air": ("air_x", "air_y", "air_z")}
REQUIRED = ("t_s", "split", "session", "q1_rad", "q2_rad", "q3_rad")
TEMPERATURE_WINDOW_S = 600.0   # causal smoothing of the temperature streams


@dataclass
class Measurements:
    """A dataset prepared for physics models (arrays with a leading axis N = rows)."""
    df: pd.DataFrame
    sensors: dict                 # sensor name -> part
    y: np.ndarray                 # (N,3) readings (m), NaN where the axis was not measured
    cos_scale: np.ndarray         # (N,3) 1 / cosine factor of the row's measured tilts (1 if
                                  # not corrected)
    cos_offset: np.ndarray        # (N,3) the correction's dead-path term s0 (1/c - 1) (m; 0 if
                                  # not corrected)
    group: np.ndarray             # (N,3) index of the (session, axis) zero, -1 where no reading
    groups: list                  # (session, axis) per group index
    cal: np.ndarray               # (N,) bool
    val: np.ndarray               # (N,) bool
    points: Points                # conditions of the N rows then of the session zeros (N + S
                                  # rows; params/home filled in per evaluation)
    zero_row: np.ndarray          # (N,) index in ``points`` of each row's session zero
    T_ref_C: float
    sensor_node_T: dict           # part temperatures taken at their sensors' readings
    # the interferometer supports' temperature (degC) where the laboratory holds them at a set
    # point (its setup's peltier_supports setpoint_C); None: they follow the table
    support_held_C: float | None = None
    # the shares of the air thermometers' temperature the supports and the table set (its
    # setup's room_climate air_support_share, air_table_share): the room is the rest
    room_shares: tuple = (0.0, 0.0)
    _statics: tuple | None = field(default=None, repr=False)

    @property
    def n(self) -> int:
        return self.y.shape[0]

    def residual_dof(self, n_residuals: int, n_directions: int) -> int:
        """Degrees of freedom of a residual of ``n_residuals`` readings fitted with
        ``n_directions`` identified directions and one zero offset per (session, axis) group;
        at least 1."""
        return max(n_residuals - n_directions - len(self.groups), 1)

    def reading_counts(self, rows: np.ndarray) -> list[int]:
        """The number of readings of each (session, axis) group on ``rows`` (N,), in group
        order (as ``projected`` lays them out)."""
        return [int(np.count_nonzero((self.group == g) & rows[:, None]))
                for g in range(len(self.groups))]

    def part_temperatures(self, effects) -> dict:
        """Part temperatures (N + S rows) under the model's ``effects``: those that say how a
        sensor reads its part (``sensed_parts``) correct the readings, else each part is at its
        sensors' reading."""
        sensed = {}
        for e in effects:
            sensed.update(e.sensed_parts(self.points) or {})
        if not sensed:
            return self.sensor_node_T
        readings = {k: v[1] for k, v in self.points.sensor_readings.items()}
        return node_temperatures({**readings, **sensed}, self.sensors, self.T_ref_C,
                                 self.points.t_s.shape[0])

    def statics(self, params: RobotParams):
        """Preload deflection (N,6) and compliance (N,6,6) at each row's position, computed
        once with the starting robot (a µm change of geometry changes them by ~1e-4)."""
        if self._statics is None:
            geom = build_geometry(params)
            st = Statics(params, geom)
            qu, inv = self.points.unique_q()
            self._statics = (st.solve(qu, gravity=False).deflection[inv], st.compliance(qu)[inv])
        return self._statics


def _cosine_dead_path(meta: dict, params: RobotParams, axes, where: str) -> dict:
    """The dead path (m per axis) the data's cosine correction assumed: metadata
    ``cosine_dead_path_m`` if given, else the nominal instrument layout's."""
    given = meta.get("cosine_dead_path_m")
    if given is None:
        return nominal_dead_path(params.mirror_cube_size_m)
    if not isinstance(given, dict):
        raise CalibrationInputError(f"{where}: metadata 'cosine_dead_path_m' must map axis -> m")
    out = {}
    for a in axes:
        v = given.get(a)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0.0 <= v < 10.0:
            raise CalibrationInputError(f"{where}: metadata 'cosine_dead_path_m' {a!r} = {v!r}: "
                                        "expected a path in metres, 0 to 10")
        out[a] = float(v)
    return out


def sensor_streams(df: pd.DataFrame, sensors: dict, window_s: float = TEMPERATURE_WINDOW_S,
                   where: str = "data") -> dict:
    """Each sensor's stream smoothed causally (local linear fit over the past ``window_s``, as a
    controller could: a thermometer's mK noise times a CTE and a 0.35 m loop leg is tens of
    nm): {sensor name: (part, level degC (N,), rate K/s (N,))}."""
    t = df["t_s"].to_numpy(dtype=np.float64)
    order = np.argsort(t, kind="stable")
    for s, part in sensors.items():
        c = f"T_{s}_C"
        if c not in df:
            raise MissingColumnsError(f"{where}: metadata 'sensors' names sensor {s!r} (on "
                                      f"{part!r}) but the data has no column {c!r}")
        bad = np.flatnonzero(~np.isfinite(df[c].to_numpy(dtype=np.float64)))
        if bad.size:
            raise CalibrationInputError(f"{where}: column {c!r}: row {int(bad[0])} is not a "
                                        "finite temperature")
    raw = df[[f"T_{s}_C" for s in sensors]].to_numpy(dtype=np.float64)
    level, rate = np.empty_like(raw), np.empty_like(raw)
    if sensors:     # every sensor in one call: the windows' normal equations are shared
        level[order], rate[order] = causal_fit(t[order], raw[order], window_s, degree=1)[:2]
    return {s: (part, np.ascontiguousarray(level[:, k]), np.ascontiguousarray(rate[:, k]))
            for k, (s, part) in enumerate(sensors.items())}


def node_temperatures(sensor_T: dict, sensors: dict, T_ref_C: float, n: int) -> dict:
    """Part temperatures (degC, (n,) each) from the temperature each sensor stands for
    (``sensor_T``: sensor name -> (n,)): the mean of the sensors on a part; a part without a
    sensor takes the mean of its sensed siblings (arm1..3, rod1..3, ...), else ``T_ref_C``."""
    cols = {}
    for s, part in sensors.items():
        cols.setdefault(part, []).append(sensor_T[s])
    T = {p: np.mean(v, axis=0) for p, v in cols.items()}
    out = {}
    for node, _, _ in PART_NODES:
        if node in T:
            out[node] = T[node]
            continue
        kin = next((g for g in SIBLINGS.values() if node in g), ())
        sensed = [T[k] for k in kin if k in T]
        out[node] = np.mean(sensed, axis=0) if sensed else np.full(n, T_ref_C)
    for a in AXES:   # the interferometer's own air sensor sits in its beam's air
        out[f"sensor:comp_{a}"] = out[f"air_{a}"]
    return out


def move_directions(t_s: np.ndarray, q: np.ndarray, session: np.ndarray):
    """The sign of each motor's last move (+1, -1; 0 before its first), (N,3) at the rows and
    (S,3) at the sessions' zeros (in order of first appearance), from the rows in time order:
    each session starts with a move to home (q = 0) for its zero, then visits its rows."""
    names = list(dict.fromkeys(session))
    order = np.argsort(t_s, kind="stable")
    first_t = np.array([t_s[session == s_].min() for s_ in names])
    # the sequence of commanded positions: every zero just before its session's first row
    key = np.concatenate([t_s[order], first_t])
    rank = np.concatenate([np.ones(order.size), np.zeros(len(names))])   # zero first on ties
    seq = np.lexsort((rank, key))
    Q = np.concatenate([q[order], np.zeros((len(names), 3))])[seq]
    step = np.sign(np.diff(Q, axis=0, prepend=np.zeros((1, 3))))
    # carry the last non-zero move forward (a motor that did not move keeps its direction)
    last = np.where(step != 0, np.arange(len(Q))[:, None], -1)
    last = np.maximum.accumulate(last, axis=0)
    d = np.where(last >= 0, step[np.maximum(last, 0), np.arange(3)], 0.0)
    out = np.empty_like(d)
    out[seq] = d
    rows = np.empty((order.size, 3))
    rows[order] = out[:order.size]
    return rows, out[order.size:]


def data_sha256(meas: Measurements) -> str | None:
    """A fingerprint of what a fit sees (SHA-256, hex): every column of the dataset, row by row
    (pandas' per-row hash), its split and readings, and what the metadata make of them (the
    sensor -> part map, the cosine correction's terms, the reference temperature, the
    supports' held temperature, the room's estimate). A fitted model file keeps it, so a
    diagnosis knows the data are the very ones the model was fitted on. None (never equal to
    a file's) when a column holds values pandas cannot hash (lists, dicts: possible only for
    data built in memory; read files are validated)."""
    h = hashlib.sha256()
    try:
        h.update(pd.util.hash_pandas_object(meas.df, index=False).to_numpy().tobytes())
    except TypeError:
        return None
    h.update(repr((list(map(str, meas.df.columns)), sorted(meas.sensors.items()),
                   float(meas.T_ref_C))).encode())
    if meas.support_held_C is not None or any(meas.room_shares):   # what the setup states
        h.update(repr((meas.support_held_C, meas.room_shares)).encode())
    for a in (meas.y, meas.cal, meas.val, meas.cos_scale, meas.cos_offset):
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()


def check_sensors(effects, meas: Measurements, where: str = "data") -> None:
    """A model whose effects read temperatures needs the data's sensors mapped to parts: without
    the map every part would sit at the reference temperature and the effect would silently do
    nothing."""
    thermal = [n for n in effects if effect_class(n).reads_temperatures]
    if thermal and not meas.sensors:
        present = temperature_columns(meas.df)
        raise CalibrationInputError(
            f"{where}: the model's effect(s) {thermal} read part temperatures, but the dataset's "
            f"metadata names no temperature sensor ('sensors': sensor -> part; temperature "
            f"columns present: {present}): map them in the metadata (the .meta.json beside a "
            "CSV, docs/data-format.md)")


def measurements(df: pd.DataFrame, meta: dict | None, params: RobotParams,
                 where: str = "data") -> Measurements:
    """Check the dataset's columns and build the conditions the model is evaluated on."""
    missing = [c for c in REQUIRED if c not in df.columns]
    if missing:
        raise MissingColumnsError(f"{where}: missing column(s) {missing} (data format: "
                                  "docs/data-format.md)")
    axes = [a for a in AXES if f"{a}_nm" in df.columns]
    if not axes:
        raise MissingColumnsError(f"{where}: no interferometer reading column (x_nm, y_nm, z_nm)")
    meta = meta or {}
    sensors = meta.get("sensors") or {}
    if not isinstance(sensors, dict):
        raise CalibrationInputError(f"{where}: metadata 'sensors' must map sensor name -> part")
    parts = {p for p, _, _ in PART_NODES}
    bad = {s: p for s, p in sensors.items() if p not in parts}
    if bad:
        raise CalibrationInputError(f"{where}: metadata 'sensors' puts {bad} on unknown parts; "
                                    f"parts: {sorted(parts)}")
    n = len(df)
    y = np.full((n, 3), np.nan)
    for a in axes:
        y[:, AXES.index(a)] = df[f"{a}_nm"].to_numpy(dtype=np.float64) * 1e-9
    cos, cos_offset = np.ones((n, 3)), np.zeros((n, 3))
    corrected = df["cosine_corrected"].to_numpy(dtype=bool) if "cosine_corrected" in df else \
        np.zeros(n, bool)
    if corrected.any():
        dead_path = _cosine_dead_path(meta, params, axes, where)
        for a in axes:
            need = [f"{c}_arcsec" for c in COSINE_ANGLES[a]]
            if any(c not in df for c in need):
                raise MissingColumnsError(f"{where}: readings are cosine corrected but the "
                                          f"angle column(s) {need} are missing")
            ang = np.radians(df[need].to_numpy(dtype=np.float64) / 3600.0)
            c = cosine_factor(ang[:, 0], ang[:, 1])
            k = AXES.index(a)
            cos[:, k] = np.where(corrected, 1.0 / c, 1.0)
            # the correction is affine in the reading: (s0 c0 + r) / c - s0 = r / c + s0 (1/c - 1)
            # + s0 (c0 - 1) / c; the last term is the zero's tilt, a constant of the session
            # to 1e-16 m (c = 1 - O(1e-7)), left to the session's offset: c0 = 1 here
            cos_offset[:, k] = np.where(corrected, cosine_correction(0.0, dead_path[a], c), 0.0)
    session = df["session"].astype(str).to_numpy()
    groups, group = [], np.full((n, 3), -1)
    for s in dict.fromkeys(session):
        for k, a in enumerate(AXES):
            m = (session == s) & np.isfinite(y[:, k]) & np.isfinite(cos[:, k])
            if m.any():
                group[m, k] = len(groups)
                groups.append((s, a))
    split = df["split"].astype(str).to_numpy()
    q = df[["q1_rad", "q2_rad", "q3_rad"]].to_numpy(dtype=np.float64)
    if not np.all(np.isfinite(q)):
        bad_row = int(np.flatnonzero(~np.all(np.isfinite(q), axis=1))[0])
        raise CalibrationInputError(f"{where}: row {bad_row}: motor coordinates not finite")
    currents = np.zeros((n, 3))
    for i in range(3):
        if f"coil{i + 1}_A" in df:
            currents[:, i] = df[f"coil{i + 1}_A"].to_numpy(dtype=np.float64)
    T_ref = params.reference_temperature_C
    stated = known_constants(meta, where)       # the laboratory's setup: supports, room
    streams = sensor_streams(df, sensors, where=where)
    # the laboratory's barometer and hygrometer, when it records them (the air_refraction
    # effect's air); without a record the air is taken at what the interferometers assume
    for c in ("p_Pa", "RH_pct"):
        if c in df and not np.all(np.isfinite(df[c].to_numpy(dtype=np.float64))):
            bad = np.flatnonzero(~np.isfinite(df[c].to_numpy(dtype=np.float64)))
            raise CalibrationInputError(f"{where}: column '{c}' is empty at row(s) "
                                        f"{bad[:10].tolist()}: the air record must cover every "
                                        "row (or drop the column: the air is then unrecorded)")
    pressure = df["p_Pa"].to_numpy(dtype=np.float64) if "p_Pa" in df else np.full(n, 101325.0)
    t_s = df["t_s"].to_numpy(dtype=np.float64)
    # each session's zero: the robot at home with the coils off, in the conditions of the
    # session's first row (the zero is taken just before it)
    names = list(dict.fromkeys(session))
    first = np.array([np.flatnonzero(session == s_)[np.argmin(t_s[session == s_])] for s_ in names])
    zero_row = n + np.array([names.index(s_) for s_ in session], dtype=np.int64)
    row_dir, zero_dir = move_directions(t_s, q, session)
    pts = Points(t_s=_with_zeros(t_s, first), q=np.concatenate([q, np.zeros((first.size, 3))]),
                 currents_A=np.concatenate([currents, np.zeros((first.size, 3))]),
                 node_T={}, room_C=None, pressure_Pa=_with_zeros(pressure, first),
                 vapour_Pa=None, support_C={}, params=params, home_p=np.zeros(3),
                 sensor_readings={}, move_direction=np.concatenate([row_dir, zero_dir]))
    meas = Measurements(df=df, sensors=dict(sensors), y=y, cos_scale=cos, cos_offset=cos_offset,
                        group=group,
                        groups=groups, cal=split == "cal", val=split == "val", points=pts,
                        zero_row=zero_row, T_ref_C=T_ref, sensor_node_T={},
                        support_held_C=supports_held_C(stated), room_shares=room_shares(stated))
    return with_sensor_streams(meas, streams)


def supports_held_C(known: dict) -> float | None:
    """The temperature (degC) the laboratory holds its interferometer supports at, as its setup
    states it (``known``: its known constants, ``known_constants``; ``peltier_supports``
    ``setpoint_C``: Peltier-stabilised heads,
    as in the papers' laboratory); None where it states none: the supports then sit on the
    table at its temperature (held supports at 25 degC are kelvins from it: the loop's
    support term then moved with the table's warming instead of standing still)."""
    held = known.get("peltier_supports", {}).get("setpoint_C")
    return None if held is None else float(held)


def room_shares(known: dict) -> tuple[float, float]:
    """(supports' share, table's share) of the air thermometers' temperature, as the data's
    setup states them (``known``: its known constants; room_climate ``air_support_share``,
    ``air_table_share``), else none: the air by the beams is then taken for the room's."""
    stated = known.get("room_climate", {})
    return (float(stated.get("air_support_share", 0.0)),
            float(stated.get("air_table_share", 0.0)))


def room_estimate_C(air_C: np.ndarray, supports_C: np.ndarray, table_C: np.ndarray,
                    shares: tuple[float, float]) -> np.ndarray:
    """The room's temperature (degC) from the air thermometers' ``air_C``: at equilibrium the
    air by the beams is (1 - s - t) room + s supports + t table (``shares`` (s, t)). Taking
    that air for the room put the papers' room 0.9 K too warm (the Peltier-held supports at
    25 degC warm it), and the thermometers' contact correction (sensor_contact) 50 mK off on
    every part, which a fit took up in the contact's leak and the loop's expansion
    coefficients."""
    s, t = shares
    if not s and not t:
        return air_C
    return (air_C - s * supports_C - t * table_C) / (1.0 - s - t)


def _with_zeros(v: np.ndarray, first: np.ndarray) -> np.ndarray:
    """``v`` (N, ...) at the rows, then at each session's zero (S, ...): at the session's
    first row in time (``first`` (S,), its index)."""
    return np.concatenate([v, v[first]])


def _first_rows(meas: Measurements) -> np.ndarray:
    """(S,) each session zero's first row in time (the zero is taken just before it)."""
    t = meas.points.t_s[:meas.n]
    return np.array([rows[np.argmin(t[rows])] for rows in
                     (np.flatnonzero(meas.zero_row == meas.n + z)
                      for z in range(meas.points.t_s.size - meas.n))], dtype=np.int64)


def with_sensor_streams(meas: Measurements, streams: dict) -> Measurements:
    """``meas`` with the temperature conditions made from the sensors' smoothed ``streams``
    ({sensor: (part, level degC, rate K/s)}, as ``sensor_streams`` gives): the parts'
    temperatures, the room's and the table's, the air's water vapour where the humidity is
    recorded; the rest shared. Arrays (N,) are taken at the session zeros as at their first
    rows; arrays (N + S,) give the zeros' own values."""
    first = _first_rows(meas)
    full = lambda v: v if v.shape[0] > meas.n else _with_zeros(v, first)
    streams = {k: (part, full(T), full(r)) for k, (part, T, r) in streams.items()}
    size = meas.n + first.size
    node_T = node_temperatures({k: v[1] for k, v in streams.items()}, meas.sensors,
                               meas.T_ref_C, size)
    supports = (node_T["table"] if meas.support_held_C is None
                else np.full(size, meas.support_held_C))
    beams_air = np.mean([node_T[f"air_{a}"] for a in AXES], axis=0)
    room = room_estimate_C(beams_air, supports, node_T["table"], meas.room_shares)
    # the hygrometer's relative humidity is of the air by the beams, where it sits
    vapour = (vapour_pressure(full(meas.df["RH_pct"].to_numpy(dtype=np.float64)), beams_air)
              if "RH_pct" in meas.df else None)
    pts = dataclasses.replace(meas.points, node_T=node_T, room_C=room, vapour_Pa=vapour,
                              support_C={a: supports for a in AXES},
                              sensor_readings=streams)
    return dataclasses.replace(meas, points=pts, sensor_node_T=node_T)


def thermometer_draw(meas: Measurements, meta: dict | None, params: RobotParams,
                     rng: np.random.Generator, u_K: float) -> Measurements:
    """``meas`` with a fresh draw of every thermometer's noise (standard deviation ``u_K``, K)
    added to its readings, the rest of the data as it is (the preload statics, which depend on
    the motor coordinates only, shared)."""
    df = meas.df.copy()
    columns = [f"T_{s}_C" for s in meas.sensors]
    df[columns] = df[columns].to_numpy() + u_K * rng.standard_normal((len(df), len(columns)))
    out = measurements(df, meta, params)
    out._statics = meas._statics
    return out


# ---------------------------------------------------------------------------------------------
# the model

