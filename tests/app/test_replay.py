"""``pmon replay``: a flight of the mock autopilot (the app and the mock in this process, the DF
feed a process of its own, as tests/sim/test_kraken_sitl.py flies it) re-run from its run log to
the same decisions, bit for bit; a changed setting, an edited input or an edited budget found at
the tick it first changes something; run logs a replay cannot read refused in one line naming
the line. The firmware flights' replays: tests/firmware/test_ardupilot_hub.py, test_px4.py."""
from __future__ import annotations

import json
import time
import types

import numpy as np
import pytest

from onboard.core.bearings import bearing, wrap
from sim.stack.sitl_stack import SitlStack

from tests.support.mavlink_gcs import QUICK_BOOT_S
from tests.support.replay_check import assert_replays_bit_for_bit, replay

pytestmark = pytest.mark.sitl
SCANS = 24.0  # s of scans the feed sends


def _fly(out, seed: int):
    run = out / "run.jsonl"
    # the first scan at the mission altitude: a scan while the vehicle is still on the ground
    # (armed, the take-off not yet reported) gets a tick without a plan, on a fast machine only
    st = SitlStack(speedup=2.0, ready_s=QUICK_BOOT_S, seed=seed, auto_launch=True, feed_duration_s=SCANS,
                   feed_start="altitude", runlog_path=str(run), truth_path=str(out / "truth.jsonl"),
                   out_dir=str(out / "rig"))
    st.start()
    try:
        assert st.wait_ready()
        st.start_feed()
        assert st.feed.p.wait(timeout=SCANS / 2 + 120) == 0
        time.sleep(1.0)
    finally:
        st.stop()
    return run


@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    # one mock flight: a second seed's cost 24 s of the suite's critical lane; the firmware flights'
    # replays (tests/firmware/test_px4.py, test_ardupilot_hub.py) are two more flights, two more seeds
    return _fly(tmp_path_factory.mktemp("replay"), 7)


def _ticks(path):
    return [json.loads(line) for line in open(path)]


def _write(path, ticks):
    path.write_text("".join(json.dumps(t) + "\n" for t in ticks))
    return path


@pytest.mark.timeout(300)
def test_a_mock_flight_replays_bit_for_bit(flight):
    ticks = assert_replays_bit_for_bit(flight, 15)
    assert sum(t["planned"] for t in ticks) >= 3  # it monitored, not only flew there
    assert all(t["replay"]["out"]["next"] is not None for t in ticks)  # a setpoint every tick


def _plans(ticks):
    """Per tick, each target's (guidance status, QP solves, lateral margin: 5 the first search's
    plan, 0 the search without the margin, None a fallback)."""
    return [list(zip(t["replay"]["out"]["plans"], t["replay"]["out"]["qp_solves"], t["replay"]["out"]["margins"]))
            for t in ticks]


def _changed_by_a_budget(ticks, n: int, cap: int) -> tuple[int | None, list[int]]:
    """With ``max_qp_solves`` at ``n`` instead of the flight's ``cap``: (the first tick a plan
    must change at, None: none; the ticks before it something may change at). A plan of the
    search with the margin changes when that search spent more than n, or n and ended by itself
    (then the budget ends it); above the cap, when the budget ended a search. A plan of the search
    without the margin, or a fallback after both, may change when the two searches spent n or more
    together: either may have reached n (the run log holds their sum). Below the cap, a reference
    plan of the particle steering (a tick's deadlines after its targets' own) that the clock
    stopped past n QP solves may change that tick's setpoint and the next tick's estimates."""
    plans = _plans(ticks)

    def must(s, q, m):
        return s == "budget" if n > cap else bool(m) and (q > n or (q == n and s == "optimal"))

    first = next((i for i, ps in enumerate(plans) if any(must(*p) for p in ps)), None)
    may = {i for i, ps in enumerate(plans) if any(not m and q >= min(n, cap) for s, q, m in ps)}
    if n < cap:
        for i, t in enumerate(ticks):
            if any(d >= len(plans[i]) and q > n for d, q in t["replay"]["stops"]):
                may |= {i, i + 1}
    return first, sorted(i for i in may if first is None or i < first)


def _first_changed(out: str) -> int | None:
    last = out.splitlines()[-1]
    return None if "no estimate or setpoint changed" in last else int(last.split("first changed at tick ")[1].split()[0])


@pytest.mark.timeout(300)
def test_a_smaller_qp_budget_changes_the_first_tick_whose_solve_reached_it(flight):
    """guidance.max_qp_solves at N, the most QP solves a search that ended by itself spent (on a
    machine so loaded that the clock stopped every search, one less than the most any spent): the
    first tick changed is the first whose search spent N and ended by itself, or more (or one
    whose searches together spent N or more: either can have reached N). The flight's own budget
    changes nothing; one above every count changes only a tick whose search the budget ended.
    (A reference plan's count is in the record only where the clock stopped it.)"""
    ticks = _ticks(flight)
    plans = _plans(ticks)
    cap = ticks[0]["replay"]["run"]["scenario"]["guidance"]["max_qp_solves"]
    ended = [q for ps in plans for s, q, m in ps if s == "optimal" and m]
    n = max(ended) if ended else max(q for ps in plans for s, q, m in ps if m) - 1
    assert 2 <= n <= cap
    first, may = _changed_by_a_budget(ticks, n, cap)
    assert first is not None
    rc, out, err = replay(flight, "--set", f"guidance.max_qp_solves={n}", "--quiet")
    assert (rc, err) == (0, "")
    changed = _first_changed(out)
    assert changed in may + [first] and (changed in may or ": guidance:" in out), (first, may, out)
    rc, out, err = replay(flight, "--set", f"guidance.max_qp_solves={cap}")  # the flight's own: no change
    assert (rc, err) == (0, "") and _first_changed(out) is None, out
    first, may = _changed_by_a_budget(ticks, 1000, cap)
    rc, out, err = replay(flight, "--set", "guidance.max_qp_solves=1000", "--quiet")
    assert (rc, err) == (0, "")
    changed = _first_changed(out)
    if first is None and not may:  # no search reached the flight's budget: nothing to change
        assert changed is None, out
    else:
        assert changed in may + [first], (first, may, out)


@pytest.mark.timeout(300)
def test_an_edited_input_is_found_at_its_tick_and_stage(flight, tmp_path):
    ticks = _ticks(flight)
    k = len(ticks) // 2
    scan_ticks = [i for i, t in enumerate(ticks) if i >= k and t["replay"]["scans"]]
    k = scan_ticks[0]
    edited = json.loads(json.dumps(ticks))
    scan = edited[k]["replay"]["scans"][0]
    # the bearing nearest a target's estimate: one far from every particle (clutter) has a
    # likelihood term that is 0.0 in floating point, and a nanoradian changes nothing there
    to_estimates = bearing(np.array(ticks[k]["replay"]["out"]["means"])[:, :2], np.array(scan["p"][:2]))
    ch, i = min(((c, i) for c, bs in enumerate(scan["b"]) for i in range(len(bs))),
                key=lambda ci: abs(wrap(scan["b"][ci[0]][ci[1]] - to_estimates[ci[0]])))
    scan["b"][ch][i] += 1e-9  # one bearing, a nanoradian
    rc, out, _ = replay(_write(tmp_path / "bearing.jsonl", edited))
    assert rc == 1 and f"diverged at tick {k} " in out and ": estimate: means differ" in out, out
    edited = json.loads(json.dumps(ticks))
    j = len(ticks) - 2
    edited[j]["replay"]["out"]["next"][1] += 1e-6  # the recorded setpoint, a micrometre off
    rc, out, _ = replay(_write(tmp_path / "next.jsonl", edited))
    assert rc == 1 and f"diverged at tick {j} " in out and "setpoint: next differs by up to 1e-06 m" in out, out


@pytest.mark.timeout(300)
def test_an_edited_budget_is_found_at_its_tick(flight, tmp_path):
    """A clock stop recorded one QP solve earlier than it was: the guidance of that tick differs."""
    ticks = _ticks(flight)
    edited = json.loads(json.dumps(ticks))
    k = next((i for i, t in enumerate(edited) if any(n > 0 for _, n in t["replay"]["stops"])), None)
    if k is None:  # no solve stopped by the clock in this flight: make one stop after its first QP
        k = next(i for i, t in enumerate(edited) if max(t["replay"]["out"]["qp_solves"]) >= 2)
        edited[k]["replay"]["stops"] = [[d, 1] for d in range(edited[k]["replay"]["deadlines"])]
    else:
        edited[k]["replay"]["stops"] = [[d, max(n - 1, 0)] for d, n in edited[k]["replay"]["stops"]]
    rc, out, _ = replay(_write(tmp_path / "stops.jsonl", edited))
    assert rc == 1 and f"diverged at tick {k} " in out and ": guidance: status" in out, out


@pytest.mark.timeout(300)
@pytest.mark.parametrize("damage, where", [
    (lambda lines: lines[:-1] + [lines[-1][: len(lines[-1]) // 2]], "last"),  # cut mid-line
    (lambda lines: lines[:3] + ["{garbled\n"] + lines[4:], 4),
    (lambda lines: lines[:2] + [json.dumps({"t": 1.0}) + "\n"] + lines[3:], 3),  # an older pmon's record
    (lambda lines: [json.dumps({**json.loads(lines[0]), "replay": {
        k: v for k, v in json.loads(lines[0])["replay"].items() if k != "run"}}) + "\n"] + lines[1:], 1),
    (lambda lines: lines[:4] + [json.dumps({**json.loads(lines[4]), "replay": {
        **json.loads(lines[4])["replay"], "scans": 7}}) + "\n"] + lines[5:], 5),  # values that do not fit
])
def test_a_damaged_run_log_is_refused_in_one_line_naming_the_line(flight, tmp_path, damage, where):
    lines = open(flight).readlines()
    bad = tmp_path / "bad.jsonl"
    bad.write_text("".join(damage(lines)))
    n = len(lines) if where == "last" else where
    rc, out, err = replay(bad)
    assert rc == 2 and out == "" and len(err.strip().splitlines()) == 1, err
    assert err.startswith(f"pmon replay: {bad}:{n}: "), err


def test_a_missing_or_empty_run_log_is_refused_in_one_line(tmp_path):
    for path, why in ((tmp_path / "none.jsonl", "cannot read"), (tmp_path / "empty.jsonl", "no tick records")):
        if why == "no tick records":
            path.write_text("\n")
        rc, out, err = replay(path)
        assert rc == 2 and len(err.strip().splitlines()) == 1 and why in err, err
    rc, _, err = replay(tmp_path / "none.jsonl", "--set", "nonsense")
    assert rc == 2 and "--set" in err and len(err.strip().splitlines()) == 1, err


def test_a_parameter_set_during_a_tick_is_recorded_for_the_tick_it_reaches():
    """The setup a tick's record holds is the one the tick ran with: a PMON parameter set (or
    the autopilot's limits read) while the core ticks, outside the app lock, reaches the next
    tick, and the replay record says so there."""
    from onboard.app.tick.core_side import MonitorCore
    from onboard.app.params import ParamTable
    from onboard.app.replay_record import ReplayRecorder
    from onboard.config import load_scenario
    from onboard.core import monitor
    from onboard.core.clock_stops import SearchClock

    sc = load_scenario("paper")
    params = ParamTable.from_scenario(sc)
    assert params.set("PMON_PARTICLES", 100) is None  # a quick tick
    limits = types.SimpleNamespace(planner=None)
    core = MonitorCore(sc, params, limits, np.random.default_rng(3))
    rec = ReplayRecorder(core, 3)
    altitudes = []
    for k in range(2):
        setup, clock = core.tick_setup(), SearchClock()
        core.state, res = monitor.tick(setup, core.state, [], core.rng, timer=clock)
        if k == 0:  # mid-tick: the new altitude and limits are the next tick's
            assert params.set("PMON_ALT", params["PMON_ALT"] + 5.0) is None
            limits.planner = (9.0, 3.0, 0.0)
        fields = rec.fields(setup, [], None, {}, clock, res)
        altitudes.append((fields["setup"]["params"]["PMON_ALT"], fields["setup"]["planner"]))
    assert altitudes == [(sc.uav.altitude_m, None), (sc.uav.altitude_m + 5.0, [9.0, 3.0, 0.0])]
