"""ISO 9283 pose accuracy AP and pose repeatability RP (position part), and their drift.

Definitions as the standard states them (ISO 9283:1998, "Manipulating industrial robots -
Performance criteria and related test methods", 7.2 "Pose accuracy and pose repeatability",
7.6 "Drift of pose characteristics"; the public summary "ISO Robot Performance Standard",
robotics-introduction.blogspot.com/2010/08: the attained positions about their barycentre,
the barycentre against the command). For a pose commanded at (x_c, y_c, z_c) and attained
at (x_j, y_j, z_j) in cycles j = 1..n (n = 30 by default):

* barycentre x̄ = (1/n) Σ_j x_j (likewise ȳ, z̄);
* position accuracy APx = x̄ - x_c, APy = ȳ - y_c, APz = z̄ - z_c,
  AP = sqrt(APx² + APy² + APz²);
* distances to the barycentre l_j = sqrt((x_j - x̄)² + (y_j - ȳ)² + (z_j - z̄)²),
  l̄ = (1/n) Σ_j l_j, S_l = sqrt(Σ_j (l_j - l̄)² / (n - 1)), position repeatability
  RP = l̄ + 3 S_l;
* drift (7.6): dAP = |AP_first - AP_last| and dRP = |RP_first - RP_last|, AP and RP of the
  first and of the last ``block`` cycles of a long run (the standard compares the pose
  characteristics at the start and at the end of its run).

Only positions: the flexure Delta's platform translates (its parasitic tilts are arcseconds,
read by the autocollimators, not a pose to command). Units: m; the summary prints nm.
"""
from __future__ import annotations

import json
from dataclasses import dataclass

import numpy as np

POSE_FIGURES = ("APx", "APy", "APz", "AP", "l_bar", "S_l", "RP")


@dataclass(frozen=True)
class PoseFigures:
    """One pose's figures (m): command, barycentre, AP and RP and their parts."""
    name: str
    n: int
    command_m: np.ndarray
    barycentre_m: np.ndarray
    APx: float
    APy: float
    APz: float
    AP: float
    l_bar: float
    S_l: float
    RP: float
    dAP: float | None = None
    dRP: float | None = None

    def figures_nm(self) -> dict:
        out = {f"{k}_nm": getattr(self, k) * 1e9 for k in POSE_FIGURES}
        out.update(dAP_nm=None if self.dAP is None else self.dAP * 1e9,
                   dRP_nm=None if self.dRP is None else self.dRP * 1e9)
        return out


@dataclass(frozen=True)
class Iso9283Result:
    """Per-pose figures; ``AP`` and ``RP`` the largest over the poses (m)."""
    poses: tuple[PoseFigures, ...]

    @property
    def AP(self) -> float:
        return max(p.AP for p in self.poses)

    @property
    def RP(self) -> float:
        return max(p.RP for p in self.poses)

    def to_json(self) -> str:
        doc = {"standard": "ISO 9283", "AP_max_nm": self.AP * 1e9, "RP_max_nm": self.RP * 1e9,
               "poses": {p.name: {"n": p.n, "command_mm": (p.command_m * 1e3).tolist(),
                                  **p.figures_nm()} for p in self.poses}}
        return json.dumps(doc, allow_nan=False)

    def summary(self) -> str:
        cols = ("pose", "n") + POSE_FIGURES
        lines = [f"ISO 9283 pose accuracy and repeatability (nm); AP max {self.AP * 1e9:.1f}, "
                 f"RP max {self.RP * 1e9:.1f}", " ".join(f"{c:>8}" for c in cols)]
        for p in self.poses:
            lines.append(f"{p.name:>8} {p.n:>8} " + " ".join(
                f"{getattr(p, k) * 1e9:8.1f}" for k in POSE_FIGURES))
        return "\n".join(lines)


def pose_figures(command_m, attained_m, name: str = "P1") -> tuple[float, ...]:
    """(APx, APy, APz, AP, l̄, S_l, RP) (m) of one pose: ``command_m`` (3,), ``attained_m``
    (cycles, 3)."""
    c = np.asarray(command_m, dtype=np.float64).reshape(3)
    x = np.asarray(attained_m, dtype=np.float64)
    if x.ndim != 2 or x.shape[1] != 3 or x.shape[0] < 2:
        raise ValueError(f"ISO 9283 pose {name}: expected (cycles >= 2, 3) attained positions, "
                         f"got shape {x.shape}")
    if not np.all(np.isfinite(x)):
        j = int(np.argwhere(~np.all(np.isfinite(x), axis=1))[0, 0])
        raise ValueError(f"ISO 9283 pose {name}: attained position of cycle {j} is not finite: "
                         f"{x[j].tolist()}")
    bary = x.mean(axis=0)
    ap = bary - c
    l = np.linalg.norm(x - bary, axis=1)
    l_bar, S_l = float(l.mean()), float(l.std(ddof=1))
    return (*map(float, ap), float(np.linalg.norm(ap)), l_bar, S_l, l_bar + 3.0 * S_l)


def evaluate(commands_m, attained_m, names=None, drift_block: int | None = None):
    """ISO 9283 figures of poses ``commands_m`` (poses, 3) attained at ``attained_m`` (poses,
    cycles, 3), m. ``drift_block`` (cycles): also the drift dAP, dRP between the first and the
    last that many cycles (needs 2 * block <= cycles)."""
    cmd = np.asarray(commands_m, dtype=np.float64)
    att = np.asarray(attained_m, dtype=np.float64)
    if cmd.ndim != 2 or cmd.shape[1] != 3 or att.ndim != 3 or att.shape[0] != cmd.shape[0]:
        raise ValueError(f"ISO 9283: commands (poses, 3) and attained (poses, cycles, 3) "
                         f"expected, got {cmd.shape} and {att.shape}")
    names = [f"P{k + 1}" for k in range(cmd.shape[0])] if names is None else list(names)
    n = att.shape[1]
    if drift_block is not None and not 2 <= drift_block <= n // 2:
        raise ValueError(f"ISO 9283 drift block = {drift_block} cycles: must be between 2 and "
                         f"half the {n} cycles")
    poses = []
    for k, name in enumerate(names):
        f = pose_figures(cmd[k], att[k], name)
        drift = {}
        if drift_block is not None:
            first = pose_figures(cmd[k], att[k, :drift_block], name)
            last = pose_figures(cmd[k], att[k, -drift_block:], name)
            drift = {"dAP": abs(first[3] - last[3]), "dRP": abs(first[6] - last[6])}
        poses.append(PoseFigures(name, n, cmd[k], att[k].mean(axis=0),
                                 **dict(zip(POSE_FIGURES, f)), **drift))
    return Iso9283Result(tuple(poses))

