"""ISO 230-2 positioning accuracy and repeatability of a numerically controlled axis.

Definitions as the standard states them (ISO 230-2:2014, "Test code for machine tools - Part 2:
Determination of accuracy and repeatability of positioning of numerically controlled axes",
clause 3; its public summaries: the ISO catalogue entry, and e.g. "ISO 230-2 Positioning
Accuracy", cnc-optimizations.pages.dev/resources/guides/iso-230-2-accuracy: accuracy A,
repeatability R, reversal B from repeated approaches in both directions). For target position
P_i (i = 1..m) approached n times in the positive (up) and n times in the negative (down)
direction, the positional deviation x_ij = measured position - target (P_ij - P_i), and

* mean unidirectional positional deviation: x̄_i↑ = (1/n) Σ_j x_ij↑, likewise x̄_i↓;
* mean bidirectional positional deviation: x̄_i = (x̄_i↑ + x̄_i↓) / 2;
* reversal value: B_i = x̄_i↑ - x̄_i↓; axis reversal B = max_i |B_i|; mean reversal
  B̄ = (1/m) Σ_i B_i;
* estimator of the unidirectional axis repeatability: s_i↑ = sqrt(Σ_j (x_ij↑ - x̄_i↑)² / (n-1)),
  likewise s_i↓;
* unidirectional repeatability R_i↑ = 4 s_i↑, R_i↓ = 4 s_i↓; bidirectional repeatability at a
  position R_i = max(2 s_i↑ + 2 s_i↓ + |B_i|, R_i↑, R_i↓); axis values R↑ = max_i R_i↑,
  R↓ = max_i R_i↓, R = max_i R_i (so no axis value falls below a per-target value);
* unidirectional systematic positioning error E↑ = max_i x̄_i↑ - min_i x̄_i↑, likewise E↓;
  bidirectional E = max(x̄_i↑, x̄_i↓) - min(x̄_i↑, x̄_i↓) over all i;
* mean bidirectional positioning error M = max_i x̄_i - min_i x̄_i;
* unidirectional accuracy A↑ = max_i(x̄_i↑ + 2 s_i↑) - min_i(x̄_i↑ - 2 s_i↑), likewise A↓;
  bidirectional accuracy A = max over i and both directions of (x̄ + 2 s) - min of (x̄ - 2 s).

Units: m throughout; the summary prints um and nm.
"""
from __future__ import annotations

import json
from dataclasses import dataclass

import numpy as np

AXIS_FIGURES = ("B", "B_mean", "R_up", "R_down", "R", "E_up", "E_down", "E", "M", "A_up",
                "A_down", "A")
TARGET_FIGURES = ("xbar_up", "xbar_down", "xbar", "B_i", "s_up", "s_down", "R_up_i",
                  "R_down_i", "R_i")


@dataclass(frozen=True)
class Iso230_2Result:
    """The figures of one axis (m). Per-target arrays (m,) end in ``_i`` or are the means and
    estimators (``xbar_up``, ``s_up``, ...); axis values are floats."""
    axis: str
    targets_m: np.ndarray
    n_up: int
    n_down: int
    xbar_up: np.ndarray
    xbar_down: np.ndarray
    xbar: np.ndarray
    B_i: np.ndarray
    s_up: np.ndarray
    s_down: np.ndarray
    R_up_i: np.ndarray
    R_down_i: np.ndarray
    R_i: np.ndarray
    B: float
    B_mean: float
    R_up: float
    R_down: float
    R: float
    E_up: float
    E_down: float
    E: float
    M: float
    A_up: float
    A_down: float
    A: float

    def figures_nm(self) -> dict:
        """The axis figures in nm, keyed ``<name>_nm``."""
        return {f"{k}_nm": getattr(self, k) * 1e9 for k in AXIS_FIGURES}

    def to_json(self) -> str:
        """Strict JSON: the axis figures and the per-target table, in nm (targets in mm)."""
        doc = {"standard": "ISO 230-2", "axis": self.axis, "n_up": self.n_up,
               "n_down": self.n_down, "axis_figures": self.figures_nm(),
               "targets_mm": (self.targets_m * 1e3).tolist(),
               "per_target_nm": {k: (getattr(self, k) * 1e9).tolist() for k in TARGET_FIGURES}}
        return json.dumps(doc, allow_nan=False)

    def summary(self) -> str:
        """The standard's table: per target, then the axis values (nm)."""
        head = (f"ISO 230-2 axis {self.axis}: {len(self.targets_m)} targets, {self.n_up} "
                f"approaches up, {self.n_down} down (nm)")
        cols = ("target_mm",) + TARGET_FIGURES
        lines = [head, " ".join(f"{c:>10}" for c in cols)]
        for i, p in enumerate(self.targets_m):
            vals = [p * 1e3] + [getattr(self, k)[i] * 1e9 for k in TARGET_FIGURES]
            lines.append(" ".join(f"{v:10.4f}" if j == 0 else f"{v:10.1f}"
                                  for j, v in enumerate(vals)))
        lines.append("axis: " + ", ".join(f"{k} {v:.1f}" for k, v in self.figures_nm().items()))
        return "\n".join(lines)


def _check(name: str, x, n_targets: int | None) -> np.ndarray:
    x = np.asarray(x, dtype=np.float64)
    if x.ndim != 2:
        raise ValueError(f"ISO 230-2 {name}: expected (targets, approaches), got shape {x.shape}")
    if n_targets is not None and x.shape[0] != n_targets:
        raise ValueError(f"ISO 230-2 {name}: {x.shape[0]} targets, the target list has "
                         f"{n_targets}")
    if x.shape[1] < 2:
        raise ValueError(f"ISO 230-2 {name}: at least 2 approaches per target are needed for "
                         f"a standard deviation, got {x.shape[1]}")
    bad = np.argwhere(~np.isfinite(x))
    if bad.size:
        i, j = bad[0]
        raise ValueError(f"ISO 230-2 {name}: deviation at target {i}, approach {j} is {x[i, j]}")
    return x


def evaluate(targets_m, dev_up_m, dev_down_m, axis: str = "x") -> Iso230_2Result:
    """The ISO 230-2 figures of an axis from its positional deviations (measured - target, m):
    ``dev_up_m`` and ``dev_down_m`` (targets, approaches) in the positive and negative
    direction, ``targets_m`` (targets,) the target positions."""
    targets = np.asarray(targets_m, dtype=np.float64).ravel()
    up = _check("deviations up", dev_up_m, targets.size)
    down = _check("deviations down", dev_down_m, targets.size)
    xu, xd = up.mean(axis=1), down.mean(axis=1)
    su, sd = up.std(axis=1, ddof=1), down.std(axis=1, ddof=1)
    xbar, B_i = 0.5 * (xu + xd), xu - xd
    Ru_i, Rd_i = 4.0 * su, 4.0 * sd
    R_i = np.maximum.reduce([2 * su + 2 * sd + np.abs(B_i), Ru_i, Rd_i])
    both_hi = np.maximum(xu + 2 * su, xd + 2 * sd)
    both_lo = np.minimum(xu - 2 * su, xd - 2 * sd)
    return Iso230_2Result(
        axis=axis, targets_m=targets, n_up=up.shape[1], n_down=down.shape[1],
        xbar_up=xu, xbar_down=xd, xbar=xbar, B_i=B_i, s_up=su, s_down=sd,
        R_up_i=Ru_i, R_down_i=Rd_i, R_i=R_i,
        B=float(np.max(np.abs(B_i))), B_mean=float(np.mean(B_i)),
        R_up=float(Ru_i.max()), R_down=float(Rd_i.max()), R=float(R_i.max()),
        E_up=float(np.ptp(xu)), E_down=float(np.ptp(xd)),
        E=float(max(xu.max(), xd.max()) - min(xu.min(), xd.min())),
        M=float(np.ptp(xbar)),
        A_up=float((xu + 2 * su).max() - (xu - 2 * su).min()),
        A_down=float((xd + 2 * sd).max() - (xd - 2 * sd).min()),
        A=float(both_hi.max() - both_lo.min()))


def from_readings(target_index, direction, deviation_m, targets_m, axis: str = "x"):
    """``evaluate`` from one row per approach: ``target_index`` (rows,) into ``targets_m``,
    ``direction`` (rows,) +1 (up) or -1 (down), ``deviation_m`` (rows,). Every target needs the
    same number of approaches in a direction."""
    idx = np.asarray(target_index, dtype=np.int64)
    d = np.asarray(direction)
    dev = np.asarray(deviation_m, dtype=np.float64)
    targets = np.asarray(targets_m, dtype=np.float64).ravel()
    tables = []
    for sign, name in ((1, "up"), (-1, "down")):
        rows = [dev[(idx == i) & (d == sign)] for i in range(targets.size)]
        counts = {r.size for r in rows}
        if len(counts) != 1:
            raise ValueError(f"ISO 230-2 axis {axis}: targets have {sorted(counts)} approaches "
                             f"{name}; every target needs the same number")
        tables.append(np.vstack(rows))
    return evaluate(targets, tables[0], tables[1], axis)
