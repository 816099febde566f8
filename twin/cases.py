"""Random discovery cases in the papers' laboratory conditions: a scenario hiding zero to three
effects from a model, written independently of the shipped hidden scenarios, to measure whether
the find-the-missing-effect loop works where it has not been tuned (benchmarks/discovery.py).

A case is one of the papers' campaigns in their conditions: the thermal campaign with the air
conditioning switched off after half an hour, 80 Pa of unrecorded pressure wander, the paper's
11 sensors, the robot hanging from a 0.6 m frame arm; or the force campaign with the air
conditioning on, servo settling, the paper's 13 sensors and the same frame. The model a
researcher would start from (``baseline``) holds the effects of the paper's analysis; the case
hides ``hidden`` of them (each at a ``magnitude``: a factor on the effect's strength, its
parameters of size scaled from the library's default), or none (a null case: the baseline is
the complete model, any claim is false). The frame arm is a known constant of the laboratory,
given to every fit (``known``).
"""
from __future__ import annotations

import textwrap
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from deltatwin.files import atomic_write_text, toml_text
from deltatwin.twin.effects import LIBRARY
from deltatwin.twin.scenario import FORMAT_VERSION as SCENARIO_FORMAT_VERSION

FRAME_ARM_M = (-0.6, 0.0)
PAPER_SENSORS = {
    "thermal": ("air_x", "air_y", "base", "arm1", "arm2", "arm3", "rod1", "rod2", "platform",
                "frame", "table"),
    "force": ("air_x", "air_y", "air_z", "base", "arm1", "arm2", "arm3", "rod1", "platform",
              "frame", "table", "coil_box", "motor1")}
# the effects of the paper's analysis (a model holds them unless the case hides one)
MODEL = {"thermal": ("geometric_errors", "thermal_expansion", "sensor_contact", "loop_drift"),
         "force": ("geometric_errors", "thermal_expansion", "sensor_contact", "loop_drift",
                   "magnetic_force")}
# what a case can hide, beyond the model's own effects
EXTRA = ("gravity_sag", "beam_misalignment", "air_refraction")
HIDEABLE = {"thermal": ("loop_drift",) + EXTRA, "force": ("loop_drift", "magnetic_force") + EXTRA}
# the laboratory around the model (no model form: part of the floor)
ENVIRONMENT = {"thermal": ("room_climate", "motor_heating", "peltier_supports"),
               "force": ("room_climate", "motor_heating", "peltier_supports", "coil_heating",
                         "servo_settling")}
# the parameters whose size is an effect's strength
STRENGTH = {"gravity_sag": ("load_factor",),
            "beam_misalignment": ("angle_rad", "abbe_offset_m"),
            "air_refraction": ("beam_room_fraction", "compensation_offset_C"),
            "loop_drift": ("table_cte_per_K", "frame_cte_per_K", "support_cte_per_K"),
            "magnetic_force": ("coil_moment_per_A",)}
MAGNITUDES = (1 / 3, 1.0, 3.0, 10.0)
CAMPAIGNS = {
    "thermal": {"kind": "thermal", "warmup_s": 7200.0, "n_positions": 1200, "cal_fraction": 0.7,
                "sessions": [{"name": "xy", "axes": ["x", "y"], "cal": 9701, "val": 4074},
                             {"name": "z", "axes": ["z"], "cal": 10390, "val": 4327}]},
    "force": {"kind": "force", "warmup_s": 7200.0, "cal_levels": 6, "val_levels": 5,
              "forces_N": [0.0, 0.5, 1.0, 1.5, 2.0], "force_per_A": 1.0, "readings": 4}}
CLIMATE = {"thermal": {"ac_setpoint_C": 20.0, "ac_off_s": 1800.0, "free_mean_C": 23.4,
                       "daily_amplitude_C": 1.4, "pressure_std_Pa": 80.0},
           "force": {"ac_off_s": 1e9, "pressure_std_Pa": 80.0}}
NOISE_M = {"thermal": 5e-9, "force": 7e-9}
# tests' scale: 5 % of the thermal campaign (1425 points, 4.5 h), 30 % of the force one (510)
REDUCED = {"thermal": 0.05, "force": 0.3}
KNOWN = {"loop_drift": {"frame_arm_m": list(FRAME_ARM_M)}}   # given to every fit


@dataclass(frozen=True)
class Case:
    """One generated case: its scenario (TOML text), what it hides and the model to start from."""
    name: str
    kind: str
    seed: int
    hidden: tuple            # ((effect, magnitude), ...); empty for a null case
    baseline: tuple          # the model's effects
    known: dict = field(default_factory=dict)   # {effect: {parameter: value}}: lab constants
    header: str = ""         # the scenario file's opening comment (default: a generated case)

    @property
    def hidden_effects(self) -> list[str]:
        return [e for e, _ in self.hidden]

    @property
    def true_effects(self) -> list[str]:
        return list(self.baseline) + self.hidden_effects

    def toml(self) -> str:
        """The scenario file of the case."""
        effects = [*self.true_effects, *ENVIRONMENT[self.kind]]
        tables = {"room_climate": dict(CLIMATE[self.kind]),
                  "loop_drift": {"frame_arm_m": list(FRAME_ARM_M), "frame_cte_per_K": 23e-6}}
        if self.kind == "force":
            tables["servo_settling"] = {"angle_std_rad": 2.5e-7}
            tables["magnetic_force"] = {"coil_moment_per_A": 0.22,
                                        "coil_offset_m": [[-0.004, -0.008, 0.0]] * 3}
        for e, m in self.hidden:
            tables[e] = {**tables.get(e, {}), **_scaled(e, m, tables.get(e, {}))}
        hidden = {"effects": self.hidden_effects, "baseline": list(self.baseline)}
        if self.known:
            hidden["known"] = self.known
        doc = {"format_version": SCENARIO_FORMAT_VERSION,
               "scenario": {"name": self.name, "description": self.description(),
                            "seed": self.seed},
               "hidden": hidden,
               "effects": {"on": effects, **{e: v for e, v in tables.items() if e in effects}},
               "sensors": {s: s for s in PAPER_SENSORS[self.kind]},
               # the papers' laboratory recorded neither the pressure nor the humidity
               "instruments": {"noise_floor_m": NOISE_M[self.kind], "cosine_correction": True,
                               "barometer": False, "hygrometer": False},
               "campaign": CAMPAIGNS[self.kind], "reduced": {"scale": REDUCED[self.kind]}}
        return toml_text(doc, self.header or "a generated discovery case (deltatwin.twin.cases)")

    def description(self) -> str:
        hidden = ", ".join(f"{e} x{m:.3g}" for e, m in self.hidden) or "nothing (null case)"
        return f"{self.kind} campaign in the papers' conditions hiding {hidden}"


def _scaled(effect: str, magnitude: float, given: dict) -> dict:
    """The strength parameters of ``effect`` at ``magnitude`` times their value (given here or
    the library's default); none for an effect without a strength (STRENGTH) at magnitude 1."""
    if effect not in STRENGTH and magnitude != 1.0:
        raise ValueError(f"{effect}: no strength parameter to scale by {magnitude}")
    defaults = {p.name: p.default for p in LIBRARY[effect].parameters}
    out = {}
    for name in STRENGTH.get(effect, ()):
        value = np.asarray(given.get(name, defaults[name]), dtype=np.float64) * magnitude
        if name == "beam_room_fraction":
            value = np.minimum(value, 1.0)       # a fraction of the beam's path
        out[name] = value.tolist()
    return out


def generate_cases(rng: np.random.Generator, n: int, kinds=("thermal", "force"),
                   null_fraction: float = 0.2, max_hidden: int = 3) -> list[Case]:
    """``n`` random cases: a campaign kind, then a null case (with probability
    ``null_fraction``) or one to ``max_hidden`` hidden effects (one half of the time, two or
    three otherwise) at magnitudes drawn from MAGNITUDES; seeds drawn from ``rng``."""
    if n < 0 or not 0 <= null_fraction <= 1 or max_hidden < 1:
        raise ValueError(f"generate_cases: n = {n}, null_fraction = {null_fraction}, "
                         f"max_hidden = {max_hidden}: need n >= 0, 0 <= null_fraction <= 1, "
                         "max_hidden >= 1")
    unknown = sorted(set(kinds) - set(CAMPAIGNS))
    if unknown:
        raise ValueError(f"generate_cases: unknown campaign kind(s) {unknown}; kinds: "
                         f"{sorted(CAMPAIGNS)}")
    cases = []
    for i in range(n):
        kind = str(rng.choice(list(kinds)))
        seed = int(rng.integers(1, 2 ** 31))
        if rng.random() < null_fraction:
            hidden = ()
        else:
            k = 1 if rng.random() < 0.5 else int(rng.integers(2, max_hidden + 1))
            names = rng.choice(HIDEABLE[kind], size=min(k, len(HIDEABLE[kind])), replace=False)
            hidden = tuple((str(e), float(rng.choice(MAGNITUDES))) for e in names)
        baseline = tuple(e for e in MODEL[kind] if e not in dict(hidden))
        known = KNOWN
        tag = "-".join(e for e, _ in hidden) or "null"
        cases.append(Case(name=f"case{i:03d}-{kind}-{tag}", kind=kind, seed=seed, hidden=hidden,
                          baseline=baseline, known=known))
    return cases


# The shipped hidden scenarios (scenarios/hidden/), in the papers' conditions: one effect (or
# two) hidden from the model of the paper's analysis, at the library's strength. Written from
# these definitions by ``write_hidden_scenarios`` (a test checks the shipped files are current).
HIDDEN_SCENARIOS = {
    "loop-drift": ("thermal", 16, ("loop_drift",), "the measurement loop (table, frame, "
                   "supports) expands with the room, the robot hanging from the frame's arm"),
    "thermal-expansion": ("thermal", 15, ("thermal_expansion",),
                          "the robot's parts expand with the room and the motors' heat"),
    "sensor-contact": ("thermal", 18, ("sensor_contact",), "each thermometer lags its part and "
                       "reads part of the way to the room air"),
    "thermal-and-loop": ("thermal", 17, ("thermal_expansion", "loop_drift"),
                         "the parts' expansion and the loop's drift together"),
    "geometric-errors": ("thermal", 11, ("geometric_errors",),
                         "the robot's lengths, joints and encoder zeros off their drawing"),
    "gravity-sag": ("thermal", 13, ("gravity_sag",), "the platform's weight through the "
                    "flexures' compliance (pose-dependent sag)"),
    "beam-misalignment": ("thermal", 12, ("beam_misalignment",),
                          "beams tilted and off the cube's centre (cosine and Abbe errors)"),
    "air-refraction": ("thermal", 19, ("air_refraction",), "the beams' air index against the "
                       "interferometers' compensation, with the pressure unrecorded"),
    "magnetic-force": ("force", 14, ("magnetic_force",),
                       "the coil-magnet force simulator through the compliance"),
}


def hidden_case(name: str) -> Case:
    """The shipped hidden scenario ``name`` as a Case (HIDDEN_SCENARIOS)."""
    kind, seed, hidden, what = HIDDEN_SCENARIOS[name]
    baseline = tuple(e for e in MODEL[kind] if e not in hidden)
    header = (f"Hidden: {', '.join(hidden)} ({what}); the model starts from the paper's "
              f"analysis without it: {', '.join(baseline)}. The papers' conditions "
              f"(deltatwin.twin.cases, the one place they are defined): {kind} campaign, "
              + ("air conditioning off after half an hour, " if kind == "thermal" else
                 "air conditioning on, servo settling, coils heating, ")
              + f"{CLIMATE[kind]['pressure_std_Pa']:g} Pa of pressure wander with no barometer, "
              f"the paper's {len(PAPER_SENSORS[kind])} sensors, the robot hanging from a "
              f"{-FRAME_ARM_M[0]:g} m frame arm given to every fit as a known constant. "
              "Generated by deltatwin.twin.cases.write_hidden_scenarios: edit there.")
    return Case(name=f"hidden-{name}", kind=kind, seed=seed,
                hidden=tuple((e, 1.0) for e in hidden), baseline=baseline, known=KNOWN,
                header=textwrap.fill(header, 96))


def write_hidden_scenarios(folder) -> list:
    """Write every HIDDEN_SCENARIOS case as ``<folder>/<name>.toml`` (atomically); the paths."""
    paths = []
    for name in HIDDEN_SCENARIOS:
        path = Path(folder) / f"{name}.toml"
        atomic_write_text(path, hidden_case(name).toml())
        paths.append(path)
    return paths
