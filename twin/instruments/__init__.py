"""Instruments: the common interface (``interface``) and the twin's simulated implementations."""
