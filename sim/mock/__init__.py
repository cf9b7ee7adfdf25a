"""The mock autopilot: a strict ArduCopter stand-in (its boot, streams, commands, defects) and the vehicle models it flies."""
