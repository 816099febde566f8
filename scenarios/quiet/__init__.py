"""Quiet laboratories hiding one library effect (no climate or a mild one, steady pressure, a
sensor on every part): the building blocks of the unit tests, benchmarks and the walkthrough.
The papers' conditions are scenarios/hidden/."""
