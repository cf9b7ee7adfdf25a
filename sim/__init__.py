"""Simulation side of pmon, a folder per role:

  mock/        the mock autopilot (a strict ArduCopter stand-in) and the vehicle models it flies
  firmware/    ArduPilot's and PX4's own SITL, and every simulated program, as child processes
  truth/       the simulated world: true targets, their kinds of motion, DF sensors, generated worlds
  evaluation/  the Monte Carlo evaluation (pmon eval): trials, methods, metrics, bounds, figures
  stack/       the SITL stack on loopback: the rig, the demo, DF feeds, proxies, recordings
  verbs.py     the pmon verbs of this side (demo, simulate, eval, worlds, feed)
"""
