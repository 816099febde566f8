"""The laboratory's setup as a dataset carries it: what a fit takes as given instead of estimating.

A dataset's metadata (docs/data-format.md, "The laboratory's setup") holds the setup in three
keys, each the one place of what it says:

- ``setup``: ``known`` ({effect: {parameter: value}}, SI: the laboratory's constants, e.g. the
  arm of the frame the robot hangs from), ``baseline`` (the effects a model starts from, where
  the data's source declares them) and ``source`` (where the setup was stated);
- ``instruments``: the instruments' specifications (``INSTRUMENT_SPECS``: the thermometers' and
  the interferometers' noise and resolution), which a fit's noise model reads;
- ``sensors``: the part each thermometer is glued on (``T_<sensor>_C`` columns).

``deltatwin simulate`` writes it from a scenario's [hidden] table (``scenario_setup``); a
laboratory states it in a small TOML file (``load_setup``; docs/lab-setup.toml) given to
``deltatwin campaign --setup`` or ``deltatwin setup DATA FILE -o OUT`` (``with_setup``). A
physics fit takes the constants the data carry (``known_constants``) where its start does not
give them; ``deltatwin fit --set`` overrides them.
"""
from __future__ import annotations

import difflib
import math
import re
import tomllib
from pathlib import Path

import numpy as np

SETUP_KEY = "setup"
FORMAT_VERSION = 1      # of a setup file (optional in it)
SETUP_FILE_KEYS = ("format_version", "baseline", "known", "instruments", "sensors")
# the instruments' specifications a setup states (metadata ``instruments``): unit, and the
# largest plausible value (a larger one is another unit: nm or mK given as m or K)
INSTRUMENT_SPECS = {"T_noise_C": ("K", 1.0), "T_resolution_C": ("K", 1.0),
                    "interferometer_noise_m": ("m", 1e-6),
                    "interferometer_resolution_m": ("m", 1e-6),
                    # the air a reading sees against its session's zero: the std of its
                    # pressure and water vapour and their correlation time (0: white, a
                    # barometer's or hygrometer's record noise; calibration/physics/air.py)
                    "air_pressure_u_Pa": ("Pa", 1e4), "air_pressure_time_s": ("s", 1e8),
                    "air_vapour_u_Pa": ("Pa", 1e4), "air_vapour_time_s": ("s", 1e8)}
# the air's fields a reading sees (as twin.world Points name them) and their two specifications
AIR_SPECS = {"pressure_Pa": ("air_pressure_u_Pa", "air_pressure_time_s"),
             "vapour_Pa": ("air_vapour_u_Pa", "air_vapour_time_s")}
SENSOR_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")   # it becomes a column name, T_<name>_C


class SetupError(ValueError):
    """A setup (file or metadata) that names an unknown effect, parameter or key, or gives a
    value of the wrong type, shape or unit."""


def _shown(value) -> str:
    """``value`` as an error message quotes it: its repr, cut at 80 characters."""
    text = repr(value)
    return text if len(text) <= 80 else text[:76] + " ..."


def _close(word: str, choices) -> str:
    close = difflib.get_close_matches(str(word), list(choices), n=1)
    return f" (did you mean {close[0]!r}?)" if close else ""


def check_known(known, where: str) -> dict:
    """``known`` ({effect: {parameter: value}}) with every effect a library effect and every
    value valid for its parameter (type, shape, finite), values as plain lists; else
    SetupError naming ``where`` and the key."""
    from deltatwin.twin.effects import LIBRARY, EffectError, make_effect

    if not isinstance(known, dict):
        raise SetupError(f"{where}: expected a table of effect = {{parameter = value}}")
    out = {}
    for effect, values in known.items():
        if effect not in LIBRARY:
            raise SetupError(f"{where}.{effect}: unknown effect{_close(effect, LIBRARY)}; "
                             f"library effects: {sorted(LIBRARY)}")
        if not isinstance(values, dict):
            raise SetupError(f"{where}.{effect} = {_shown(values)}: expected a table of "
                             "parameter = value (SI units)")
        try:
            made = make_effect(effect, values, where=where, check_minimum=False)
        except EffectError as exc:
            raise SetupError(str(exc)) from None
        out[effect] = {p: np.asarray(made.values[p]).tolist() for p in values}
    return out


def check_baseline(baseline, where: str) -> list[str]:
    """``baseline``: a list of library effect names, each once, else SetupError."""
    from deltatwin.twin.effects import LIBRARY

    if not isinstance(baseline, list) or not all(isinstance(e, str) for e in baseline):
        raise SetupError(f"{where} = {_shown(baseline)}: expected a list of effect names")
    for k, effect in enumerate(baseline):
        if effect in baseline[:k]:
            raise SetupError(f"{where}: effect {_shown(effect)} is named twice")
        if effect not in LIBRARY:
            raise SetupError(f"{where}: unknown effect {_shown(effect)}{_close(effect, LIBRARY)}; "
                             f"library effects: {sorted(LIBRARY)}")
    return list(baseline)


def check_instruments(specs, where: str) -> dict:
    """``specs``: INSTRUMENT_SPECS keys, each a number from 0 below its largest plausible
    value, else SetupError."""
    if not isinstance(specs, dict):
        raise SetupError(f"{where}: expected a table of specification = value")
    for key, value in specs.items():
        if key not in INSTRUMENT_SPECS:
            raise SetupError(f"{where}: unknown key {_shown(key)}{_close(key, INSTRUMENT_SPECS)}; "
                             f"allowed: {list(INSTRUMENT_SPECS)}")
        unit, largest = INSTRUMENT_SPECS[key]
        if isinstance(value, bool) or not isinstance(value, (int, float)) \
                or not math.isfinite(value) or not 0 <= value < largest:
            raise SetupError(f"{where}.{key} = {_shown(value)}: expected a number in {unit}, 0 to "
                             f"{largest:g} (SI units)")
    return {k: float(v) for k, v in specs.items()}


def check_sensors(sensors, where: str) -> dict:
    """``sensors`` ({sensor: part}): names that make a column ``T_<sensor>_C``, parts of the
    thermal network, else SetupError."""
    from deltatwin.twin.thermal import PART_NODES

    parts = [p for p, _, _ in PART_NODES]
    if not isinstance(sensors, dict):
        raise SetupError(f"{where}: expected a table of sensor = \"part\"")
    for name, part in sensors.items():
        if not SENSOR_NAME.match(name):
            raise SetupError(f"{where}.{name}: a sensor name is letters, digits and _ (it "
                             "names the column T_<name>_C)")
        if not isinstance(part, str) or part not in parts:
            raise SetupError(f"{where}.{name} = {_shown(part)}: unknown part{_close(part, parts)}; "
                             f"parts: {parts}")
    return dict(sensors)


def load_setup(path) -> dict:
    """A laboratory's setup file (TOML, docs/lab-setup.toml) as {"baseline", "known",
    "instruments", "sensors"} (the tables it gives), every key checked: an unknown effect,
    parameter or key, a value of the wrong type, shape or unit is a SetupError naming the file
    and the key."""
    path = Path(path)
    if not path.is_file():
        raise SetupError(f"{path}: no such setup file" if not path.exists() else
                         f"{path}: is a folder, not a setup file")
    try:
        doc = tomllib.loads(path.read_text(encoding="utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise SetupError(f"{path}: not a TOML setup file ({exc})") from None
    for key in doc:
        if key not in SETUP_FILE_KEYS:
            raise SetupError(f"{path}: unknown key {_shown(key)}{_close(key, SETUP_FILE_KEYS)}; "
                             f"allowed: {list(SETUP_FILE_KEYS)}")
    if not doc:
        raise SetupError(f"{path}: states nothing: give at least one of "
                         f"{list(SETUP_FILE_KEYS[1:])} (docs/lab-setup.toml)")
    version = doc.pop("format_version", FORMAT_VERSION)
    if version != FORMAT_VERSION or isinstance(version, bool):
        raise SetupError(f"{path}: format_version = {_shown(version)}: this deltatwin reads setup "
                         f"files of version {FORMAT_VERSION}")
    checks = {"baseline": check_baseline, "known": check_known,
              "instruments": check_instruments, "sensors": check_sensors}
    return {key: checks[key](value, f"{path}: {key}") for key, value in doc.items()}


def scenario_setup(hidden: dict | None, source: str, effects=()) -> dict:
    """The metadata ``setup`` a scenario declares: its [hidden] known constants and baseline
    (none for a scenario without [hidden]), and what its laboratory sets itself or measures
    once, and so knows (unless [hidden] states otherwise): the constants of its effects that
    a model uses and never fits, where they are not the library's (``effects``: the
    scenario's; ``fixed_constants``: a frame's arm is measured with a rule), the set point of
    Peltier-held interferometer supports, and the shares of the beams' air temperature the
    supports and the table set (room_climate's ``air_support_share``, ``air_table_share``:
    what the room's estimate from the air thermometers by the beams needs; twin/thermal.py
    ``beam_air_shares``); ``source`` names the scenario."""
    from deltatwin.twin.thermal import beam_air_shares

    hidden = hidden or {}
    known = merged(fixed_constants(effects), dict(hidden.get("known", {})))
    held = next((e for e in effects if e.name == "peltier_supports"), None)
    if held is not None:
        known["peltier_supports"] = {"setpoint_C": float(held.setpoint_C),
                                     **known.get("peltier_supports", {})}
    shares = dict(zip(("air_support_share", "air_table_share"), beam_air_shares(held is not None)))
    # to four decimals, as a laboratory would state them (10 uK of the room's estimate)
    known["room_climate"] = {**{k: round(v, 4) for k, v in shares.items() if v},
                             **known.get("room_climate", {})}
    setup = {"source": source, "known": known}
    if "baseline" in hidden:
        setup["baseline"] = list(hidden["baseline"])
    return setup


def fixed_constants(effects) -> dict:
    """{effect: {parameter: value}}: the parameters of ``effects`` (instances) of library
    effects with a model form that a fit never adjusts (no ``fit_scale``) and whose value is
    not the library's default: what a laboratory states about its own setup (e.g. the frame's
    arm). A researcher's own effect carries its constants in its own code, not in the setup
    (which names library effects only)."""
    from deltatwin.twin.effects import LIBRARY

    out = {}
    for e in effects:
        if LIBRARY.get(e.name) is not type(e) or not type(e).model_stages():
            continue
        for p in type(e).parameters:
            value = e.values[p.name]
            if p.fit_scale is None and not np.array_equal(np.asarray(value, dtype=np.float64),
                                                          np.asarray(p.default, dtype=np.float64)):
                out.setdefault(e.name, {})[p.name] = np.asarray(value, dtype=np.float64).tolist()
    return out


def with_setup(meta: dict, setup: dict, source: str, temperature_columns) -> dict:
    """A copy of the metadata ``meta`` with a setup file's ``setup`` (``load_setup``) put in:
    its known constants and baseline replace the data's, its instrument specifications replace
    those it names, its sensor map replaces the data's. A sensor of the map without its column
    in ``temperature_columns`` is a SetupError naming ``source``: nothing is written."""
    meta = dict(meta)
    old = meta.get(SETUP_KEY) or {}
    meta[SETUP_KEY] = {"source": source, "known": setup.get("known", old.get("known", {}))}
    baseline = setup.get("baseline", old.get("baseline"))
    if baseline is not None:
        meta[SETUP_KEY]["baseline"] = baseline
    if "instruments" in setup:
        meta["instruments"] = {**(meta.get("instruments") or {}), **setup["instruments"]}
    if "sensors" in setup:
        missing = [s for s in setup["sensors"] if f"T_{s}_C" not in set(temperature_columns)]
        if missing:
            raise SetupError(f"{source}: sensors: {missing} have no column "
                             f"{', '.join(f'T_{s}_C' for s in missing)} in the data; its "
                             f"temperature columns: {list(temperature_columns)}")
        meta["sensors"] = dict(setup["sensors"])
    return meta


def setup_problem(setup) -> str | None:
    """What is wrong with a metadata ``setup`` (None: fine): the dataset reader's check."""
    if not isinstance(setup, dict):
        return "not a JSON object"
    try:
        check_known(setup.get("known", {}), "known")
        if "baseline" in setup:
            check_baseline(setup["baseline"], "baseline")
    except SetupError as exc:
        return str(exc)
    if not isinstance(setup.get("source", ""), str):
        return f"source = {_shown(setup['source'])} is not text"
    return None


def known_constants(meta: dict | None, where: str = "data") -> dict:
    """The laboratory's known constants the data carry ({effect: {parameter: value}}, SI;
    empty without a setup), checked: SetupError naming ``where`` otherwise."""
    setup = (meta or {}).get(SETUP_KEY)
    if setup is None:
        return {}
    problem = setup_problem(setup)
    if problem:
        raise SetupError(f"{where}: metadata setup: {problem}")
    return check_known(setup.get("known", {}), f"{where}: metadata setup known")


def baseline_of(meta: dict | None) -> list[str] | None:
    """The baseline effects the data's setup declares, None if it declares none."""
    baseline = ((meta or {}).get(SETUP_KEY) or {}).get("baseline")
    return None if baseline is None else list(baseline)


def merged(lower: dict | None, upper: dict | None) -> dict:
    """{effect: {parameter: value}} of ``lower`` with ``upper`` put over it parameter by
    parameter: a given frame arm replaces the setup's arm, not the loop drift's other values."""
    lower, upper = lower or {}, upper or {}
    return {e: {**lower.get(e, {}), **upper.get(e, {})} for e in {**lower, **upper}}


def with_known(meta: dict | None, known: dict | None) -> dict:
    """A copy of the metadata ``meta`` whose setup's known constants have ``known`` ({effect:
    {parameter: value}}: a fit's, e.g. given by ``--set``) put over them (``merged``)."""
    meta = dict(meta or {})
    setup = dict(meta.get(SETUP_KEY) or {})
    setup["known"] = merged(setup.get("known", {}), known)
    meta[SETUP_KEY] = setup
    return meta


def _same(a, b) -> bool:
    return np.array_equal(np.asarray(a, dtype=float), np.asarray(b, dtype=float))


def overridden(given: dict, setup_known: dict) -> list[tuple[str, object, object]]:
    """(``effect.parameter``, given value, setup value) of each constant of ``given`` (e.g.
    ``--set``) that replaces another value of the data's setup ``setup_known``."""
    return [(f"{e}.{p}", v, setup_known[e][p])
            for e, values in given.items() for p, v in values.items()
            if p in setup_known.get(e, {}) and not _same(v, setup_known[e][p])]


def used_constants(effects, known: dict, setup_known: dict | None = None) -> dict:
    """{effect: {parameter: value}}: the laboratory's constants a model used: ``known`` (those
    of effects outside the model) and the parameters of its ``effects`` (Effect instances) it
    does not fit whose values the setup gives or that are not the library's defaults."""
    setup_known = setup_known or {}
    out = {e: {p: np.asarray(v).tolist() for p, v in values.items()}
           for e, values in known.items()}
    for effect in effects:
        for p in type(effect).parameters:
            value = effect.values[p.name]
            if p.fit_scale is None and (p.name in setup_known.get(effect.name, {})
                                        or not _same(value, p.default)):
                out.setdefault(effect.name, {})[p.name] = np.asarray(value).tolist()
    return out


def model_overrides(effects, known: dict, meta: dict | None, where: str = "data") -> list[str]:
    """One line per constant a fitted model used (its ``effects``, Effect instances, and the
    ``known`` constants of effects outside it) that is not the value of the data's setup."""
    setup = known_constants(meta, where)
    return [f"the model's {key} = {used} overrides the data's setup value {value} (refit to "
            "use the setup's)"
            for key, used, value in overridden(used_constants(effects, known, setup), setup)]


def beyond_setup(constants: dict, setup_known: dict) -> dict:
    """The ``constants`` ({effect: {parameter: value}}) a command must state with ``--set``
    on data whose setup gives ``setup_known``: those the setup does not give as they are."""
    out = {}
    for e, values in constants.items():
        for p, v in values.items():
            if p not in setup_known.get(e, {}) or not _same(v, setup_known[e][p]):
                out.setdefault(e, {})[p] = v
    return out


def set_options(constants: dict) -> str:
    """``constants`` as the command line gives them: `` --set EFFECT.PARAM=V1,V2`` each."""
    return "".join(f" --set {e}.{p}={','.join(str(x) for x in np.ravel(v))}"
                   for e, values in constants.items() for p, v in values.items())


def describe(meta: dict) -> str:
    """One line: the setup the data carry (known constants, baseline, sensors, instruments)."""
    setup = meta.get(SETUP_KEY) or {}
    known = "; ".join(f"{e}.{p} = {v}" for e, values in setup.get("known", {}).items()
                      for p, v in values.items()) or "no known constants"
    baseline = setup.get("baseline")
    spec = meta.get("instruments") or {}
    words = [known, f"baseline {','.join(baseline)}" if baseline else "no baseline",
             f"{len(meta.get('sensors') or {})} thermometers"]
    if "T_noise_C" in spec:
        words.append(f"thermometer noise {spec['T_noise_C'] * 1e3:g} mK")
    if "interferometer_noise_m" in spec:
        words.append(f"interferometer noise {spec['interferometer_noise_m'] * 1e9:g} nm")
    if spec.get("air_pressure_u_Pa"):
        time_s = spec.get("air_pressure_time_s", 0.0)
        words.append(f"air pressure {spec['air_pressure_u_Pa']:g} Pa "
                     + (f"over {time_s / 3600:g} h" if time_s else "white"))
    return "; ".join(words) + (f" (from {setup['source']})" if setup.get("source") else "")
