"""Plan one tick: the onboard core's filter and planner, once, on the paper's scenario.

Shows the functional core (``onboard.core.monitor``) without sockets, clocks or threads: the
scenario's defaults under the flight policy, every target's belief from its initial mean, one
scan of noise-free bearings taken from the UAV's start, one ``tick``, and the point the UAV would
be sent to next (ENU, m, in the mission frame).

Run:
    python examples/plan_one_tick.py [--scenario paper] [--policy flight|paper] [--seed 1]
"""
import argparse

import numpy as np

from onboard.config import load_scenario
from onboard.core.bearings import bearing
from onboard.core.monitor import MonitorSetup, Scan, UavState, initial_state, tick
from onboard.policy import DEFAULT, POLICIES, with_policy


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default="paper")
    ap.add_argument("--policy", default=DEFAULT, choices=sorted(POLICIES))
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args()

    sc = with_policy(load_scenario(args.scenario), args.policy)
    setup = MonitorSetup.from_scenario(sc)
    rng = np.random.default_rng(args.seed)
    state = initial_state(setup, rng)

    uav = np.array([*sc.uav.start_m[:2], sc.uav.altitude_m])  # ENU, m
    # one bearing per target channel (rad, clockwise from north), from the UAV to the initial mean
    bearings = tuple(np.atleast_1d(bearing(m[:2], uav[:2])) for m in setup.initial_means)
    state, result = tick(setup, state, [Scan(uav, bearings)], rng, plan_from=UavState(uav))

    print(f"scenario {sc.name}, policy {args.policy}: {setup.n_targets} targets, "
          f"{setup.n_particles} particles each, planner {setup.planner}")
    for j, mean in enumerate(result.means):
        print(f"target {j}: estimate E {mean[0]:.1f} m, N {mean[1]:.1f} m")
    e, n, u = result.next_position
    print(f"UAV at E {uav[0]:.1f} N {uav[1]:.1f} m -> next point E {e:.1f} N {n:.1f} U {u:.1f} m "
          f"(tick {1000 * result.timings_s['tick']:.0f} ms)")


if __name__ == "__main__":
    main()
