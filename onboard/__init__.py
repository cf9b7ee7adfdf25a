"""Passive Monitor: the flight software (functional core in ``onboard.core``, shell around it)."""
