"""Shipped scenarios: declarative TOML files read through importlib.resources (twin.scenario)."""
