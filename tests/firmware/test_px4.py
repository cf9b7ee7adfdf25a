"""PX4's own firmware in the loop: PX4 v1.16.0 SITL (SIH quadrotor, ../shared/px4 or
$PMON_PX4_SITL) run by sim/firmware/px4.py, flying docs/SITL.md's procedure with the real programs
(``pmon run``, ``pmon feed live``, ``pmon gcs``), as tests/firmware/test_ardupilot.py flies ArduCopter's.

- the driver: PX4 in a network namespace of its own, reachable on 127.0.0.1 only, two
  instances side by side, home, parameters at boot over rcS's own, a restart on the same ports,
  the console log and the ULog kept;
- flight A (``launched``): ``pmon gcs launch`` as PX4 boots (arm in Hold, take off AMSL, PX4's
  own switch to Hold, setpoints streaming, OFFBOARD, start), 100 s of monitoring with every scan
  ticked and every setpoint held, a pilot's Hold and POSCTL (sticks centred: PX4 takes POSCTL
  only with manual control) each followed by ``resume``, then the app stopped: PX4 holds
  (COM_OBL_RC_ACT 5, the value docs/SITL.md recommends); ``pmon locate`` reads PX4's own ULog of it;
- flight B (``by_hand``): ``pmon gcs`` on PX4's ground-station link reads the vehicle and
  reaches the app's parameters through PX4's forwarding; ``arm --wait``, ``takeoff 40 --wait``;
  what PX4 does with OFFBOARD (a companion-like client: the ACK is not proof, the stream first,
  the stream stopped); ``start``; the app's link cut (a UDP relay); PX4 restarted, ``launch``.
"""
from __future__ import annotations

import json
import math
import os
import struct
import time

import pytest

from onboard.app.mavlink2 import mavutil
from sim.firmware.px4 import Px4Sitl, find_sitl, links_of, skip_reason
from sim.stack.procedure import Mission, MissionConfig, fly_launch_procedure

pytestmark = [pytest.mark.px4, pytest.mark.sitl,
              pytest.mark.skipif(skip_reason() is not None, reason=skip_reason() or "")]

HOLD = (4 << 16) | (3 << 24)  # PX4 custom_mode: AUTO (4) / LOITER (3)
TAKEOFF = (4 << 16) | (2 << 24)
OFFBOARD = 6 << 16
POSCTL = 3 << 16
MONITOR_S = 100.0
TICK_S = 1.0
MASK_POS = 0b110111111000  # SET_POSITION_TARGET_LOCAL_NED: position only


def param_value(m) -> float:
    """PARAM_VALUE's value: PX4 sends integer parameters bytewise (the int's bytes in the float)."""
    if m.param_type in (mavutil.mavlink.MAV_PARAM_TYPE_REAL32, mavutil.mavlink.MAV_PARAM_TYPE_REAL64):
        return m.param_value
    return struct.unpack("<i", struct.pack("<f", m.param_value))[0]


class Client:
    """A pymavlink client of one PX4 link, every message timed on PX4's clock."""

    def __init__(self, url: str, sysid: int = 245, compid: int = 190):
        self.c = mavutil.mavlink_connection(url, source_system=sysid, source_component=compid,
                                            dialect="ardupilotmega")
        self.hb = None
        self.t = 0.0  # PX4's time_boot_ms, s
        self.pos = None  # LOCAL_POSITION_NED (x, y, z)
        self.gpi = None
        self.acks: list[tuple[float, int, int]] = []  # (t, command, result)
        self.modes: list[tuple[float, int]] = []  # (t, custom_mode) changes
        self.params: dict[str, float] = {}
        self._hb_sent = -math.inf

    def pump(self, wall_s: float = 0.05) -> None:
        if time.monotonic() - self._hb_sent >= 1.0:  # a client that sends first keeps saying so
            self._hb_sent = time.monotonic()
            self.c.mav.heartbeat_send(mavutil.mavlink.MAV_TYPE_ONBOARD_CONTROLLER, 8, 0, 0, 4)
        end = time.monotonic() + wall_s
        while True:
            m = self.c.recv_match(blocking=True, timeout=max(0.0, end - time.monotonic()))
            if m is None:
                return
            kind = m.get_type()
            if hasattr(m, "time_boot_ms") and m.get_srcComponent() == 1:
                self.t = m.time_boot_ms / 1000.0
            if kind == "HEARTBEAT" and m.get_srcComponent() == 1:
                self.hb = m
                if not self.modes or self.modes[-1][1] != m.custom_mode:
                    self.modes.append((self.t, m.custom_mode))
            elif kind == "LOCAL_POSITION_NED":
                self.pos = (m.x, m.y, m.z)
            elif kind == "GLOBAL_POSITION_INT":
                self.gpi = m
            elif kind == "COMMAND_ACK":
                self.acks.append((self.t, m.command, m.result))
            elif kind == "PARAM_VALUE":
                self.params[m.param_id] = param_value(m)
            if time.monotonic() >= end:
                return

    def until(self, pred, wall_s: float, what: str) -> None:
        end = time.monotonic() + wall_s
        while not pred():
            assert time.monotonic() < end, f"{what}: not within {wall_s:g} s wall (modes {self.modes[-3:]})"
            self.pump()

    def command(self, cmd: int, *p: float) -> None:
        self.c.mav.command_long_send(1, 1, cmd, 0, *(list(p) + [0.0] * (7 - len(p))))

    def setpoint(self, pos) -> None:
        self.c.mav.set_position_target_local_ned_send(int(self.t * 1000), 1, 1, mavutil.mavlink.MAV_FRAME_LOCAL_NED,
                                                      MASK_POS, *pos, 0, 0, 0, 0, 0, 0, 0, 0)

    def stream(self, pos, sim_s: float, hz: float = 10.0, then=None) -> None:
        """Send ``pos`` at ``hz`` (PX4's clock) for ``sim_s``; ``then()`` once after the first."""
        t_end, t_next = self.t + sim_s, self.t
        while self.t < t_end:
            if self.t >= t_next:
                self.setpoint(pos)
                t_next = self.t + 1.0 / hz
                if then is not None:
                    then()
                    then = None
            self.pump(0.01)

    def mode(self) -> int | None:
        return None if self.hb is None else self.hb.custom_mode

    def read_param(self, name: str) -> float:
        self.params.pop(name, None)
        self.c.mav.param_request_read_send(1, 1, name.encode(), -1)
        self.until(lambda: name in self.params, 5, f"PARAM_VALUE {name}")
        return self.params[name]


# --------------------------------------------------------------------------- the driver
def _px4_pid(sitl: Px4Sitl) -> int:
    relay = sitl.proc.pid
    return int(open(f"/proc/{relay}/task/{relay}/children").read().split()[0])


def _host_udp_ports() -> set[int]:
    ports = set()
    for path in ("/proc/net/udp", "/proc/net/udp6"):
        with open(path) as f:
            for line in f.readlines()[1:]:
                ports.add(int(line.split()[1].rsplit(":", 1)[1], 16))
    return ports


def test_px4_runs_on_loopback_only_two_instances_side_by_side_each_at_its_home(tmp_path):
    homes = [(35.1468, 33.4126, 160.0), (35.20, 33.50, 300.0)]
    sitls = [Px4Sitl(find_sitl(), h, speed=1, params={"COM_OBL_RC_ACT": 5} if i == 0 else {},
                     workdir=tmp_path / f"w{i}") for i, h in enumerate(homes)]
    try:
        for s in sitls:
            s.start()
        assert sitls[0].instance != sitls[1].instance
        mine = os.readlink("/proc/self/ns/net")
        host = _host_udp_ports()
        for s, home in zip(sitls, homes):
            # PX4 in a namespace of its own: none of its ports is bound where we are
            assert os.readlink(f"/proc/{_px4_pid(s)}/ns/net") != mine
            assert not {p for pair in links_of(s.instance).values() for p in pair} & host
            assert all(sock.getsockname()[0] == "127.0.0.1" for sock in s._host.values())
            c = Client(s.url("api"))
            c.until(lambda: c.hb is not None and c.gpi is not None and c.gpi.lat != 0, 20, "heartbeat, position")
            assert c.hb.autopilot == mavutil.mavlink.MAV_AUTOPILOT_PX4 and c.hb.get_srcSystem() == 1
            assert c.mode() == HOLD
            # each sees its own vehicle, where its driver put it
            north = (c.gpi.lat * 1e-7 - home[0]) * 111_000
            east = (c.gpi.lon * 1e-7 - home[1]) * 111_000 * math.cos(math.radians(home[0]))
            assert math.hypot(north, east) < 3.0 and abs(c.gpi.alt * 1e-3 - home[2]) < 3.0, (c.gpi, home)
            c.c.close()
        c = Client(sitls[0].talk_url("gcs"), sysid=255)
        c.c.mav.heartbeat_send(6, 8, 0, 0, 4)
        assert c.read_param("COM_OBL_RC_ACT") == 5  # a parameter at boot, over rcS's
        c.c.close()
    finally:
        for s in sitls:
            s.stop()
    for s in sitls:  # the firmware's own logs stay where the driver said
        assert "Startup script returned successfully" in s.log_file.read_text()
        assert s.ulogs() and s.ulogs()[0].stat().st_size > 0


def test_speed_factor_keeps_px4s_own_timeouts_and_a_restart_keeps_ports_and_parameters(tmp_path):
    s = Px4Sitl(find_sitl(), speed=2, params={"MPC_XY_VEL_MAX": 11.5}, workdir=tmp_path / "w").start()
    try:
        c = Client(s.talk_url("api"))
        c.c.mav.heartbeat_send(18, 8, 0, 0, 4)
        # rcS multiplies COM_OF_LOSS_T by the speed factor; PX4's clock is the simulation's, so
        # the driver puts back the default (1 s of simulated time)
        assert c.read_param("COM_OF_LOSS_T") == pytest.approx(1.0)
        assert c.read_param("COM_OBC_LOSS_T") == pytest.approx(5.0)
        assert c.read_param("MPC_XY_VEL_MAX") == pytest.approx(11.5)
        c.until(lambda: c.t > 3.0, 10, "3 s of PX4 time")
        port, before = s.port("api"), c.t
        s.restart(down_s=0.5)
        assert s.boots == 2 and s.port("api") == port
        c.c.mav.heartbeat_send(18, 8, 0, 0, 4)  # the same client socket: the relay learns it again
        c.until(lambda: 0 < c.t < before, 20, "PX4's clock after the restart")
        assert c.read_param("MPC_XY_VEL_MAX") == pytest.approx(11.5)
        c.c.close()
    finally:
        s.stop()


# --------------------------------------------------------------------------- flight A: the launch
def _ok(call, want: str = "") -> None:
    assert call.rc == 0 and want in call.stdout, f"pmon gcs {' '.join(call.args)}: exit {call.rc}: " \
        f"{call.stdout.strip()} {call.stderr.strip()}"


def _modes_between(m, t0: float, t1: float) -> list[tuple[float, int]]:
    with m.observer.lock:
        modes = [(t, mo) for t, mo, _ in m.observer.modes if t is not None]
    before = [mo for t, mo in modes if t <= t0][-1:]
    return [(t0, before[0])] * bool(before) + [(t, mo) for t, mo in modes if t0 < t <= t1]


def _flight_a_figures(m, rec) -> dict:
    """The procedure's targets as flight A measured them (printed: docs/SITL.md quotes them)."""
    import numpy as np

    acc = rec["account"]
    d = m.follow_errors_m()
    entered = next((t for t, mo in _modes_between(m, rec["start_t"], math.inf) if mo == OFFBOARD), None)
    modes = _modes_between(m, entered, rec["start_t"] + MONITOR_S) if entered is not None else []
    return {"operator_launches": sum(c.args == ("launch",) for c in m.commands),
            "scans": acc["scans"], "ticks": acc["ticks"], "monitoring_ticks": acc["monitoring_ticks"],
            "scans_unticked": acc["scans_unticked"], "unticked_t": acc["unticked_t"],
            "ticks_skipped": acc["ticks_skipped"], "ticks_late": acc["ticks_late"], "late_t": acc["late_t"],
            "offboard_after_start_s": None if entered is None else round(entered - rec["start_t"], 2),
            "out_of_offboard_while_monitoring": sum(mo != OFFBOARD for _, mo in modes),
            "takeover_reaction_s": [round(r, 3) for r in rec["reactions"]],
            "from_plan_at_next_tick_m_median": round(float(np.median(d)), 2) if d else None,
            "from_plan_at_next_tick_m_p95": round(float(np.percentile(d, 95)), 2) if d else None,
            "follow_samples": len(d), "stick_gap_s": rec["stick_gap_s"]}


@pytest.fixture(scope="module")
def launched(tmp_path_factory):
    """The procedure from PX4's boot: ``pmon gcs launch`` at once, MONITOR_S of monitoring (a
    pilot's sticks live, centred), the pilot takes Hold then POSCTL, each followed by ``pmon gcs
    resume``; then the app stops (its setpoint stream with it)."""
    out = tmp_path_factory.mktemp("px4_launch")
    cfg = MissionConfig(autopilot="px4", speedup=2.0, params={"COM_OBL_RC_ACT": 5},
                        feed_duration_s=MONITOR_S + 80, seed=1)
    with Mission(cfg, out) as m:
        rec = fly_launch_procedure(m, MONITOR_S, during=lambda m, rec: m.take_sticks(),
                                   takeovers=(("mode", "HOLD"), ("mode", "POSCTL")))
        rec["m"] = m
        rec["monitor_end_t"] = rec["start_t"] + MONITOR_S
        rec["gcs_saw_estimates"] = sorted({e[1] for e in m.observer.estimates})
        rec["reactions"] = m.takeover_reactions()
        rec["stick_gap_s"] = m.sticks.gap_s
        rec["account"] = m.tick_account()  # of every scan the feed sent: it stops first
        m.rig.feed.stop(timeout=10)
        m.sim_sleep(1.5)
        rec["account"] = m.tick_account()
        rec["figures"] = _flight_a_figures(m, rec)
        print("px4 flight A:", json.dumps(rec["figures"], default=str))
        rec["stop_asked_t"] = m.observer.t
        m.app.stop()
        # PX4's loss timeout runs from the app's last setpoint (its own tlog), not from the stop's
        # request: the app streams on while it stops (SIGINT, its threads joined), or stopped
        # before, when a failsafe had already taken PX4 out of OFFBOARD (the pilot's sticks
        # lapsed past COM_RC_LOSS_T: Hold, then RTL, which the list then shows). PX4's mode is
        # watched for 4 s of its clock after the app is gone.
        ended_t = m.observer.t or rec["stop_asked_t"]
        rec["stop_t"] = _last_setpoint_t(m.out / "app.tlog", rec["stop_asked_t"])
        deadline = time.monotonic() + 20
        while (m.observer.t or 0) < max(ended_t, rec["stop_t"]) + 4.0 and time.monotonic() < deadline:
            time.sleep(0.1)
        rec["modes_after_stop"] = _modes_between(m, rec["stop_t"], math.inf)[1:]
        print("px4 flight A, the app stopped:", json.dumps({
            "asked_t": rec["stop_asked_t"], "last_setpoint_t": rec["stop_t"], "gone_t": ended_t,
            "modes_after": [(t, hex(mo)) for t, mo in rec["modes_after_stop"]]}))
    yield rec


def _last_setpoint_t(tlog, default: float) -> float:
    """PX4 s of the app's last SET_POSITION_TARGET_LOCAL_NED (its time_boot_ms: the app's clock
    of PX4's), from the app's own tlog; ``default`` if it sent none."""
    conn = mavutil.mavlink_connection(str(tlog), dialect="ardupilotmega")
    last = default
    while (msg := conn.recv_match(type="SET_POSITION_TARGET_LOCAL_NED")) is not None:
        last = msg.time_boot_ms / 1000.0
    conn.close()
    return last


@pytest.mark.timeout(900)
def test_the_flight_replays_to_the_same_decisions_bit_for_bit(launched):
    """``pmon replay`` of the flight's run log (docs/MAVLINK.md "Replay"): every estimate and setpoint
    again, the guidance's clock stops replayed as counts."""
    from tests.support.replay_check import assert_replays_bit_for_bit
    ticks = assert_replays_bit_for_bit(launched["m"].out / "run.jsonl", MONITOR_S)
    assert sum(t["planned"] for t in ticks) >= MONITOR_S / 2


def test_launch_from_boot_flies_without_a_retry(launched):
    """One ``launch`` from PX4's boot: armed in Hold, the take-off AMSL, PX4's own switch back
    to Hold, then setpoints streaming before OFFBOARD was asked for."""
    from onboard.app.mavlink2 import mavutil as mu

    m = launched["m"]
    _ok(launched["launch"], "accepted by the onboard app")
    assert [c.args for c in m.commands][:1] == [("launch",)] and sum(c.args == ("launch",) for c in m.commands) == 1
    texts = m.observer.app_texts()
    for want in ("PMON: launch: AUTO.LOITER, arm, take off, OFFBOARD", "PMON: launch: armed",
                 "PMON: launch: climbing to 40 m", "PMON: OFFBOARD: monitoring"):
        assert want in texts, texts
    assert any(t.startswith("PMON: monitoring: switching to OFFBOARD (setpoints streaming") for t in texts), texts
    assert not any("launch failed" in t or "aborted" in t or "not entered" in t for t in texts), texts
    # the app's own tlog: take-off AMSL (home 160 m + 40), arm before any OFFBOARD request, and
    # its first OFFBOARD request >= 1 s of PX4's clock after the first setpoint
    conn = mu.mavlink_connection(str(m.out / "app.tlog"), dialect="ardupilotmega")
    first = {}
    t = None
    while (msg := conn.recv_match()) is not None:
        if msg.get_srcComponent() == 1 and hasattr(msg, "time_boot_ms"):
            t = msg.time_boot_ms / 1000.0
        key = None
        if msg.get_type() == "COMMAND_LONG" and msg.get_srcComponent() == 191:
            key = {400: "arm", 22: "takeoff"}.get(msg.command)
            if msg.command == 176 and msg.param2 == 6:
                key = "offboard"
            if key == "takeoff":
                first.setdefault("takeoff_alt", msg.param7)
        elif msg.get_type() == "SET_POSITION_TARGET_LOCAL_NED":
            key = "setpoint"
        if key and key not in first:
            first[key] = t
    assert first["arm"] < first["takeoff"] < first["setpoint"] < first["offboard"], first
    assert first["offboard"] - first["setpoint"] >= 1.0, first
    from sim.firmware.px4 import home_of
    home_amsl = home_of(m.sc)[2]  # where the driver put PX4's home
    assert first["takeoff_alt"] == pytest.approx(home_amsl + 40.0, abs=2.0), first
    assert m.sitl.boots == 1 and m.autopilot_crashes() == 0


def test_every_scan_ticked_and_every_setpoint_followed_for_100_s_in_offboard_throughout(launched):
    import numpy as np

    m = launched["m"]
    acc = launched["account"]
    assert acc["scans_unticked"] == 0 and acc["ticks_skipped"] == 0 and acc["ticks_late"] == 0, acc
    assert acc["monitoring_ticks"] >= MONITOR_S, acc
    d = m.follow_errors_m()
    assert len(d) >= MONITOR_S * 0.9
    assert np.median(d) <= 1.5 and np.percentile(d, 95) <= 3.0, (np.median(d), np.percentile(d, 95))
    # never out of OFFBOARD while monitoring (PX4 leaves it 1 s after a lapse of the stream)
    # (from OFFBOARD's entry: the app says "monitoring" from the moment it streams its hold)
    entered = next(t for t, mo in _modes_between(m, launched["start_t"], math.inf) if mo == OFFBOARD)
    assert entered - launched["start_t"] <= 3.0
    modes = _modes_between(m, entered, launched["monitor_end_t"])
    assert modes and all(mo == OFFBOARD for _, mo in modes), ([(t, hex(mo)) for t, mo in modes],
                                                              launched["stick_gap_s"], m.observer.app_texts())
    c = m.containment()
    assert c["outside_area"] == 0 and c["in_obstacle"] == 0, c


def test_the_ground_station_on_px4s_gcs_link_sees_every_estimate(launched):
    """Through PX4's forwarding (its GCS link), besides the echo PX4 sends of the app's last
    DEBUG_FLOAT_ARRAY as its own (1/1), which the observer, as the hub, ignores."""
    assert launched["gcs_saw_estimates"] == [0, 1, 2, 3]


def test_takeover_by_hold_and_by_posctl_stops_the_setpoints_within_a_tick_and_resume_flies_again(launched):
    m = launched["m"]
    for key, name in (("HOLD", "AUTO.LOITER"), ("POSCTL", "POSCTL")):
        _ok(launched[key], f"mode {name}")
        assert launched[f"{key}_app"] == "pilot override"
        _ok(launched[f"{key}_resume"], "app monitoring")
        # the app's own log: the ground station's copy comes through PX4's forwarding, which
        # dropped this two-chunk STATUSTEXT once in three runs under load (its queue holds two
        # messages per link); the app's state (its HEARTBEAT, above) is what pmon gcs shows
        assert f"PMON: pilot override (mode {name}): setpoints stopped" in m.app_log()
    reactions = launched["reactions"]
    assert len(reactions) == 2 and max(reactions) <= TICK_S, reactions
    assert launched["end_state"] == "monitoring"


def test_when_the_app_stops_px4_leaves_offboard_for_hold_within_its_loss_timeout(launched):
    modes = launched["modes_after_stop"]
    assert modes and modes[0][1] == HOLD and modes[0][0] - launched["stop_t"] <= 2.5, modes


def test_pmon_locate_finds_both_emitters_from_this_flights_ulog(launched, tmp_path, capsys):
    """``pmon locate`` on PX4's own ULog of this flight (tests/support/locate_check.py): its poses
    are the positions PX4 reported, when it reported them (SIH writes no UTC: the recording's
    boot time is given); a KrakenSDR recording drawn along them locates two emitters 250-600 m
    away within 15 m, the ellipses consistent (NEES)."""
    from tests.support.locate_check import locate_from_flight
    locate_from_flight(launched["m"], "ulg", tmp_path, capsys, airborne_s=MONITOR_S)


# --------------------------------------------------------------------------- flight B: by hand
@pytest.fixture(scope="module")
def by_hand(tmp_path_factory):
    """``pmon gcs`` on PX4's GCS link with the app idle, ``arm --wait``, ``takeoff 40 --wait``; a
    companion-like client on the offboard link shows what PX4 makes of OFFBOARD; ``start``; the
    app's link cut for 3 s; PX4 restarted, ``launch`` again (the app in fault until told)."""
    out = tmp_path_factory.mktemp("px4_by_hand")
    cfg = MissionConfig(autopilot="px4", speedup=2.0, params={"COM_OBL_RC_ACT": 5}, feed_duration_s=400, seed=7,
                        link_proxy=True)
    rec: dict = {}
    with Mission(cfg, out) as m:
        rec["m"] = m
        m.wait(lambda o: o.app_state is not None and o.origin is not None, 30, "the app's heartbeat")
        rec["status"] = m.gcs("status")
        rec["param_get"] = m.gcs("params", "get", "PMON_CLUTTER")
        rec["param_set"] = m.gcs("params", "set", "PMON_CLUTTER", "1.5")
        rec["brake"] = m.gcs("mode", "BRAKE")
        rec["arm"] = m.gcs("arm", "--wait", timeout=60)
        rec["takeoff"] = m.gcs("takeoff", "40", "--wait", timeout=60)
        c = rec["client"] = Client(m.sitl.talk_url("api"), sysid=1, compid=196)
        c.c.mav.heartbeat_send(18, 8, 0, 0, 4)
        c.until(lambda: c.pos is not None and c.hb is not None and c.t >= (m.observer.t or 0), 20, "position")
        c.until(lambda: c.mode() == HOLD, 20, "Hold after the take-off")
        rec["after_takeoff"] = (c.t, c.mode(), c.pos)
        hover = (c.pos[0], c.pos[1], c.pos[2])
        # OFFBOARD asked with no setpoint stream
        n = len(c.acks)
        c.command(mavutil.mavlink.MAV_CMD_DO_SET_MODE, 1, 6, 0)
        t0 = c.t
        c.until(lambda: c.t > t0 + 3.0, 10, "3 s")
        rec["no_stream"] = ([a for a in c.acks[n:] if a[1] == 176], c.mode())
        # the stream first, then the switch: confirmed by HEARTBEAT
        n = len(c.acks)
        c.stream(hover, 1.2)
        rec["switch_t"] = c.t
        c.stream(hover, 3.0, then=lambda: c.command(mavutil.mavlink.MAV_CMD_DO_SET_MODE, 1, 6, 0))
        rec["with_stream"] = ([a for a in c.acks[n:] if a[1] == 176], list(c.modes))
        rec["client_stop_t"] = c.t
        c.until(lambda: c.mode() != OFFBOARD, 10, "out of OFFBOARD")
        rec["left"] = (c.t, c.mode())
        c.c.close()
        rec["start"] = m.gcs("start")
        m.sim_sleep(15.0)
        rec["state_before_cut"] = m.observer.app_state
        # the app's link drops for 3 s (wall): its stream with it
        rec["cut_t"] = m.observer.t
        m.proxy.cut(3.0)
        rec["back"] = m.wait(lambda o: any("link back" in t for t in o.app_texts()), 30, "link back")
        m.wait(lambda o: o.app_state == "fault", 5, "fault")
        rec["state_after_cut"] = m.observer.app_state
        rec["modes_after_cut"] = _modes_between(m, rec["cut_t"], math.inf)[1:]
        rec["resume"] = m.gcs("resume")
        m.sim_sleep(6.0)
        rec["state_after_resume"] = m.observer.app_state
        restart_wall = time.monotonic()
        m.sitl.restart(down_s=2.0)
        rec["rebooted"] = m.wait(lambda o: o.boots >= 1 and o.t is not None, 60, "reboot")
        rec["said_reboot"] = m.wait(lambda o: any("autopilot rebooted" in t for t in o.app_texts()), 30, "reboot")
        m.wait(lambda o: o.app_state == "fault", 10, "fault")
        rec["state_after"] = m.observer.app_state
        rec["launch"] = m.gcs("launch")
        rec["monitoring_again"] = m.wait(lambda o: o.app_state == "monitoring", 150, "monitoring")
        rec["texts"] = m.observer.app_texts()
        modes = rec["modes_after_cut"]
        print("px4 flight B:", json.dumps({
            "arm_wait_s": round(rec["arm"].wall_s, 1), "takeoff_wait_s": round(rec["takeoff"].wall_s, 1),
            "cut_to_hold_s": round(modes[0][0] - rec["cut_t"], 2) if modes else None,
            "restart_to_monitoring_wall_s": round(time.monotonic() - restart_wall, 1),
            "restart_to_monitoring_px4_s": m.observer.t, "monitoring_again": rec["monitoring_again"],
            "operator_commands": [" ".join(c.args) for c in m.commands]}))
    yield rec


def test_the_app_finds_px4_and_pmon_gcs_reaches_the_app_through_px4s_forwarding(by_hand):
    m = by_hand["m"]
    log = m.app_log()
    assert "PMON: autopilot 1/1 found" in log and "PMON: NED origin fixed" in log, log[-2000:]
    assert "PMON: PX4 cannot sign MAVLink: the autopilot link cannot be signed" in log
    assert "PMON: planning at " in log  # from MPC_XY_VEL_MAX and MPC_ACC_HOR
    _ok(by_hand["status"], "vehicle 1: AUTO.LOITER, disarmed")
    assert "onboard app: idle" in by_hand["status"].stdout
    # PARAM_REQUEST_READ / PARAM_SET to component 191, from PX4's GCS link to its offboard link
    _ok(by_hand["param_get"], "PMON_CLUTTER = 1")
    _ok(by_hand["param_set"], "PMON_CLUTTER = 1.5")
    # an ArduCopter mode PX4 has not: said, not sent (BRAKE = 17 was ACKed and did nothing)
    assert by_hand["brake"].rc == 1 and "PX4 has no mode BRAKE: use AUTO.LOITER" in by_hand["brake"].stderr
    assert m.autopilot_crashes() == 0


def test_arm_wait_in_hold_and_takeoff_40_reaches_40_m_above_home_with_the_amsl_altitude(by_hand):
    _ok(by_hand["arm"], "accepted by the autopilot; AUTO.LOITER, armed")
    _ok(by_hand["takeoff"], "at 40 m after")
    t, mode, pos = by_hand["after_takeoff"]
    assert mode == HOLD  # PX4 ends its take-off in Hold by itself
    assert -pos[2] == pytest.approx(40.0, abs=1.5), pos


def test_offboard_needs_the_stream_first_and_only_heartbeat_says_the_mode(by_hand):
    acks, mode = by_hand["no_stream"]
    # answered, and even ACCEPTED first, but nothing changed
    assert acks and acks[0][2] == mavutil.mavlink.MAV_RESULT_ACCEPTED, acks
    assert any(a[2] == mavutil.mavlink.MAV_RESULT_TEMPORARILY_REJECTED for a in acks), acks
    assert mode == HOLD
    acks, modes = by_hand["with_stream"]
    assert acks and all(a[2] == mavutil.mavlink.MAV_RESULT_ACCEPTED for a in acks), acks
    entered = [t for t, mo in modes if mo == OFFBOARD and t >= by_hand["switch_t"]]
    assert entered and entered[0] - by_hand["switch_t"] <= 1.5, modes  # one heartbeat (1 Hz) later


def test_px4_leaves_offboard_for_hold_when_the_stream_stops(by_hand):
    t, mode = by_hand["left"]
    assert mode == HOLD, hex(mode)  # COM_OBL_RC_ACT 5; PX4's default (0) is POSCTL, which descends without RC
    assert 0.9 <= t - by_hand["client_stop_t"] <= 2.5  # COM_OF_LOSS_T 1 s, seen at the next heartbeat


def test_start_enters_offboard_by_itself_the_way_px4_requires(by_hand):
    _ok(by_hand["start"], "app monitoring")
    assert by_hand["state_before_cut"] == "monitoring"
    texts = by_hand["texts"]
    assert "PMON: OFFBOARD: monitoring" in texts, texts


def test_a_cut_link_stops_the_stream_px4_holds_and_the_app_waits_for_resume(by_hand):
    """The app's link cut for 3 s wall (6 s of PX4's): PX4 leaves OFFBOARD 1 s after the last
    setpoint, for Hold (COM_OBL_RC_ACT 5); the app, link back, flies again only when told."""
    modes = by_hand["modes_after_cut"]
    assert modes and modes[0][1] == HOLD and modes[0][0] - by_hand["cut_t"] <= 2.5, modes
    assert by_hand["back"] and by_hand["state_after_cut"] == "fault"
    assert any(t.startswith("PMON: link back (lost ") and t.endswith(": send resume") for t in by_hand["texts"])
    _ok(by_hand["resume"], "app monitoring")
    assert by_hand["state_after_resume"] == "monitoring"


def test_px4_restarted_mid_mission_is_survived_and_the_app_flies_again_only_when_told(by_hand):
    assert by_hand["rebooted"] and by_hand["said_reboot"] and by_hand["state_after"] == "fault"
    assert not any("NED origin moved" in t for t in by_hand["texts"]), by_hand["texts"]
    _ok(by_hand["launch"], "accepted by the onboard app")
    assert by_hand["monitoring_again"], by_hand["texts"]


# --------------------------------------------------------------------------- signing
def test_signing_with_px4_the_autopilot_link_is_unsigned_and_said_and_nothing_signed_passes_px4(tmp_path):
    """PX4 v1.16 cannot sign: it checks no signature, signs nothing, and replaces the signature
    block of every message it forwards with other bytes (measured: the app's signed HEARTBEAT
    reached the GCS link with link id 0 and a different timestamp and signature). With a key,
    ``pmon run`` hears PX4 only with ``--autopilot-unsigned`` and says so plainly either way; a
    ground station's signed commands forwarded by PX4 fail their check and are not obeyed, and
    both ends say why (a signed ground-station link must not pass through PX4: docs/SAFETY.md)."""
    import subprocess
    import sys
    import threading

    from onboard.app.signing import make_key_file

    key = tmp_path / "pmon.key"
    make_key_file(key)
    sitl = Px4Sitl(find_sitl(), speed=2, workdir=tmp_path / "px4", listeners={"gcs": 1, "api": 1}).start()
    procs = []

    def app(*extra):
        p = subprocess.Popen([sys.executable, "-m", "onboard.cli", "run", "--mavlink", sitl.url("api"),
                              "--df", "127.0.0.1:0", "--signing-key", str(key), *extra],
                             stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        p.lines = []
        threading.Thread(target=lambda: p.lines.extend(p.stdout), daemon=True).start()
        procs.append(p)
        return p

    def until(p, want: str, wall_s: float) -> str:
        end = time.monotonic() + wall_s
        while not any(want in x for x in p.lines) and time.monotonic() < end:
            time.sleep(0.1)
        return "".join(p.lines)

    def gcs(*args):
        return subprocess.run([sys.executable, "-m", "onboard.cli", "gcs", "--connect", sitl.url("gcs"),
                               "--timeout", "4", *args], capture_output=True, text=True, timeout=60)
    try:
        deaf = app()
        out = until(deaf, "no autopilot heard", 20)
        assert "no autopilot heard: " in out and "needs --autopilot-unsigned" in out, out
        deaf.terminate()
        deaf.wait(10)
        heard = app("--autopilot-unsigned")
        out = until(heard, "NED origin fixed", 30)
        assert "PMON: autopilot 1/1 found" in out and "the autopilot link is UNSIGNED" in out, out
        signed = ("--signing-key", str(key), "--autopilot-unsigned")
        st = gcs(*signed, "status")
        assert st.returncode == 0 and "vehicle 1: AUTO.LOITER" in st.stdout, st.stdout + st.stderr
        assert "failed the signature check: PX4 rewrites the signature of what it forwards" in st.stdout, st.stdout
        ps = gcs(*signed, "params", "set", "PMON_CLUTTER", "1.5")
        assert ps.returncode == 3 and "no answer from the onboard app" in ps.stderr, ps.stdout + ps.stderr
        out = until(heard, "fail their signature", 10)
        assert "packets from 255/190 fail their signature (PX4 rewrites the signature of every message it " \
               "forwards" in out, out
        no_flag = gcs("--signing-key", str(key), "status")
        assert no_flag.returncode == 3 and "needs --autopilot-unsigned" in no_flag.stderr, no_flag.stderr
        stranger = gcs("params", "set", "PMON_CLUTTER", "2")  # no key: PX4 forwards it, the app drops it
        assert stranger.returncode == 3 and "no answer from the onboard app" in stranger.stderr, stranger.stderr
    finally:
        for p in procs:
            p.terminate()
            p.wait(10)
        sitl.stop()
