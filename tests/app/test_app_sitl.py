"""End to end over real loopback sockets: mock autopilot, live DF feed and the onboard app, paper
scenario, accelerated. One flight (module fixture) is checked by several tests:

  takeoff by the app itself -> >= 60 s of monitoring -> a pilot switches to LOITER (through a
  ground-station link) -> 3 s later the GCS commands "resume" -> the app flies again.

The app and the mock run as threads of this process; the DF feed is a process of its own
(``pmon feed live``), as on the vehicle: its truth world runs the same guidance as the targets,
and in this process it held the GIL exactly while the app ticked (both start at the scan time).

Timing is judged on the autopilot's clock: a setpoint counts when the mock autopilot RECEIVES it
(its own time), not when the app thinks it sent it. The mock runs SITL-like (``max_lag_s``):
when this loaded machine starves the process, autopilot time slips instead of jumping ahead
3x the stall, which no onboard computer could see (a real autopilot's clock is not stopped by
the companion's load). What stays on the app: its tick (tracking, guidance bounded by
PMON_GUID_S, planning) and its scheduling, at 1.5x the real-time pressure.
"""
from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from onboard.app.mavlink2 import mavlink
from sim.mock.autopilot import Mode

from tests.support.mavlink_gcs import Gcs

from onboard.app.contract import State
from onboard.core.obstacles import Obstacles
from sim.stack.rig import GCS_PORT, Rig, RigConfig
import json

pytestmark = [pytest.mark.sitl, pytest.mark.slow]

# 1.5x: the app's tick must fit 0.9 s of autopilot time = 600 ms local. At 4x (225 ms) it did
# not, under load, every run; at 3x (300 ms) a 2-core VM twice as slow missed it by 60 ms
SPEEDUP = 1.5
MONITOR_S = 62  # monitoring ticks before the pilot takes over
BUDGET_S = 0.9  # PMON_BUDGET: setpoint sent within 0.9 s (autopilot) of the scan's time
LAG_MEDIAN_MAX_M = 15.0  # see test_uav_follows_commanded_positions
LAG_MAX_M = 30.0
RMSE_MAX_M = 50.0


@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    out = {"positions": [], "setpoints_rx": []}
    truth_path = tmp_path_factory.mktemp("sitl") / "truth.jsonl"
    # the scenario as written (the paper policy: position-only setpoints), at the mission origin
    rig = Rig(RigConfig(policy="paper", seed=2, autopilot_seed=3, feed_seed=4, speedup=SPEEDUP, home="origin",
                        ready_s=4.0, in_process=True, auto_launch=True, feed_duration_s=300,
                        truth_path=str(truth_path)),
              # every setpoint the autopilot receives, with its own clock
              on_setpoint=lambda t, msg: out["setpoints_rx"].append((t, rig.ap.copter.mode, (msg.x, msg.y, msg.z))))
    out["sc"] = rig.sc
    gcs = None
    stop_sampler = threading.Event()
    with rig:
        ap, app = rig.ap, rig.app
        try:
            gcs = Gcs(rig.port(GCS_PORT))

            def sample():
                while not stop_sampler.is_set():
                    s = ap.state()
                    out["positions"].append((s.time_boot_ms / 1000, s.pos_enu, s.armed, s.mode))
                    time.sleep(0.01)
            sampler = threading.Thread(target=sample, daemon=True)
            sampler.start()

            def monitoring_ticks():
                return sum(1 for t in app.ticks if t["planned"] and t["channels"])
            deadline = time.monotonic() + 140
            while monitoring_ticks() < MONITOR_S and time.monotonic() < deadline:
                time.sleep(0.1)
            assert monitoring_ticks() >= MONITOR_S, f"only {monitoring_ticks()} monitoring ticks: {app.events}"
            out["ticks_before"] = [dict(t) for t in app.ticks]
            # the pilot takes over: LOITER from the ground station, via the autopilot
            ack = gcs.command(1, mavlink.MAV_CMD_DO_SET_MODE, mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, Mode.LOITER)
            assert ack is not None and ack.result == mavlink.MAV_RESULT_ACCEPTED
            assert ap.wait_until(lambda s: s.mode == Mode.LOITER, 5)
            out["t_mode_change"] = next(p[0] for p in reversed(out["positions"]) if p[3] != Mode.LOITER)
            assert ap.wait_until(lambda s: s.time_boot_ms / 1000 > out["t_mode_change"] + 3.0, 10)
            out["state_after_override"] = app.state
            out["statustexts"] = [m.text for m in gcs.msgs if m.get_type() == "STATUSTEXT"]
            out["resume_ack"] = gcs.command(191, mavlink.MAV_CMD_USER_1, 3)
            t_resume = ap.sim_time
            assert ap.wait_until(lambda s: s.time_boot_ms / 1000 > t_resume + 3.0, 10)
            out["t_resume"] = t_resume
            out["state_after_resume"] = app.state
            out["mode_after_resume"] = ap.state().mode
            out["ticks"] = list(app.ticks)
            with open(truth_path) as f:
                out["records"] = [r for r in map(json.loads, f) if "header" not in r]
            out["counters"] = dict(app.counters)
            out["ap_counters"] = ap.counters()
            out["rejected"] = app.scans.rejected_total
            stop_sampler.set()  # the tests read the positions as they are now (a list still growing
            sampler.join(timeout=2)  # while a test read it twice had two lengths: an IndexError)
            yield out
        finally:
            stop_sampler.set()
            if gcs is not None:
                gcs.close()


def _monitoring(ticks):
    return [t for t in ticks if t["planned"] and t["channels"]]


def _received_at(flight, tick) -> float | None:
    """Autopilot time at which the mock first received this tick's setpoint (home = the
    mission origin, so local NED = (north, east, -up) of the mission ENU)."""
    e, n, u = tick["next"]
    for t, _mode, (x, y, z) in flight["setpoints_rx"]:
        if t >= tick["t"] and abs(x - n) < 0.01 and abs(y - e) < 0.01 and abs(z + u) < 0.01:
            return t
    return None


@pytest.mark.timeout(200)
def test_every_tick_produced_a_setpoint_within_its_budget(flight):
    ticks = _monitoring(flight["ticks_before"])
    assert len(ticks) >= MONITOR_S
    assert all(t["sent"] for t in ticks), [t["refused"] for t in ticks if not t["sent"]]
    # the budget runs from the scan's time, or from its arrival when the DF delivered it late:
    # the feed is a simulator sharing this loaded machine (its truth world re-plans at the same
    # moments as the app); a real DF's delivery lag is milliseconds and not the app's to spend
    rows = []
    for t in ticks:
        r = _received_at(flight, t)
        start = max(t["t"], t["arrived_t"] if t["arrived_t"] is not None else t["t"])
        rows.append((t["t"], start - t["t"], None if r is None else r - start))
    late = [(t, round(lag, 2), d if d is None else round(d, 2)) for t, lag, d in rows
            if d is None or d > BUDGET_S]
    print("setpoint at the autopilot after its scan (or its late arrival), autopilot s: median %.2f "
          "max %.2f; DF delivery lag median %.2f max %.2f; mock clock slips %s" % (
              np.median([d for *_, d in rows if d is not None]), max(d for *_, d in rows if d is not None),
              np.median([lag for _, lag, _ in rows]), max(lag for _, lag, _ in rows),
              flight["ap_counters"].get("clock_slips", 0)))
    assert not late, f"(scan t, DF lag, setpoint delay) later than {BUDGET_S} s: {late}"
    assert sum(t["skipped_before"] for t in ticks) == 0
    assert flight["counters"].get("tick_errors", 0) == 0 and flight["counters"].get("io_errors", 0) == 0
    # between ticks the setpoint is re-sent at >= 5 Hz of autopilot time
    rx = [t for t, mode, _ in flight["setpoints_rx"] if ticks[5]["t"] <= t <= ticks[-1]["t"]]
    assert len(rx) / (ticks[-1]["t"] - ticks[5]["t"]) >= 5.0


@pytest.mark.timeout(200)
def test_uav_follows_commanded_positions(flight):
    """Position-only setpoints make the autopilot brake towards each one, and the next tick
    (centred on where the vehicle IS) moves it again: the vehicle lags its setpoint. Stated
    tolerance, with the paper's steps of up to N_r * Delta_r = 20 m per tick and the demo's
    vehicle limits: at the next tick the vehicle is within LAG_MAX_M = 30 m of the position
    commanded one tick earlier, median <= 15 m (measured: median ~13 m, p90 ~18 m, max ~26 m);
    its altitude stays within 1 m of h."""
    ticks = _monitoring(flight["ticks_before"])
    pos = flight["positions"]
    times = np.array([p[0] for p in pos])
    enu = np.array([p[1] for p in pos])
    ds = []
    for k, t in enumerate(ticks[:-1]):
        goal = np.array(t["next"])
        i = min(np.searchsorted(times, ticks[k + 1]["t"]), len(enu) - 1)
        ds.append(np.linalg.norm(enu[i, :2] - goal[:2]))
    ds = np.array(ds)
    print("distance to the commanded position at the next tick: median %.1f p90 %.1f max %.1f m" % (
        np.median(ds), np.percentile(ds, 90), ds.max()))
    assert ds.max() <= LAG_MAX_M and np.median(ds) <= LAG_MEDIAN_MAX_M
    steady = (times > ticks[3]["t"]) & (times < ticks[-1]["t"])
    assert np.abs(enu[steady, 2] - 40.0).max() < 1.0


@pytest.mark.timeout(200)
def test_never_left_the_area_nor_entered_an_obstacle(flight):
    sc = flight["sc"]
    enu = np.array([p[1] for p in flight["positions"] if p[2]])  # while armed
    lo, hi = np.array(sc.area.min_m), np.array(sc.area.max_m)
    assert np.all(enu >= lo - 0.5) and np.all(enu <= hi + 0.5)
    obstacles = Obstacles.from_boxes(sc.obstacles)
    assert not obstacles.contains(enu).any()
    inflated = obstacles.inflate(sc.uav.obstacle_margin_m)
    commanded = np.array([t["next"] for t in _monitoring(flight["ticks"])])
    assert not inflated.contains(commanded).any()


@pytest.mark.timeout(200)
def test_final_rmse_is_below_threshold(flight):
    truth = {r["t"]: np.array(r["targets"])[:, :2] for r in flight["records"]}
    errs = np.array([np.linalg.norm(np.array(t["means"])[:, :2] - truth[t["t"]], axis=1)
                     for t in flight["ticks"] if t["t"] in truth])
    assert len(errs) >= MONITOR_S
    final = errs[-20:]  # the last 20 s of the flight
    rmse = np.sqrt((final ** 2).mean(axis=0))
    print("RMSE per target over the last 20 s [m]:", rmse.round(1))
    assert np.all(rmse < RMSE_MAX_M), rmse


@pytest.mark.timeout(200)
def test_pilot_mode_change_stops_setpoints_within_one_tick_and_resume_needs_a_command(flight):
    t_c = flight["t_mode_change"]
    after = [t for t, _, _ in flight["setpoints_rx"] if t_c < t < flight["t_resume"]]
    assert not after or max(after) <= t_c + 1.0, f"setpoints {after[-3:]} after the change at {t_c}"
    assert flight["state_after_override"] == State.PILOT_OVERRIDE
    assert any("pilot override" in s for s in flight["statustexts"]), flight["statustexts"]
    # nothing flies the vehicle until the GCS says so; then the app takes GUIDED back itself
    ack = flight["resume_ack"]
    assert ack is not None and ack.result == mavlink.MAV_RESULT_ACCEPTED
    assert flight["state_after_resume"] == State.MONITORING
    assert flight["mode_after_resume"] == Mode.GUIDED
    resumed = [t for t, mode, _ in flight["setpoints_rx"] if t > flight["t_resume"] and mode == Mode.GUIDED]
    assert len(resumed) >= 5

