"""The autopilot clock follows the autopilot, not a forged message (issue 23, part 3): a sample
far off the clock's timeline moves nothing until the samples after it confirm it. Local time is
a fake monotonic clock; samples come at 10 Hz like GLOBAL_POSITION_INT."""
from __future__ import annotations

import pytest

from onboard.app.autopilot.clock import AutopilotClock


class Fake:
    def __init__(self):
        self.t = 1000.0

    def __call__(self) -> float:
        return self.t


def run(clock: AutopilotClock, local: Fake, seconds: float, rate: float = 1.0, ap0: float | None = None,
        spoof=None, step: float = 0.1) -> list[float]:
    """Feed genuine samples for ``seconds`` local s at ``rate``; ``spoof(i)`` -> extra sample (ms)
    sent right after sample i, or None. Returns now() after each step."""
    out = []
    ap = ap0 if ap0 is not None else (clock.now() or 0.0)
    for i in range(int(round(seconds / step))):
        local.t += step
        ap += step * rate
        clock.observe(ap * 1000)
        if spoof is not None and (s := spoof(i, ap)) is not None:
            clock.observe(s)
        out.append(clock.now())
    return out


def test_a_forged_sample_an_hour_ahead_moves_nothing_and_is_counted():
    local, clock = Fake(), None
    clock = AutopilotClock(local)
    run(clock, local, 5.0, ap0=100.0)
    times = run(clock, local, 5.0, spoof=lambda i, ap: (ap + 3600) * 1000 if i in (10, 30) else None)
    steps = [b - a for a, b in zip(times, times[1:])]
    assert max(steps) < 0.2 and min(steps) > 0.0, "the clock ran smoothly through the forgeries"
    assert clock.jumps == 0 and clock.jumps_ignored == 2
    assert clock.rate == pytest.approx(1.0, abs=0.02), "nor was the measured rate touched"


def test_a_forged_sample_far_behind_is_not_taken_for_a_reboot():
    local = Fake()
    clock = AutopilotClock(local)
    run(clock, local, 5.0, ap0=500.0)
    times = run(clock, local, 3.0, spoof=lambda i, ap: 0 if i == 5 else None)
    assert min(times) > 500.0 and clock.resets == 0 and clock.jumps == 0 and clock.jumps_ignored == 1


def test_a_reboot_is_followed_once_confirmed():
    local = Fake()
    clock = AutopilotClock(local)
    run(clock, local, 5.0, ap0=500.0)
    before = clock.now()
    times = run(clock, local, 3.0, ap0=0.0)  # the autopilot restarts its time_boot_ms
    assert times[0] > before, "one sample is not enough"
    assert clock.resets == 1 and clock.jumps == 1 and clock.last_jump_s == pytest.approx(-505.0, abs=1.5)
    assert times[-1] == pytest.approx(3.0, abs=0.2)


def test_a_reboot_is_followed_when_its_messages_come_slightly_out_of_order():
    """PX4 stamps each message with its own uORB sample's time: after a restart (v1.16 SITL) the
    app's tlog went from 37.1 s to 0.196 s while ATTITUDE, GLOBAL_POSITION_INT, LOCAL_POSITION_NED
    ... arrived a few ms out of order; each such sample used to restart the candidate, so the
    reboot was never confirmed (the app said "link back", never "autopilot rebooted")."""
    local = Fake()
    clock = AutopilotClock(local)
    run(clock, local, 5.0, ap0=37.0)
    # after every sample, another stamped 4 ms earlier (a different stream's)
    run(clock, local, 3.0, ap0=0.1, spoof=lambda i, ap: (ap - 0.004) * 1000)
    assert clock.resets == 1 and clock.jumps == 1 and clock.now() == pytest.approx(3.1, abs=0.2)


def test_a_forger_who_keeps_sending_is_cancelled_by_every_genuine_sample():
    local = Fake()
    clock = AutopilotClock(local)
    run(clock, local, 5.0, ap0=100.0)
    # a forged sample after every genuine one, for 10 s: the candidate never gets confirmed
    times = run(clock, local, 10.0, spoof=lambda i, ap: (ap + 3600) * 1000)
    assert max(times) < 116.0 and clock.jumps == 0 and clock.jumps_ignored >= 99


def test_free_run_through_a_link_loss_and_a_rate_change_are_not_jumps():
    local = Fake()
    clock = AutopilotClock(local)
    run(clock, local, 5.0, ap0=100.0)
    local.t += 30.0  # 30 s without samples; the autopilot ran 20 % faster meanwhile
    run(clock, local, 2.0, ap0=105.0 + 36.0)
    assert clock.jumps == 0 and clock.jumps_ignored == 0
    run(clock, local, 10.0, rate=4.0)  # a SITL speedup changed from 1 to 4
    assert clock.jumps == 0 and clock.rate == pytest.approx(4.0, rel=0.05)


def test_a_reboot_is_pending_from_its_first_sample_until_confirmed():
    """The app holds a new GPS_GLOBAL_ORIGIN back meanwhile: PX4's came before its clock confirmed
    the reboot, and was refused as the old origin moved by 1 m."""
    local = Fake()
    clock = AutopilotClock(local)
    run(clock, local, 5.0, ap0=37.0)
    assert not clock.reboot_pending
    run(clock, local, 0.3, ap0=0.1)
    assert clock.reboot_pending and clock.resets == 0
    run(clock, local, 2.0, ap0=0.4)
    assert not clock.reboot_pending and clock.resets == 1
    run(clock, local, 1.0, spoof=lambda i, ap: (ap + 3600) * 1000 if i == 3 else None)
    assert not clock.reboot_pending  # a sample far ahead is a candidate, not a reboot


def test_the_feed_sees_a_reboot_that_came_before_it_went_to_sleep():
    """PX4 restarted while the feed waited out scans with no position: the reboot was followed
    before the feed's next sleep, which then waited for the new clock to reach the old scan time
    (78 s of PX4's time without DF scans after a restart, tests/firmware/test_px4.py flight B, measured)."""
    import threading
    import time

    from sim.stack.feed import _sleep_until

    class Rebooted:
        resets = 1  # the caller last saw 0

        def now(self):
            return 3.0  # the new boot's clock, far below the old timeline's t = 107

    stop = threading.Event()
    t0 = time.monotonic()
    assert _sleep_until(Rebooted(), 107.0, stop, resets=0) and time.monotonic() - t0 < 0.5
    stop.set()
    assert not _sleep_until(Rebooted(), 107.0, stop)  # by itself it counts from its own call
