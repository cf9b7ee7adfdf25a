"""Planning: where the UAV scans next (the greedy rule, the lookahead's routes, the planners)."""
