"""Planning a campaign before the laboratory: sweeps of simulated campaigns (simulate -> fit ->
diagnose), detection power, pose selection and uncertainty budgets."""
