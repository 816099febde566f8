"""Campaigns for the tests, all simulated by the twin: shipped scenarios at a reduced scale, or
the first paper's thermal campaign (scenarios/paper-thermal.toml) with slower points.

A reduced paper-thermal campaign at the paper's pace (~10 s a point) lasts a few hours: the
room hardly warms, so temperature terms hardly matter and the black-box ladder has nothing to
show.  ``slow_paper_thermal`` keeps the shipped scenario as it is (effects, climate, sensors,
split) and only makes every point wait longer, so that a few percent of the paper's points span
a day or more of its temperature history.
"""
from __future__ import annotations

import tomllib
from pathlib import Path

import tomli_w

from deltatwin.calibration.streams import DEFAULT_WINDOW_S
from deltatwin.twin.instruments.simulated import InstrumentSettings
from deltatwin.twin.scenario import SCENARIO_DIR, Scenario

PAPER_POINT_S = 10.0          # the first paper: ~10 s per point (move, wait 5 s, read)
# Five points in the causal derivative window (600 s): a quadratic through them gives the
# temperatures' first and second derivatives (at one point per 300 s or more the second
# derivative is undefined and the DGM's d2T terms are constant columns).
POINT_S = DEFAULT_WINDOW_S / 5


def slow_paper_thermal(directory: Path, scale: float, sensors=None, seed: int | None = None):
    """(df, meta) of paper-thermal at ``scale``, each point taking ``POINT_S`` instead of the
    paper's ~10 s.  ``sensors``: a subset of the scenario's sensor names (default: all 11).
    The derived TOML is written to ``directory``."""
    doc = tomllib.loads((SCENARIO_DIR / "paper-thermal.toml").read_text(encoding="utf-8"))
    doc["instruments"]["wait_s"] = InstrumentSettings.wait_s + POINT_S - PAPER_POINT_S
    if sensors is not None:
        missing = set(sensors) - set(doc["sensors"])
        if missing:
            raise ValueError(f"paper-thermal has no sensor(s) {sorted(missing)}")
        doc["sensors"] = {s: doc["sensors"][s] for s in sensors}
    name = "slow-paper-thermal" + ("" if sensors is None else "-" + "-".join(sensors))
    doc["scenario"]["name"] = name
    path = Path(directory) / f"{name}.toml"
    path.write_text(tomli_w.dumps(doc), encoding="utf-8")
    return Scenario.load(path, seed=seed, scale=scale).simulate(scale)
