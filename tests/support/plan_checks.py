"""How the flight policy's plans join up, as the mock (tests/app/test_follow_plan.py) and the
firmware (tests/firmware/test_ardupilot.py) flights check it from the app's tick records."""
from __future__ import annotations

import numpy as np

from onboard.core.setpoint import plan_setpoint


def assert_plans_start_at_their_scans_and_join(ticks: list[dict], min_sent: int, min_joined: int) -> None:
    """Each sent plan starts at the scan it answers (its time, where the DF was then) with an
    acceleration, and a plan one tick after another starts with the acceleration the last one
    ended with (no step for the autopilot's jerk-limited shaper); the plans do turn."""
    sent = [r for r in ticks if r["sent"] and r["segment"]]
    assert len(sent) >= min_sent, len(sent)
    for r in sent:
        seg = r["segment"]
        assert seg["t0"] == r["t"]  # the scan's time, not the tick's (later) snapshot
        np.testing.assert_allclose(seg["p0"][:2], r["uav_enu"][:2], atol=1e-3)  # where the DF was then
        assert seg["a0"] is not None
    joined = 0
    for a, b in zip(sent, sent[1:]):
        if abs(b["t"] - a["t"] - 1.0) < 1e-6:
            s = a["segment"]
            end = plan_setpoint(s["p0"][:2], s["v0"], s["v1"], s["tick_s"], s["tick_s"], s["a0"])[2]
            np.testing.assert_allclose(b["segment"]["a0"], end, atol=1e-9)
            joined += 1
    assert joined >= min_joined, (joined, min_joined)
    # the acceleration is there to be continuous
    assert max(np.linalg.norm(r["segment"]["a0"]) for r in sent) > 1.0
