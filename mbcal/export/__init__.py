"""Writing calibrated models: the .mdl text with estimates as nominal values, calibrated URDFs."""
