"""sim.evaluation.metrics.error_split (bench/consistency.py reports it): the window error along and across
each target's line of sight, near an obstacle and free, on hand-made trials where the answer is
known."""
from types import SimpleNamespace

import numpy as np
import pytest

from sim.evaluation.metrics import NEAR_M, error_split


def _trial(truth, est, uav):
    return SimpleNamespace(truth=truth, traces={"m": SimpleNamespace(estimate_xy=est, uav=uav)})


def test_error_split_separates_range_from_bearing_error_and_near_from_free():
    box = SimpleNamespace(center_m=(0.0, 0.0, 10.0), size_m=(100.0, 100.0, 20.0))
    cfg = SimpleNamespace(scenario=SimpleNamespace(obstacles=[box]), window_start=1)
    K = 4
    uav = np.zeros((K, 3))
    uav[:, 1] = -300.0  # the UAV south of both targets
    truth = np.zeros((K, 2, 6))
    truth[:, 0, :2] = (0.0, 50.0 + NEAR_M - 1.0)  # T1 just inside NEAR_M of the box's north face
    truth[:, 1, :2] = (400.0, 0.0)  # T2 far east of it: free
    est = truth[:, :, :2].copy()
    est[:, 0, 1] += 6.0  # T1: 6 m too far, along its line of sight (north)
    los = truth[0, 1, :2] - uav[0, :2]
    u = los / np.linalg.norm(los)
    est[:, 1] += 3.0 * np.array([-u[1], u[0]])  # T2: 3 m across its line of sight
    est[0] += 1000.0  # tick 0 is before the window: not counted
    out = error_split(cfg, [_trial(truth, est, uav)], "m")
    assert out["near"]["cells"] == out["free"]["cells"] == K - 1
    assert out["near"]["along_m"] == pytest.approx(6.0) and out["near"]["across_m"] == pytest.approx(0.0)
    assert out["free"]["along_m"] == pytest.approx(0.0) and out["free"]["across_m"] == pytest.approx(3.0)
    assert out["near"]["share"] == pytest.approx(0.8) and out["free"]["share"] == pytest.approx(0.2)
    assert out["free"]["range_m"] == round(float(np.linalg.norm(los)))
