"""Comparing a model with measurements and finding what is missing: where it fails (compare),
which library effect it lacks or which variable its residual follows (diagnose), the achievable
floor, extrapolation, and the report."""
