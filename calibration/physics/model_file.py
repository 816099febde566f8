"""The fitted physics model on disk (fitted.toml): writing and reading it back."""
from __future__ import annotations

import math
import re
import tomllib
from pathlib import Path

import numpy as np

from deltatwin.calibration.errors import FitError
from deltatwin.calibration.physics.fit import PhysicsFit, checked_directions
from deltatwin.calibration.physics.model import PhysicsModel
from deltatwin.calibration.physics.table import correlation_matrix
from deltatwin.files import CONTENT_SHA256, content_damage, content_sha256, toml_text
from deltatwin.twin.effects import EffectError, code_sha256, effect_class
from deltatwin.twin.lab_setup import known_constants, used_constants

FORMAT = "deltatwin-physics-model"
# 2: a fitted file carries content_sha256 (deltatwin.files), checked on reading; 1 is still read.
# A file without it (hand-written, or edited and the line removed) gets the checks below only.
FORMAT_VERSION = 2


def fitted_toml(fit: PhysicsFit, data: str) -> str:
    """The fitted model as TOML: effects and every parameter value (SI), the fit's figures."""
    code = code_sha256(fit.model_.classes.values())
    doc = {"format": FORMAT, "format_version": FORMAT_VERSION,
           "model": {"effects": fit.model_.specs, "data": data,
                     # the fitted rows' fingerprint: a diagnosis on the very same data keeps
                     # the values as fitted (fit.py ``fitted_on``)
                     **({"data_sha256": fit.data_sha256_} if fit.data_sha256_ else {}),
                     # ... by this code (an effect edited since is refined, not kept)
                     **({"code_sha256": code} if code else {}),
                     "noise_nm": fit.noise_nm,
                     # whether the values are corrected for the thermometers' noise: a
                     # diagnosis on the same data judges them as they were fitted
                     "thermometer_corrected": bool(getattr(fit, "thermometer_corrected_", False)),
                     "identifiable_ratio": fit.identifiable_ratio,
                     # the sensor -> part map the temperatures were taken from (the data's metadata)
                     "sensors": dict(fit.measurements_.sensors if fit.measurements_ is not None
                                     else fit.meta_.get("sensors") or {})},
           "fit": {"val_err90_nm": _or_nan(fit.val_["all"]["err_p90"]),
                   "cal_err90_nm": _or_nan(fit.cal_["all"]["err_p90"]),
                   "n_parameters": fit.model_.n_free,
                   "n_identified_directions": fit.identifiability_["n_identified_directions"],
                   "not_identifiable": fit.identifiability_["not_identifiable"]},
           "effects": fit.model_.values(),
           # the directions the fit determined (its parameters' combinations, in fit scales):
           # a diagnosis judges on them whether the values are converged on the data, as the
           # fit judged it (the directions identified at the fitted values are not the same)
           "identification": {"parameters": fit.model_.labels,
                              "directions": [] if fit.identified_directions_ is None
                              else fit.identified_directions_.T.tolist()}}
    if fit.identified_directions_ is None:          # read from a file that had none
        del doc["identification"]
    if fit.parameters_ is not None:
        doc["uncertainty"] = uncertainty_table(fit)
    known = used_constants(fit.model_.effects, fit.known_, known_constants(fit.meta_))
    if known:
        # the laboratory's constants the fit used (the data's setup, --set): those of effects
        # outside the model a diagnosis gives to the candidates it adds; those of the model's
        # effects are also in [effects], and `diagnose` compares them with the data's setup
        doc["known"] = known
    doc = {"format": FORMAT, "format_version": FORMAT_VERSION, CONTENT_SHA256: content_sha256(doc),
           **doc}
    return toml_text(doc, "deltatwin physics model; load with "
                          "`deltatwin compare DATA --model THIS`")


def uncertainty_table(fit: PhysicsFit) -> dict:
    """[uncertainty]: per parameter (the model's order, its units) the standard uncertainty,
    the prior the fit held undetermined directions at, the share of it the data determine;
    and the parameters' correlation matrix, exact: a prediction's uncertainty propagated
    through the model needs every digit (geometric errors held at their prior are correlated
    to within 1e-5 of one and cancel in the readings: rounded to four decimals, the band of a
    force model's validation error went from 4.0-6.4 nm to 6.3-32.5)."""
    return {"standard_uncertainty": [p["uncertainty"] for p in fit.parameters_],
            "prior": [p["start"] for p in fit.parameters_],
            "identified_fraction": [p["identified_fraction"] for p in fit.parameters_],
            "correlation": correlation_matrix(fit.covariance_).tolist()}


def load_fit(path, trust_effects=False) -> PhysicsFit:
    """A fitted model read back from its file as a PhysicsFit (``PhysicsFit.load``): its
    model, values, identified directions, parameter table and covariance (files written
    before they were saved have no table: ``parameters_`` and ``covariance_`` None) and
    figures as the file recorded them; no data (``measurements_`` None). It predicts and
    scores other data, writes the same file again, and starts a refit with ``fit``."""
    model, doc = load_fitted(path, trust_effects)
    fit = PhysicsFit(model.names, start={**doc.get("known", {}), **model.values()},
                     noise_nm=float(doc["model"].get("noise_nm", 5.0)),
                     identifiable_ratio=float(doc["model"].get("identifiable_ratio", 0.3)))
    figures = doc.get("fit", {})
    ident = {"n_parameters": model.n_free,
             "n_identified_directions": figures.get("n_identified_directions"),
             "not_identifiable": figures.get("not_identifiable", [])}
    fit.model_, fit.theta_, fit.measurements_ = model, model.theta(), None
    fit.meta_ = {"sensors": dict(doc["model"].get("sensors", {}))}
    fit.data_ = doc["model"].get("data", "")
    fit.data_sha256_ = doc["model"].get("data_sha256")
    fit.identified_directions_ = saved_directions(doc)
    fit.identifiability_ = ident
    fit.cal_ = {"all": {"err_p90": _or_none(figures.get("cal_err90_nm"))}}
    fit.val_ = {"all": {"err_p90": _or_none(figures.get("val_err90_nm"))}}
    fit.converged_, fit.n_evaluations_ = None, None
    fit.status_ = f"read from {path}"
    fit.parameters_, fit.covariance_ = saved_uncertainty(doc, model)
    return fit


def _or_nan(x):
    """A fitted figure for a file: NaN where the fit has none (TOML has no null)."""
    return math.nan if x is None else x


def _or_none(x):
    return None if x is None or not math.isfinite(x) else float(x)


def saved_uncertainty(doc: dict, model: PhysicsModel) -> tuple[list | None, np.ndarray | None]:
    """(parameters_, covariance_) as the fit that wrote ``doc`` had them (SI), from its
    [uncertainty] table; (None, None) for a file without one."""
    table = doc.get("uncertainty")
    if table is None:
        return None, None
    sigma = np.array(table["standard_uncertainty"], dtype=float)
    theta = model.theta()
    units = [f.unit for f in model.free for _ in range(f.sl.stop - f.sl.start)]
    parameters = [{"label": label, "value": float(theta[j]), "start": float(table["prior"][j]),
                   "unit": units[j], "uncertainty": float(sigma[j]),
                   "identified_fraction": float(table["identified_fraction"][j])}
                  for j, label in enumerate(model.labels)]
    correlation = np.array(table["correlation"], dtype=float).reshape(len(sigma), len(sigma))
    return parameters, correlation * np.outer(sigma, sigma)


def load_fitted(path, trust_effects=False) -> tuple[PhysicsModel, dict]:
    """(model, file contents) from a fitted-model TOML file. A user effect it names
    (``file.py:Class``) is code: it runs only with ``trust_effects`` True (or a list of the
    specs whose code may run), else FitError naming the file and the code (twin/effects:
    ``trust``)."""
    path = Path(path)
    if path.is_dir():
        raise FitError(f"{path}: is a folder, not a fitted-model TOML file")
    if not path.exists():
        raise FitError(f"{path}: no such model file")
    try:
        doc = tomllib.loads(path.read_text(encoding="utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise FitError(f"{path}: not a fitted-model TOML file ({exc})") from exc
    model = doc.get("model")
    if not isinstance(model, dict) or "effects" not in model:
        raise FitError(f"{path}: no [model] effects = [...]: not a fitted physics model "
                       "(write one with `deltatwin fit DATA --effects ... -o FILE`)")
    version = doc.get("format_version", 0)      # files written before the version key: 0
    if doc.get("format", FORMAT) != FORMAT or not isinstance(version, int) \
            or isinstance(version, bool) or not 0 <= version <= FORMAT_VERSION:
        raise FitError(f"{path}: format {doc.get('format')!r} format_version {version!r}: this "
                       f"deltatwin reads {FORMAT!r} up to version {FORMAT_VERSION}")
    damage = content_damage(doc)
    if damage:
        raise FitError(f"{path}: {damage}; refit or restore it")
    _check_layout(path, doc)
    # a fitted file cut short must not fall back on default values: every effect with free
    # parameters needs its table (a hand-written model without [fit] starts at the defaults)
    tables = doc.get("effects", {})
    try:
        # library names, or where the researcher's own effects came from (file.py:Class)
        classes = [effect_class(e, where=f"{path} [model] effects", trust=trust_effects)
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
    _check_identification(path, doc, model)
    _check_uncertainty(path, doc, model)
    return model, doc


def saved_directions(doc: dict) -> np.ndarray | None:
    """The fit's identified directions (p, k) from a file ``load_fitted`` read, None if the
    file has none (written before they were saved, or hand-written)."""
    ident = doc.get("identification")
    if ident is None:
        return None
    return np.array(ident["directions"], dtype=float).reshape(
        len(ident["directions"]), len(ident["parameters"])).T


def fitted_on(doc: dict, model: PhysicsModel) -> str | None:
    """The fingerprint of the data a file's values were fitted on (``PhysicsFit.fit``'s
    ``fitted_on``), when the code that evaluates ``model`` now is the code that fitted them:
    else None, and a diagnosis checks or refines the values instead of keeping them as fitted."""
    code = doc["model"].get("code_sha256")
    if code is None or code != code_sha256(model.classes.values()):
        return None
    return doc["model"].get("data_sha256")


def _check_identification(path: Path, doc: dict, model: PhysicsModel) -> None:
    """[identification]: the model's parameters in its order, and directions over them."""
    ident = doc.get("identification")
    if ident is None:
        return
    if not isinstance(ident, dict) or ident.get("parameters") != model.labels:
        raise FitError(f"{path}: [identification] parameters must list the model's "
                       f"{model.n_free} free parameters in its order")
    rows = ident.get("directions")
    if not isinstance(rows, list) or not all(
            isinstance(row, list) and len(row) == model.n_free
            and all(isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)
                    for x in row) for row in rows):
        raise FitError(f"{path}: [identification] directions must be a list of directions, each "
                       f"{model.n_free} finite numbers (one per parameter)")
    try:
        checked_directions(saved_directions(doc), model.n_free)
    except FitError:
        raise FitError(f"{path}: [identification] directions must be orthonormal (as the fit "
                       "wrote them)") from None


def _check_uncertainty(path: Path, doc: dict, model: PhysicsModel) -> None:
    """[uncertainty]: one finite number per parameter in each list (uncertainties >= 0,
    fractions in 0..1), a symmetric correlation matrix of them in -1..1."""
    table = doc.get("uncertainty")
    if table is None:
        return
    p = model.n_free
    _check_keys(path, "[uncertainty] ", table, UNCERTAINTY_KEYS)
    missing = [k for k in UNCERTAINTY_KEYS if k not in table]
    if missing:
        raise FitError(f"{path}: [uncertainty] has no {missing[0]!r}: the file is incomplete "
                       "(cut short?); refit or restore it")
    ranges = {"standard_uncertainty": (0.0, math.inf), "prior": (-math.inf, math.inf),
              "identified_fraction": (0.0, 1.0 + 1e-9)}
    for key, (low, high) in ranges.items():
        if not _numbers(table[key], p) or not all(low <= x <= high for x in table[key]):
            raise FitError(f"{path}: [uncertainty] {key} must be {p} finite numbers (one per "
                           f"parameter) in {low:g} .. {high:.3g}")
    rows = table["correlation"]
    if not (isinstance(rows, list) and len(rows) == p and all(_numbers(r, p) for r in rows)):
        raise FitError(f"{path}: [uncertainty] correlation must be {p} rows of {p} finite "
                       "numbers (one per parameter)")
    c = np.array(rows, dtype=float).reshape(p, p)
    if np.any(np.abs(c) > 1.0) or np.any(c != c.T):
        raise FitError(f"{path}: [uncertainty] correlation must be symmetric, each entry in -1 .. 1")


def _numbers(values, n: int) -> bool:
    return (isinstance(values, list) and len(values) == n
            and all(isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)
                    for x in values))


# what a fitted file may hold: a key outside these is a typo, refused rather than ignored
TOP_KEYS = ("format", "format_version", CONTENT_SHA256, "model", "fit", "effects",
            "identification", "known", "uncertainty")
UNCERTAINTY_KEYS = ("standard_uncertainty", "prior", "identified_fraction", "correlation")
MODEL_KEYS = ("effects", "data", "data_sha256", "code_sha256", "noise_nm", "identifiable_ratio",
              "sensors", "thermometer_corrected")


def _check_keys(path: Path, where: str, table: dict, allowed) -> None:
    import difflib

    for key in table:
        if key not in allowed:
            close = difflib.get_close_matches(key, allowed, n=1)
            raise FitError(f"{path}: {where}unknown key {key!r}"
                           + (f" (did you mean {close[0]!r}?)" if close else "")
                           + f"; allowed: {list(allowed)}")


def _check_layout(path: Path, doc: dict) -> None:
    """The types of what a fitted file holds (a hand-written or edited one has no checksum)."""
    def fail(key, what):
        raise FitError(f"{path}: {key} must be {what}")

    _check_keys(path, "", doc, TOP_KEYS)
    _check_keys(path, "[model] ", doc["model"], MODEL_KEYS)

    effects = doc["model"]["effects"]
    if not isinstance(effects, list) or not all(isinstance(e, str) for e in effects):
        fail("[model] effects", "a list of effect names")
    for key in ("effects", "fit", "known", "identification", "uncertainty"):
        if key in doc and not isinstance(doc[key], dict):
            fail(f"[{key}]", "a table")
    for name, table in doc.get("effects", {}).items():
        if not isinstance(table, dict):
            fail(f"[effects.{name}]", "a table of parameter values")
    sensors = doc["model"].get("sensors", {})
    if not isinstance(sensors, dict):
        fail("[model.sensors]", "a table sensor = \"part\"")
    for name, part in sensors.items():
        if not isinstance(part, str):
            fail(f"[model.sensors] {name}", f"a part name, got {part!r}")
    for key, value in doc.get("fit", {}).items():      # the fit's figures (a report)
        if key == "not_identifiable":
            if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
                fail(f"[fit] {key}", f"a list of parameter names, got {value!r}")
        elif key.startswith("n_"):
            if isinstance(value, bool) or not isinstance(value, int) or value < 0:
                fail(f"[fit] {key}", f"an integer >= 0, got {value!r}")
        elif isinstance(value, bool) or not isinstance(value, (int, float)):
            fail(f"[fit] {key}", f"a number (nan: not evaluated), got {value!r}")
    if not isinstance(doc["model"].get("thermometer_corrected", False), bool):
        fail("[model] thermometer_corrected", "true or false, got "
             f"{doc['model']['thermometer_corrected']!r}")
    if not isinstance(doc["model"].get("data", ""), str):
        fail("[model] data", f"the path of the fitted data, got {doc['model']['data']!r}")
    for key, what in (("data_sha256", "the fitted data's"), ("code_sha256", "the effects' code's")):
        sha = doc["model"].get(key)
        if sha is not None and not (isinstance(sha, str) and re.fullmatch(r"[0-9a-f]{64}", sha)):
            fail(f"[model] {key}", f"{what} SHA-256 in hex, got {str(sha)[:80]!r}")
    for key in ("noise_nm", "identifiable_ratio"):
        value = doc["model"].get(key, 1.0)
        if isinstance(value, bool) or not isinstance(value, (int, float)) \
                or not math.isfinite(value) or value < 0:
            fail(f"[model] {key}", f"a finite number >= 0, got {value!r}")
