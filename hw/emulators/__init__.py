"""Emulators: one per instrument, each speaking its instrument's protocol on its own
pseudo-terminal (or TCP port), backed by any ``InstrumentSet`` (see base.py and lab.py)."""
