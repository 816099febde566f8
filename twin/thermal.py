"""Lumped thermal network of the robot, its measurement loop and the room.

Nodes are parts with a heat capacity (J/K) joined by conductances (W/K); the room air, the Peltier-
stabilised interferometer supports and the heat sources (motors, coils) are inputs. Temperature
sensors with a real contact (effect ``sensor_contact``) are nodes too: a small capacity glued to its
part and leaking a little to the air, so a sensor lags its part and misses part of its gradient to
the room (the reason the seeds' temperature derivatives help).

The network is linear, C dT/dt = -K T + F u, and is integrated exactly (zero-order hold on a fixed
grid) in its modal coordinates: with K V = C V diag(lam) and V^T C V = I every mode is a
first-order filter (``first_order_filter``), so three days at 1 s steps take milliseconds, and
integrating in pieces (``ThermalState``, used by the simulated instruments as the campaign clock
advances) gives the same temperatures. Units: degC, s, J/K, W/K, W."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.linalg import eigh, solve_banded

GRID_S = 1.0  # integration step; inputs are held constant over a step


def first_order_filter(u: np.ndarray, a, y_before) -> np.ndarray:
    """y[k] = a y[k-1] + u[k] along axis 0 of ``u`` ((n,) or (n, m)), from y[-1] =
    ``y_before``, for decays ``a`` in [0, 1) (a scalar or one per column): what
    ``scipy.signal.lfilter([1], [1, -a], u, zi=[a * y_before])`` computes, without importing
    scipy.signal (0.33 s CPU with the scipy.stats it loads, a third of a short simulation). The
    recursion is the lower bidiagonal system (1 on the diagonal, -a below it) that LAPACK's
    banded solver takes row by row: the same operations as the recursion, one solve per decay."""
    u = np.asarray(u, dtype=np.float64)
    if u.shape[0] == 0:
        return u.copy()
    columns = u.reshape(u.shape[0], -1)
    m = columns.shape[1]
    a = np.broadcast_to(np.asarray(a, np.float64), (m,))
    if not np.all((a >= 0.0) & (a < 1.0)):
        raise ValueError(f"first_order_filter: decays {a[~((a >= 0.0) & (a < 1.0))]} are not "
                         "in [0, 1)")
    y_before = np.broadcast_to(np.asarray(y_before, np.float64), (m,))
    rhs = columns.copy()
    rhs[0] += a * y_before
    if u.shape[0] == 1:
        # already the answer; and scipy < 1.14's solve_banded divides one row by the band
        # below the diagonal (zero) instead of the diagonal
        return rhs.reshape(u.shape)
    bands = np.zeros((2, u.shape[0]))
    bands[0] = 1.0
    decays, column_decay = np.unique(a, return_inverse=True)
    for d, decay in enumerate(decays):
        same = np.flatnonzero(column_decay == d)
        bands[1, :-1] = -decay
        rhs[:, same] = solve_banded((1, 0), bands, rhs[:, same], overwrite_b=True,
                                    check_finite=False)
    return rhs.reshape(u.shape)


# (node, heat capacity J/K, conductance to the room air W/K); time constants alone = C/G
PART_NODES = (
    ("table", 6.0e5, 25.0),        # granite/steel table, ~6.7 h
    ("frame", 1.2e5, 8.0),         # metrology frame, ~4.2 h
    ("base", 4.0e4, 3.5),          # titanium base with the motors, ~3.2 h
    ("arm1", 2.5e3, 0.8), ("arm2", 2.5e3, 0.8), ("arm3", 2.5e3, 0.8),   # ~52 min
    ("rod1", 300.0, 0.12), ("rod2", 300.0, 0.12), ("rod3", 300.0, 0.12),  # rod pairs, ~42 min
    ("platform", 350.0, 0.15),     # platform + mirror cube + magnets, ~39 min
    ("motor1", 900.0, 0.6), ("motor2", 900.0, 0.6), ("motor3", 900.0, 0.6),
    ("coil1", 400.0, 0.05), ("coil2", 400.0, 0.05), ("coil3", 400.0, 0.05),  # insulated box
    ("coil_box", 3.0e3, 1.2),
    ("air_x", 60.0, 1.0), ("air_y", 60.0, 1.0), ("air_z", 60.0, 1.0),   # beam air, ~1 min
)
# conductances between nodes (W/K): the mechanical joints and the air around the beams
LINKS = (
    ("table", "frame", 6.0), ("frame", "base", 1.5),
    ("base", "arm1", 0.35), ("base", "arm2", 0.35), ("base", "arm3", 0.35),
    ("motor1", "base", 0.8), ("motor2", "base", 0.8), ("motor3", "base", 0.8),
    ("motor1", "arm1", 0.5), ("motor2", "arm2", 0.5), ("motor3", "arm3", 0.5),
    ("arm1", "rod1", 0.02), ("arm2", "rod2", 0.02), ("arm3", "rod3", 0.02),
    ("rod1", "platform", 0.02), ("rod2", "platform", 0.02), ("rod3", "platform", 0.02),
    ("coil1", "coil_box", 0.6), ("coil2", "coil_box", 0.6), ("coil3", "coil_box", 0.6),
    ("coil_box", "table", 0.8), ("coil_box", "platform", 0.01),
    ("air_x", "table", 0.05), ("air_y", "table", 0.05), ("air_z", "table", 0.05),
)
# inputs: room air, the three Peltier supports (fixed temperatures), heat powers
SUPPORTS = ("support_x", "support_y", "support_z")
SUPPORT_LINKS = (("support_x", "table", 3.5), ("support_y", "table", 3.5), ("support_z", "table", 3.5),
                 ("support_x", "air_x", 0.3), ("support_y", "air_y", 0.3), ("support_z", "air_z", 0.3))
HEATED = ("motor1", "motor2", "motor3", "coil1", "coil2", "coil3")


def beam_air_shares(supports_on: bool, axis: str = "x") -> tuple[float, float]:
    """(supports' share, table's share) of the temperature of the air by an interferometer's
    beam (``air_<axis>``) at equilibrium: its conductance to each over its conductances to all
    (the room's the rest): Peltier-held supports warm it, the table a little. What a
    laboratory whose only air thermometers sit by the beams states for the room's estimate
    (room_climate's ``air_support_share`` and ``air_table_share``)."""
    node = f"air_{axis}"
    g_room = next(g for name, _, g in PART_NODES if name == node)
    g_table = sum(g for a, b, g in LINKS if {a, b} == {node, "table"})
    g_support = sum(g for sup, n, g in SUPPORT_LINKS if n == node) if supports_on else 0.0
    total = g_room + g_table + g_support
    return g_support / total, g_table / total


@dataclass(frozen=True)
class Sensor:
    """A temperature sensor on ``part`` (a part node or an air node). With ``glue_W_per_K``
    None its contact is ideal and it reads its part exactly; otherwise it is a node of capacity
    ``capacity_J_per_K`` joined to its part by ``glue_W_per_K`` and to the room air by
    ``leak_W_per_K``, so it lags its part and misses part of its gradient to the room (the
    effect ``sensor_contact`` sets these)."""
    name: str
    part: str
    glue_W_per_K: float | None = None
    leak_W_per_K: float = 0.0
    capacity_J_per_K: float = 2.0


def sensor_set(names_parts: dict[str, str]) -> tuple[Sensor, ...]:
    """Sensors with ideal contact from ``{sensor name: part}``."""
    return tuple(Sensor(name, part) for name, part in names_parts.items())


@dataclass
class Inputs:
    """Network inputs on the integration grid ``t_grid`` (s, campaign time; each array
    (n_grid,)): room air and supports in degC, heat powers in W by heated node."""
    t_grid: np.ndarray
    room_C: np.ndarray
    supports_C: dict[str, np.ndarray] = field(default_factory=dict)
    power_W: dict[str, np.ndarray] = field(default_factory=dict)
    pressure_Pa: np.ndarray | None = None     # barometric pressure (not a network input)
    vapour_Pa: np.ndarray | None = None       # water-vapour partial pressure (not an input)


class ThermalNetwork:
    """The linear network and its modal decomposition (built once per scenario)."""

    def __init__(self, sensors: tuple[Sensor, ...] = (), supports_on: bool = True):
        parts = [p for p, _, _ in PART_NODES]
        for s in sensors:
            if s.part not in parts:
                raise ValueError(f"sensor {s.name!r}: unknown part {s.part!r}; parts: {parts}")
        glued = [s for s in sensors if s.glue_W_per_K is not None]
        names = parts + [f"sensor:{s.name}" for s in glued]
        self.nodes = tuple(names)
        self.index = {n: i for i, n in enumerate(names)}
        self.sensors = sensors
        # a sensor with ideal contact is its part's temperature, not a node of its own
        self.aliases = {f"sensor:{s.name}": s.part for s in sensors if s.glue_W_per_K is None}
        n = len(names)
        C = np.array([c for _, c, _ in PART_NODES] + [s.capacity_J_per_K for s in glued])
        K = np.zeros((n, n))
        self.inputs = ("room",) + SUPPORTS + HEATED
        F = np.zeros((n, len(self.inputs)))

        def link(a, b, g):
            i, j = self.index[a], self.index[b]
            K[i, i] += g
            K[j, j] += g
            K[i, j] -= g
            K[j, i] -= g

        for name, _, g_room in PART_NODES:
            K[self.index[name], self.index[name]] += g_room
            F[self.index[name], 0] += g_room
        for a, b, g in LINKS:
            link(a, b, g)
        for sup, node, g in SUPPORT_LINKS:
            if supports_on:
                K[self.index[node], self.index[node]] += g
                F[self.index[node], self.inputs.index(sup)] += g
        for s in glued:
            link(f"sensor:{s.name}", s.part, s.glue_W_per_K)
            i = self.index[f"sensor:{s.name}"]
            K[i, i] += s.leak_W_per_K
            F[i, 0] += s.leak_W_per_K
        for h in HEATED:
            F[self.index[h], self.inputs.index(h)] = 1.0
        self.C, self.K, self.F = C, K, F
        lam, V = eigh(K, np.diag(C))          # K V = C V diag(lam), V^T C V = I
        self.lam, self.V = lam, V
        self.decay = np.exp(-lam * GRID_S)
        self.gain = (1.0 - self.decay) / lam  # exact ZOH for a constant input over a step
        self.VtF = V.T @ F

    def input_matrix(self, inputs: Inputs) -> np.ndarray:
        """Inputs as an (n_grid, n_inputs) array, in ``self.inputs`` order."""
        n = inputs.room_C.shape[0]
        U = np.zeros((n, len(self.inputs)))
        U[:, 0] = inputs.room_C
        for j, name in enumerate(self.inputs[1:], start=1):
            src = inputs.supports_C if name in SUPPORTS else inputs.power_W
            if name in src:
                U[:, j] = src[name]
            elif name in SUPPORTS:
                U[:, j] = inputs.room_C   # an unpowered support sits at room temperature
        return U

    def steady_state(self, u: np.ndarray) -> np.ndarray:
        return np.linalg.solve(self.K, self.F @ u)

    def start(self, u0: np.ndarray) -> ThermalState:
        """State in equilibrium with constant inputs ``u0`` (n_inputs,)."""
        z = self.V.T @ (self.C * self.steady_state(u0))   # modal coordinates: z = V^T C T
        return ThermalState(self, z)


class ThermalState:
    """Modal state of a network; ``advance`` integrates grid steps of inputs."""

    def __init__(self, net: ThermalNetwork, z: np.ndarray):
        self.net, self.z = net, z.copy()

    def advance(self, U: np.ndarray) -> np.ndarray:
        """Integrate len(U) grid steps with inputs U (n, n_inputs) held per step; return the
        node temperatures (n, n_nodes) at the END of each step and keep the final state."""
        net = self.net
        drive = (U @ net.VtF.T) * net.gain                   # (n, n_modes)
        Z = first_order_filter(drive, net.decay, self.z)     # one first-order filter per mode
        self.z = Z[-1].copy()
        return Z @ net.V.T
