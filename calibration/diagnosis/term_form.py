"""The form of a missing term: a sparse regression of a model's residual on a library of
candidate functions, in the spirit of PySINDy (the function library kept apart from the
optimizer), for a static model's residual.

``candidate_library`` builds the functions of the laboratory variables (attribution.py), each a
``Candidate`` (one or two columns and how to print it with its coefficients):
polynomials of degree 1 to 3 of each coordinate, of time and of the force (powers of the
force), and the force's powers times each Cartesian coordinate (a load's effect follows the
compliance, which varies over the workspace); a sine and cosine of each coordinate and of time
at the period the residual's Lomb-Scargle periodogram peaks at (irregular sampling); a step
and a ramp in time at the scanned moment that fits best; the direction of each motor's last
move (a direction-dependent offset); each temperature and temperature rate; coil currents and
rotations.

``sparse_form`` is the optimizer: forward selection per axis (the candidate that lowers the
calibration residual most joins), kept only while it is significant (partial F test on the
calibration rows with the scanned period or moment counted as a parameter, Bonferroni over the
candidates) and explains at least ``MIN_SHARE`` of the validation residual power; at most
``MAX_TERMS`` terms. Each term is printed with its coefficient in nm and its share of the
validation residual (what it explains beyond the others); the whole form with its joint share.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import pandas as pd
from scipy import special

from deltatwin.calibration.diagnosis.attribution import (
    MIN_SHARE,
    Residual,
    Variable,
    laboratory_variables,
    scans,
)
from deltatwin.calibration.stats import ALPHA
from deltatwin.twin.instruments.optics import AXES

MAX_TERMS = 4

# how a variable is printed: (display unit, SI per display unit, centred at its mean)
DISPLAY = {"q": ("mrad", 1e-3, True), "xyz": ("mm", 1e-3, True), "t_s": ("h", 3600.0, False),
           "T": ("K", 1.0, True), "dT": ("mK/min", 1e-3 / 60.0, False), "F_N": ("N", 1.0, False),
           "coil": ("A", 1.0, False), "ac": ("arcsec", 1.0, True), "dir": ("", 1.0, False)}


def _display(name: str) -> tuple[str, float, bool]:
    if name.startswith("q") and name.endswith("_rad"):
        return DISPLAY["q"]
    if name in ("x_m", "y_m", "z_m"):
        return DISPLAY["xyz"]
    if name.startswith("dT_"):
        return DISPLAY["dT"]
    if name.startswith("T_"):
        return DISPLAY["T"]
    if name.startswith("coil"):
        return DISPLAY["coil"]
    if name.endswith("_arcsec"):
        return DISPLAY["ac"]
    if name.startswith("dir_"):
        return DISPLAY["dir"]
    return DISPLAY.get(name, ("", 1.0, False))


def _short(name: str) -> str:
    """q1_rad -> q1, x_m -> x, T_base_C -> T_base, t_s -> t."""
    for suffix in ("_rad", "_m", "_C", "_K_per_s", "_s", "_arcsec", "_A", "_N"):
        if name.endswith(suffix) and name != suffix:
            return name[: -len(suffix)] if name != "t_s" else "t"
    return name


def _about(v: str, centre: float, unit: str) -> str:
    """'(q1 - 0.3 mrad)', '(q1 + 0.3 mrad)'."""
    return f"({v} {'-' if centre >= 0 else '+'} {abs(centre):.4g} {unit})"


@dataclass
class Candidate:
    """One function of the library: ``columns`` (N,k) SI, fitted on each reading axis with
    coefficients of its own, or (N,3,k) already the readings' response on every axis with k
    coefficients shared by the axes (a load's or a motor's, model_form.py); the ``kind`` (poly,
    sine, step, ramp, sign, product, load, motor_sign, motor_sine) with what defines it
    (variable, power, period, moment, centre)."""
    kind: str
    variable: str
    columns: np.ndarray
    scanned: int = 0
    power: int = 1
    period: float | None = None
    moment_s: float | None = None
    centre: float = 0.0
    extra: dict = field(default_factory=dict)

    def describe(self, coef_m: np.ndarray) -> dict:
        """The term with coefficients ``coef_m`` (m per column): a printable formula (nm) and
        its numbers."""
        unit, si, _ = _display(self.variable)
        v = _short(self.variable)
        c_nm = np.asarray(coef_m) * 1e9
        out = {"kind": self.kind, "variable": self.variable}
        if self.kind == "sine":
            a, b = c_nm
            amp, phase = math.hypot(a, b), math.atan2(b, a)
            out.update(amplitude_nm=amp, period=self.period, phase_rad=phase,
                       formula=f"{amp:.1f} nm * sin(2 pi {v} / {self.period / si:.4g} {unit} "
                               f"{'+' if phase >= 0 else '-'} {abs(phase):.2f})")
        elif self.kind == "step":
            out.update(coefficient_nm=float(c_nm[0]), moment_s=self.moment_s,
                       formula=f"{c_nm[0]:.1f} nm * H(t - {self.moment_s:.0f} s)")
        elif self.kind == "ramp":
            out.update(coefficient_nm_per_h=float(c_nm[0] * 3600.0), moment_s=self.moment_s,
                       formula=f"{c_nm[0] * 3600.0:.3g} nm/h * max(t - {self.moment_s:.0f} s, 0)")
        elif self.kind == "product":
            by, centre = self.extra["by"], self.extra["centre"]
            per = c_nm[0] * 1e-3          # nm per N^k per mm
            out.update(coefficient_nm=float(per), coefficient_si=float(coef_m[0]),
                       power=self.power, by=by, centre=centre,
                       formula=f"{per:.3g} nm * (F/N)" + (f"^{self.power}" if self.power > 1
                                                          else "")
                               + f" * {_about(_short(by), centre * 1e3, 'mm')}/mm")
        elif self.kind == "load":
            # the column is the reading's response in m per N of the force (model_form.py)
            force, direction = float(coef_m[0]), self.extra["direction"]
            out.update(force_N=force, power=self.power, direction=direction,
                       formula=f"{force:.3g} N * (I/A)" + (f"^{self.power}" if self.power > 1
                                                           else "")
                               + f" along {direction} (through the compliance)")
        elif self.kind == "motor_sign":
            # the column is the readings' response in m per rad of the motor's offset
            # (model_form.py)
            motor = self.extra["motor"]
            out.update(backlash_rad=float(coef_m[0]), motor=motor,
                       formula=f"{coef_m[0] * 1e6:.3g} urad * sign(last move of q{motor}) "
                               f"where motor {motor} sits (through the kinematics)")
        elif self.kind == "motor_sine":
            motor, (a, b) = self.extra["motor"], coef_m
            amp, phase = math.hypot(a, b), math.atan2(b, a)
            out.update(sin_rad=float(a), cos_rad=float(b), period=self.period, motor=motor,
                       formula=f"{amp * 1e6:.3g} urad * sin(2 pi q{motor} / "
                               f"{self.period * 1e3:.4g} mrad {'+' if phase >= 0 else '-'} "
                               f"{abs(phase):.2f}) where motor {motor} sits (through the "
                               "kinematics)")
        elif self.kind == "sign":
            out.update(coefficient_nm=float(c_nm[0]),
                       formula=f"{c_nm[0]:.1f} nm * sign(last move of {v[4:]})")
        else:
            # a power of the variable in its display unit, about its centre when it has one
            per = c_nm[0] * si ** self.power
            base = (_about(v, self.centre / si, unit) if self.centre
                    else f"({v}/{unit})" if unit else v)
            out.update(coefficient_nm=float(per), coefficient_si=float(coef_m[0]),
                       power=self.power, centre=self.centre,
                       display_unit=unit,
                       formula=f"{per:.3g} nm * {base}" + (f"^{self.power}"
                                                            if self.power > 1 else ""))
        return out


def candidate_library(variables: list[Variable], target: Residual) -> list[Candidate]:
    """The candidate functions of the variables (module docstring); periods and step moments
    are scanned on ``target``'s calibration rows."""
    out = []
    for var in variables:
        v = var.values
        if var.kind == "session" or not np.any(np.isfinite(v)):
            continue
        if var.kind == "sign":
            out.append(Candidate("sign", var.name, v[:, None].astype(np.float64)))
            continue
        _, _, centred = _display(var.name)
        centre = float(np.nanmean(v[target.cal])) if centred else 0.0
        x = v - centre
        top = 3 if var.kind in ("coordinate", "time") or var.name == "F_N" else 1
        for k in range(1, top + 1):
            out.append(Candidate("poly", var.name, (x ** k)[:, None], power=k, centre=centre))
        info = scans(var, target)
        if "period" in info:
            period = info["period"]
            out.append(Candidate("sine", var.name, np.column_stack(
                [np.sin(2 * np.pi * v / period), np.cos(2 * np.pi * v / period)]),
                scanned=1, period=period))
        if "step_s" in info:
            tau = info["step_s"]
            out.append(Candidate("step", var.name, (v > tau).astype(np.float64)[:, None],
                                 scanned=1, moment_s=tau))
        if var.kind == "time":
            taus = np.quantile(v[target.cal], np.linspace(0.05, 0.95, 19))
            ramps = np.maximum(v[:, None] - taus, 0.0)
            best = int(np.argmin(target.rss_each(ramps)))
            out.append(Candidate("ramp", var.name, ramps[:, best:best + 1].copy(), scanned=1,
                                 moment_s=float(taus[best])))
    # a load's effect depends on where the platform is (the compliance varies over the
    # workspace): powers of the force times the Cartesian position
    by_name = {v.name: v for v in variables}
    if "F_N" in by_name:
        F = by_name["F_N"].values
        for c in ("x_m", "y_m", "z_m"):
            if c in by_name:
                centre = float(np.nanmean(by_name[c].values[target.cal]))
                for k in (1, 2, 3):
                    out.append(Candidate("product", "F_N", (F ** k * (by_name[c].values - centre))
                                         [:, None], power=k, extra={"by": c, "centre": centre}))
    return out


def sparse_form(candidates: list[Candidate], target: Residual, alpha: float = ALPHA,
                min_share: float = MIN_SHARE, max_terms: int = MAX_TERMS) -> list[dict]:
    """Per axis, the few candidates that explain the residual (module docstring):
    [{axis, terms: [{formula, explained_fraction, ...}], explained_fraction, val_rms_nm,
    val_rms_after_nm}], axes whose residual no candidate explains left out."""
    out = []
    for k, rows, _ in target.axes:
        axis = target.only(k)
        p0 = axis.val_power()
        if p0 <= 0:
            continue
        n_val = int(axis.val[rows].sum())
        chosen: list[int] = []
        design = lambda idx: (np.column_stack([candidates[i].columns for i in idx]) if idx
                              else np.zeros((target.res.shape[0], 0)))
        _, current = axis.fit(design(chosen))
        limit = alpha / max(len(candidates), 1)
        while len(chosen) < max_terms:
            best = None
            for i in range(len(candidates)):
                if i in chosen:
                    continue
                _, after = axis.fit(design(chosen + [i]))
                if best is None or after["rss_cal"] < best[1]["rss_cal"]:
                    best = (i, after)
            if best is None:
                break
            i, after = best
            kk = after["rank"] - current["rank"] + candidates[i].scanned
            df2 = after["n_cal"] - after["rank"] - 1
            if kk <= 0 or df2 <= 0 or after["rss_cal"] >= current["rss_cal"]:
                break
            F = ((current["rss_cal"] - after["rss_cal"]) / kk) / (after["rss_cal"] / df2)
            if (special.fdtrc(kk, df2, F) >= limit
                    or current["val_power"] - after["val_power"] < min_share * p0):
                break
            chosen.append(i)
            current = after
        if not chosen:
            continue
        fitted, full = axis.fit(design(chosen))
        coef = fitted[0][2]
        terms, start = [], 0
        for i in chosen:
            n_col = candidates[i].columns.shape[1]
            term = candidates[i].describe(coef[start:start + n_col])
            start += n_col
            _, without = axis.fit(design([j for j in chosen if j != i]))
            term["explained_fraction"] = max(without["val_power"] - full["val_power"], 0.0) / p0
            terms.append(term)
        terms.sort(key=lambda t: -t["explained_fraction"])
        out.append({"axis": AXES[k], "terms": terms,
                    "explained_fraction": 1.0 - full["val_power"] / p0,
                    "val_rms_nm": float(np.sqrt(p0 / max(n_val, 1)) * 1e9),
                    "val_rms_after_nm": float(np.sqrt(full["val_power"] / max(n_val, 1)) * 1e9)})
    return out


def missing_term_form(df: pd.DataFrame, target: Residual,
                      variables: list[str] | None = None) -> list[dict]:
    """The proposed form of the missing term on each axis of ``target`` (the residual of the
    rows of ``df``, ``Residual.of``). ``variables``: restrict the library to these variables;
    default all the laboratory variables."""
    lab = laboratory_variables(df)
    if variables is not None:
        lab = [v for v in lab if v.name in set(variables)]
    return sparse_form(candidate_library(lab, target), target)


def form_message(form: list[dict], limit: int = 2) -> str:
    """'x: 28.7 nm * sin(2 pi q1 / 1.9 mrad + 0.40) explains 91 %; ...'."""
    parts = []
    for f in form:
        terms = " + ".join(f"{t['formula']}" for t in f["terms"][:limit])
        parts.append(f"{f['axis']}: {terms} explains {100 * f['explained_fraction']:.0f} %")
    return "; ".join(parts)
