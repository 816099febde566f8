"""Scenarios: one TOML file says everything a synthetic campaign needs (scenarios/*.toml).

Tables: [scenario] name, description, seed; [robot] file (robot parameter TOML, default the
nominal robot); [effects] on = [names] and one sub-table of parameters per effect;
[sensors] sensor name = part; [instruments] InstrumentSettings fields + cosine_correction;
[campaign] kind = "thermal" | "force" | "iso9283" | "iso230-2" | "iso230-3" and its plan
(the last three: the standards' tests, twin/standard_tests.py); [reduced] scale for tests; [hidden] effects,
baseline and known (the laboratory's constants given to every fit) for a hidden-effect case.
Every key is checked: an unknown or misspelled key, a value of the wrong type or unit, an
impossible value, all raise ScenarioError naming the file, the key and the reason.
"""
from __future__ import annotations

import dataclasses
import difflib
import hashlib
import tomllib
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import numpy as np
import pandas as pd

from deltatwin.models.params import ParameterError, load_params
from deltatwin.twin.campaign import Plan, force_plan, run_campaign, simulate_campaign, thermal_plan
from deltatwin.twin.effects import LIBRARY, EffectError, effect_class, make_effect
from deltatwin.twin.instruments.optics import nominal_dead_path, saturation_vapour_pressure
from deltatwin.twin.instruments.simulated import InstrumentSettings, SimulatedLab
from deltatwin.twin.lab_setup import SENSOR_NAME, scenario_setup
from deltatwin.twin.noise import quantised_u
from deltatwin.twin.thermal import PART_NODES
from deltatwin.twin.world import Twin, random_streams

# Shipped scenarios are package data (deltatwin.scenarios), found the same way in a source tree,
# an editable install and a wheel.
SCENARIO_DIR = Path(str(resources.files("deltatwin.scenarios")))


def shipped_scenarios() -> list[str]:
    """Names of the shipped scenarios, as ``Scenario.load`` accepts them (``paper-thermal``,
    ``hidden/gravity-sag`` in the papers' conditions, ``quiet/gravity-sag`` in a quiet
    laboratory, ...)."""
    return sorted(p.relative_to(SCENARIO_DIR).with_suffix("").as_posix()
                  for p in SCENARIO_DIR.rglob("*.toml"))
# of the scenario files deltatwin writes (twin/cases.py, calibration/design/sweep.py); a
# hand-written scenario may omit the top-level format_version
FORMAT_VERSION = 1
TABLES = {"scenario": {"name", "description", "seed"}, "robot": {"file"},
          "effects": None, "sensors": None, "instruments": None, "campaign": None,
          "reduced": {"scale"}, "hidden": {"effects", "baseline", "known"}}
CAMPAIGN_KEYS = {"thermal": {"kind", "warmup_s", "n_positions", "cal_fraction", "sessions"},
                 "force": {"kind", "warmup_s", "cal_levels", "val_levels", "forces_N",
                           "force_per_A", "readings", "order"},
                 "iso9283": {"kind", "warmup_s", "cycles", "order", "corner_fraction",
                             "stroke_fraction"},
                 "iso230-2": {"kind", "warmup_s", "axes", "targets", "approaches", "overrun",
                              "stroke_fraction"},
                 "iso230-3": {"kind", "warmup_s", "duration_h", "position_m", "stroke_fraction"}}
STANDARD_TESTS = ("iso9283", "iso230-2", "iso230-3")   # twin/standard_tests.py
FORCE_ORDERS = ("papers", "interleaved")   # the cal grid then the val grid, or merged
SESSION_KEYS = {"name", "axes", "cal", "val"}


# The laboratory's error sources beyond the robot, which Scenario.with_perfect can make perfect:
# what each is.
ERROR_SOURCES = {"interferometers": "the interferometers' noise and resolution (and the "
                                    "autocollimators' of the cosine correction)",
                 "thermometers": "the thermometers' noise and resolution",
                 "air": "the air's pressure and humidity: their unrecorded wander, or the "
                        "barometer's and hygrometer's noise where the lab records them",
                 "servo_settling": "where the motors' controllers settled"}


def air_wander(settings: InstrumentSettings, climate: dict | None, barometer: bool,
               hygrometer: bool, room_C: float = 20.0) -> dict:
    """What a reading sees of the air against its session's zero, as the laboratory states it:
    {"pressure_Pa": (std Pa, correlation time s), "vapour_Pa": (std Pa, time s)}. Where the
    laboratory records it (``barometer``, ``hygrometer``) the record's noise and resolution,
    white (time 0; the hygrometer's %RH as vapour at ``room_C``); else the room's wander
    (room_climate's values ``climate``, its defaults for what it does not give)."""
    from deltatwin.twin.effects.room_climate import RoomClimate

    c = {p.name: p.default for p in RoomClimate.parameters} | (climate or {})
    pressure = ((quantised_u(settings.barometer_noise_Pa, settings.barometer_resolution_Pa), 0.0)
                if barometer else (float(c["pressure_std_Pa"]), float(c["pressure_time_s"])))
    per_pct = float(saturation_vapour_pressure(room_C)) / 100.0
    vapour = ((quantised_u(settings.hygrometer_noise_pct, settings.hygrometer_resolution_pct)
               * per_pct, 0.0) if hygrometer
              else (float(c["vapour_std_Pa"]), float(c["vapour_time_s"])))
    return {"pressure_Pa": pressure, "vapour_Pa": vapour}


class ScenarioError(ValueError):
    """A scenario file that cannot be used; the message names file, key and reason."""


SCALE_HELP = "fraction of the campaign's points, 0 < SCALE <= 1 (1: the full campaign)"


def check_scale(scale, where: str = "scale") -> float | None:
    """A campaign's scale: None (the full campaign) or a fraction of its points in (0, 1];
    anything else (0, negative, above 1, NaN, infinite, not a number) raises ScenarioError
    naming ``where`` (a command line passes its option, ``--scale``)."""
    if scale is None:
        return None
    if isinstance(scale, bool) or not isinstance(scale, (int, float, np.integer, np.floating)) \
            or not 0 < scale <= 1:
        raise ScenarioError(f"{where} = {scale!r}: expected a {SCALE_HELP}")
    return float(scale)


def _check_keys(where, table: dict, allowed) -> None:
    for key in table:
        if key not in allowed:
            close = difflib.get_close_matches(key, allowed, n=1)
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            raise ScenarioError(f"{where}: unknown key {key!r}{hint}; allowed: {sorted(allowed)}")


def _number(where, value, minimum=None, integer=False, maximum=None, above=False):
    """``value`` checked as a number in [minimum, maximum] (``above``: > minimum)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ScenarioError(f"{where} = {value!r}: expected a number in the unit its name states"
                            " (SI: m, s, rad, A, N; degC where the name ends in _C)")
    if not np.isfinite(value):
        raise ScenarioError(f"{where} = {value!r}: must be a finite number")
    if integer and int(value) != value:
        raise ScenarioError(f"{where} = {value!r}: expected an integer")
    low_ok = minimum is None or (value > minimum if above else value >= minimum)
    if not low_ok or (maximum is not None and value > maximum):
        low = "" if minimum is None else f"{'>' if above else '>='} {minimum:g}"
        high = "" if maximum is None else f"<= {maximum:g}"
        raise ScenarioError(f"{where} = {value!r}: must be {' and '.join(x for x in (low, high) if x)}")
    return int(value) if integer else float(value)


MAX_DAYS = 60.0                 # the longest campaign the twin simulates (its environment is
                                # integrated over the whole campaign before it starts)


def noise_floor(df: pd.DataFrame, noise_free: pd.DataFrame) -> dict:
    """The dataset's noise floor per axis (nm): the validation error (90th percentile of |error|)
    of the true model, i.e. of the readings against what a perfect instrument would have read
    on the same timeline."""
    val = (df["split"] == "val").to_numpy()
    out = {}
    for a in ("x", "y", "z"):
        c = f"{a}_nm"
        if c in df:
            e = np.abs(df[c].to_numpy()[val] - noise_free[c].to_numpy()[val])
            e = e[np.isfinite(e)]
            if e.size:
                out[a] = float(np.quantile(e, 0.9))
    return out


@dataclass
class Scenario:
    path: Path
    text: str
    name: str
    seed: int
    params: object
    effects: list
    sensors: dict
    settings: InstrumentSettings
    cosine: bool
    campaign: dict
    reduced_scale: float
    hidden: dict | None = None     # [hidden] effects the data holds and the baseline lacks
    scale: float | None = None     # the campaign's scale when a method is given none (None: full)

    # -- construction -------------------------------------------------------------------------
    @classmethod
    def load(cls, path, seed: int | None = None, scale: float | None = None,
             trust_effects=False) -> Scenario:
        """Read and validate a scenario (a path, or a name in scenarios/). ``seed`` replaces its
        [scenario] seed. ``scale`` (a fraction of the campaign's points in (0, 1]) is the scale
        ``simulate``, ``run``, ``build`` and ``plan`` use when they are given none (None: the
        full campaign); the plan is checked at it now. A user effect its [effects] on names
        (``file.py:Class``) is code: it runs only with ``trust_effects`` True (or a list of the
        specs whose code may run), else ScenarioError naming the file and the code
        (twin/effects: ``trust``)."""
        path = Path(path)
        if not path.exists() and (SCENARIO_DIR / f"{path}.toml").exists():
            path = SCENARIO_DIR / f"{path}.toml"
        if not path.exists():
            raise ScenarioError(f"{path}: no such scenario file (shipped: "
                                f"{', '.join(shipped_scenarios())})")
        if not path.is_file():
            raise ScenarioError(f"{path}: is a directory, not a scenario file")
        try:
            text = path.read_text(encoding="utf-8")
        except UnicodeDecodeError as exc:
            raise ScenarioError(f"{path}: not a UTF-8 text file ({exc})") from exc
        return cls.from_text(text, path, seed, scale, trust_effects)

    @classmethod
    def from_text(cls, text: str, path, seed: int | None = None, scale: float | None = None,
                  trust_effects=False) -> Scenario:
        """Validate a scenario's TOML ``text`` as the file ``path`` (relative paths in it are
        from that file's folder; ``trust_effects``: ``load``'s)."""
        path = Path(path)
        scale = check_scale(scale)
        try:
            doc = tomllib.loads(text)
        except tomllib.TOMLDecodeError as exc:
            raise ScenarioError(f"{path}: not valid TOML ({exc})") from exc
        f = str(path)
        version = doc.pop("format_version", FORMAT_VERSION)
        if not isinstance(version, int) or isinstance(version, bool) \
                or not 1 <= version <= FORMAT_VERSION:
            raise ScenarioError(f"{f} format_version = {version!r}: this deltatwin reads scenario "
                                f"files of version 1 to {FORMAT_VERSION}")
        _check_keys(f, doc, TABLES)
        for t, keys in TABLES.items():
            if t in doc and not isinstance(doc[t], dict):
                raise ScenarioError(f"{f} {t} = {doc[t]!r}: expected a table [{t}]")
            if keys is not None and t in doc:
                _check_keys(f"{f} [{t}]", doc[t], keys)
        sc = doc.get("scenario", {})
        for key in ("name", "description"):
            if not isinstance(sc.get(key, ""), str):
                raise ScenarioError(f"{f} [scenario] {key} = {sc[key]!r}: expected a string")
        name = sc.get("name", path.stem)
        seed = seed if seed is not None else _number(f"{f} [scenario] seed", sc.get("seed", 0), 0,
                                                     True, 2**63 - 1)
        robot_file = doc.get("robot", {}).get("file")
        if robot_file is not None and (not isinstance(robot_file, str)
                                       or (path.parent / robot_file).is_dir()):
            raise ScenarioError(f"{f} [robot] file = {robot_file!r}: expected the path of a "
                                "parameter TOML file")
        try:
            params = load_params(path.parent / robot_file if robot_file else None)
        except (ParameterError, FileNotFoundError) as exc:
            raise ScenarioError(f"{f} [robot] file: {exc}") from exc
        eff_doc = dict(doc.get("effects", {}))
        on = eff_doc.pop("on", [])
        if not isinstance(on, list):
            raise ScenarioError(f"{f} [effects] on: expected a list of effect names")
        # an entry of ``on`` is a library name or the researcher's own 'file.py:Class' (a
        # relative path from this file's folder); parameter tables go by the effect's name
        try:
            classes = [effect_class(n, path.parent, f"{f} [effects] on", trust_effects)
                       for n in on]
        except EffectError as exc:
            raise ScenarioError(str(exc)) from exc
        names = [c.name for c in classes]
        for key, table in eff_doc.items():
            if not isinstance(table, dict):
                raise ScenarioError(f"{f} [effects] {key} = {table!r}: expected a table "
                                    f"[effects.{key}] of parameter values")
        for extra in eff_doc:
            if extra not in names:
                raise ScenarioError(f"{f} [effects.{extra}]: parameters for an effect that is not "
                                    f"in [effects] on = {on}" + ("" if extra in LIBRARY else
                                    f" (and not a known effect: {sorted(LIBRARY)})"))
        try:
            effects = [make_effect(c, eff_doc.get(c.name), where=f"{f} [effects]")
                       for c in classes]
        except EffectError as exc:
            raise ScenarioError(str(exc)) from exc
        sensors = doc.get("sensors", {})
        parts = {p for p, _, _ in PART_NODES}
        if not isinstance(sensors, dict):
            raise ScenarioError(f"{f} [sensors]: expected a table of sensor = \"part\"")
        for sname, part in sensors.items():
            if not SENSOR_NAME.match(sname):
                raise ScenarioError(f"{f} [sensors] {sname!r}: a sensor name is letters, digits "
                                    "and _ (it names the column T_<name>_C and a scanner channel)")
            if not isinstance(part, str):
                raise ScenarioError(f"{f} [sensors] {sname} = {part!r}: expected one part name "
                                    "(a string)")
            if part not in parts:
                close = difflib.get_close_matches(str(part), parts, n=1)
                raise ScenarioError(f"{f} [sensors] {sname} = {part!r}: unknown part"
                                    + (f" (did you mean {close[0]!r}?)" if close else "")
                                    + f"; parts: {sorted(parts)}")
        inst = dict(doc.get("instruments", {}))
        cosine = inst.pop("cosine_correction", True)
        if not isinstance(cosine, bool):
            raise ScenarioError(f"{f} [instruments] cosine_correction: expected true or false")
        fields = {fl.name: fl for fl in dataclasses.fields(InstrumentSettings)}
        _check_keys(f"{f} [instruments]", inst, fields)
        switches = {k: inst.pop(k) for k in InstrumentSettings.SWITCHES if k in inst}
        for k, v in switches.items():
            if not isinstance(v, bool):
                raise ScenarioError(f"{f} [instruments] {k} = {v!r}: expected true (the "
                                    "laboratory records it) or false")
        ranges = InstrumentSettings.RANGES
        settings = InstrumentSettings(**switches, **{
            k: _number(f"{f} [instruments] {k}", v, ranges[k][0], fields[k].type == "int",
                       ranges[k][1], above=not ranges[k][2])
            for k, v in inst.items()})
        camp = doc.get("campaign", {})
        kind = camp.get("kind")
        if not isinstance(kind, str) or kind not in CAMPAIGN_KEYS:
            raise ScenarioError(f"{f} [campaign] kind = {kind!r}: expected one of "
                                f"{sorted(CAMPAIGN_KEYS)}")
        _check_keys(f"{f} [campaign]", camp, CAMPAIGN_KEYS[kind])
        red = _number(f"{f} [reduced] scale", doc.get("reduced", {}).get("scale", 0.05), 0.0,
                      maximum=1.0, above=True)
        hidden = doc.get("hidden")
        if hidden is not None:
            for key in ("effects", "baseline"):
                names = hidden.get(key)
                if not isinstance(names, list) or not all(isinstance(x, str) for x in names):
                    raise ScenarioError(f"{f} [hidden] {key}: expected a list of effect names")
                for x in names:
                    if x not in LIBRARY and x not in on:
                        close = difflib.get_close_matches(x, LIBRARY, n=1)
                        raise ScenarioError(f"{f} [hidden] {key}: unknown effect {x!r}"
                                            + (f" (did you mean {close[0]!r}?)" if close else ""))
            not_on = [x for x in hidden["effects"] + hidden["baseline"]
                      if x not in on and x not in [e.name for e in effects]]
            if not_on:
                raise ScenarioError(f"{f} [hidden]: effect(s) {not_on} are not in [effects] on "
                                    f"= {on}: the data cannot hold them")
            both = sorted(set(hidden["effects"]) & set(hidden["baseline"]))
            if both:
                raise ScenarioError(f"{f} [hidden]: {both} both hidden and in the baseline")
            # the laboratory's known constants, given to every fit (e.g. the frame's arm)
            known = hidden.get("known", {})
            if not isinstance(known, dict) or not all(isinstance(v, dict) for v in known.values()):
                raise ScenarioError(f"{f} [hidden] known: expected a table of effect = "
                                    "{parameter = value} (the laboratory's known constants)")
            for x, values in known.items():
                try:
                    make_effect(x, values, where=f"{f} [hidden] known", base_dir=path.parent,
                                trust=trust_effects)
                except EffectError as exc:
                    raise ScenarioError(str(exc)) from exc
        sc = cls(path=path, text=text, name=name, seed=seed, params=params, effects=effects,
                 sensors=sensors, settings=settings, cosine=cosine, campaign=camp,
                 reduced_scale=red, hidden=hidden, scale=scale)
        sc._timeline(sc.plan(random_streams(0)["campaign"]))   # validate the plan now
        if not sensors:
            raise ScenarioError(f"{f} [sensors]: no sensor; every campaign scans its "
                                "thermometers: name at least one (sensor = \"part\")")
        return sc

    def file_name(self) -> str:
        """The file this scenario was read from, as a user names it: a shipped scenario's
        name (``quiet/magnetic-force``, which ``load`` accepts), else its path. Its [scenario]
        name may differ (quiet/magnetic-force.toml is named hidden-magnetic-force)."""
        path = Path(self.path).resolve()
        if path.is_relative_to(SCENARIO_DIR.resolve()):
            return path.relative_to(SCENARIO_DIR.resolve()).with_suffix("").as_posix()
        return str(self.path)

    def with_campaign(self, campaign: dict, path=None, instruments: dict | None = None,
                      trust_effects=False) -> Scenario:
        """This scenario (robot, laboratory, seed) with another [campaign] table, e.g. a
        standard's test (``{"kind": "iso9283", "cycles": 30}``), and ``instruments`` settings
        changed: its TOML text rewritten and validated again, as the file ``path`` (default:
        this one's; ``trust_effects``: ``load``'s)."""
        import tomli_w

        doc = tomllib.loads(self.text)
        doc["campaign"] = campaign
        if instruments:
            doc["instruments"] = {**doc.get("instruments", {}), **instruments}
        return Scenario.from_text(tomli_w.dumps(doc), path or self.path, self.seed, self.scale,
                                  trust_effects=trust_effects)

    # -- the laboratory's error sources -------------------------------------------------------
    def sources(self) -> list[str]:
        """The laboratory's error sources (keys of ERROR_SOURCES) present in this scenario: the
        interferometers and thermometers always, the air where its index moves (air_refraction),
        the servos where they settle (servo_settling)."""
        names = {e.name for e in self.effects}
        return [s for s in ERROR_SOURCES if s not in ("air", "servo_settling") or
                {"air": "air_refraction", "servo_settling": "servo_settling"}[s] in names]

    def air_wander(self) -> dict:
        """The air's wander a reading sees in this laboratory (``air_wander``: the barometer's
        and hygrometer's noise where it records them, else room_climate's wander); none where
        the air does not reach the readings (no air_refraction); without room_climate the
        twin's air stands still at its standard values (the records' noise remains)."""
        if "air" not in self.sources():
            return {"pressure_Pa": (0.0, 0.0), "vapour_Pa": (0.0, 0.0)}
        climate = next((e.values for e in self.effects if e.name == "room_climate"),
                       {"pressure_std_Pa": 0.0, "vapour_std_Pa": 0.0})
        s = self.settings
        return air_wander(s, climate, s.barometer, s.hygrometer,
                          self.params.reference_temperature_C)

    def air_specification(self) -> dict:
        """``air_wander`` as the data's instrument specifications state it
        (twin/lab_setup.py ``AIR_SPECS``)."""
        from deltatwin.twin.lab_setup import AIR_SPECS

        wander = self.air_wander()
        return {key: value for field, keys in AIR_SPECS.items()
                for key, value in zip(keys, wander[field])}

    def with_perfect(self, sources) -> Scenario:
        """This scenario with the laboratory's error ``sources`` (keys of ERROR_SOURCES) made
        perfect: the same seed, timeline and random draws (the twin multiplies a perfect
        instrument's draws by zero), so two runs differ by those sources' errors alone. A
        source the scenario lacks is ignored; an unknown one raises ScenarioError."""
        unknown = set(sources) - set(ERROR_SOURCES)
        if unknown:
            raise ScenarioError(f"{self.name}: unknown error source(s) {sorted(unknown)}; "
                                f"known: {list(ERROR_SOURCES)}")
        s = self.settings
        change = {}
        if "interferometers" in sources:
            change.update(noise_floor_m=0.0, resolution_m=0.0, ac_noise_rad=0.0,
                          ac_resolution_rad=0.0)
        if "thermometers" in sources:
            change.update(T_noise_C=0.0, T_resolution_C=0.0)
        if "air" in sources:
            change.update(barometer_noise_Pa=0.0, barometer_resolution_Pa=0.0,
                          hygrometer_noise_pct=0.0, hygrometer_resolution_pct=0.0)
        effects = []
        for e in self.effects:
            quiet = {}
            if e.name == "room_climate" and "air" in sources:
                # what the lab does not record stands still at its mean
                quiet.update({} if s.barometer else {"pressure_std_Pa": 0.0})
                quiet.update({} if s.hygrometer else {"vapour_std_Pa": 0.0})
            if e.name == "servo_settling" and "servo_settling" in sources:
                quiet["angle_std_rad"] = 0.0
            effects.append(make_effect(type(e), {**e.values, **quiet}) if quiet else e)
        return dataclasses.replace(self, settings=dataclasses.replace(s, **change),
                                   effects=effects)

    # -- the campaign -------------------------------------------------------------------------
    def plan(self, rng, scale: float | None = None) -> Plan:
        """The campaign plan, at full scale or scaled (number of points times ``scale``; None:
        the scenario's own scale, given to ``load``)."""
        c, f = self.campaign, f"{self.path} [campaign]"
        if c["kind"] in STANDARD_TESTS:
            return self.standard_test(rng, scale).plan
        scale = self._scale(scale)
        stroke = self.params.stroke_rad
        if c["kind"] == "thermal":
            sessions = []
            for i, s in enumerate(c.get("sessions", [])):
                w = f"{f} sessions[{i}]"
                _check_keys(w, s, SESSION_KEYS)
                axes = tuple(s.get("axes", ()))
                if not axes or any(a not in ("x", "y", "z") for a in axes):
                    raise ScenarioError(f"{w} axes = {list(axes)}: expected some of x, y, z")
                n_cal = _number(f"{w} cal", s.get("cal"), 1, True, 10**6)
                n_val = _number(f"{w} val", s.get("val"), 1, True, 10**6)
                n_cal, n_val = (max(1, int(round(n * scale))) for n in (n_cal, n_val))
                sessions.append((s.get("name", f"s{i}"), axes, n_cal, n_val))
            if not sessions:
                raise ScenarioError(f"{f} sessions: at least one session is needed")
            n_pos = _number(f"{f} n_positions", c.get("n_positions", 1000), 2, True, 10**6)
            n_pos = max(10, int(round(n_pos * min(1.0, 4 * scale))))
            frac = _number(f"{f} cal_fraction", c.get("cal_fraction", 0.7), 0.0)
            if not 0 < frac < 1:
                raise ScenarioError(f"{f} cal_fraction = {frac}: must be between 0 and 1")
            return thermal_plan(rng, stroke, n_pos, frac, sessions)
        levels = lambda k, d: _number(f"{f} {k}", c.get(k, d), 2, True, 50)
        cal, val = levels("cal_levels", 6), levels("val_levels", 5)
        if scale < 1.0:
            cal, val = max(2, int(round(cal * scale ** (1 / 3)))), max(2, int(round(val * scale ** (1 / 3))))
        forces = c.get("forces_N", [0.0, 0.5, 1.0, 1.5, 2.0])
        if not isinstance(forces, list) or not forces:
            raise ScenarioError(f"{f} forces_N = {forces!r}: expected a non-empty list of forces "
                                "(N), e.g. [0.0, 0.5, 1.0, 1.5, 2.0]")
        forces = [_number(f"{f} forces_N", x, 0.0) for x in forces]
        per_A = _number(f"{f} force_per_A", c.get("force_per_A", 1.0), 0.0, maximum=100.0,
                        above=True)
        if max(forces) / per_A > 2.0 + 1e-12:
            raise ScenarioError(f"{f} forces_N: {max(forces)} N needs {max(forces) / per_A:.2f} A, "
                                "above the coils' 2 A")
        readings = _number(f"{f} readings", c.get("readings", 4), 1, True, 100)
        order = c.get("order", "papers")
        if order not in FORCE_ORDERS:
            raise ScenarioError(f"{f} order = {order!r}: expected one of {list(FORCE_ORDERS)} "
                                "(the papers' cal grid then val grid, or the two merged)")
        return force_plan(stroke, cal, val, forces, per_A, readings,
                          interleaved=order == "interleaved")

    def standard_test(self, rng, scale: float | None = None):
        """The standard's test of an ``iso*`` campaign (``twin.standard_tests.StandardTest``:
        its plan and what each point is), at full scale or scaled: fewer cycles (ISO 9283),
        targets and approaches (ISO 230-2), hours (ISO 230-3)."""
        from deltatwin.twin import standard_tests as st

        c, f = self.campaign, f"{self.path} [campaign]"
        scale = self._scale(scale)
        num = lambda k, d, lo, integer=False, hi=None: _number(f"{f} {k}", c.get(k, d), lo,
                                                                integer, hi)
        shrink = lambda n, low: max(low, int(round(n * scale)))
        frac = num("stroke_fraction", st.STROKE_FRACTION, 0.0, hi=1.0)
        try:
            if c["kind"] == "iso9283":
                order = c.get("order", list(st.ISO9283_ORDER))
                return st.iso9283_plan(self.params, shrink(num("cycles", st.ISO9283_CYCLES, 2,
                                                               True, 10**4), 2),
                                       tuple(order) if isinstance(order, list) else order,
                                       num("corner_fraction", st.ISO9283_CORNER_FRACTION, 0.0),
                                       frac)
            if c["kind"] == "iso230-2":
                axes = c.get("axes", ["x", "y", "z"])
                if not isinstance(axes, list):
                    raise ValueError(f"axes = {axes!r}: expected a list of x, y, z")
                return st.iso230_2_plan(
                    self.params, rng, tuple(axes),
                    shrink(num("targets", st.ISO230_2_TARGETS, 2, True, 1000), 3),
                    shrink(num("approaches", st.ISO230_2_APPROACHES, 2, True, 1000), 2),
                    num("overrun", st.ISO230_2_OVERRUN, 0.0, hi=0.5), frac)
            position = c.get("position_m")
            if position is not None and (not isinstance(position, list) or len(position) != 3):
                raise ValueError(f"position_m = {position!r}: expected [x, y, z] in m")
            return st.iso230_3_plan(self.params, self.settings,
                                    num("duration_h", st.ISO230_3_HOURS, 0.0, hi=720.0) * scale,
                                    position, frac)
        except ValueError as exc:
            if isinstance(exc, ScenarioError):
                raise
            raise ScenarioError(f"{f}: {exc}") from exc

    def _scale(self, scale: float | None) -> float:
        """The scale a method uses: the one given, else the scenario's own, else 1 (checked)."""
        scale = self.scale if scale is None else check_scale(scale)
        return 1.0 if scale is None else scale

    def dead_path(self) -> dict:
        """Nominal beam path head -> cube face (m) per axis, for the cosine correction."""
        return nominal_dead_path(self.params.mirror_cube_size_m)

    def horizon_s(self, plan: Plan) -> float:
        """Upper bound of the campaign's duration (the twin's environment is made this long)."""
        s = self.settings
        lo, hi = self.params.stroke_rad
        per_point = (s.coil_settle_s + s.move_time(hi - lo) + s.wait_s
                     + plan.readings * (4 * s.window_s + s.ac_read_s) + s.overhead_s)
        return len(plan) * per_point + len(plan.sessions) * (s.session_gap_s + 600.0) + 3600.0

    def _timeline(self, plan: Plan) -> tuple[float, float]:
        """(horizon, warm-up) in s, checked against the longest campaign the twin simulates."""
        warmup = _number(f"{self.path} [campaign] warmup_s", self.campaign.get("warmup_s", 7200.0),
                         0.0, maximum=7 * 86400.0)
        horizon = self.horizon_s(plan)
        if horizon + warmup > MAX_DAYS * 86400.0:
            raise ScenarioError(f"{self.path}: the campaign would last "
                                f"{(horizon + warmup) / 86400:.0f} days (points, timing and gaps "
                                f"of [campaign] and [instruments]); the twin simulates at most "
                                f"{MAX_DAYS:g} days")
        return horizon, warmup

    def build(self, scale: float | None = None):
        """(twin, plan) for this scenario and seed."""
        plan = self.plan(random_streams(self.seed)["campaign"], scale)
        horizon, warmup = self._timeline(plan)
        twin = Twin(self.params, self.effects, self.sensors, self.seed, horizon, warmup)
        return twin, plan

    def identity(self, scale: float | None) -> dict:
        """What makes two runs of this scenario the same world: its name, the SHA-256 of its
        TOML text, the seed and the scale (1.0 for the full campaign)."""
        return {"scenario": self.name,
                "scenario_sha256": hashlib.sha256(self.text.encode()).hexdigest(),
                "seed": self.seed, "scale": self._scale(scale)}

    def metadata(self, twin: Twin, scale, noise_floor_nm: dict | None = None) -> dict:
        from deltatwin import __version__
        return {"source": "twin", "scenario": self.name, "scenario_toml": self.text,
                "seed": self.seed, "scale": self._scale(scale),
                "deltatwin_version": __version__, "sensors": dict(self.sensors),
                # the laboratory's instrument specifications, which a fit's noise model uses
                "instruments": {"T_noise_C": self.settings.T_noise_C,
                                "T_resolution_C": self.settings.T_resolution_C,
                                "interferometer_noise_m": self.settings.noise_floor_m,
                                "interferometer_resolution_m": self.settings.resolution_m,
                                **self.air_specification()},
                "truth": {"effects": [e.describe() for e in self.effects],
                          "hidden": self.hidden,
                          "reading_noise_std_nm": self.settings.noise_floor_m * 1e9,
                          "noise_floor_nm": noise_floor_nm,
                          "cosine_correction": self.cosine},
                "cosine_dead_path_m": self.dead_path(),
                # what the laboratory states about itself: its [hidden] known constants and
                # baseline, its supports' set point (twin/lab_setup.py; the instruments and
                # sensors above)
                "setup": scenario_setup(self.hidden, f"scenario {self.file_name()}",
                                        self.effects)}

    def simulate(self, scale: float | None = None) -> tuple[pd.DataFrame, dict]:
        """The campaign's dataset through the vectorised fast path."""
        twin, plan = self.build(scale)
        df, clean = simulate_campaign(plan, twin, self.settings, self.cosine, self.dead_path(),
                                      noise_free=True)
        return df, self.metadata(twin, scale, noise_floor(df, clean))

    def run(self, scale: float | None = None, progress: bool = True, instruments=None):
        """The same campaign point by point through the instrument interface (simulated
        instruments unless an InstrumentSet is given)."""
        twin, plan = self.build(scale)
        inst = instruments or SimulatedLab(twin, self.settings).instrument_set()
        df = run_campaign(plan, inst, self.settings, self.cosine, self.dead_path(), progress)
        return df, self.metadata(twin, scale)
