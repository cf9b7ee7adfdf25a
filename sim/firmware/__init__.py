"""The real firmware's SITL (ArduPilot, PX4) and every simulated program as child processes at the scheduling the product documents."""
