"""Calibrated models: DGM per axis (first paper), IGM by Newton-Raphson on the DGM, direct IGM
per motor (second paper), and their JSON export / load.

Estimators follow scikit-learn's shape: parameters are given to the constructor and checked
there, ``fit(df)`` learns from a dataset table (docs/data-format.md) and sets attributes
ending in ``_``, ``predict(df)`` returns SI arrays.

* :class:`DGM` — ``reading_axis = f(q1, q2, q3, temperatures, their derivatives)``, one
  stepwise fit per measured axis, on the rows where that axis was measured (``x_nm``, ``y_nm``
  in the ``xy`` session, ``z_nm`` in the ``z`` session), calibration split only.
* :class:`IGM` — the controller's model: position + temperatures -> motor coordinates,
  by vectorised Newton-Raphson on a fitted DGM; each point converges to ``tol_m`` or is
  reported as not converged.
* :class:`DirectIGM` — ``q_i = f(X, Y, Z, F)``, one stepwise fit per motor.

A fitted model is a list of :class:`OutputModel` (one per axis or motor): the kept terms,
their coefficients in SI, the intercept, and the standardisation used for the regression.
Every prediction goes through one evaluator that factorises each term into a geometric
monomial times an auxiliary monomial (temperatures, rates, force), so the IGM's Newton
iterations only re-evaluate the <= 20 geometric monomials.
"""
