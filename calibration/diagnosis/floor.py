"""The honest floor: what the complete, true model reaches when refitted on the same data.

The instrument floor (``truth.noise_floor_nm``) counts the interferometers' noise only. A model
reads its conditions through instruments too: thermometers (mK noise and resolution, smoothed
causally) through long levers (the frame's lift on Z, a frame arm on X), barometric pressure and
humidity when the lab records them (else the air index wanders unrecorded), the servos'
settling. No effect added to a model removes those errors, so a model is *at the floor* when it
reaches what the twin's own effects reach when fitted to the same data, the **achievable
floor**. ``achievable_floor`` fits that true model (the data's model effects at the twin's
values, their free parameters refitted as any model's are) and gives its validation error and a
budget: the interferometers' share (the instrument floor) and what the other instruments add
above it (the quadrature difference: thermometers through each lever, unrecorded air and
settling together; the figure is measured, the split between them is not).
"""
from __future__ import annotations

import numpy as np

from deltatwin.calibration.physics.fit import PhysicsFit
from deltatwin.calibration.physics.model import model_effects
from deltatwin.twin.instruments.optics import AXES

AT_FLOOR = 1.1   # a model within 1.1x the achievable floor is at the floor


def true_model(meta: dict) -> tuple[list[str], dict]:
    """The data's model effects (those of the twin's truth with a model form) and the twin's
    values of all their parameters: ({effect: {parameter: value}})."""
    truth = (meta or {}).get("truth") or {}
    forms = set(model_effects())
    effects = [e for e in truth.get("effects", []) if e["name"] in forms]
    return ([e["name"] for e in effects],
            {e["name"]: {p: v["value"] for p, v in e["parameters"].items()} for e in effects})


def achievable_floor(df, meta: dict, noise_nm: float = 5.0) -> dict:
    """Fit the true model (``true_model``) to the data's calibration rows: its validation error
    90 % per axis and pooled (nm), the fit's status, and the budget (nm per source)."""
    effects, values = true_model(meta)
    # what the data cannot determine stays at the twin's values (the truth is the prior)
    fit = PhysicsFit(effects, start=values, prior=values, noise_nm=noise_nm).fit(df, meta)
    floor = {a: fit.val_[a]["err_p90"] for a in (*AXES, "all") if a in fit.val_}
    instrument = ((meta or {}).get("truth") or {}).get("noise_floor_nm") or {}
    budget = {}
    for a in AXES:
        if a in floor and a in instrument:
            rest = float(np.sqrt(max(floor[a] ** 2 - instrument[a] ** 2, 0.0)))
            budget[a] = {"interferometer_noise_nm": instrument[a],
                         "other_instruments_nm": rest}
    return {"achievable_floor_nm": floor, "effects": effects, "converged": fit.converged_,
            "status": fit.status_, "budget_nm": budget}


def record_achievable_floor(df, meta: dict) -> dict:
    """Put the achievable floor, its budget and its fit's effects and status into the dataset's
    truth (``meta["truth"]``); returns the floor (nm by axis and pooled)."""
    floor = achievable_floor(df, meta)
    meta["truth"]["achievable_floor_nm"] = floor["achievable_floor_nm"]
    meta["truth"]["floor_budget_nm"] = floor["budget_nm"]
    meta["truth"]["achievable_floor_fit"] = {"effects": floor["effects"],
                                             "status": floor["status"]}
    return floor["achievable_floor_nm"]


def floor_of(meta: dict | None) -> tuple[dict | None, str]:
    """The floor a model is judged against, and its kind: the achievable floor when the data
    carry it, else the instrument (interferometer noise) floor, else none."""
    truth = (meta or {}).get("truth") or {}
    if truth.get("achievable_floor_nm"):
        return truth["achievable_floor_nm"], "achievable"
    if truth.get("noise_floor_nm"):
        return truth["noise_floor_nm"], "instrument"
    return None, "none"
