"""Failsafes of the onboard app, each shown over real loopback sockets (issue 7).

One accelerated flight (module fixture): mock autopilot (in process, SITL-like clock), the app,
a scripted direction finder (UDP datagrams on the autopilot's clock: static targets, so faults
are easy to inject), and a ground station on its own TCP link. After the app has launched
itself and monitors, the faults come one after the other, each followed by recovery:

  1. sensor silence 15 s       -> predict only, uncertainty grows, warned; picks up again
  2. guidance gets no time     -> previous plan shifted / coasting, reported; ticks go on
  3. a NaN in T1's particles  -> T1 re-seeded from its last estimate, reported; others untouched
  4. a tick stalls 1.5 s wall  -> the watchdog reports it, overrun scans skipped (not queued),
                                  the vehicle holds the last checked setpoint meanwhile
  5. a setpoint outside the fence -> refused and logged, never sent (nor clipped)
  6. autopilot link cut 6 s (link timeout 1 s local = 3 s autopilot) -> stop commanding, keep estimating, link back by itself,
                                  no setpoint until the GCS says resume
Pilot takeover (another mode) is shown in tests/app/test_app_sitl.py.
"""
from __future__ import annotations

import time
from dataclasses import replace

import numpy as np
import pytest

from onboard.app.mavlink2 import mavlink
from sim.mock.autopilot import BootTimeline, MockAutopilot
from sim.firmware.priority import app_config_priority, vehicle_threads

from tests.support.mavlink_gcs import Gcs
from tests.support.app_helpers import FaultyTick, ScriptedDf, wait_autopilot_s, wait_for

from onboard.app.app_config import AppConfig
from onboard.app.app import OnboardApp
from onboard.app.contract import State
from onboard.config import load_scenario
from onboard.policy import with_policy
from onboard.core.tracking.filter import ParticleSet
from sim.mock.multicopter import DEMO_VEHICLE_PARAMS

pytestmark = [pytest.mark.sitl, pytest.mark.timeout(240)]

SPEEDUP = 3.0


@pytest.fixture(scope="module")
def flight():
    sc = with_policy(load_scenario("paper"), "paper")
    o = sc.origin
    out: dict = {"rx": []}
    ap = MockAutopilot(home=(o.lat_deg, o.lon_deg, o.alt_m), speedup=SPEEDUP, seed=5,
                       endpoints=["tcpin:127.0.0.1:0"] * 2, params=DEMO_VEHICLE_PARAMS, max_lag_s=0.1,
                       boot=BootTimeline.scaled(3.0))
    ap.watch("SET_POSITION_TARGET_LOCAL_NED", lambda msg: out["rx"].append((ap.copter.t, (msg.x, msg.y, msg.z))))
    ap.start()
    vehicle_threads(ap._thread)  # scheduled as a flight is (sim/firmware/priority.py)
    app = df = gcs = None
    tick = FaultyTick()  # the core tick the worker calls: faults are injected through it
    try:
        app = OnboardApp(AppConfig(f"tcp:127.0.0.1:{ap.port('tcpin', 0)}", sensor_port=0,
                                   auto_launch=True, seed=1, **app_config_priority(), link_timeout_s=1.0), sc, tick=tick).start()
        df = ScriptedDf(ap, app.sensor_port, np.array([t.mean for t in sc.targets])).start()
        vehicle_threads(df._t)
        gcs = Gcs(ap.port("tcpin", 1))
        assert wait_for(lambda: app.state == State.MONITORING
                     and sum(1 for t in app.ticks if t["planned"]) >= 5, 90), list(app.events)

        _sensor_silence(ap, app, df, out)
        _no_guidance_time(ap, gcs, out)
        _particle_collapse(ap, app, tick, out)
        _stalled_tick(ap, app, tick, out)
        _point_outside_the_area(ap, app, tick, out)
        _link_cut(ap, app, gcs, out)
        out["texts"] = gcs.texts()
        out["events"] = [e for _, e in app.events]
        out["ticks"] = list(app.ticks)
        out["counters"] = dict(app.counters)
        out["watchdog"] = dict(app.watchdog.counts)
        yield out
    finally:
        tick.fault = None
        if df is not None:
            df.stop()
        if gcs is not None:
            gcs.close()
        if app is not None:
            app.stop()
        ap.stop()


def _sensor_silence(ap, app, df, out) -> None:
    """1. The direction finder falls silent for 15 s of autopilot time, then speaks again."""
    df.silent = True
    out["silence"] = (ap.sim_time, wait_autopilot_s(ap, 15.0))
    df.silent = False
    assert wait_for(lambda: any(t["channels"] and t["t"] > out["silence"][1] for t in app.ticks), 30)


def _no_guidance_time(ap, gcs, out) -> None:
    """2. Guidance gets no time at all (PMON_GUID_S = 0), then its time back."""
    out["guid_set"] = gcs.param_set("PMON_GUID_S", 0.0)
    t0 = ap.sim_time
    wait_autopilot_s(ap, 5.0)
    out["guid_reset"] = gcs.param_set("PMON_GUID_S", 0.3)
    out["guidance"] = (t0, ap.sim_time)
    wait_autopilot_s(ap, 3.0)


def _particle_collapse(ap, app, tick, out) -> None:
    """3. Particle collapse of T1: a NaN appears in its belief (a numerical fault in the core;
    with the clutter-aware likelihood in log space, no finite datagram can cause it)."""

    def nan_tick(*a, real, **k):
        state, res = real(*a, **k)
        if "collapse_t" not in out:
            out["collapse_t"] = ap.sim_time
            b = state.beliefs[0]
            p = b.particles.copy()
            p[::7, 0] = np.nan
            state = replace(state, beliefs=(ParticleSet(p, b.log_weights),) + state.beliefs[1:])
        return state, res
    tick.fault = nan_tick
    assert wait_for(lambda: app.counters.get("reseeds", 0) >= 1, 30), list(app.events)[-10:]
    tick.fault = None
    wait_autopilot_s(ap, 3.0)


def _stalled_tick(ap, app, tick, out) -> None:
    """4. One tick stalls 1.5 s of wall time (4.5 s of autopilot time at 3x)."""
    stalled = {"done": False}

    def slow_tick(*a, real, **k):
        if not stalled["done"]:
            stalled["done"] = True
            stalled["t"] = ap.sim_time
            time.sleep(1.5)  # the stall itself (wall time), not a wait for a condition
            stalled["t_end"] = ap.sim_time
        return real(*a, **k)
    skipped0 = app.counters.get("ticks_skipped", 0)
    tick.fault = slow_tick
    assert wait_for(lambda: "t_end" in stalled, 30)
    tick.fault = None
    wait_autopilot_s(ap, 3.0)
    out["stall"] = stalled
    out["skipped_by_stall"] = app.counters.get("ticks_skipped", 0) - skipped0


def _point_outside_the_area(ap, app, tick, out) -> None:
    """5. The planner proposes a point outside the area (a fault in the core): refused."""

    def bad_tick(*a, real, **k):
        state, res = real(*a, **k)
        if res.planning is not None and "bad_t" not in out:
            out["bad_t"] = ap.sim_time
            cand = res.planning.candidates.copy()
            cand[res.planning.index] = (-50.0, 200.0, 40.0)
            res = replace(res, planning=replace(res.planning, candidates=cand))
        return state, res
    refused0 = app.counters.get("setpoints_refused", 0)
    tick.fault = bad_tick
    assert wait_for(lambda: "bad_t" in out, 30)
    wait_autopilot_s(ap, 1.0)
    tick.fault = None
    out["refused"] = app.counters.get("setpoints_refused", 0) - refused0
    wait_autopilot_s(ap, 2.0)


def _link_cut(ap, app, gcs, out) -> None:
    """6. The app's link to the autopilot goes dead both ways for 9 s, then the operator resumes."""
    ticks_before_cut = len([t for t in app.ticks])
    assert ap.cut_link(191, 9.0) == 1
    out["cut"] = (ap.sim_time, ap.sim_time + 9.0)
    assert wait_for(lambda: app.state == State.FAULT, 30), list(app.events)[-5:]
    out["state_in_cut"] = app.state
    wait_autopilot_s(ap, 9.5 - (ap.sim_time - out["cut"][0]))
    assert wait_for(lambda: app.counters.get("link_regained", 0) >= 1, 30), list(app.events)[-5:]
    out["ticks_in_cut"] = [t for t in list(app.ticks)[ticks_before_cut:] if out["cut"][0] < t["t"] < out["cut"][1]]
    out["back_t"] = ap.sim_time
    wait_autopilot_s(ap, 3.0)
    out["state_after_back"] = app.state
    out["resume_t"] = ap.sim_time
    out["resume_ack"] = gcs.command(191, mavlink.MAV_CMD_USER_1, 3)
    wait_autopilot_s(ap, 8.0)
    out["state_after_resume"] = app.state


def _between(ticks, t0, t1):
    return [t for t in ticks if t0 < t["t"] <= t1]


def test_sensor_silence_predicts_only_with_growing_uncertainty_and_picks_up_again(flight):
    t0, t1 = flight["silence"]
    coast = [t for t in _between(flight["ticks"], t0, t1) if not t["channels"]]
    assert len(coast) >= 3, "the filters must keep stepping on the 1 s grid without data"
    assert all(t["sent"] for t in coast if t["planned"]), "monitoring goes on (predicted beliefs)"
    sig = np.array([np.linalg.norm(t["sigmas_xy"], axis=1) for t in coast])  # (ticks, targets)
    assert np.all(np.diff(sig, axis=0) > 0), f"uncertainty must grow every coast tick: {sig.round(1)}"
    assert any("no DF data: predicting only" in s for s in flight["texts"])
    assert any("DF data back" in s for s in flight["texts"])
    after = [t for t in flight["ticks"] if t["t"] > t1 and t["channels"]]
    assert after and after[0]["t"] <= t1 + 3.0


def test_guidance_without_time_falls_back_and_never_stalls_the_tick(flight):
    assert flight["guid_set"] is not None and flight["guid_set"].param_value == 0.0
    t0, t1 = flight["guidance"]
    ticks = _between(flight["ticks"], t0 + 1.0, t1)
    assert len(ticks) >= 3
    for t in ticks:
        assert all(s.startswith("fallback") for s in t["plans"]), t["plans"]
        assert t["sent"], "setpoints go on from the fallback predictions"
    assert flight["counters"].get("fallback_previous", 0) + flight["counters"].get("fallback_coast", 0) >= 4 * 3
    assert any("guidance failed" in s for s in flight["texts"])
    assert any("guidance back" in s for s in flight["texts"])
    assert flight["counters"].get("tick_errors", 0) == 0


def test_particle_collapse_reseeds_that_target_only(flight):
    hit = [t for t in flight["ticks"] if t["reseeded"]]
    assert hit and all(t["reseeded"] == [0] for t in hit), [t["reseeded"] for t in hit]
    k = flight["ticks"].index(hit[0])
    at, after = hit[0], flight["ticks"][k + 1]  # the re-seed shows in the tick after it
    # T1 was re-seeded at 4x its covariance plus the initial one: its spread about doubles
    # (one bearing narrows it across the bearing only; measured 1.80-2.23). A target re-seeded
    # by mistake would double too; one carried on changes by its usual tick: +0-10 %, up to
    # +22 % (a CI run) and +35 % (T4 the tick after, under two busy cores) as the static targets'
    # beliefs spread under the moving-target model.
    spread = [np.hypot(*after["sigmas_xy"][j]) / np.hypot(*at["sigmas_xy"][j]) for j in range(4)]
    assert spread[0] > 1.5 and all(0.5 < r < 1.5 for r in spread[1:]), spread
    assert any("T1: particle collapse: re-seeded" in s for s in flight["texts"])
    later = flight["ticks"][k + 1:k + 4]
    assert all(np.all(np.isfinite(t["means"])) and not t["reseeded"] for t in later)


def test_stalled_tick_is_reported_and_its_overrun_skipped_not_queued(flight):
    st = flight["stall"]
    assert st["t_end"] - st["t"] > 3.0  # autopilot s: past the watchdog's 3 s
    assert flight["watchdog"].get("tick_stuck", 0) >= 1
    assert any("watchdog: tick" in e for e in flight["events"])
    assert flight["skipped_by_stall"] >= 2, "scans due during the stall are skipped"
    # no queue: the tick after the stall is the newest scan, not the oldest
    after = [t for t in flight["ticks"] if t["t"] > st["t"] and t["channels"]]
    assert after[0]["skipped_before"] >= 2 and after[0]["t"] >= st["t_end"] - 1.5
    # meanwhile the vehicle kept receiving the last checked setpoint (it holds a safe point)
    during = [p for t, p in flight["rx"] if st["t"] + 0.5 < t < st["t_end"]]
    assert len(during) >= 5 and len({tuple(np.round(p, 2)) for p in during}) == 1


def test_setpoint_outside_the_fence_is_refused_and_logged_never_sent(flight):
    assert flight["refused"] >= 1
    assert any("setpoint refused: outside the area" in s for s in flight["texts"])
    # what the autopilot received never left the area (home = origin: NED = (n, e, -u))
    east = np.array([p[1] for _, p in flight["rx"]])
    assert east.min() >= 0.0


def test_link_loss_stops_commanding_keeps_estimating_and_needs_resume(flight):
    c0, c1 = flight["cut"]
    assert flight["state_in_cut"] == State.FAULT
    assert any("autopilot link lost" in e for e in flight["events"])
    assert len(flight["ticks_in_cut"]) >= 4, "the filters keep stepping through the link loss"
    assert any("PMON: link back (lost" in e for e in flight["events"])
    assert flight["state_after_back"] == State.FAULT, "link back is not an order to fly"
    assert not [t for t, _ in flight["rx"] if c1 < t < flight["resume_t"]], "no setpoint before resume"
    ack = flight["resume_ack"]
    assert ack is not None and ack.result == mavlink.MAV_RESULT_ACCEPTED
    assert flight["state_after_resume"] == State.MONITORING
    assert len([t for t, _ in flight["rx"] if t > flight["resume_t"] + 0.5]) >= 5
    assert flight["counters"].get("io_errors", 0) == 0 and flight["counters"].get("tick_errors", 0) == 0
