"""``pmon replay``: a flight of the mock autopilot (the app and the mock in this process, the DF
feed a process of its own, as tests/sim/test_kraken_sitl.py flies it) re-run from its run log to
the same decisions, bit for bit; a changed setting, an edited input or an edited budget found at
the tick it first changes something; run logs a replay cannot read refused in one line naming
the line. The firmware flights' replays: tests/firmware/test_ardupilot_hub.py, test_px4.py."""
from __future__ import annotations

import json
import time

import pytest

from sim.stack import SitlStack

from tests.support.mavlink_gcs import QUICK_BOOT_S
from tests.support.replay_check import assert_replays_bit_for_bit, replay

pytestmark = pytest.mark.sitl
SCANS = 24.0  # s of scans the feed sends


def _fly(out, seed: int):
    run = out / "run.jsonl"
    st = SitlStack(speedup=2.0, ready_s=QUICK_BOOT_S, seed=seed, auto_launch=True, feed_duration_s=SCANS,
                   runlog_path=str(run), truth_path=str(out / "truth.jsonl"), out_dir=str(out / "rig"))
    st.start()
    try:
        assert st.wait_ready()
        st.start_feed()
        assert st.feed.p.wait(timeout=SCANS / 2 + 120) == 0
        time.sleep(1.0)
    finally:
        st.stop()
    return run


@pytest.fixture(scope="module", params=[7, 8])
def flight(request, tmp_path_factory):
    return _fly(tmp_path_factory.mktemp(f"replay{request.param}"), request.param)


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


@pytest.mark.timeout(300)
def test_a_smaller_qp_budget_changes_the_first_tick_whose_solve_reached_it(flight):
    """guidance.max_qp_solves at N, the most QP solves a search that ended by itself spent: the
    first tick changed is the first whose search spent N and ended by itself, or more and was not
    stopped by the clock at N (or one with the search without the margin: two searches, either
    can reach N)."""
    ticks = _ticks(flight)
    plans = [list(zip(t["replay"]["out"]["plans"], t["replay"]["out"]["qp_solves"], t["replay"]["out"]["margins"]))
             for t in ticks]
    n = max(q for ps in plans for s, q, m in ps if s == "optimal" and m)
    assert n >= 2
    first = next(i for i, ps in enumerate(plans)
                 if any(m and (q > n or (q == n and s == "optimal")) for s, q, m in ps))
    retried = [i for i, ps in enumerate(plans[:first]) if any(m == 0.0 and q >= n for s, q, m in ps)]
    rc, out, err = replay(flight, "--set", f"guidance.max_qp_solves={n}", "--quiet")
    assert (rc, err) == (0, "")
    changed = int(out.split("first changed at tick ")[1].split()[0])
    assert changed in retried + [first] and ": guidance:" in out, (first, retried, out)
    rc, out, err = replay(flight, "--set", "guidance.max_qp_solves=1000")  # above every count: no change
    assert rc == 0 and "no estimate or setpoint changed" in out.splitlines()[-1], out


@pytest.mark.timeout(300)
def test_an_edited_input_is_found_at_its_tick_and_stage(flight, tmp_path):
    ticks = _ticks(flight)
    k = len(ticks) // 2
    scan_ticks = [i for i, t in enumerate(ticks) if i >= k and t["replay"]["scans"]]
    k = scan_ticks[0]
    edited = json.loads(json.dumps(ticks))
    b = edited[k]["replay"]["scans"][0]["b"]
    ch = next(c for c, x in enumerate(b) if x)
    b[ch][0] += 1e-9  # one bearing, a nanoradian
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
