"""Short form of bench/soak.py (the 2 h run is a bench, not CI): a 1-minute mission at 2x.
What must hold at any length: no setpoint the autopilot received is outside the fence, no
exception anywhere, and the app's in-memory history stays bounded."""
from __future__ import annotations

import pytest

from tests.support.processes import run_json

pytestmark = [pytest.mark.sitl, pytest.mark.slow, pytest.mark.timeout(150)]


def test_short_soak_keeps_the_fence_raises_nothing_and_stays_bounded():
    # 2x: the feed process must keep up on a shared CI machine
    r = run_json("bench.soak", "--duration", "60", "--speedup", "2", "--seed", "2", timeout=140)
    print(r)
    assert r["setpoints_received"] > 50
    assert r["setpoints_outside_fence"] == 0, r["outside_examples"]
    assert r["exceptions"] == 0
    assert r["kept_tick_records"] <= r["history"]
    assert r["ticks"] >= 30
