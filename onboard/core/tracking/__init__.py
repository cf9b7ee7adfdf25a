"""Tracking: the particle filter, the targets' intents and the particle steering of the prediction."""
