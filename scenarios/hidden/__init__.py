"""Hidden-effect scenarios: a library effect the baseline model lacks, for the diagnosis."""
