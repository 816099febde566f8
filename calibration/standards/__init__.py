"""Acceptance tests in the language of the trade, evaluated from readings (the figures in
pure numpy):

* ``iso230_2``: ISO 230-2 positioning accuracy and repeatability of a linear axis;
* ``iso9283``: ISO 9283 pose accuracy AP and pose repeatability RP (and their drift);
* ``iso230_3``: ISO 230-3 environmental temperature variation error (ETVE) and its relation
  to the room's temperature;
* ``uncertainty``: expanded uncertainties (k = 2) of the figures from the instruments'
  specifications (ISO/TR 230-9 spirit) and ISO 14253-1 conformance with a guard band;
* ``gaussian``: what the repeatability figures are for Gaussian reading noise alone;
* ``campaign``: a standard test's campaign (``twin.standard_tests``) evaluated from its dataset;
* ``report``: the figures' table, the Markdown report and its figures.

The plans that measure them are ``twin.standard_tests``. Inside: SI (m, s, degC); nm and um
only in the summaries and the JSON (names carry the unit).
"""
