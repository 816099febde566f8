"""How we learn from data. Two paths and the diagnosis that joins them:

* ``blackbox/``: the papers' path: feature families, MATLAB-compatible stepwise regression,
  the DGM per axis, its inverse (IGM), the direct IGM per motor, validation and the ladder;
* ``physics/``: physics models made of the twin's own effects, fitted to measurements, with an
  identifiability report;
* ``diagnosis/``: compare a model with measurements, rank what is missing, the report.

``errors`` and ``metrics`` are shared by all three (see docs/architecture.md)."""
