"""deltatwin: digital twin, synthetic data and calibration for the flexure-hinge Delta robot."""
__version__ = "0.1.0"
