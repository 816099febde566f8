"""deltatwin: digital twin, synthetic data and calibration for the flexure-hinge Delta robot.

The nouns a researcher uses, in the order data flows (scenario -> twin -> instruments ->
dataset -> calibration -> report)::

    import deltatwin as dt

    sc = dt.Scenario.load("quiet/magnetic-force")              # a shipped scenario, or a path
    df, meta = sc.simulate(0.3)                                   # the twin's campaign at 30 %
    dt.write_dataset(df, meta, "data.parquet")                    # and back: dt.read_dataset
    fit = dt.PhysicsFit(["geometric_errors"]).fit(df, meta)       # a physics model
    fit.parameter_table()                                         # DataFrame with uncertainties
    d = dt.diagnose(fit)                                          # which library effect is missing
    dt.ranking_table(d)                                           # DataFrame, strongest first

Everything is imported on first use (importing ``deltatwin`` loads neither numpy nor MuJoCo),
and importing changes no global state and prints nothing. Units are SI inside; columns and
keys that carry other units say so in their names (``x_nm``, ``val_err90_nm``).
"""
from __future__ import annotations

import importlib

__version__ = "0.2.0"

# public name -> module that defines it (imported lazily, PEP 562)
_API = {
    # what the robot is
    "load_params": "deltatwin.models.params",
    "RobotParams": "deltatwin.models.params",
    "build_geometry": "deltatwin.models.geometry",
    "build_model": "deltatwin.models.mjcf",
    # how it behaves: scenarios, the effect library, the instruments, datasets
    "Scenario": "deltatwin.twin.scenario",
    "ScenarioError": "deltatwin.twin.scenario",
    "shipped_scenarios": "deltatwin.twin.scenario",
    "Effect": "deltatwin.twin.effects",
    "Parameter": "deltatwin.twin.effects",
    "LIBRARY": "deltatwin.twin.effects",
    "make_effect": "deltatwin.twin.effects",
    "InstrumentSet": "deltatwin.twin.instruments.interface",
    "InstrumentError": "deltatwin.twin.instruments.interface",
    "SimulatedLab": "deltatwin.twin.instruments.simulated",
    "read_dataset": "deltatwin.twin.dataset",
    "write_dataset": "deltatwin.twin.dataset",
    # how we talk to a real laboratory
    "open_lab": "deltatwin.hw.lab",
    # how we learn from data: the physics path
    "PhysicsFit": "deltatwin.calibration.physics.fit",
    "PhysicsModel": "deltatwin.calibration.physics.model",
    "load_fitted": "deltatwin.calibration.physics.model_file",
    # the papers' black-box path
    "stepwisefit": "deltatwin.calibration.blackbox.stepwise",
    "DGM": "deltatwin.calibration.blackbox.dgm",
    "IGM": "deltatwin.calibration.blackbox.igm",
    "DirectIGM": "deltatwin.calibration.blackbox.direct_igm",
    "load_model": "deltatwin.calibration.blackbox.model_file",
    # comparing a model with measurements and finding what is missing
    "compare": "deltatwin.calibration.diagnosis.compare",
    "diagnose": "deltatwin.calibration.diagnosis.diagnose",
    "ranking_table": "deltatwin.calibration.diagnosis.diagnose",
    "effect_ladder": "deltatwin.calibration.diagnosis.diagnose",
    "DecisionRule": "deltatwin.calibration.stats",
    # the report
    "write_recording": "deltatwin.view",
}

__all__ = sorted(_API) + ["__version__"]


def __getattr__(name: str):
    module = _API.get(name)
    if module is None:
        raise AttributeError(f"module 'deltatwin' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value          # later look-ups skip this function
    return value


def __dir__() -> list[str]:
    return __all__
