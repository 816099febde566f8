"""The fitted physics model on disk (fitted.toml): writing and reading it back."""
from __future__ import annotations

import tomllib
from pathlib import Path

from deltatwin.calibration.errors import FitError
from deltatwin.calibration.physics.fit import PhysicsFit, _or_nan
from deltatwin.calibration.physics.model import PhysicsModel
from deltatwin.files import toml_value
from deltatwin.twin.effects import EffectError


def fitted_toml(fit: PhysicsFit, data: str) -> str:
    """The fitted model as TOML: effects and every parameter value (SI), the fit's figures."""
    lines = ["# deltatwin physics model (calibration/physics.py); load with "
             "`deltatwin compare DATA --model THIS`",
             "[model]", f"effects = {toml_value(fit.effects)}", f"data = {toml_value(data)}",
             f"noise_nm = {fit.noise_nm!r}", f"identifiable_ratio = {fit.identifiable_ratio!r}",
             # the sensor -> part map the temperatures were taken from (the data's metadata)
             "sensors = { " + ", ".join(f"{toml_value(s)} = {toml_value(p)}" for s, p in
                                        fit.measurements_.sensors.items()) + " }",
             "", "[fit]", f"val_err90_nm = {toml_value(_or_nan(fit.val_['all']['err_p90']))}",
             f"cal_err90_nm = {toml_value(_or_nan(fit.cal_['all']['err_p90']))}",
             f"n_parameters = {fit.model_.n_free}",
             f"n_identified_directions = {fit.identifiability_['n_identified_directions']}",
             f"not_identifiable = {toml_value(fit.identifiability_['not_identifiable'])}"]
    for name, vals in fit.model_.values().items():
        lines += ["", f"[effects.{name}]"] + [f"{k} = {toml_value(v)}" for k, v in vals.items()]
    return "\n".join(lines) + "\n"


def load_fitted(path) -> tuple[PhysicsModel, dict]:
    """(model, file contents) from a fitted-model TOML file."""
    path = Path(path)
    try:
        doc = tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise FitError(f"{path}: not a fitted-model TOML file ({exc})") from exc
    if "model" not in doc or "effects" not in doc.get("model", {}):
        raise FitError(f"{path}: no [model] effects = [...]: not a fitted physics model "
                       "(write one with `deltatwin fit DATA --effects ... -o FILE`)")
    try:
        model = PhysicsModel(doc["model"]["effects"], None, doc.get("effects", {}),
                             where=f"{path} [effects]")
    except EffectError as exc:
        raise FitError(str(exc)) from exc
    return model, doc
