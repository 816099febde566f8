"""The fitted physics model on disk (fitted.toml): writing and reading it back."""
from __future__ import annotations

import tomllib
from pathlib import Path

from deltatwin.calibration.errors import FitError
from deltatwin.calibration.physics.fit import PhysicsFit, _or_nan
from deltatwin.calibration.physics.model import PhysicsModel
from deltatwin.files import toml_text
from deltatwin.twin.effects import EffectError, effect_class

FORMAT = "deltatwin-physics-model"
FORMAT_VERSION = 1


def fitted_toml(fit: PhysicsFit, data: str) -> str:
    """The fitted model as TOML: effects and every parameter value (SI), the fit's figures."""
    doc = {"format": FORMAT, "format_version": FORMAT_VERSION,
           "model": {"effects": fit.model_.specs, "data": data, "noise_nm": fit.noise_nm,
                     "identifiable_ratio": fit.identifiable_ratio,
                     # the sensor -> part map the temperatures were taken from (the data's metadata)
                     "sensors": dict(fit.measurements_.sensors)},
           "fit": {"val_err90_nm": _or_nan(fit.val_["all"]["err_p90"]),
                   "cal_err90_nm": _or_nan(fit.cal_["all"]["err_p90"]),
                   "n_parameters": fit.model_.n_free,
                   "n_identified_directions": fit.identifiability_["n_identified_directions"],
                   "not_identifiable": fit.identifiability_["not_identifiable"]},
           "effects": fit.model_.values()}
    if fit.known_:
        # the laboratory's known constants of effects outside the model (--set): a diagnosis
        # gives them to the candidates it adds
        doc["known"] = fit.known_
    return toml_text(doc, "deltatwin physics model; load with "
                          "`deltatwin compare DATA --model THIS`")


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
    version = doc.get("format_version", 0)      # files written before the version key: 0
    if doc.get("format", FORMAT) != FORMAT or not isinstance(version, int) \
            or version > FORMAT_VERSION:
        raise FitError(f"{path}: format {doc.get('format')!r} version {version!r}: this deltatwin "
                       f"reads {FORMAT!r} up to version {FORMAT_VERSION}")
    # a fitted file cut short must not fall back on default values: every effect with free
    # parameters needs its table (a hand-written model without [fit] starts at the defaults)
    tables = doc.get("effects", {})
    try:
        # library names, or where the researcher's own effects came from (file.py:Class)
        classes = [effect_class(e, where=f"{path} [model] effects")
                   for e in doc["model"]["effects"]]
    except EffectError as exc:
        raise FitError(str(exc)) from exc
    missing = [c.name for c in classes
               if "fit" in doc and c.name not in tables and c.free_parameters()]
    if missing:
        raise FitError(f"{path}: no [effects.{missing[0]}] table"
                       + (f" (nor {', '.join(missing[1:])})" if missing[1:] else "")
                       + ": the file is incomplete (cut short?); refit or restore it")
    try:
        model = PhysicsModel(doc["model"]["effects"], None, doc.get("effects", {}),
                             where=f"{path} [effects]")
    except EffectError as exc:
        raise FitError(str(exc)) from exc
    return model, doc
