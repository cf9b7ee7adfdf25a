"""PX4's own firmware in the loop: PX4 v1.16.0 SITL (SIH quadrotor, ../shared/px4 or
$PMON_PX4_SITL) run by sim/px4.py, with the real programs where they already work on PX4.

What holds today (issue 30, phase 1):
- the driver: PX4 in a network namespace of its own, reachable on 127.0.0.1 only, two
  instances side by side, home, parameters at boot over rcS's own, a restart on the same ports,
  the console log and the ULog kept;
- ``pmon run`` finds PX4 and fixes its NED origin; ``pmon gcs`` on PX4's ground-station link
  reads the vehicle and reaches the app's parameters through PX4's forwarding;
- arming in Hold, ``pmon gcs takeoff 40 --wait`` (PX4 reads the altitude AMSL) and PX4 in Hold
  after it; OFFBOARD entered the way PX4 requires (a setpoint stream first), the mode known from
  HEARTBEAT only (a DO_SET_MODE without the stream is answered ACCEPTED, then
  TEMPORARILY_REJECTED, and nothing changes); the stream stopped: PX4 leaves OFFBOARD for Hold
  (COM_OBL_RC_ACT 5).

The documented procedure end to end (launch, by hand, takeovers, stream loss, restart) is below,
marked xfail and not run: it needs the app to speak PX4 (phase 2; the reason on each test says
what fails today, measured against this firmware).
"""
from __future__ import annotations

import math
import os
import struct
import time

import pytest

from sim.px4 import Px4Sitl, find_sitl, links_of, skip_reason
from sim.procedure import Mission, MissionConfig, fly_launch_procedure

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil  # noqa: E402

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


# --------------------------------------------------------------------------- the app and the firmware
@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    """pmon run, pmon feed live and pmon gcs against PX4 at 2x (COM_OBL_RC_ACT 5: Hold when the
    offboard stream stops), the app left idle; a companion-like client on the offboard link arms
    and enters OFFBOARD the way PX4 requires."""
    out = tmp_path_factory.mktemp("px4_flight")
    rec: dict = {}
    cfg = MissionConfig(autopilot="px4", speedup=2.0, params={"COM_OBL_RC_ACT": 5}, feed_duration_s=300)
    with Mission(cfg, out) as m:
        rec["m"] = m
        m.wait(lambda o: o.app_state is not None and o.origin is not None, 30, "the app's heartbeat")
        rec["status"] = m.gcs("status")
        rec["param_get"] = m.gcs("params", "get", "PMON_CLUTTER")
        rec["param_set"] = m.gcs("params", "set", "PMON_CLUTTER", "1.5")
        c = rec["client"] = Client(m.sitl.talk_url("api"), sysid=1, compid=196)
        c.c.mav.heartbeat_send(18, 8, 0, 0, 4)
        c.until(lambda: c.pos is not None and c.hb is not None, 20, "position")
        rec["boot_t"] = c.t
        while not c.hb.base_mode & mavutil.mavlink.MAV_MODE_FLAG_SAFETY_ARMED:
            c.command(mavutil.mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1)
            c.until(lambda: c.acks and c.acks[-1][1] == 400, 5, "arm ACK")
            c.pump(0.5)
            assert c.t - rec["boot_t"] < 30, f"not armable in 30 s: {c.acks}"
        rec["armed_t"] = c.t
        rec["takeoff"] = m.gcs("takeoff", "40", "--wait", timeout=60)
        done = m.observer.t  # the client read nothing meanwhile: through its backlog first
        c.until(lambda: c.t >= done and c.mode() == HOLD, 20, "Hold after the take-off")
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
        # the stream stops
        rec["stop_t"] = c.t
        c.until(lambda: c.mode() != OFFBOARD, 10, "out of OFFBOARD")
        rec["left"] = (c.t, c.mode())
        c.c.close()
    yield rec


def test_the_app_finds_px4_and_pmon_gcs_reaches_the_app_through_px4s_forwarding(flight):
    m = flight["m"]
    log = m.app_log()
    assert "PMON: autopilot 1/1 found" in log and "PMON: NED origin fixed" in log, log[-2000:]
    st = flight["status"]
    assert st.rc == 0 and "vehicle 1:" in st.stdout and "onboard app: idle" in st.stdout, st.stdout + st.stderr
    # PARAM_REQUEST_READ / PARAM_SET to component 191, from PX4's GCS link to its offboard link
    assert flight["param_get"].rc == 0 and "PMON_CLUTTER = 1" in flight["param_get"].stdout
    assert flight["param_set"].rc == 0 and "PMON_CLUTTER = 1.5" in flight["param_set"].stdout
    assert m.autopilot_crashes() == 0


def test_armed_in_hold_and_takeoff_40_reaches_40_m_above_home_with_the_amsl_altitude(flight):
    assert flight["armed_t"] - flight["boot_t"] < 15.0  # armable ~5 s after boot (PX4's README): long since
    call = flight["takeoff"]
    assert call.rc == 0 and "at 40 m after" in call.stdout, call.stdout + call.stderr
    t, mode, pos = flight["after_takeoff"]
    assert mode == HOLD  # PX4 ends its take-off in Hold by itself
    assert -pos[2] == pytest.approx(40.0, abs=1.5), pos


def test_offboard_needs_the_stream_first_and_only_heartbeat_says_the_mode(flight):
    acks, mode = flight["no_stream"]
    # answered, and even ACCEPTED first, but nothing changed
    assert acks and acks[0][2] == mavutil.mavlink.MAV_RESULT_ACCEPTED, acks
    assert any(a[2] == mavutil.mavlink.MAV_RESULT_TEMPORARILY_REJECTED for a in acks), acks
    assert mode == HOLD
    acks, modes = flight["with_stream"]
    assert acks and all(a[2] == mavutil.mavlink.MAV_RESULT_ACCEPTED for a in acks), acks
    entered = [t for t, mo in modes if mo == OFFBOARD and t >= flight["switch_t"]]
    assert entered and entered[0] - flight["switch_t"] <= 1.5, modes  # one heartbeat (1 Hz) later


def test_px4_leaves_offboard_for_hold_when_the_stream_stops(flight):
    t, mode = flight["left"]
    assert mode == HOLD, hex(mode)  # COM_OBL_RC_ACT 5; PX4's default (0) is POSCTL, which descends without RC
    assert 0.9 <= t - flight["stop_t"] <= 2.5  # COM_OF_LOSS_T 1 s, seen at the next heartbeat


# --------------------------------------------------------------------------- phase 2: the procedure
PHASE2 = "issue 30 phase 2: "
NOT_YET = dict(run=False, strict=True)


@pytest.fixture(scope="module")
def launched(tmp_path_factory):
    """The procedure from PX4's boot: ``pmon gcs launch`` at once, MONITOR_S of monitoring, the
    pilot takes Hold then POSCTL, each followed by ``pmon gcs resume``; then the app stops (its
    setpoint stream with it)."""
    out = tmp_path_factory.mktemp("px4_launch")
    cfg = MissionConfig(autopilot="px4", speedup=1.5, params={"COM_OBL_RC_ACT": 5},
                        feed_duration_s=MONITOR_S + 80, seed=1)
    with Mission(cfg, out) as m:
        rec = fly_launch_procedure(m, MONITOR_S, takeovers=(("mode", "HOLD"), ("mode", "POSCTL")))
        rec["m"] = m
        rec["gcs_saw_estimates"] = sorted({e[1] for e in m.observer.estimates})
        rec["stop_t"] = m.observer.t
        m.app.stop()
        m.sim_sleep(4.0)
        with m.observer.lock:
            rec["modes_after_stop"] = [(t, mo) for t, mo, _ in m.observer.modes if t is not None and t > rec["stop_t"]]
    yield rec


@pytest.mark.xfail(reason=PHASE2 + "launch takes OFFBOARD before any setpoint and before arming: PX4 shows OFFBOARD "
                   "on the ground, then refuses every ARM (TEMPORARILY_REJECTED, reason only in EVENT 410) forever",
                   **NOT_YET)
def test_launch_from_boot_flies_without_a_retry(launched):
    m = launched["m"]
    texts = m.observer.app_texts()
    assert "PMON: monitoring started" in texts and not any("launch failed" in t for t in texts), texts
    assert m.sitl.boots == 1 and m.autopilot_crashes() == 0


@pytest.mark.xfail(reason=PHASE2 + "the app never enters OFFBOARD by itself (see the launch)", **NOT_YET)
def test_every_scan_ticked_and_every_setpoint_followed_for_100_s(launched):
    m = launched["m"]
    acc = m.tick_account()
    assert acc["scans_unticked"] == 0 and acc["ticks_skipped"] == 0 and acc["ticks_late"] == 0, acc
    assert acc["monitoring_ticks"] >= MONITOR_S, acc
    d = m.follow_errors_m()
    assert len(d) >= MONITOR_S * 0.9
    import numpy as np
    assert np.median(d) <= 1.5 and np.percentile(d, 95) <= 3.0, (np.median(d), np.percentile(d, 95))
    c = m.containment()
    assert c["outside_area"] == 0 and c["in_obstacle"] == 0, c


@pytest.mark.xfail(reason=PHASE2 + "no monitoring without OFFBOARD; PX4 echoes DEBUG_FLOAT_ARRAY as its own "
                   "(1/1) besides forwarding the app's (1/191)", **NOT_YET)
def test_the_ground_station_on_px4s_gcs_link_sees_every_estimate(launched):
    assert launched["gcs_saw_estimates"] == [0, 1, 2, 3]


@pytest.mark.xfail(reason=PHASE2 + "pmon gcs mode names are ArduCopter's (LOITER = 5 is PX4's ACRO: refused); "
                   "resume asks OFFBOARD with no stream: ACCEPTED then TEMPORARILY_REJECTED, the app pauses",
                   **NOT_YET)
def test_takeover_by_hold_and_by_posctl_stops_the_setpoints_within_a_tick_and_resume_flies_again(launched):
    m = launched["m"]
    for key in ("HOLD", "POSCTL"):
        assert launched[key].rc == 0 and launched[f"{key}_app"] == "pilot override"
        assert launched[f"{key}_resume"].rc == 0
    reactions = m.takeover_reactions()
    assert len(reactions) == 2 and max(reactions) <= TICK_S, reactions
    assert launched["end_state"] == "monitoring"


@pytest.mark.xfail(reason=PHASE2 + "needs monitoring in OFFBOARD first", **NOT_YET)
def test_when_the_app_stops_px4_leaves_offboard_for_hold_within_its_loss_timeout(launched):
    modes = launched["modes_after_stop"]
    assert modes and modes[0][1] == HOLD and modes[0][0] - launched["stop_t"] <= 2.5, modes


@pytest.fixture(scope="module")
def by_hand(tmp_path_factory):
    """``pmon gcs arm --wait``, ``takeoff 40 --wait``, ``start``; PX4 restarted mid-mission;
    ``launch`` again (the app in fault until told)."""
    out = tmp_path_factory.mktemp("px4_by_hand")
    cfg = MissionConfig(autopilot="px4", speedup=2.0, params={"COM_OBL_RC_ACT": 5}, feed_duration_s=400, seed=7)
    rec: dict = {}
    with Mission(cfg, out) as m:
        rec["m"] = m
        rec["arm"] = m.gcs("arm", "--wait", timeout=60)
        rec["takeoff"] = m.gcs("takeoff", "40", "--wait", timeout=60)
        rec["start"] = m.gcs("start")
        m.sim_sleep(20.0)
        rec["state_before"] = m.observer.app_state
        m.sitl.restart(down_s=2.0)
        rec["rebooted"] = m.wait(lambda o: o.boots >= 1 and o.t is not None, 60, "reboot")
        rec["back"] = m.wait(lambda o: m.app_log().count("link back") >= 1, 60, "link back")
        m.wait(lambda o: o.app_state == "fault", 10, "fault")
        rec["state_after"] = m.observer.app_state
        rec["launch"] = m.gcs("launch")
        rec["monitoring_again"] = m.wait(lambda o: o.app_state == "monitoring", 150, "monitoring")
    yield rec


@pytest.mark.xfail(reason=PHASE2 + "pmon gcs arm sends ArduCopter's GUIDED (4): PX4 takes AUTO.MISSION and refuses "
                   "to arm (no mission); start asks OFFBOARD with no stream and pauses", **NOT_YET)
def test_arm_wait_takeoff_wait_start_each_succeed_once(by_hand):
    for key, want in (("arm", "armed"), ("takeoff", "at 40 m after"), ("start", "app monitoring")):
        assert by_hand[key].rc == 0 and want in by_hand[key].stdout, (key, by_hand[key].stdout, by_hand[key].stderr)
    assert by_hand["state_before"] == "monitoring"


@pytest.mark.xfail(reason=PHASE2 + "needs monitoring first; after a restart the app must enter OFFBOARD again "
                   "the way PX4 requires", **NOT_YET)
def test_px4_restarted_mid_mission_is_survived_and_the_app_flies_again_only_when_told(by_hand):
    assert by_hand["rebooted"] and by_hand["back"] and by_hand["state_after"] == "fault"
    assert by_hand["launch"].rc == 0 and by_hand["monitoring_again"]
