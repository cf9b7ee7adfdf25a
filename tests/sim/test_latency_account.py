"""The miss accounting (``sim.stack.tick_account.TickAccount``: bench/latency.py, bench/soak.py and the
ArduPilot procedure), on a scripted mission: every kind of miss is counted once, and nothing that
was on time is."""
from __future__ import annotations

from sim.stack import tick_account as latency


def rec(t, planned=True, sent=True, nxt=(10.0, 20.0, 40.0), arrived=None, skipped=0, channels=(0, 1)):
    return {"t": t, "channels": list(channels), "planned": planned, "sent": sent,
            "next": list(nxt) if nxt is not None else None, "arrived_t": arrived if arrived is not None else t,
            "skipped_before": skipped, "tick_ms": 30.0, "latency_ms": 40.0 if sent else None}


def ned(enu):  # the mock's home is the mission origin: local NED = (north, east, -up)
    e, n, u = enu
    return (n, e, -u)


def test_every_kind_of_miss_is_counted_once():
    acc = latency.TickAccount()
    budget = 0.9
    acc.on_tick(rec(1.0, planned=False), budget)  # take-off: ticked, no setpoint due
    acc.on_tick(rec(2.0, planned=False), budget)
    acc.on_setpoint(2.5, ned((0.0, 0.0, 40.0)))  # an older setpoint being re-sent
    acc.on_tick(rec(3.0, nxt=(1.0, 2.0, 40.0)), budget)
    acc.on_setpoint(3.4, ned((1.0, 2.0, 40.0)))  # received 0.4 s after the scan: on time
    # scan 4 skipped at an overrun (tick 5 took it); scan 5's setpoint arrives 1.2 s after it: late
    acc.on_tick(rec(5.0, nxt=(3.0, 4.0, 40.0), skipped=1), budget)
    acc.on_setpoint(6.2, ned((3.0, 4.0, 40.0)))
    # scan 6 was delivered 2 s late: its budget runs from the arrival, and 0.5 s after it is on time
    acc.on_setpoint(8.5, ned((5.0, 6.0, 40.0)))  # received before the tick's record is in
    acc.on_tick(rec(6.0, nxt=(5.0, 6.0, 40.0), arrived=8.0), budget)
    # scan 7: a monitoring tick whose setpoint was refused (not sent): late
    acc.on_tick(rec(7.0, sent=False), budget)
    # scan 8: a coast tick (no channel) does not tick the scan; scan 9's setpoint never arrives
    acc.on_tick(rec(8.0, channels=()), budget)
    acc.on_tick(rec(9.0, nxt=(7.0, 8.0, 40.0)), budget)
    f = acc.finish(iter([1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 9.0, 10.0]))
    assert f["scans"] == 10 and f["ticks"] == 7 and f["monitoring_ticks"] == 5
    assert f["scans_unticked"] == 3 and f["ticks_skipped"] == 1  # 4 (skipped), 8 (coasted), 10 (never)
    assert f["unticked_t"] == [4.0, 8.0, 10.0]
    assert f["ticks_late"] == 3 and sorted(f["late_t"]) == [5.0, 7.0, 9.0]
    assert f["ticks_missed"] == 6
    assert f["feed_lag_s_max"] == 2.0
    assert abs(f["setpoint_delay_s_median"] - 0.5) < 0.01 and abs(f["setpoint_delay_s_max"] - 1.2) < 1e-9


def test_a_clean_mission_has_no_miss_and_quantiles_come_from_the_histogram():
    acc = latency.TickAccount()
    for k in range(1, 101):
        t = float(k)
        acc.on_tick({**rec(t, nxt=(k, 0.0, 40.0)), "latency_ms": 20.0 + k / 10}, 0.9)
        acc.on_setpoint(t + 0.2, ned((k, 0.0, 40.0)))
    f = acc.finish(float(k) for k in range(1, 101))
    assert f["ticks_missed"] == 0 and f["ticks"] == 100 and f["unticked_t"] == []
    assert abs(f["latency_ms_median"] - 25.0) <= 0.15 and f["latency_ms_max"] == 30.0
    assert abs(f["setpoint_delay_s_median"] - 0.2) <= 0.001


def test_a_continuous_plans_receipt_is_not_the_target_held_before_it_was_sent():
    """The flight policy's plan starts at the scan, where the vehicle flying the last plan was:
    the target the autopilot holds until the tick's setpoint comes is on the new plan too
    (within the match's 0.5 m). A report of it before the app sent the setpoint (sent_t) is not
    the receipt: the one after is, and a tick sent too late for its budget is late."""
    acc = latency.TickAccount()
    seg = {"t0": 3.0, "p0": [0.0, 0.0, 40.0], "v0": [8.0, 0.0], "v1": [8.0, 0.0], "tick_s": 1.0, "a0": [0.0, 0.0]}
    acc.on_setpoint(3.05, ned((0.4, 0.0, 40.0)))  # the last plan's target, carried on: on the new plan at 3.05
    acc.on_tick({**rec(3.0, nxt=(8.0, 0.0, 40.0)), "segment": seg, "sent_t": 3.09}, 0.9)
    acc.on_setpoint(3.15, ned((1.2, 0.0, 40.0)))  # the tick's setpoint, held
    late = {**seg, "t0": 4.0, "p0": [8.0, 0.0, 40.0]}
    acc.on_setpoint(4.5, ned((12.0, 0.0, 40.0)))  # before the late send: the last plan's target
    acc.on_tick({**rec(4.0, nxt=(16.0, 0.0, 40.0)), "segment": late, "sent_t": 4.95}, 0.9)
    acc.on_setpoint(5.0, ned((16.0, 0.0, 40.0)))
    f = acc.finish(iter([3.0, 4.0]))
    assert f["ticks_late"] == 1 and f["late_t"] == [4.0]
    assert abs(f["setpoint_delay_s_median"] - 0.15) < 0.01
