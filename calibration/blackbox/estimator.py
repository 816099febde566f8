"""The stepwise estimator shared by the DGM and the direct IGM: one stepwise fit per output on a
feature set, the fitted outputs (kept terms, coefficients in SI, standardisation), one evaluator
for every prediction, and the JSON form of a fitted model."""
from __future__ import annotations

import json
import math
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from deltatwin.calibration.blackbox.features import (
    CARTESIAN_INPUTS,
    DEFAULT_T_REF_K,
    JOINT_INPUTS,
    FeatureSet,
    Term,
    temperature_variables,
    term_matrix,
    variable_unit,
)
from deltatwin.calibration.blackbox.stepwise import PENTER_DEFAULT, resolve_thresholds, stepwisefit
from deltatwin.calibration.errors import (
    CalibrationInputError,
    DroppedRowsWarning,
    MissingColumnsError,
    MissingMetadataWarning,
    ModelFileError,
    TooFewPointsError,
)
from deltatwin.calibration.stats import sandwich_covariance
from deltatwin.calibration.streams import DEFAULT_WINDOW_S
from deltatwin.files import CONTENT_SHA256, atomic_write_text, content_sha256

MODEL_FORMAT = "deltatwin-calibration-model"
# 2: the file carries content_sha256 (deltatwin.files), checked on reading; 1 is still read
MODEL_FORMAT_VERSION = 2
NM = 1e-9
AXIS_COLUMNS = {"x": "x_nm", "y": "y_nm", "z": "z_nm"}
MOTOR_COLUMNS = {"q1": "q1_rad", "q2": "q2_rad", "q3": "q3_rad"}
_CARTESIAN_COLUMN = {"X": "x_nm", "Y": "y_nm", "Z": "z_nm"}



def thermal_sensors(df: pd.DataFrame, meta: dict | None, sensors=None) -> list[str]:
    """The temperature sensors of the thermal preset.

    An explicit list wins (each must have a ``T_<name>_C`` column).  Otherwise the sensors of
    ``meta['sensors']`` whose part is not air (``air``, or an air volume such as the twin's
    ``air_x``: the first paper's 9 of 11), in table order.
    Without that metadata: every ``T_*_C`` column whose name does not start with ``air``,
    with a :class:`MissingMetadataWarning` naming the choice.
    """
    present = [c[2:-2] for c in df.columns if c.startswith("T_") and c.endswith("_C")]
    if sensors is not None:
        sensors = list(sensors)
        missing = [s for s in sensors if s not in present]
        if missing:
            raise MissingColumnsError(f"temperature sensor(s) {missing} asked for but their "
                                      f"column(s) {[f'T_{s}_C' for s in missing]} are not in "
                                      f"the data; sensors present: {present}")
        if not sensors:
            raise CalibrationInputError("the explicit temperature sensor list is empty")
        return sensors
    parts = (meta or {}).get("sensors")
    if isinstance(parts, dict) and parts:
        chosen = [s for s in present if s in parts and not str(parts[s]).lower().startswith("air")]
        unknown = [s for s in present if s not in parts]
        if unknown:
            warnings.warn(f"temperature column(s) {[f'T_{s}_C' for s in unknown]} have no entry "
                          "in metadata 'sensors' and are not used", MissingMetadataWarning,
                          stacklevel=3)
    else:
        chosen = [s for s in present if not s.lower().startswith("air")]
        warnings.warn("no 'sensors' metadata: using every temperature column whose name does "
                      f"not start with 'air' as a structure sensor: {chosen}",
                      MissingMetadataWarning, stacklevel=3)
    if not chosen:
        raise MissingColumnsError(f"no structure temperature sensor in the data (temperature "
                                  f"sensors present: {present}); the thermal features need "
                                  "at least one")
    return chosen


# ----- one fitted output -------------------------------------------------------------

@dataclass
class OutputModel:
    """One fitted output (an axis reading or a motor coordinate)."""
    output: str                 # "x" / "q1"
    unit: str                   # SI unit of the output
    column: str                 # dataset column it is fitted to
    column_to_si: float         # factor from the column's unit to SI
    terms: list[Term]           # kept terms
    coef: np.ndarray            # SI coefficients of the kept terms
    intercept: float
    term_mean: np.ndarray       # standardisation of the kept terms (for the record)
    term_std: np.ndarray
    y_mean: float
    y_std: float
    n_cal: int = 0
    rmse: float = math.nan
    n_candidates: int = 0
    steps: list = field(default_factory=list)   # [(action, term name), ...]
    # the kept terms' standard errors (SI, as coef) and p-values (t test, dfe degrees of
    # freedom), as stepwisefit reports them; None for a model saved before they were kept
    se: np.ndarray | None = None
    p_value: np.ndarray | None = None
    dfe: int = 0
    # the kept terms' coefficients' covariance ((k, k), SI as coef): the sandwich with the
    # calibration residual's serial correlation (calibration/stats.py sandwich_covariance),
    # what a prediction band draws from; None for a model saved before it was kept
    covariance: np.ndarray | None = None

    @property
    def terms_kept(self) -> int:
        return len(self.terms)

    @property
    def coef_standardized(self) -> np.ndarray:
        return self.coef * self.term_std / self.y_std

    def term_matrix(self, values: dict[str, np.ndarray]) -> np.ndarray:
        """(n, k): the kept terms evaluated on base variables ``values`` (SI arrays)."""
        return term_matrix(self.terms, values)

    def to_dict(self) -> dict:
        return {"output": self.output, "unit": self.unit, "column": self.column,
                "column_to_si": self.column_to_si,
                "terms": [{"name": t.name, "factors": t.to_list()} for t in self.terms],
                "coef": [float(c) for c in self.coef], "intercept": float(self.intercept),
                "scaling": {"term_mean": [float(v) for v in self.term_mean],
                            "term_std": [float(v) for v in self.term_std],
                            "y_mean": float(self.y_mean), "y_std": float(self.y_std),
                            "coef_standardized": [float(v) for v in self.coef_standardized]},
                "terms_kept": self.terms_kept, "n_cal": int(self.n_cal),
                "rmse": float(self.rmse) if math.isfinite(self.rmse) else None,
                "n_candidates": int(self.n_candidates),
                "steps": [[a, n] for a, n in self.steps],
                **({} if self.se is None else
                   {"se": _finite_or_none(self.se), "p_value": _finite_or_none(self.p_value),
                    "dfe": int(self.dfe)}),
                **({} if self.covariance is None else
                   {"covariance": [[float(v) for v in row] for row in self.covariance]})}

    def coefficient_rows(self) -> list[dict]:
        """The kept terms as stepwisefit lists them: term, coefficient, its unit (SI), standard
        error, t statistic and p-value (None where the model file has none)."""
        se = self.se if self.se is not None else np.full(len(self.terms), np.nan)
        p = self.p_value if self.p_value is not None else np.full(len(self.terms), np.nan)
        rows = []
        for k, t in enumerate(self.terms):
            rows.append({"term": t.name, "coefficient": float(self.coef[k]),
                         "unit": coefficient_unit(self.unit, t),
                         "se": _finite_or_none([se[k]])[0],
                         "t": _finite_or_none([self.coef[k] / se[k] if se[k] > 0
                                               else np.nan])[0],
                         "p_value": _finite_or_none([p[k]])[0]})
        return rows

    @staticmethod
    def from_dict(d: dict) -> OutputModel:
        try:
            terms = [Term.from_list(t["factors"]) for t in d["terms"]]
            for t, td in zip(terms, d["terms"]):
                if td.get("name", t.name) != t.name:
                    raise ModelFileError(f"output {d['output']!r}: term name {td['name']!r} "
                                         f"does not match its factors ({t.name})")
            sc = d["scaling"]
            om = OutputModel(
                output=str(d["output"]), unit=str(d["unit"]), column=str(d["column"]),
                column_to_si=float(d["column_to_si"]), terms=terms,
                coef=np.array(d["coef"], dtype=float), intercept=float(d["intercept"]),
                term_mean=np.array(sc["term_mean"], dtype=float),
                term_std=np.array(sc["term_std"], dtype=float),
                y_mean=float(sc["y_mean"]), y_std=float(sc["y_std"]),
                n_cal=int(d.get("n_cal", 0)),
                rmse=math.nan if d.get("rmse") is None else float(d["rmse"]),
                n_candidates=int(d.get("n_candidates", 0)),
                steps=[tuple(s) for s in d.get("steps", [])],
                se=_optional_array(d.get("se")), p_value=_optional_array(d.get("p_value")),
                dfe=int(d.get("dfe", 0)),
                covariance=(None if d.get("covariance") is None
                            else np.array(d["covariance"], dtype=float).reshape(
                                len(d["terms"]), len(d["terms"]))))
        except (KeyError, TypeError, ValueError) as exc:
            if isinstance(exc, ModelFileError):
                raise
            raise ModelFileError(f"output entry is malformed ({type(exc).__name__}: {exc})") \
                from exc
        n = len(om.terms)
        if not (om.coef.shape == om.term_mean.shape == om.term_std.shape == (n,)):
            raise ModelFileError(f"output {om.output!r}: {n} terms but {om.coef.size} "
                                 f"coefficients / {om.term_mean.size} scalings")
        if not (np.all(np.isfinite(om.coef)) and math.isfinite(om.intercept)):
            raise ModelFileError(f"output {om.output!r}: non-finite coefficient")
        for name in ("se", "p_value"):
            v = getattr(om, name)
            if v is not None and v.shape != (n,):
                raise ModelFileError(f"output {om.output!r}: {n} terms but {v.size} {name} "
                                     "values")
        if om.covariance is not None and not (
                np.all(np.isfinite(om.covariance))
                and np.allclose(om.covariance, om.covariance.T, rtol=1e-12, atol=0.0)
                and np.all(np.diag(om.covariance) >= 0)):
            raise ModelFileError(f"output {om.output!r}: its covariance is not a finite "
                                 "symmetric matrix with a non-negative diagonal")
        return om


def p_value_text(p: float | None) -> str:
    """A p-value as a table shows it: 3 significant digits, below double precision's
    smallest number as such."""
    if p is None:
        return "-"
    return "< 1e-300" if p == 0 else f"{p:.3g}"


def _finite_or_none(values) -> list:
    """Numbers as JSON takes them: NaN and infinities as None."""
    return [float(v) if v is not None and math.isfinite(v) else None for v in values]


def _optional_array(values) -> np.ndarray | None:
    """A saved list of numbers (None entries: NaN) as an array; None stays None."""
    if values is None:
        return None
    return np.array([math.nan if v is None else v for v in values], dtype=float)


def coefficient_unit(output_unit: str, term: Term) -> str:
    """The SI unit of a term's coefficient: the output's unit over the term's
    (``m/(rad^2*K)``)."""
    powers: dict[str, int] = {}
    for v, p in term.factors:
        powers[variable_unit(v)] = powers.get(variable_unit(v), 0) + p
    parts = [u if p == 1 else f"({u})^{p}" if "/" in u else f"{u}^{p}" for u, p in powers.items()]
    unit = "*".join(parts)
    return f"{output_unit}/({unit})" if len(parts) > 1 else f"{output_unit}/{unit}"


# ----- evaluator ---------------------------------------------------------------------

class _Evaluator:
    """sum_o = sum over (aux monomial a, geometric monomial g) W[o, a, g] * aux_a * geo_g."""

    def __init__(self, outputs: list[OutputModel], geo_inputs: tuple[str, ...]):
        self.geo_inputs = tuple(geo_inputs)
        gi = {v: i for i, v in enumerate(self.geo_inputs)}
        aux_vars: dict[str, None] = {}
        for om in outputs:
            for t in om.terms:
                for v in t.variables:
                    if v not in gi:
                        aux_vars.setdefault(v, None)
        self.aux_vars = tuple(aux_vars)
        ai = {v: i for i, v in enumerate(self.aux_vars)}
        geo_monos = {(0,) * len(gi): 0}
        aux_monos = {(0,) * len(ai): 0}
        entries = []
        for o, om in enumerate(outputs):
            entries.append((o, aux_monos[(0,) * len(ai)], 0, om.intercept))
            for t, c in zip(om.terms, om.coef):
                ge = [0] * len(gi)
                ae = [0] * len(ai)
                for v, p in t.factors:
                    if v in gi:
                        ge[gi[v]] += p
                    else:
                        ae[ai[v]] += p
                g = geo_monos.setdefault(tuple(ge), len(geo_monos))
                a = aux_monos.setdefault(tuple(ae), len(aux_monos))
                entries.append((o, a, g, float(c)))
        self.geo_exp = np.array(list(geo_monos), dtype=int).reshape(len(geo_monos), len(gi))
        self.aux_exp = np.array(list(aux_monos), dtype=int).reshape(len(aux_monos), len(ai))
        W = np.zeros((len(outputs), len(aux_monos), len(geo_monos)))
        for o, a, g, c in entries:
            W[o, a, g] += c
        self.W = W
        self.max_pow = int(self.geo_exp.max()) if self.geo_exp.size else 0
        # (geometric monomial, input) pairs with a non-zero derivative: e * g^(e-1) * rest
        self.grad_pairs = [(gidx, j) for gidx in range(self.geo_exp.shape[0])
                           for j in range(len(gi)) if self.geo_exp[gidx, j] > 0]
        self.W2 = np.ascontiguousarray(
            W.transpose(0, 2, 1).reshape(len(outputs) * len(geo_monos), len(aux_monos)))

    # Arrays are laid out (items, points): every operation is a contiguous vector op.
    def aux_matrix(self, aux: dict[str, np.ndarray], n: int) -> np.ndarray:
        """H (n_aux_monomials, n)."""
        H = np.ones((self.aux_exp.shape[0], n))
        for k, v in enumerate(self.aux_vars):
            if v not in aux:
                raise MissingColumnsError(f"the model needs variable {v!r} "
                                          f"({variable_unit(v)}), not given")
            x = np.asarray(aux[v], dtype=float).reshape(-1)
            if x.size == 1 and n != 1:
                x = np.full(n, x.item())
            if x.size != n:
                raise CalibrationInputError(f"variable {v!r} has {x.size} values for {n} points")
            e = self.aux_exp[:, k]
            for p in np.unique(e[e > 0]):
                H[e == p] *= x**p
        return H

    def coefficients(self, aux: dict[str, np.ndarray], n: int) -> np.ndarray:
        """C (n_out, n_geo, n): per-point coefficients of the geometric monomials."""
        H = self.aux_matrix(aux, n)
        return (self.W2 @ H).reshape(self.W.shape[0], self.W.shape[2], n)

    def _powers(self, g: np.ndarray):
        """pw[j][e] = g[j]**e, for the inputs g (d, n)."""
        pw = []
        for j in range(g.shape[0]):
            row = [None, g[j]]
            for _ in range(2, self.max_pow + 1):
                row.append(row[-1] * g[j])
            pw.append(row)
        return pw

    def _monomial(self, pw, exps, n, skip=-1):
        out = None
        for j, e in enumerate(exps):
            if e == 0 or j == skip:
                continue
            out = pw[j][e] if out is None else out * pw[j][e]
        return out

    def value(self, C: np.ndarray, g: np.ndarray) -> np.ndarray:
        """Outputs (n_out, n) for per-point coefficients C and inputs g (d, n)."""
        n = g.shape[1]
        pw = self._powers(g)
        f = C[:, 0, :].copy()                    # monomial 0 is the constant
        for gidx in range(1, self.geo_exp.shape[0]):
            f += C[:, gidx, :] * self._monomial(pw, self.geo_exp[gidx], n)
        return f

    def value_and_jacobian(self, C, g):
        """(f (n_out, n), J (n_out, d, n))."""
        n = g.shape[1]
        d = g.shape[0]
        pw = self._powers(g)
        f = C[:, 0, :].copy()
        for gidx in range(1, self.geo_exp.shape[0]):
            f += C[:, gidx, :] * self._monomial(pw, self.geo_exp[gidx], n)
        J = np.zeros((C.shape[0], d, n))
        for gidx, j in self.grad_pairs:
            e = int(self.geo_exp[gidx, j])
            rest = self._monomial(pw, self.geo_exp[gidx], n, skip=j)
            dm = pw[j][e - 1] if e > 1 else None
            if dm is None:
                dm = rest if rest is not None else 1.0
            elif rest is not None:
                dm = dm * rest
            J[:, j, :] += C[:, gidx, :] * (e * dm if e > 1 else dm)
        return f, J


def solve3(J: np.ndarray, r: np.ndarray):
    """Solve J x = r for stacks laid out J (3, 3, n), r (3, n) by cofactors; also det."""
    a, b, c = J[0]
    d, e, f = J[1]
    g, h, i = J[2]
    A = e * i - f * h
    B = f * g - d * i
    Cc = d * h - e * g
    det = a * A + b * B + c * Cc
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / det
        x0 = (A * r[0] + (c * h - b * i) * r[1] + (b * f - c * e) * r[2]) * inv
        x1 = (B * r[0] + (a * i - c * g) * r[1] + (c * d - a * f) * r[2]) * inv
        x2 = (Cc * r[0] + (b * g - a * h) * r[1] + (a * e - b * d) * r[2]) * inv
    return np.stack([x0, x1, x2]), det


# ----- shared estimator machinery ------------------------------------------------------

class StepwiseModel:
    """Shared by DGM and DirectIGM: features -> per-output stepwise fits."""
    kind = "?"
    geo_inputs: tuple[str, ...] = ()
    preset_name = "?"
    output_columns: dict[str, str] = {}    # output name -> its data column
    output_noun = "output(s)"               # what the outputs are, for error messages

    def __init__(self, features=None, *, sensors=None, penter=PENTER_DEFAULT,
                 premove=None, maxiter=None, window_s: float = DEFAULT_WINDOW_S,
                 T_ref_K: float = DEFAULT_T_REF_K, outputs=None, min_rows_margin: int = 2):
        if features is None:
            features = self.preset_name
        if isinstance(features, str):
            if features not in ("preset", self.preset_name):
                raise CalibrationInputError(f"{self.kind}: features {features!r} unknown; use "
                                            f"{self.preset_name!r} or a FeatureSet")
        elif not isinstance(features, FeatureSet):
            raise CalibrationInputError(f"{self.kind}: features must be a preset name or a "
                                        f"FeatureSet, got {type(features).__name__}")
        self.features = features
        self.sensors = None if sensors is None else list(sensors)
        self.penter, self.premove = resolve_thresholds(penter, premove)
        self.maxiter = maxiter
        if not (window_s > 0):
            raise CalibrationInputError(f"{self.kind}: window_s = {window_s} must be > 0")
        if not (T_ref_K > 0):
            raise CalibrationInputError(f"{self.kind}: T_ref_K = {T_ref_K} must be > 0 K")
        self.window_s = float(window_s)
        self.T_ref_K = float(T_ref_K)
        self.outputs = None if outputs is None else list(outputs)
        if self.outputs is not None:
            bad = [o for o in self.outputs if o not in self.output_columns]
            if bad:
                raise CalibrationInputError(f"{self.kind}: unknown {self.output_noun} {bad}; "
                                            f"use {', '.join(self.output_columns)}")
        self.min_rows_margin = int(min_rows_margin)

    # -- to override
    def _output_specs(self, df) -> list[tuple[str, str, str, float]]:
        raise NotImplementedError

    def _default_features(self, sensors) -> FeatureSet:
        raise NotImplementedError

    # -- features and variables
    def _resolve_features(self, df, meta):
        if isinstance(self.features, FeatureSet):
            fs = self.features
            sens = []
            for v in fs.variables:
                for pre in ("d2T_", "dT_", "T_"):
                    if v.startswith(pre):
                        s = v[len(pre):]
                        if s not in sens:
                            sens.append(s)
                        break
            if self.sensors is not None and set(self.sensors) != set(sens):
                raise CalibrationInputError(f"{self.kind}: sensors {self.sensors} differ from "
                                            f"those of the feature set {sens}")
            if sens:
                thermal_sensors(df, meta, sens)          # their columns must be present
            return fs, sens
        sens = self._sensors_for(df, meta)
        return self._default_features(sens), sens

    def _sensors_for(self, df, meta):
        return []

    def variables(self, df: pd.DataFrame) -> dict[str, np.ndarray]:
        """Base variables (SI) of every row of ``df`` needed by the fitted model."""
        self._check_fitted()
        return base_variables(df, self.variables_needed_, self.sensors_, self.T_ref_K,
                               self.window_s)

    def _check_fitted(self):
        if not hasattr(self, "outputs_"):
            raise CalibrationInputError(f"{self.kind} is not fitted: call fit(df) or load_model()")

    # -- fit
    def fit(self, df: pd.DataFrame, meta: dict | None = None, split: str | None = "cal"):
        """Fit one stepwise model per output on the rows of ``split`` (None: all rows).

        Temperature derivatives are computed on the whole table (each session's full
        stream), as a controller sees it, before the rows are selected.
        """
        if not isinstance(df, pd.DataFrame):
            raise CalibrationInputError(f"{self.kind}.fit expects a pandas DataFrame")
        from deltatwin.calibration.metrics import check_disjoint
        if "split" in df.columns:
            check_disjoint(df)
        fs, sens = self._resolve_features(df, meta)
        specs = self._output_specs(df)
        needed = fs.variables
        values = base_variables(df, needed, sens, self.T_ref_K, self.window_s)
        Xall = fs.matrix(values)
        if split is not None:
            if "split" not in df.columns:
                raise MissingColumnsError(f"{self.kind}.fit: split={split!r} asked but the "
                                          "table has no 'split' column")
            in_split = (df["split"].astype(str) == split).to_numpy()
        else:
            in_split = np.ones(len(df), bool)
        outputs = []
        # the residual's serial correlation is counted in time order
        times = (df["t_s"].to_numpy(dtype=float) if "t_s" in df.columns
                 else np.arange(len(df), dtype=float))
        sessions = (df["session"].astype(str).to_numpy() if "session" in df.columns
                    else np.full(len(df), "all"))
        for name, unit, column, to_si in specs:
            y = df[column].to_numpy(dtype=float) * to_si
            rows = in_split & np.isfinite(y)
            # a NaN reading in a session that measures this output is a lost reading
            measured = np.isin(sessions, np.unique(sessions[np.isfinite(y)]))
            lost = in_split & measured & ~np.isfinite(y)
            if lost.any():
                warnings.warn(f"{self.kind} output {name!r}: {int(lost.sum())} row(s) of a "
                              f"session that measures {column!r} have no value there and are "
                              "dropped", DroppedRowsWarning, stacklevel=2)
            okx = np.all(np.isfinite(Xall), axis=1)
            dropped = rows & ~okx
            if dropped.any():
                bad = [v for v in needed if not np.all(np.isfinite(values[v][dropped]))]
                warnings.warn(f"{self.kind} output {name!r}: {int(dropped.sum())} row(s) with "
                              f"NaN inputs dropped (NaN in {bad[:8]})", DroppedRowsWarning,
                              stacklevel=2)
            rows &= okx
            n = int(rows.sum())
            need = len(fs) + self.min_rows_margin
            if n < need:
                why = ""
                if dropped.any():
                    bad = [v for v in needed if not np.all(np.isfinite(values[v][dropped]))]
                    why = f", {int(dropped.sum())} more dropped for NaN in {bad[:8]}"
                raise TooFewPointsError(
                    f"{self.kind} output {name!r}: {n} usable calibration row(s){why}, for "
                    f"{len(fs)} candidate terms; at least {need} are needed "
                    f"(candidates + intercept + 1 residual degree of freedom)")
            res = stepwisefit(Xall[rows], y[rows], penter=self.penter, premove=self.premove,
                              maxiter=self.maxiter, names=fs.names)
            sel = np.flatnonzero(res.inmodel & ~res.aliased)
            outputs.append(OutputModel(
                output=name, unit=unit, column=column, column_to_si=to_si,
                terms=[fs.terms[j] for j in sel], coef=res.coef[sel].copy(),
                intercept=res.intercept, term_mean=res.x_mean[sel].copy(),
                term_std=res.x_std[sel].copy(), y_mean=res.y_mean, y_std=res.y_std,
                n_cal=n, rmse=res.rmse, n_candidates=len(fs),
                steps=[(h.action, h.name) for h in res.history],
                se=res.se[sel].copy(), p_value=res.pval[sel].copy(), dfe=res.dfe,
                covariance=_coefficient_covariance(Xall[rows][:, sel], y[rows], res, sel,
                                                   times[rows])))
            setattr(self, f"_stepwise_{name}", res)
        self.features_ = fs
        self.sensors_ = sens
        self._set_outputs(outputs)
        return self

    @classmethod
    def from_outputs(cls, features: FeatureSet, outputs: list[OutputModel], sensors=(),
                     **kw):
        """A fitted model from given outputs (terms and coefficients), e.g. for a
        controller or a test; every term must belong to ``features``."""
        obj = cls(features=features, sensors=list(sensors) or None, **kw)
        obj.features_ = features
        obj.sensors_ = list(sensors)
        obj._set_outputs(outputs, CalibrationInputError)
        return obj

    def stepwise_result(self, output: str):
        """The full :class:`StepwiseResult` of an output (after fit, not after load)."""
        return getattr(self, f"_stepwise_{output}")

    def _set_outputs(self, outputs, foreign_term_error: type[Exception] | None = None):
        """Install fitted outputs. With ``foreign_term_error`` (outputs given from outside: a
        file, a caller), first check that every term belongs to ``self.features_`` and raise
        that error class naming the output and the foreign terms otherwise."""
        if foreign_term_error is not None:
            cand = set(self.features_.names)
            for o in outputs:
                extra = [t.name for t in o.terms if t.name not in cand]
                if extra:
                    raise foreign_term_error(f"output {o.output!r}: term(s) {extra[:5]} not in "
                                             f"the feature set {self.features_.name!r}")
        self.outputs_ = list(outputs)
        self.output_names_ = [o.output for o in self.outputs_]
        vs: dict[str, None] = {}
        for v in self.geo_inputs:
            vs.setdefault(v, None)
        for o in self.outputs_:
            for t in o.terms:
                for v in t.variables:
                    vs.setdefault(v, None)
        self.variables_needed_ = list(vs)
        self._eval = _Evaluator(self.outputs_, self.geo_inputs)

    @property
    def terms_kept_(self) -> dict[str, int]:
        self._check_fitted()
        return {o.output: o.terms_kept for o in self.outputs_}

    def output(self, name: str) -> OutputModel:
        self._check_fitted()
        for o in self.outputs_:
            if o.output == name:
                return o
        raise CalibrationInputError(f"{self.kind} has no output {name!r}; it has "
                                    f"{self.output_names_}")

    # -- predict
    def _geo(self, values) -> np.ndarray:
        missing = [v for v in self.geo_inputs if v not in values]
        if missing:
            raise MissingColumnsError(f"{self.kind}: no values for input(s) {missing}")
        return np.vstack([np.asarray(values[v], dtype=float).reshape(-1)
                          for v in self.geo_inputs])

    def predict_values(self, values: dict[str, np.ndarray]) -> np.ndarray:
        """Predict from base variables (SI arrays): (n, n_outputs) in SI."""
        self._check_fitted()
        g = self._geo(values)
        C = self._eval.coefficients(values, g.shape[1])
        return self._eval.value(C, g).T

    def predict(self, df: pd.DataFrame) -> np.ndarray:
        """Predictions for every row of ``df``: (n, n_outputs) in SI (m or rad); NaN rows
        where an input is NaN."""
        self._check_fitted()
        return self.predict_values(self.variables(df))

    def targets(self, df: pd.DataFrame) -> np.ndarray:
        """Measured outputs of every row (SI), NaN where not measured."""
        self._check_fitted()
        cols = []
        for o in self.outputs_:
            if o.column not in df.columns:
                raise MissingColumnsError(f"{self.kind}: column {o.column!r} of output "
                                          f"{o.output!r} is not in the data")
            cols.append(df[o.column].to_numpy(dtype=float) * o.column_to_si)
        return np.column_stack(cols)

    def errors_m(self, df: pd.DataFrame) -> np.ndarray:
        """(n, n_outputs) the model's error on every row in metres: prediction minus
        reading (NaN where either is missing)."""
        return self.predict(df) - self.targets(df)

    def score(self, df: pd.DataFrame) -> float:
        """Minus the validation error 90 % in metres (higher is better, as scikit-learn's
        ``score``): the 90th percentile of |error| (``errors_m``) pooled over the outputs on
        the rows of ``df`` whose ``split`` is ``val`` (every row when there are none)."""
        e = self.errors_m(df)
        split = (df["split"].astype(str).to_numpy() if "split" in df.columns
                 else np.full(len(df), ""))
        rows = split == "val" if (split == "val").any() else np.ones(len(df), bool)
        e = np.abs(e[rows])
        e = e[np.isfinite(e)]
        if not e.size:
            raise CalibrationInputError(f"{self.kind}.score: no row with both a reading and a "
                                        "prediction")
        return -float(np.percentile(e, 90))

    def coefficient_table(self, output: str):
        """The kept terms of ``output`` as stepwisefit shows them (term, coefficient, unit,
        standard error, t, p-value): a table with text, HTML and ``as_dict`` forms."""
        from deltatwin.calibration.tables import Table, number
        o = self.output(output)
        title = (f"{self.kind} output {o.output} ({o.unit}): {o.terms_kept} of "
                 f"{o.n_candidates} candidate terms, intercept {number(o.intercept)} {o.unit}, "
                 f"RMSE {number(o.rmse)} {o.unit}, {o.n_cal} calibration rows")
        return Table(title, ("term", "coefficient", "unit", "std. error", "t", "p-value"),
                     o.coefficient_rows(),
                     lambda r: [r["term"], number(r["coefficient"]), r["unit"], number(r["se"]),
                                number(r["t"]), p_value_text(r["p_value"])])

    @classmethod
    def load(cls, path):
        """A model written by ``save`` (``deltatwin calibrate -o``), checked to be of this
        kind (calibration/blackbox/model_file.py ``load_model``)."""
        from deltatwin.calibration.blackbox.model_file import load_model
        return load_model(path, expect_kind=cls.kind)

    def __repr__(self) -> str:
        features = (self.features if isinstance(self.features, str)
                    else self.features.preset or self.features.name)
        if not hasattr(self, "outputs_"):
            return (f"{self.kind}(features={features!r}, penter={self.penter:g}, "
                    f"premove={self.premove:g}) (not fitted)")
        kept = ", ".join(f"{o.output} {o.terms_kept}" for o in self.outputs_)
        return (f"{self.kind}(features={features!r}, sensors={list(self.sensors_)}: "
                f"{len(self.features_)} candidate terms; terms kept {kept})")

    # -- export
    def to_dict(self) -> dict:
        self._check_fitted()
        inputs = {}
        for v in self.variables_needed_:
            inputs[v] = {"unit": variable_unit(v), **_input_source(v)}
        return {
            "format": MODEL_FORMAT, "format_version": MODEL_FORMAT_VERSION, "kind": self.kind,
            "features": self.features_.to_dict(),
            "candidate_terms": self.features_.names,
            "geometric_inputs": list(self.geo_inputs),
            "sensors": list(self.sensors_),
            "inputs": inputs,
            "temperature": {"reference_K": self.T_ref_K,
                            "meaning": "T_<s> = (T_<s>_C + 273.15) - reference_K, in K"},
            "derivatives": {"method": "causal trailing-window least-squares polynomial",
                            "degree": 2, "window_s": self.window_s,
                            "per": "session, time order, rows with finite temperatures"},
            "regression": {"method": "stepwisefit (MATLAB semantics)", "penter": self.penter,
                           "premove": self.premove},
            "evaluation": "output = intercept + sum_k coef_k * prod_(v,p) v**p over the "
                          "term's factors, variables in SI (see inputs)",
            "outputs": [o.to_dict() for o in self.outputs_],
        }

    def save(self, path) -> Path:
        """Write the model as JSON, atomically (temporary file, then rename)."""
        path = Path(path)
        d = self.to_dict()
        head = {"format": d.pop("format"), "format_version": d.pop("format_version")}
        d = {**head, CONTENT_SHA256: content_sha256({**head, **d}), **d}
        try:
            text = json.dumps(d, indent=1, allow_nan=False)   # strict JSON
        except ValueError as exc:
            raise CalibrationInputError(f"{self.kind}: the model holds a non-finite number "
                                        f"and cannot be exported ({exc})") from exc
        atomic_write_text(path, text)
        return path

    @classmethod
    def _from_dict(cls, d: dict):
        obj = cls(features=FeatureSet.from_dict(d["features"]), sensors=d.get("sensors"),
                  penter=d["regression"]["penter"], premove=d["regression"]["premove"],
                  window_s=d["derivatives"]["window_s"],
                  T_ref_K=d["temperature"]["reference_K"])
        obj.features_ = obj.features
        if d.get("candidate_terms") is not None and list(d["candidate_terms"]) != obj.features_.names:
            raise ModelFileError("the model's candidate term list does not match its feature "
                                 "families")
        obj.sensors_ = list(d.get("sensors") or [])
        obj._set_outputs([OutputModel.from_dict(o) for o in d["outputs"]], ModelFileError)
        return obj


def _coefficient_covariance(X: np.ndarray, y: np.ndarray, res, sel: np.ndarray,
                            t_s: np.ndarray) -> np.ndarray:
    """(k, k) SI: the covariance of the kept terms' coefficients (columns ``sel`` of the
    stepwise result ``res``, fitted to ``y`` on the candidate columns ``X`` (n, k) of rows
    taken at ``t_s``), the residual's serial correlation counted: a thermal model's misfit
    drifts over tens of readings, which stepwisefit's standard errors (independent residuals)
    do not see. Given the terms the stepwise kept: what their selection adds is not in it."""
    centred = X - X.mean(axis=0)
    r = y - res.intercept - X @ res.coef[sel]
    # in standardised columns: a cubic term's column in m^3 and a temperature's in K are
    # decades apart, and the sandwich's inverse in raw units loses the small ones
    scale = centred.std(axis=0)
    scale[scale == 0] = 1.0
    cov = sandwich_covariance(centred / scale, r, np.arange(y.size), t_s) / np.outer(scale, scale)
    return 0.5 * (cov + cov.T)


def _input_source(v: str) -> dict:
    if v in JOINT_INPUTS:
        return {"column": f"{v}_rad", "column_to_si": 1.0}
    if v in CARTESIAN_INPUTS:
        return {"column": _CARTESIAN_COLUMN[v], "column_to_si": NM}
    if v == "F":
        return {"column": "F_N", "column_to_si": 1.0}
    for pre, order in (("d2T_", 2), ("dT_", 1)):
        if v.startswith(pre):
            return {"derivative_of": f"T_{v[len(pre):]}", "order": order}
    if v.startswith("T_"):
        return {"column": f"{v}_C", "conversion": "degC + 273.15 - reference_K"}
    return {}


def base_variables(df, needed, sensors, T_ref_K, window_s) -> dict[str, np.ndarray]:
    needed = list(needed)
    out: dict[str, np.ndarray] = {}
    missing = []
    for v in needed:
        src = _input_source(v)
        col = src.get("column")
        if v in JOINT_INPUTS or v in CARTESIAN_INPUTS or v == "F":
            if col not in df.columns:
                missing.append(col)
            else:
                out[v] = pd.to_numeric(df[col], errors="coerce").to_numpy(dtype=float) \
                    * src["column_to_si"]
    if missing:
        raise MissingColumnsError(f"column(s) {missing} needed by the features are not in the "
                                  f"data; columns present: {list(df.columns)}")
    tv = [v for v in needed if v.startswith(("T_", "dT_", "d2T_"))]
    if tv:
        if "t_s" not in df.columns:
            raise MissingColumnsError("column 't_s' is needed for the temperature derivatives")
        out.update(temperature_variables(df, sensors, set(tv), T_ref_K, window_s))
    return out


# ----- DGM -------------------------------------------------------------------------------

