"""The diagnosis' results as typed objects: ``Diagnosis`` (what ``diagnose`` returns) and
``Candidate`` (one row of its ranking). Each is the JSON-ready mapping the command line prints
with ``--json`` (key by key as ``diagnose`` documents it), with the fields a researcher reads
most as attributes, a ``to_json`` and a ``repr`` that says what was found."""
from __future__ import annotations

from deltatwin.calibration.tables import strict_json


class Candidate(dict):
    """A library effect the model lacks, tried against the data: ``effect``,
    ``explained_fraction`` (of the validation residual), ``p_value`` (calibration F test),
    ``delta_bic``, ``p_validation``, ``significant`` and ``verdict`` (in words)."""

    effect = property(lambda self: self["effect"])
    explained_fraction = property(lambda self: self["explained_fraction"])
    p_value = property(lambda self: self["p_value"])
    delta_bic = property(lambda self: self["delta_bic"])
    p_validation = property(lambda self: self["p_validation"])
    significant = property(lambda self: bool(self["significant"]))
    verdict = property(lambda self: self.get("verdict", ""))

    def to_json(self, **kwargs) -> str:
        return strict_json(self, **kwargs)

    def decided_by(self) -> str:
        """What the row's verdict rests on, the rule's route (calibration/stats.py
        ``DecisionRule.routes``): "refit" (the model refitted with the candidate: significant
        through its refit's tests), "calibration" (its calibration test), "validation" (the
        calibration and validation tests combined), or "" (not significant, or failed)."""
        if not self.get("significant") or "failed" in self:
            return ""
        return self.get("decided_by", "")

    def table_figures(self) -> tuple[float, float, float, float]:
        """(explained fraction, validation error 90 % after (nm), calibration p, dBIC) of the
        tests the verdict rests on: a refit's where the refit decided, else the linearised
        candidate's; the table prints these beside the verdict, so the two agree."""
        if self.decided_by() == "refit":
            return (self["refit_explained_fraction"],
                    self.get("refit_val_err90_after_nm", self["val_err90_after_nm"]),
                    self["refit_p_value"], self["refit_delta_bic"])
        return (self["explained_fraction"], self["val_err90_after_nm"], self["p_value"],
                self["delta_bic"])

    def __repr__(self) -> str:
        return (f"Candidate({self.effect!r}, explains {100 * self.explained_fraction:.0f} %, "
                f"p {self.p_value:.2g}, significant {self.significant})")


class Diagnosis(dict):
    """``diagnose``'s result: ``effects`` (the model's), ``val_err90_nm`` (its validation
    error 90 %), ``ranking`` (Candidates, the significant first), ``missing_effect`` (the
    effect named, or None), ``at_floor`` (within the rule's at_floor of the floor, or None without one),
    ``floor_nm`` and ``unexplained`` (what the residual depends on when no effect is named)."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self["ranking"] = [c if isinstance(c, Candidate) else Candidate(c)
                           for c in self.get("ranking", [])]

    effects = property(lambda self: self["effects"])
    val_err90_nm = property(lambda self: self["val_err90_nm"])
    ranking = property(lambda self: self["ranking"])
    missing_effect = property(lambda self: self.get("missing_effect"))
    at_floor = property(lambda self: self.get("at_floor"))
    floor_nm = property(lambda self: self.get("floor_nm"))
    unexplained = property(lambda self: self.get("unexplained", {}))

    def to_json(self, **kwargs) -> str:
        return strict_json(self, **kwargs)

    def __repr__(self) -> str:
        found = (f"missing {self.missing_effect}" if self.missing_effect else
                 "no library effect significant")
        floor = {True: ", at the floor", False: ", above the floor"}.get(self.at_floor, "")
        return (f"Diagnosis({'+'.join(self.effects)}: validation error 90 % "
                f"{self.val_err90_nm:.1f} nm, {found}{floor})")
