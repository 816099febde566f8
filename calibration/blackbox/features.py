"""Feature library: named, composable families of candidate terms, the papers' presets,
and the causal temperature derivatives.  Kept apart from the optimiser that selects terms.

A *term* is a monomial of base variables, all in SI units:

=================  ======  ==========================================================
variable           unit    meaning
=================  ======  ==========================================================
``q1`` ``q2`` ``q3``  rad  motor coordinates
``X`` ``Y`` ``Z``   m      end-effector position (interferometer readings)
``F``              N       nominal force of the force simulator
``T_<s>``          K       temperature of sensor ``<s>`` minus the reference ``T_ref_K``
``dT_<s>``         K/s     its first time derivative (causal estimate)
``d2T_<s>``        K/s^2   its second time derivative (causal estimate)
=================  ======  ==========================================================

A family produces an ordered list of terms; a :class:`FeatureSet` concatenates families
(order = column order = MATLAB's tie-break order).  Families and feature sets serialise to
plain dicts (kept in exported models) and are rebuilt from them.

Temperature derivatives (see :func:`causal_derivatives`): at each sample, a least-squares
polynomial of degree 2 in time is fitted to the samples of the same session in the trailing
window ``[t - window_s, t]`` (past and present only, any spacing), and its first and second
derivatives at ``t`` are taken.  With fewer than 3 distinct times in the window the degree
drops (2 samples: slope, second derivative 0; 1 sample: both 0), as a controller starting up
would do.  The default window is 600 s (about 60 samples of a 10 s temperature loop).
"""
from __future__ import annotations

import hashlib
import itertools
import warnings
from dataclasses import dataclass

import numpy as np
import pandas as pd

from deltatwin.calibration.errors import (
    CalibrationInputError,
    MissingColumnsError,
    MissingMetadataWarning,
)
from deltatwin.calibration.streams import causal_derivatives

__all__ = [
    "Term", "Family", "Monomials", "Variables", "Powers", "Product", "FeatureSet",
    "geometric", "temperatures", "temperature_rates", "force_powers",
    "thermal_preset", "force_preset", "thermal_ladder", "force_ladder",
    "variable_unit", "DEFAULT_T_REF_K",
]

DEFAULT_T_REF_K = 293.15          # 20 degC, the reference temperature of dimensional metrology
ZERO_CELSIUS_K = 273.15
JOINT_INPUTS = ("q1", "q2", "q3")
CARTESIAN_INPUTS = ("X", "Y", "Z")


def variable_unit(var: str) -> str:
    """SI unit of a base variable, from its name."""
    if var in JOINT_INPUTS:
        return "rad"
    if var in CARTESIAN_INPUTS:
        return "m"
    if var == "F":
        return "N"
    if var.startswith("d2T_"):
        return "K/s^2"
    if var.startswith("dT_"):
        return "K/s"
    if var.startswith("T_"):
        return "K"
    raise CalibrationInputError(f"unknown base variable {var!r}")


@dataclass(frozen=True)
class Term:
    """A monomial: ``((variable, power), ...)``, powers >= 1, each variable once."""
    factors: tuple[tuple[str, int], ...]

    @property
    def name(self) -> str:
        return "*".join(v if p == 1 else f"{v}^{p}" for v, p in self.factors)

    @property
    def variables(self) -> tuple[str, ...]:
        return tuple(v for v, _ in self.factors)

    def times(self, other: Term) -> Term:
        powers: dict[str, int] = {}
        for v, p in self.factors + other.factors:
            powers[v] = powers.get(v, 0) + p
        return Term(tuple(powers.items()))

    def to_list(self) -> list:
        return [[v, p] for v, p in self.factors]

    @staticmethod
    def from_list(factors) -> Term:
        try:
            return Term(tuple((str(v), int(p)) for v, p in factors))
        except (TypeError, ValueError) as exc:
            raise CalibrationInputError(f"bad term factors {factors!r}: {exc}") from exc


class Family:
    """A named, ordered list of candidate terms."""
    name: str = "family"

    def terms(self) -> list[Term]:
        raise NotImplementedError

    def to_dict(self) -> dict:
        raise NotImplementedError

    def __len__(self) -> int:
        return len(self.terms())

    @staticmethod
    def from_dict(d: dict) -> Family:
        kinds = {"monomials": Monomials, "variables": Variables, "powers": Powers,
                 "product": Product}
        try:
            cls = kinds[d["kind"]]
        except (KeyError, TypeError) as exc:
            raise CalibrationInputError(f"unknown feature family description {d!r}") from exc
        return cls._from_dict(d)


class Monomials(Family):
    """All monomials of the given total orders in ``inputs`` (order 1: q1, q2, q3; then
    q1^2, q1*q2, q1*q3, q2^2, ...).  Orders 1-3 of three inputs give the papers' 19 terms."""

    def __init__(self, inputs=JOINT_INPUTS, orders=(1, 2, 3), name="geometric"):
        self.inputs = tuple(inputs)
        self.orders = tuple(int(o) for o in orders)
        self.name = name
        if not self.inputs or any(o < 1 for o in self.orders):
            raise CalibrationInputError(f"Monomials({self.inputs}, {self.orders}): "
                                        "need inputs and orders >= 1")

    def terms(self):
        out = []
        for order in self.orders:
            for combo in itertools.combinations_with_replacement(range(len(self.inputs)), order):
                counts = {}
                for i in combo:
                    counts[self.inputs[i]] = counts.get(self.inputs[i], 0) + 1
                out.append(Term(tuple(counts.items())))
        return out

    def to_dict(self):
        return {"kind": "monomials", "name": self.name, "inputs": list(self.inputs),
                "orders": list(self.orders)}

    @classmethod
    def _from_dict(cls, d):
        return cls(d["inputs"], d["orders"], d.get("name", "geometric"))


class Variables(Family):
    """Each variable on its own (e.g. each temperature)."""

    def __init__(self, variables, name="variables"):
        self.variables = tuple(variables)
        self.name = name

    def terms(self):
        return [Term(((v, 1),)) for v in self.variables]

    def to_dict(self):
        return {"kind": "variables", "name": self.name, "variables": list(self.variables)}

    @classmethod
    def _from_dict(cls, d):
        return cls(d["variables"], d.get("name", "variables"))


class Powers(Family):
    """Powers of one variable (e.g. F, F^2, F^3)."""

    def __init__(self, variable="F", powers=(1, 2, 3), name="force"):
        self.variable = str(variable)
        self.powers = tuple(int(p) for p in powers)
        self.name = name

    def terms(self):
        return [Term(((self.variable, p),)) for p in self.powers]

    def to_dict(self):
        return {"kind": "powers", "name": self.name, "variable": self.variable,
                "powers": list(self.powers)}

    @classmethod
    def _from_dict(cls, d):
        return cls(d["variable"], d["powers"], d.get("name", "force"))


class Product(Family):
    """Every product of a term of ``a`` with a term of ``b`` (a-major order)."""

    def __init__(self, a: Family, b: Family, name=None):
        self.a, self.b = a, b
        self.name = name or f"{a.name} x {b.name}"

    def terms(self):
        tb = self.b.terms()
        return [x.times(z) for x in self.a.terms() for z in tb]

    def to_dict(self):
        return {"kind": "product", "name": self.name, "a": self.a.to_dict(),
                "b": self.b.to_dict()}

    @classmethod
    def _from_dict(cls, d):
        return cls(Family.from_dict(d["a"]), Family.from_dict(d["b"]), d.get("name"))


# ----- named families -------------------------------------------------------------------

def geometric(inputs=JOINT_INPUTS, orders=(1, 2, 3)) -> Monomials:
    return Monomials(inputs, orders, name="geometric")


def temperatures(sensors) -> Variables:
    return Variables([f"T_{s}" for s in sensors], name="temperatures")


def temperature_rates(sensors, order: int = 1) -> Variables:
    if order not in (1, 2):
        raise CalibrationInputError(f"temperature_rates: order {order} must be 1 or 2")
    prefix = "dT_" if order == 1 else "d2T_"
    return Variables([f"{prefix}{s}" for s in sensors],
                     name="temperature rates" if order == 1 else "temperature accelerations")


def force_powers(max_power: int = 3) -> Powers:
    return Powers("F", tuple(range(1, max_power + 1)), name="force")


def term_matrix(terms, values: dict[str, np.ndarray]) -> np.ndarray:
    """(n, len(terms)): each term (a product of powers of base variables) evaluated on
    ``values`` (base-variable arrays, SI), the powers computed once."""
    n = len(next(iter(values.values()))) if values else 0
    cache: dict[tuple[str, int], np.ndarray] = {}

    def power(v, p):
        key = (v, p)
        if key not in cache:
            base = np.asarray(values[v], dtype=float)
            cache[key] = base if p == 1 else base * power(v, p - 1)
        return cache[key]

    out = np.empty((n, len(terms)))
    for j, t in enumerate(terms):
        col = power(*t.factors[0])
        for v, p in t.factors[1:]:
            col = col * power(v, p)
        out[:, j] = col
    return out


class FeatureSet:
    """An ordered concatenation of families: the candidate columns given to the optimiser."""

    def __init__(self, families, name: str = "custom", preset: str | None = None):
        self.families = list(families)
        self.name = name
        self.preset = preset
        terms = [t for f in self.families for t in f.terms()]
        names = [t.name for t in terms]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise CalibrationInputError(f"feature set {name!r}: duplicate terms {dup[:10]}")
        self.terms = terms
        self.names = names
        for t in terms:                        # every variable must have a known unit
            for v in t.variables:
                variable_unit(v)

    def __len__(self):
        return len(self.terms)

    @property
    def variables(self) -> list[str]:
        """Base variables used, in first-appearance order."""
        seen = {}
        for t in self.terms:
            for v in t.variables:
                seen.setdefault(v, None)
        return list(seen)

    @property
    def signature(self) -> str:
        """Hash of the ordered term names: two feature sets match iff their signatures do."""
        return hashlib.sha256("\n".join(self.names).encode()).hexdigest()[:16]

    def family_of(self) -> list[str]:
        """Family name of each term, in column order."""
        return [f.name for f in self.families for _ in f.terms()]

    def matrix(self, values: dict[str, np.ndarray]) -> np.ndarray:
        """Evaluate every term: (n, len(self)) from a dict of base-variable arrays (SI)."""
        missing = [v for v in self.variables if v not in values]
        if missing:
            raise MissingColumnsError(f"feature set {self.name!r}: no values for base "
                                      f"variable(s) {missing}")
        return term_matrix(self.terms, values)

    def to_dict(self) -> dict:
        return {"name": self.name, "preset": self.preset,
                "families": [f.to_dict() for f in self.families],
                "n_terms": len(self.terms), "signature": self.signature}

    @staticmethod
    def from_dict(d: dict) -> FeatureSet:
        try:
            fs = FeatureSet([Family.from_dict(f) for f in d["families"]],
                            name=d.get("name", "custom"), preset=d.get("preset"))
        except KeyError as exc:
            raise CalibrationInputError(f"feature set description lacks {exc}") from exc
        if "signature" in d and d["signature"] != fs.signature:
            raise CalibrationInputError(
                f"feature set {fs.name!r}: stored signature {d['signature']} does not match "
                f"its families ({fs.signature}); the description was edited or is corrupt")
        return fs

    def subset(self, family_names, name: str) -> FeatureSet:
        fams = [f for f in self.families if f.name in set(family_names)]
        return FeatureSet(fams, name=name, preset=self.preset)

    def __repr__(self):
        return (f"FeatureSet({self.name!r}, {len(self)} terms: "
                + ", ".join(f"{f.name} {len(f)}" for f in self.families) + ")")


# ----- presets --------------------------------------------------------------------------

def thermal_preset(sensors) -> FeatureSet:
    """The first paper's set: 19 geometric (q), each temperature, geometric x temperature,
    first and second derivatives of each temperature.  9 sensors -> 217 terms."""
    sensors = list(sensors)
    if not sensors:
        raise CalibrationInputError("thermal preset: no temperature sensor given")
    geo = geometric(JOINT_INPUTS)
    temps = temperatures(sensors)
    return FeatureSet([geo, temps, Product(geo, temps, name="geometric x temperature"),
                       temperature_rates(sensors, 1), temperature_rates(sensors, 2)],
                      name="thermal", preset="thermal")


def force_preset() -> FeatureSet:
    """The second paper's set: 19 geometric (X, Y, Z), F, F^2, F^3, geometric x those: 79."""
    geo = geometric(CARTESIAN_INPUTS)
    f = force_powers(3)
    return FeatureSet([geo, f, Product(geo, f, name="geometric x force")],
                      name="force", preset="force")


def thermal_ladder(sensors) -> list[tuple[str, FeatureSet]]:
    """The first paper's ladder (its Fig. 11): geometric; Set A; Set B; Set C."""
    full = thermal_preset(sensors)
    rungs = [("geometric only", ["geometric"]),
             ("A: + temperatures", ["geometric", "temperatures"]),
             ("B: + temperature x geometric",
              ["geometric", "temperatures", "geometric x temperature"]),
             ("C: complete (+ derivatives)", [f.name for f in full.families])]
    return [(n, full.subset(f, n)) for n, f in rungs]


def force_ladder() -> list[tuple[str, FeatureSet]]:
    full = force_preset()
    return [("geometric only", full.subset(["geometric"], "geometric only")),
            ("with force terms", full)]


# ----- from a dataset table to base variables -------------------------------------------

def sensor_column(sensor: str) -> str:
    return f"T_{sensor}_C"


def temperature_variables(df: pd.DataFrame, sensors, needed: set[str], T_ref_K: float,
                          window_s: float, degree: int = 2,
                          session_col: str = "session") -> dict[str, np.ndarray]:
    """``T_<s>``, ``dT_<s>``, ``d2T_<s>`` arrays (SI) for the rows of ``df``.

    Derivatives are computed per session on the session's own stream, in time order, from
    the rows whose temperatures are all finite; rows with a NaN temperature get NaN.
    """
    cols = [sensor_column(s) for s in sensors]
    missing = [c for c in cols if c not in df.columns]
    if missing:
        raise MissingColumnsError(f"temperature column(s) {missing} not in the data; "
                                  f"temperature columns present: "
                                  f"{[c for c in df.columns if c.startswith('T_')]}")
    T = df[cols].to_numpy(dtype=float)
    out: dict[str, np.ndarray] = {}
    for j, s in enumerate(sensors):
        if f"T_{s}" in needed:
            out[f"T_{s}"] = (T[:, j] + ZERO_CELSIUS_K) - T_ref_K
    want_rates = any(f"dT_{s}" in needed or f"d2T_{s}" in needed for s in sensors)
    if not want_rates:
        return out
    d1 = np.full(T.shape, np.nan)
    d2 = np.full(T.shape, np.nan)
    t = df["t_s"].to_numpy(dtype=float)
    if session_col in df.columns:
        sessions = df[session_col].astype(str).to_numpy()
    else:
        warnings.warn(f"no {session_col!r} column: the temperature derivatives treat the whole "
                      "table as one stream in time order", MissingMetadataWarning, stacklevel=3)
        sessions = np.full(len(df), "all")
    ok = np.all(np.isfinite(T), axis=1) & np.isfinite(t)
    for sess in pd.unique(sessions):
        rows = np.flatnonzero((sessions == sess) & ok)
        if rows.size == 0:
            continue
        order = rows[np.argsort(t[rows], kind="stable")]
        a, b, _ = causal_derivatives(t[order], T[order], window_s=window_s, degree=degree)
        d1[order] = a
        d2[order] = b
    for j, s in enumerate(sensors):
        if f"dT_{s}" in needed:
            out[f"dT_{s}"] = d1[:, j]
        if f"d2T_{s}" in needed:
            out[f"d2T_{s}"] = d2[:, j]
    return out
