"""Synthetic campaigns in the dataset format, for tests and benchmarks of the calibration.

These are *not* the twin's physics: a smooth, mildly nonlinear map from motor coordinates to
the end-effector position (linear + quadratic + cubic + a small non-polynomial part), with
thermal effects shaped like the first paper's (expansion scaling the geometry, offsets per
part temperature, a thermal lag seen through the temperature rate) and, for the force
campaign, a position-dependent compliance to the force simulator.  Every random draw comes
from the ``numpy.random.Generator`` passed in.
"""
from __future__ import annotations

import numpy as np
import pandas as pd
from scipy.ndimage import uniform_filter1d

from deltatwin.calibration.blackbox.features import DEFAULT_T_REF_K, ZERO_CELSIUS_K

__all__ = ["STRUCTURE_SENSORS", "AIR_SENSORS", "geometric_map", "thermal_campaign",
           "force_campaign", "sensor_metadata"]

STRUCTURE_SENSORS = ("base", "arm1", "arm2", "arm3", "rod1", "rod2", "rod3", "platform",
                     "frame")
AIR_SENSORS = ("air_x", "air_y")

_A = np.array([[0.080, -0.040, -0.040],
               [0.000, 0.0693, -0.0693],
               [-0.046, -0.046, -0.046]])          # m/rad, Delta-like mixing


def geometric_map(q: np.ndarray) -> np.ndarray:
    """Position (m) of motor coordinates q (n, 3) rad: smooth, mildly nonlinear."""
    q = np.asarray(q, float)
    lin = q @ _A.T
    s = q.sum(axis=1)
    quad = np.column_stack([0.03 * q[:, 0] ** 2 - 0.02 * q[:, 1] * q[:, 2],
                            0.025 * q[:, 1] ** 2 - 0.025 * q[:, 2] ** 2 + 0.01 * q[:, 0] * q[:, 1],
                            0.04 * (q ** 2).sum(axis=1) - 0.01 * s ** 2])
    cub = np.column_stack([0.2 * q[:, 0] ** 3, -0.15 * q[:, 1] ** 2 * q[:, 2],
                           0.1 * q[:, 0] * q[:, 1] * q[:, 2]])
    nonpoly = 1e-4 * np.column_stack([np.sin(3 * q[:, 0]), np.sin(3 * q[:, 1]),
                                      np.cos(3 * q[:, 2])])
    return lin + quad + cub + nonpoly


def sensor_metadata(sensors=STRUCTURE_SENSORS, air=AIR_SENSORS) -> dict:
    parts = {s: s.rstrip("0123456789") for s in sensors}
    parts.update({a: "air" for a in air})
    return parts


def _temperatures(rng, t_s, sensors, room0_C, amp_C, ramp_C_per_h):
    """Part temperatures: first-order lags of a drifting room, + 1 mK noise. (n, k) degC.

    Room: ``room0_C`` + a ramp (the air conditioning switched off, as in the first paper's
    campaign) limited to +3 K, + a daily and a 4 h oscillation."""
    dt = 10.0
    grid = np.arange(t_s.min() - 7200.0, t_s.max() + dt, dt)
    ph = rng.uniform(0, 2 * np.pi, 2)
    ramp = np.minimum(ramp_C_per_h * np.maximum(grid, 0.0) / 3600.0, 3.0)
    room = (room0_C + ramp + amp_C * np.sin(2 * np.pi * grid / 86400.0 + ph[0])
            + 0.4 * amp_C * np.sin(2 * np.pi * grid / 14400.0 + ph[1]))
    out = []
    for _ in sensors:
        tau = rng.uniform(600.0, 4000.0)
        gain = rng.uniform(0.8, 1.0)
        off = rng.uniform(-0.3, 0.5)
        a = np.exp(-dt / tau)
        y = np.empty_like(room)
        y[0] = room[0]
        for i in range(1, grid.size):
            y[i] = a * y[i - 1] + (1 - a) * room[i]
        out.append(np.interp(t_s, grid, gain * (y - room0_C) + room0_C + off))
    T = np.column_stack(out)
    return T + rng.normal(0.0, 1e-3, T.shape)


def thermal_campaign(rng: np.random.Generator, n_positions: int = 400, n_xy: int = 1200,
                     n_z: int = 1200, q_max_rad: float = 0.045, noise_m: float = 5e-9,
                     room0_C: float = 21.0, amp_C: float = 1.0, ramp_C_per_h: float = 0.4,
                     val_fraction: float = 0.3,
                     sensors=STRUCTURE_SENSORS, air=AIR_SENSORS):
    """A thermal campaign: session ``xy`` (x_nm, y_nm) then session ``z`` (z_nm).

    Returns ``(df, meta, truth)``; ``truth`` holds the coefficients used.
    """
    k = len(sensors)
    q_pos = rng.uniform(-q_max_rad, q_max_rad, (n_positions, 3))
    perm = rng.permutation(n_positions)
    n_val = int(round(val_fraction * n_positions))
    split_of = np.full(n_positions, "cal", dtype=object)
    split_of[perm[:n_val]] = "val"
    alpha = 8.6e-6
    w_scale = rng.uniform(0.0, 0.25, (3, k))            # share of each part in the expansion
    # m/K offsets: each part's expansion over a lever of 1-8 cm, mostly in one direction
    d_off = (alpha * rng.uniform(0.01, 0.08, (3, k))
             * np.where(rng.uniform(size=(3, k)) < 0.8, 1.0, -1.0))
    lag_s = rng.uniform(200.0, 900.0, (3, k))           # thermal lag seen through dT/dt
    truth = {"alpha_per_K": alpha, "w_scale": w_scale, "d_off_m_per_K": d_off, "lag_s": lag_s}
    frames = []
    t0 = 0.0
    for session, n_read, axes in (("xy", n_xy, (0, 1)), ("z", n_z, (2,))):
        t = t0 + np.cumsum(rng.uniform(8.0, 12.0, n_read))
        t0 = t[-1] + 3600.0
        pid = rng.integers(0, n_positions, n_read)
        q = q_pos[pid] + rng.normal(0.0, 1e-8, (n_read, 3))     # encoder noise
        T = _temperatures(rng, t, tuple(sensors) + tuple(air), room0_C, amp_C, ramp_C_per_h)
        Ts = T[:, :k]
        dT = (Ts + ZERO_CELSIUS_K) - DEFAULT_T_REF_K
        # true rates from a smoothed version (what the structure follows), no noise
        rate = np.gradient(Ts, t, axis=0)
        rate = uniform_filter1d(rate, 15, axis=0, mode="nearest")
        geo = geometric_map(q)
        # expansion scales the geometry; each part adds an offset; the structure lags
        # its sensor: offset of (T - lag * dT/dt)
        pos = (geo * (1.0 + alpha * dT @ w_scale.T) + dT @ d_off.T
               - np.einsum("nk,ak,ak->na", rate, lag_s, d_off))
        pos = pos + rng.normal(0.0, noise_m, pos.shape)
        pos = pos - pos[0]                                 # interferometers zeroed
        row = {"t_s": t, "pos_id": pid.astype(np.int64),
               "split": split_of[pid].astype(str), "session": session,
               "q1_rad": q[:, 0], "q2_rad": q[:, 1], "q3_rad": q[:, 2]}
        for a, name in enumerate("xyz"):
            row[f"{name}_nm"] = pos[:, a] / 1e-9 if a in axes else np.full(n_read, np.nan)
        for j, s in enumerate(tuple(sensors) + tuple(air)):
            row[f"T_{s}_C"] = T[:, j]
        row["F_N"] = np.zeros(n_read)
        frames.append(pd.DataFrame(row))
    df = pd.concat(frames, ignore_index=True)
    meta = {"sensors": sensor_metadata(sensors, air), "source": "synthetic",
            "scenario": "calibration.synthetic.thermal_campaign"}
    return df, meta, truth


def force_campaign(rng: np.random.Generator, n_cal_grid: int = 6, n_val_grid: int = 5,
                   forces_N=(0.0, 0.5, 1.0, 1.5, 2.0), q_max_rad: float = 0.04,
                   noise_m: float = 5e-9):
    """The second paper's campaign: motor grid n^3 (cal) and a non-coincident grid (val),
    each position at every force.  Returns ``(df, meta)``."""
    def grid(n, lim):
        g = np.linspace(-lim, lim, n)
        return np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)

    q_cal = grid(n_cal_grid, q_max_rad)
    q_val = grid(n_val_grid, 0.8 * q_max_rad)
    comp = np.array([145e-9, 350e-9, 84e-9])            # m/N at the centre
    rows = []
    t = 0.0
    pid0 = 0
    for split, qs in (("cal", q_cal), ("val", q_val)):
        for i, q in enumerate(qs):
            for F in forces_N:
                t += rng.uniform(8.0, 12.0)
                geo = geometric_map(q[None, :])[0]
                low = 1.0 - 8.0 * geo[2]                 # stronger low in the workspace
                defl = comp * F * low * (1.0 + 0.05 * F) * (1.0 + 3.0 * q[[1, 2, 0]])
                pos = geo + defl + rng.normal(0.0, noise_m, 3)
                rows.append((t, pid0 + i, split, "xyz", *q, *(pos / 1e-9), F, 22.0))
        pid0 += len(qs)
    df = pd.DataFrame(rows, columns=["t_s", "pos_id", "split", "session", "q1_rad", "q2_rad",
                                     "q3_rad", "x_nm", "y_nm", "z_nm", "F_N", "T_base_C"])
    df["pos_id"] = df["pos_id"].astype(np.int64)
    zero = df.loc[0, ["x_nm", "y_nm", "z_nm"]].to_numpy(dtype=float)
    df[["x_nm", "y_nm", "z_nm"]] -= zero
    meta = {"sensors": {"base": "base"}, "source": "synthetic",
            "scenario": "calibration.synthetic.force_campaign"}
    return df, meta
