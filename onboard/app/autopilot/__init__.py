"""The autopilot side: which firmware it is, what it reports, the pose and clock taken from it, and what is sent it to fly (setpoints, the launch)."""
