"""Finding, naming and fitting what the model misses, from falcon logs."""
