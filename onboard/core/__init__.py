"""The functional core: pure numpy/scipy maths.

No sockets, clocks (timers are injected), threads, logging side effects or global RNG state here;
every random function takes a ``numpy.random.Generator``. SI units and radians throughout;
positions are in the ENU mission frame (x east, y north, z up), metres.

  monitor.py         one tick: scans in; estimates, target plans and the next UAV position out
  monitor_setup.py   what is static about a mission, built once from a scenario
  planner_choice.py  the UAV planner a setup names
  tracking/          the particle filter, the targets' intents, the particle steering
  planning/          where the UAV scans next: the greedy rule, the lookahead's routes, the planners
  guidance/          the targets' guidance, Problem P1
  the rest           the motion model, obstacles, bearings, DOA, the setpoint, clock stops
"""
