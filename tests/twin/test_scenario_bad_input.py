"""Bad scenarios, tried as a laboratory would write them: every one is refused with a clear
error naming the file and the key (a ScenarioError), never a traceback, a hang, an attempt to
allocate terabytes, or a silent acceptance. Outcomes are counted so a regression shows which."""
import copy
import math
import tomllib
from pathlib import Path

import pytest
import tomli_w

from deltatwin.twin.instruments.simulated import InstrumentSettings
from deltatwin.twin.scenario import SCENARIO_DIR, Scenario, ScenarioError


def _base(name):
    return tomllib.loads((SCENARIO_DIR / f"{name}.toml").read_text())


def _set(table, key, value):
    def change(doc):
        doc.setdefault(table, {})[key] = value
    return change


def _session(key, value):
    def change(doc):
        doc["campaign"]["sessions"][0][key] = value
    return change


# (name, base scenario, change of the parsed TOML, key the message must name)
CASES = [
    ("speed 0", "paper-force", _set("instruments", "speed_rad_s", 0.0), "speed_rad_s"),
    ("scan period 0", "paper-force", _set("instruments", "scan_period_s", 0.0), "scan_period_s"),
    ("session gap 1e12 s", "paper-force", _set("instruments", "session_gap_s", 1e12),
     "session_gap_s"),
    ("acceptance limit 0 (hung)", "paper-force", _set("instruments", "std_limit_m", 0.0),
     "std_limit_m"),
    ("autocollimator range 0 (NaN readings)", "paper-force",
     _set("instruments", "ac_range_rad", 0.0), "ac_range_rad"),
    ("negative window", "paper-force", _set("instruments", "window_s", -1.0), "window_s"),
    ("negative resolution", "paper-force", _set("instruments", "resolution_m", -1e-9),
     "resolution_m"),
    ("noise as text", "paper-force", _set("instruments", "noise_floor_m", "5e-9"),
     "noise_floor_m"),
    ("fractional samples", "paper-force", _set("instruments", "samples_per_window", 1.5),
     "samples_per_window"),
    ("negative rereads", "paper-force", _set("instruments", "max_rereads", -1), "max_rereads"),
    ("nan thermometer noise", "paper-force", _set("instruments", "T_noise_C", math.nan),
     "T_noise_C"),
    ("unknown instrument key", "paper-force", _set("instruments", "nosie_floor_m", 1e-9),
     "nosie_floor_m"),
    ("warm-up 1e13 s", "paper-force", _set("campaign", "warmup_s", 1e13), "warmup_s"),
    ("100000 levels", "paper-force", _set("campaign", "cal_levels", 100000), "cal_levels"),
    ("one level", "paper-force", _set("campaign", "val_levels", 1), "val_levels"),
    ("forces as a number", "paper-force", _set("campaign", "forces_N", 2.0), "forces_N"),
    ("no forces", "paper-force", _set("campaign", "forces_N", []), "forces_N"),
    ("force above the coils' 2 A", "paper-force", _set("campaign", "forces_N", [0.0, 3.0]),
     "forces_N"),
    ("zero readings", "paper-force", _set("campaign", "readings", 0), "readings"),
    ("zero force per ampere", "paper-force", _set("campaign", "force_per_A", 0.0),
     "force_per_A"),
    ("unknown campaign kind", "paper-force", _set("campaign", "kind", "cutting"), "kind"),
    ("10^9 positions", "paper-thermal", _set("campaign", "n_positions", 10**9), "n_positions"),
    ("cal fraction 1.5", "paper-thermal", _set("campaign", "cal_fraction", 1.5), "cal_fraction"),
    ("no sessions", "paper-thermal", _set("campaign", "sessions", []), "sessions"),
    ("session axis w", "paper-thermal", _session("axes", ["w"]), "axes"),
    ("session with 0 calibration points", "paper-thermal", _session("cal", 0), "cal"),
    ("sensor part as a list", "paper-force", _set("sensors", "base", ["base", "arm1"]), "base"),
    ("sensor name with a space", "paper-force", _set("sensors", "base plate", "base"),
     "base plate"),
    ("unknown part", "paper-force", _set("sensors", "base", "bas"), "bas"),
    ("negative seed", "paper-force", _set("scenario", "seed", -1), "seed"),
    ("fractional seed", "paper-force", _set("scenario", "seed", 1.5), "seed"),
    ("robot file a folder", "paper-force", _set("robot", "file", "."), "file"),
    ("robot file missing", "paper-force", _set("robot", "file", "nope.toml"), "file"),
    ("effects on not a list", "paper-force", _set("effects", "on", "geometric_errors"), "on"),
    ("unknown effect", "paper-force", _set("effects", "on", ["geometric_erors"]),
     "geometric_erors"),
    ("reduced scale 0", "paper-force", _set("reduced", "scale", 0.0), "scale"),
    ("reduced scale 2", "paper-force", _set("reduced", "scale", 2.0), "scale"),
]


def _outcome(path: Path, key: str) -> str:
    try:
        sc = Scenario.load(path)
        sc.simulate(scale=0.02)
    except ScenarioError as exc:
        text = str(exc)
        return "clear" if str(path) in text and key in text else f"vague: {text}"
    except Exception as exc:                                    # noqa: BLE001 - counted
        return f"traceback: {type(exc).__name__}: {exc}"
    return "silent"


def test_every_bad_scenario_is_refused_clearly(tmp_path):
    outcomes = {}
    for name, base, change, key in CASES:
        doc = copy.deepcopy(_base(base))
        change(doc)
        path = tmp_path / f"{name.replace(' ', '_')}.toml"
        path.write_text(tomli_w.dumps(doc))
        outcomes[name] = _outcome(path, key)
    bad = {n: o for n, o in outcomes.items() if o != "clear"}
    assert not bad, f"{len(bad)} of {len(CASES)} not refused clearly:\n" + "\n".join(
        f"  {n}: {o}" for n, o in bad.items())


@pytest.mark.parametrize("content", [b"[scenario\nname = 1", b"\xff\xfe\x00garbage"])
def test_unreadable_files_name_the_file(tmp_path, content):
    path = tmp_path / "bad.toml"
    path.write_bytes(content)
    with pytest.raises(ScenarioError, match="bad.toml"):
        Scenario.load(path)


def test_every_instrument_setting_has_a_range():
    import dataclasses
    fields = {f.name for f in dataclasses.fields(InstrumentSettings)}
    # every setting has a range, but the switches saying which instruments the lab has
    assert set(InstrumentSettings.RANGES) == fields - set(InstrumentSettings.SWITCHES)
    defaults = InstrumentSettings()
    assert all(isinstance(getattr(defaults, k), bool) for k in InstrumentSettings.SWITCHES)
    for k, (lo, hi, lo_ok) in InstrumentSettings.RANGES.items():
        v = getattr(defaults, k)
        assert (v >= lo if lo_ok else v > lo) and v <= hi, k


def test_generated_scenarios_carry_a_format_version_that_is_checked(tmp_path):
    """Scenario files deltatwin writes (generated cases, design sweeps) name their format
    version; a newer one is refused naming the file; a hand-written scenario may omit it."""
    import numpy as np

    from deltatwin.twin.cases import generate_cases
    from deltatwin.twin.scenario import FORMAT_VERSION

    text = generate_cases(np.random.default_rng(1), 1)[0].toml()
    assert f"\nformat_version = {FORMAT_VERSION}\n" in text
    path = tmp_path / "case.toml"
    path.write_text(text)
    Scenario.load(path)
    path.write_text(text.replace(f"format_version = {FORMAT_VERSION}", "format_version = 99"))
    with pytest.raises(ScenarioError, match=r"case.toml format_version = 99"):
        Scenario.load(path)
