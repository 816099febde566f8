"""Reference evaluator of an exported black-box model (the JSON of ``deltatwin calibrate -o``),
for whoever implements it in a real-time controller: plain Python (``json`` and ``math`` only),
one point at a time, written from the file format (docs/compensation.md), not from the fitting
code, so that a test comparing it with the fitted model checks the format as well.

* ``evaluate(model, inputs)``: every output, ``intercept + sum_k coef_k * prod v**p`` over each
  kept term's factors, inputs in SI (see the file's ``inputs``: rad, m, N; temperatures in K
  relative to ``temperature.reference_K``; their first and second time derivatives in K/s and
  K/s^2, which the controller estimates as ``derivatives`` says).
* ``inverse(model, target_m, inputs, stroke_rad)`` for a DGM (outputs x, y, z = readings of
  q1, q2, q3): Newton-Raphson with the terms' exact derivatives, from q = 0 and, if that does
  not end inside the stroke, from 27 starts inside it with the iterates held in it; returns
  ``(q, status)`` with status ``converged``, ``out_of_stroke`` or ``out_of_reach``.
* A direct IGM (outputs q1, q2, q3 of X, Y, Z, F) is evaluated directly.

Standalone: copy this file next to a model file and run it with any Python 3.
"""
from __future__ import annotations

import json
import math

FORMAT = "deltatwin-calibration-model"
# version 2 adds content_sha256 (checked by deltatwin's own reader; the layout is unchanged)
FORMAT_VERSIONS = (1, 2)
AXES = ("x", "y", "z")
MOTORS = ("q1", "q2", "q3")


def load(path) -> dict:
    """The model file's contents, with its format checked."""
    with open(path, encoding="utf-8") as f:
        model = json.load(f)
    if model.get("format") != FORMAT or model.get("format_version") not in FORMAT_VERSIONS:
        raise ValueError(f"{path}: not a {FORMAT} file of version {FORMAT_VERSIONS}")
    return model


def _term(factors, inputs) -> float:
    value = 1.0
    for name, power in factors:
        value *= inputs[name] ** power
    return value


def evaluate(model: dict, inputs: dict) -> dict:
    """{output: value (SI)} of every output at ``inputs`` ({variable: value, SI})."""
    out = {}
    for o in model["outputs"]:
        value = o["intercept"]
        for term, coef in zip(o["terms"], o["coef"]):
            value += coef * _term(term["factors"], inputs)
        out[o["output"]] = value
    return out


def _value_and_gradient(o: dict, inputs: dict, wrt) -> tuple[float, list]:
    """An output and its derivatives with respect to the variables ``wrt``."""
    value, grad = o["intercept"], [0.0] * len(wrt)
    for term, coef in zip(o["terms"], o["coef"]):
        factors = term["factors"]
        value += coef * _term(factors, inputs)
        for i, v in enumerate(wrt):
            d = 0.0
            for name, power in factors:
                if name == v:
                    rest = _term([f for f in factors if f[0] != v], inputs)
                    d = power * inputs[v] ** (power - 1) * rest
            grad[i] += coef * d
    return value, grad


def _solve3(J, r):
    """x with J x = r (3x3, Cramer's rule); None if singular."""
    (a, b, c), (d, e, f), (g, h, i) = J
    det = a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g)
    if det == 0.0 or not math.isfinite(det):
        return None
    x0 = (r[0] * (e * i - f * h) - b * (r[1] * i - f * r[2]) + c * (r[1] * h - e * r[2])) / det
    x1 = (a * (r[1] * i - f * r[2]) - r[0] * (d * i - f * g) + c * (d * r[2] - r[1] * g)) / det
    x2 = (a * (e * r[2] - r[1] * h) - b * (d * r[2] - r[1] * g) + r[0] * (d * h - e * g)) / det
    return [x0, x1, x2]


def _newton(outputs, target, inputs, q, lo, hi, tol_m, max_iter, bounded):
    """(q, max residual m) after Newton from q; the iterates held in [lo, hi] if bounded."""
    resid = math.inf
    for _ in range(max_iter + 1):
        point = dict(inputs, q1=q[0], q2=q[1], q3=q[2])
        rows = [_value_and_gradient(o, point, MOTORS) for o in outputs]
        r = [rows[k][0] - target[k] for k in range(3)]
        resid = max(abs(x) for x in r)
        if resid <= tol_m or not math.isfinite(resid):
            break
        dq = _solve3([g for _, g in rows], r)
        if dq is None:
            break
        q = [q[k] - dq[k] for k in range(3)]
        if bounded:
            q = [min(max(x, lo), hi) for x in q]
    return q, resid


def inverse(model: dict, target_m, inputs: dict, stroke_rad, tol_m: float = 1e-12,
            max_iter: int = 30) -> tuple[list, str]:
    """Motor coordinates (rad) at which a DGM reads ``target_m`` (x, y, z in m) with the
    temperature ``inputs``; ``stroke_rad`` = (low, high)."""
    by_name = {o["output"]: o for o in model["outputs"]}
    if model.get("kind") != "DGM" or any(a not in by_name for a in AXES):
        raise ValueError("inverse needs a DGM with outputs x, y, z")
    outputs = [by_name[a] for a in AXES]
    lo, hi = stroke_rad
    inside = lambda q: all(lo - 1e-12 <= x <= hi + 1e-12 for x in q)
    q, resid = _newton(outputs, target_m, inputs, [0.0, 0.0, 0.0], lo, hi, tol_m, max_iter,
                       False)
    if resid <= tol_m and inside(q):
        return q, "converged"
    outside_root = resid <= tol_m
    mid, half = 0.5 * (lo + hi), 0.5 * (hi - lo)
    grid = [mid + f * half for f in (-0.6, 0.0, 0.6)]
    found = None
    for s1 in grid:
        for s2 in grid:
            for s3 in grid:
                qs, rs = _newton(outputs, target_m, inputs, [s1, s2, s3], lo, hi, tol_m,
                                 max_iter, True)
                if rs <= tol_m and inside(qs):
                    d = math.hypot(*qs)
                    if found is None or d < found[0]:
                        found = (d, qs)
    if found is not None:
        return found[1], "converged"
    return q, "out_of_stroke" if outside_root else "out_of_reach"
