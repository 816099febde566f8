"""Physics models fitted to measurements: the twin's own effects, evaluated on the conditions the
data recorded, with their free parameters found by nonlinear least squares.

A physics model is a list of effects from the library (twin/effects/). Its prediction of an
interferometer reading runs the twin's stages (twin/world.py: robot -> part temperatures ->
exact kinematics -> load through the compliance -> optics) on conditions taken from the data:
motor coordinates, coil currents and the temperature sensors (each sensor stands for the part it
is glued on, ``metadata['sensors']``; a part without a sensor takes the mean of its sensed
siblings — arm1..3, rod1..3, ... — or the reference temperature). Readings are relative to each
session's zero, as the interferometer counts it: (n s - n0 s0) / n_comp, where n0 s0 is the optical
path at the zero (the robot at home, coils off, the conditions of the session's first row). The
zero's path is a constant, but divided by the compensation index it is not: that is the dead-path
error of an index change, hundreds of nm per kelvin on a 0.1 m dead path, so the model evaluates
the zero too. What remains is an unknown offset per (session, axis): it is projected out of the
fit (variable projection) and estimated on the calibration rows. Cosine-corrected data are
compared with the model's reading put through the same correction (deltatwin.twin.instruments.optics:
cosine_correction) with the measured angles.

The fit (``PhysicsFit``, scikit-learn style: ``fit`` then attributes ending in ``_``) works in
parameter units scaled by each parameter's ``fit_scale`` (its typical size): the Jacobian is
exact to ~1e-7 (the kinematics' pose derivative by the implicit function theorem at each point's
thermally corrected geometry, Richardson-extrapolated central differences elsewhere; checked
against central differences in tests); its singular value decomposition says which parameter
combinations the data determine to better than ``identifiable_ratio`` of their typical size,
given the readings' noise. Only those are fitted (a trust-region Gauss-Newton re-using its
Jacobian while steps succeed, stopping when the step left, by an exact Jacobian, moves the
parameters by less than 0.1 of their uncertainty); the others
stay at their prior and are named in the identifiability report, never fitted to noise. A model
that lacks an effect fits badly: it returns its best fit with ``converged_`` and ``status_``
and a logged warning, never an error. Units: SI inside (m, rad, K), nm in reports.
"""
