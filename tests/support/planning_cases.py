"""Planning cases the core's planning and setpoint tests share: a candidate grid, a motion model,
a vehicle, the lookahead's declared defaults and its scoring, an area, and beliefs around targets
standing still."""
from __future__ import annotations

import math

import numpy as np

from onboard.core.dynamics import MotionModel
from onboard.core.obstacles import Obstacles
from onboard.core.planning.next_position import Area, Moves, RouteScoring
from onboard.core.planning.inputs import JUMP, CandidateGrid, LookaheadParams, UavMotion
from onboard.settings.sections import Lookahead

GRID = CandidateGrid(step_m=5.0, n_radial=4, n_heading=15, altitude_m=40.0)
MODEL = MotionModel.create(1.0, 0.2, 1300.0, [30.0, 30.0, 1e-10, 3.0, 3.0, 1e-10])
VEHICLE = UavMotion("vehicle", speed_max_mps=10.0, accel_max_mps2=2.5, jerk_max_mps3=0.0)
LOOKAHEAD = LookaheadParams.from_config(Lookahead())  # the declared defaults
AREA = ((-2e3, -2e3, 0.0), (2e3, 2e3, 1e3))
SCORING = RouteScoring(MODEL, math.radians(1.0), 0.95, LOOKAHEAD)  # 1 deg bearings, q 0.95


def moves(motion: UavMotion = JUMP, obstacles: Obstacles | None = None, box=AREA) -> Moves:
    """GRID's moves in ``box`` (default AREA) around ``obstacles`` (default none)."""
    return Moves(GRID, Area(*box, Obstacles.empty() if obstacles is None else obstacles), motion)


def still_targets(rng, centres, n=2000, pos_sd=(15.0, 60.0), H=30):
    """Beliefs around targets standing still at ``centres`` (M, 2), and their (constant) plans."""
    M = len(centres)
    particles = np.zeros((M, n, 6))
    particles[:, :, 0] = np.asarray(centres)[:, :1] + rng.normal(0, pos_sd[0], (M, n))
    particles[:, :, 1] = np.asarray(centres)[:, 1:] + rng.normal(0, pos_sd[1], (M, n))
    particles[:, :, 3:5] = rng.normal(0, 1.0, (M, n, 2))
    logw = np.full((M, n), -math.log(n))
    plans = np.zeros((M, H, 6))
    plans[:, :, :2] = np.asarray(centres)[:, None, :]
    return particles, logw, plans
