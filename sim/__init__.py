"""Simulation side of pmon: truth world, sensor feed, mock autopilot, evaluation."""
