"""The core's closed loop without sockets or an autopilot: the benches' and the route score's
rig (bench/tick.py, planner.py, route_score.py; sim.evaluation.route_score)."""
from __future__ import annotations


def closed_loop(setup, ticks: int, seed: int, start_xy=(150.0, 200.0), timer=None):
    """The core's closed loop without sockets (bench/tick.py, planner.py, route_score.py): each
    target's truth follows its own plan, the DF's bearings carry noise, and the UAV, starting at
    start_xy (m, ENU), goes where the planner says, with the velocity it says for the vehicle
    motion. Yields (k, state, result, uav) for k = 0..ticks-1: the state and TickResult after
    tick k, and where that tick's scan was taken (x, y, z). ``timer``: the tick's clock (default
    ``time.perf_counter``; ``time.process_time`` counts this process's CPU only)."""
    import time

    import numpy as np

    from onboard.core.bearings import bearing, wrap
    from onboard.core.guidance.predictor import GuidanceWorkspace
    from onboard.core.monitor import Scan, UavState, initial_state, tick

    rng = np.random.default_rng(seed)
    state = initial_state(setup, rng)
    truth = setup.initial_means.copy()
    uav = np.array([*start_xy, setup.grid.altitude_m], float)
    vel = np.zeros(2)
    ws = GuidanceWorkspace()
    for k in range(ticks):
        bearings = tuple(np.array([float(wrap(bearing(truth[j], uav) + rng.normal(0, setup.sensor.sigma_rad)))])
                         for j in range(setup.n_targets))
        state, res = tick(setup, state, [Scan(uav, bearings)], rng, plan_from=UavState(uav, vel), workspace=ws,
                          timer=timer or time.perf_counter)
        yield k, state, res, uav
        truth = np.array([p.means[0] for p in res.plans])
        p = res.planning
        if p is not None and p.index is not None:
            uav = p.position
            vel = p.velocities[p.index] if p.velocities is not None else np.zeros(2)


def tick_timings(setup, ticks: int, seed: int, timer=None, start_xy=(150.0, 200.0)) -> dict:
    """ms per tick of ``closed_loop`` from start_xy (default the paper's UAV start), split as
    TickResult.timings_s (tick, tracking, guidance, planning): arrays over the ticks after the
    first, which includes the guidance's first exploratory face search."""
    import numpy as np

    out = {k: [] for k in ("tick", "tracking", "guidance", "planning")}
    for _, _, res, _ in closed_loop(setup, ticks, seed, start_xy=start_xy, timer=timer):
        for k in out:
            out[k].append(res.timings_s[k] * 1e3)
    return {k: np.array(v[1:]) for k, v in out.items()}
