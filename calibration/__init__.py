"""Calibration: feature families, MATLAB-compatible stepwise regression, DGM / IGM models,
validation figures and the papers' ladder (see docs/calibration.md)."""
from deltatwin.calibration.blackbox.stepwise import StepwiseResult, stepwisefit

__all__ = ["stepwisefit", "StepwiseResult"]
