"""The fitted physics model as tables a researcher reads, as statsmodels' results do: the
parameter table (value, unit, 1-sigma uncertainty, 95 % interval, prior, identified or not) and
the fit's summary, each with a text form (``str``), an HTML form (``_repr_html_``, shown by
Jupyter) and a JSON-ready form (``as_dict``, ``to_json``).

The 95 % interval is the value +- 1.96 standard uncertainties (a normal distribution of the
estimate). A parameter is *identified* when the directions the data determine hold at least
half of it (``identified_fraction`` >= 0.5, the fit's ``not_identifiable`` rule); an
undetermined one stays at its prior and its uncertainty is the prior's (its width, the effect
library's Parameter ``tolerance``): its interval says what the data did not tell.
"""
from __future__ import annotations

import html

import numpy as np

from deltatwin.calibration.tables import Table, number, strict_json

Z95 = 1.959963984540054        # the normal distribution's two-sided 95 % quantile
IDENTIFIED = 0.5               # identified_fraction at or above: the data determine it
COLUMNS = ("parameter", "value", "unit", "uncertainty", "ci95_low", "ci95_high", "prior",
           "prior_uncertainty", "identified")
HEADINGS = ("parameter", "value", "unit", "uncertainty (1 sigma)", "95 % interval",
            "prior (value +- 1 sigma)", "identified")


# the summary's header keys (those of the JSON form) as the text says them
HEADER_NAMES = {"n_parameters": "free parameters", "n_identified_directions":
                "identified directions", "n_evaluations": "model evaluations",
                "cal": "calibration error 90 % (nm)", "val": "validation error 90 % (nm)",
                "val_err90_nm": "validation error 90 %, all axes (nm)"}


def parameter_rows(parameters: list[dict], prior_sigma) -> list[dict]:
    """The table's rows from a fit's ``parameters_`` ({label, value, start, unit, uncertainty,
    identified_fraction}; ``start`` is the prior the undetermined directions are held at) and
    the prior's standard uncertainty of each parameter (its ``tolerance``, same unit)."""
    rows = []
    for p, s in zip(parameters, np.asarray(prior_sigma, dtype=float)):
        u = float(p["uncertainty"])
        rows.append({"parameter": p["label"], "value": float(p["value"]), "unit": p["unit"],
                     "uncertainty": u, "ci95_low": float(p["value"]) - Z95 * u,
                     "ci95_high": float(p["value"]) + Z95 * u, "prior": float(p["start"]),
                     "prior_uncertainty": float(s),
                     "identified": bool(p["identified_fraction"] >= IDENTIFIED),
                     "identified_fraction": float(p["identified_fraction"])})
    return rows


def parameter_cells(row: dict) -> list[str]:
    """One row of the parameter table as the text of its cells, in ``HEADINGS`` order."""
    return [row["parameter"], number(row["value"]), row["unit"], number(row["uncertainty"]),
            f"{number(row['ci95_low'])} .. {number(row['ci95_high'])}",
            f"{number(row['prior'])} +- {number(row['prior_uncertainty'])}",
            "yes" if row["identified"] else "undetermined"]


class ParameterTable(Table):
    """The fitted parameters, one row each (``records``: dicts with the keys of ``COLUMNS``
    and ``identified_fraction``), in SI units (the ``unit`` column)."""

    def __init__(self, rows: list[dict], title: str = "fitted parameters"):
        super().__init__(title, HEADINGS, rows, parameter_cells)

    def to_frame(self, index: str | None = "parameter"):
        return super().to_frame(index)


class FitSummary:
    """A fitted physics model's summary, as statsmodels' ``Summary``: ``str()`` the text,
    ``_repr_html_()`` the HTML, ``as_dict()`` the JSON-ready dict (``to_json()`` its text).

    ``header``: {name: value} of the fit's figures (what the text shows above the table),
    ``table``: the ParameterTable, ``details``: further JSON-ready results (identifiability,
    offsets, the values of every parameter) that only ``as_dict`` carries."""

    def __init__(self, header: dict, table: ParameterTable, details: dict):
        self.header = header
        self.table = table
        self.details = details

    def header_lines(self) -> list[tuple[str, str]]:
        out = []
        for key, value in self.header.items():
            if value is None:
                continue
            if isinstance(value, dict):
                value = ", ".join(f"{k} {number(v)}" for k, v in value.items())
            elif isinstance(value, float):
                value = number(value)
            elif isinstance(value, list):
                value = ", ".join(map(str, value)) or "none"
            out.append((HEADER_NAMES.get(key, key.replace("_", " ")), str(value)))
        return out

    def __str__(self) -> str:
        width = max((len(k) for k, _ in self.header_lines()), default=0)
        head = [f"{k:<{width}}  {v}" for k, v in self.header_lines()]
        return "\n".join(["physics model fit", *head, "", str(self.table)])

    def _repr_html_(self) -> str:
        rows = "".join(f"<tr><th>{html.escape(k)}</th><td>{html.escape(v)}</td></tr>"
                       for k, v in self.header_lines())
        return (f"<table><caption>physics model fit</caption>{rows}</table>"
                + self.table._repr_html_())

    def as_dict(self) -> dict:
        return {**self.header, **self.details, "parameter_table": self.table.as_dict()}

    def to_json(self, **kwargs) -> str:
        """Strict JSON (a figure that does not exist is null)."""
        return strict_json(self.as_dict(), **kwargs)

    def __getitem__(self, key):
        """``summary()[key]``: the dict form's entries."""
        return self.as_dict()[key]


def correlation_matrix(covariance: np.ndarray) -> np.ndarray:
    """The correlation matrix of a covariance (symmetric to round-off: made exactly so), 1 on
    the diagonal; 0 off it for a parameter of zero variance."""
    cov = 0.5 * (covariance + covariance.T)
    sigma = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    scale = np.outer(sigma, sigma)
    c = np.divide(cov, scale, out=np.zeros_like(cov), where=scale > 0)
    np.fill_diagonal(c, 1.0)
    return np.clip(c, -1.0, 1.0)


def summary_of(fit) -> FitSummary:
    """The summary of a fitted PhysicsFit (or one read back with ``PhysicsFit.load``: its
    figures as the file recorded them)."""
    ident = fit.identifiability_
    header = {"effects": list(fit.effects), "n_parameters": fit.model_.n_free,
              "n_identified_directions": ident["n_identified_directions"],
              "converged": fit.converged_, "status": fit.status_,
              "n_evaluations": fit.n_evaluations_,
              "cal": {k: v["err_p90"] for k, v in fit.cal_.items()},
              "val": {k: v["err_p90"] for k, v in fit.val_.items()},
              "val_err90_nm": fit.val_.get("all", {}).get("err_p90")}
    meas = getattr(fit, "measurements_", None)     # a fit read back from its file has none
    details = {"offsets_nm": {f"{s}.{a}": o * 1e9 for (s, a), o in
                              zip(meas.groups, fit.offsets_)} if meas is not None else None,
               "identifiability": ident, "parameters": fit.parameters_,
               "values": fit.model_.values()}
    if fit.parameters_ is None:          # a file written before the uncertainties were saved
        table = ParameterTable([], "fitted parameters: their file holds no uncertainties")
    else:
        table = ParameterTable(parameter_rows(fit.parameters_, fit.model_.tolerances))
    return FitSummary(header, table, details)
