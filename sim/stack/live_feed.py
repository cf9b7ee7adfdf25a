"""The live simulated direction-finder feed (``pmon feed live``): truth world + DF model, paced by
the autopilot's telemetry.

Live: the feed is an ordinary MAVLink client of the autopilot on its OWN connection (so it works
against the mock, an ArduPilot SITL or anything else that streams GLOBAL_POSITION_INT). From that
telemetry it learns the autopilot clock and the UAV's position; at every whole second T of
autopilot time it takes the DF scan of the true targets from where the UAV was at T
(interpolated telemetry), sends one datagram per channel (docs/DATAGRAM.md) to the app, writes
the truth to a JSONL file (its format: sim/stack/feed.py's docstring) and steps the truth world by one dt.

The truth world does not depend on the UAV, so it is stepped AHEAD on a thread of its own
(``TruthAhead``, at most ``LiveFeedConfig.ahead`` states, from the moment the feed starts, i.e.
also while it waits for the vehicle to arm): a scan at T then only costs the DF model. Without
this the targets' own guidance (a QP per target per step; the first one ~1 s of warm-up, later
re-plans around obstacles 0.2-0.7 s) made the feed deliver scans seconds late at a SITL speedup
of 5, and the app rightly refused them as stale: misses of the simulator, not of the app. The
truth world and the DF noise draw from separate random streams (``SeedSequence(seed).spawn``),
so a seed gives the same flight whatever the threads' timing.

The replay of a recorded file and ``pmon feed``'s command line: sim/stack/feed.py; the same feed writing
a KrakenSDR's output instead of datagrams: sim/stack/kraken.py.
"""
from __future__ import annotations

import json
import math
import queue
import socket
import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Callable

import numpy as np

from onboard.app.df import datagram as dg
from onboard.app.autopilot.clock import AutopilotClock, UtcMap
from onboard.app.autopilot.launch import AT_ALTITUDE_M
from onboard.app.mavlink_connection import Link, mavlink
from onboard.app.autopilot.pose import Frame, PoseHistory, valid_global_position_int

READY_STATES = 5  # truth states computed before the first scan is sent
# a scan sent this long (autopilot s) after its time counts as late: the feed waits for a
# telemetry sample at or after T (GLOBAL_POSITION_INT every 0.1 s), so ~0.1 s is normal
LATE_S = 0.25
FEED_SYSID = 245  # a client of its own, never mistaken for the vehicle or the app
FEED_COMPID = mavlink.MAV_COMP_ID_USER1
START_MODES = ("armed", "altitude", "now")  # LiveFeedConfig.start: when the first scan goes out


class Telemetry:
    """Clock and pose of the vehicle from a MAVLink connection, read on a thread."""

    def __init__(self, url: str, frame: Frame, tlog_path: str | None = None, signing_key: bytes | None = None):
        self.link = Link(url, tlog_path=tlog_path, source_system=FEED_SYSID, source_component=FEED_COMPID,
                         signing_key=signing_key, wait_for_peer=True)
        self.frame = frame
        self.clock = AutopilotClock()
        self.poses = PoseHistory(keep_s=60.0, max_extrapolation_s=0.5)
        self.utc = UtcMap()  # the autopilot's UTC (SYSTEM_TIME): a simulated KrakenSDR's stamps
        self.sysid: int | None = None
        self.compid: int | None = None
        self.armed = False
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="feed-telemetry", daemon=True)
        self._hb = 0.0
        self._asked = -math.inf  # local s of the last rate request
        self._pose_local = -math.inf  # local s of the last position

    def _ask_rates(self) -> None:
        """Our own link's rates: enough to interpolate the pose at a scan time. Asked again
        while positions do not come (an autopilot that rebooted starts from its defaults)."""
        self._asked = time.monotonic()
        for msg_id, hz in ((mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT, 10.0),
                           (mavlink.MAVLINK_MSG_ID_SYSTEM_TIME, 2.0)):
            self.link.send(self.link.mav.command_long_encode(
                self.sysid, self.compid, mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 0,
                msg_id, 1e6 / hz, 0, 0, 0, 0, 0))

    def start(self) -> "Telemetry":
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5.0)
        self.link.close()

    def _run(self) -> None:
        import select
        while not self._stop.is_set():
            fd = self.link.fileno()
            if fd is not None:
                try:
                    select.select([fd], [], [], 0.005)
                except (OSError, ValueError):
                    time.sleep(0.005)
            else:
                time.sleep(0.002)
            for _ in range(500):
                msg = self.link.recv()
                if msg is None:
                    break
                try:
                    self._on(msg)
                except Exception:  # one odd message must not stop the feed
                    pass
            now = time.monotonic()
            if self.sysid is not None and now - self._pose_local > 2.0 and now - self._asked > 2.0:
                self._ask_rates()
            if self.sysid is not None and now - self._hb > 1.0:
                self._hb = now
                self.link.send(self.link.mav.heartbeat_encode(
                    mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, mavlink.MAV_STATE_ACTIVE))

    def _on(self, msg) -> None:
        mtype = msg.get_type()
        src = (msg.get_srcSystem(), msg.get_srcComponent())
        if mtype == "HEARTBEAT":
            if msg.autopilot == mavlink.MAV_AUTOPILOT_INVALID or msg.type in (
                    mavlink.MAV_TYPE_GCS, mavlink.MAV_TYPE_ONBOARD_CONTROLLER):
                return
            if self.sysid is None:
                self.sysid, self.compid = src
                self._ask_rates()
            if src == (self.sysid, self.compid):
                self.armed = bool(msg.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
            return
        if src != (self.sysid, self.compid):
            return
        tb = getattr(msg, "time_boot_ms", None)
        if tb is not None:
            self.clock.observe(tb)
        if mtype == "GLOBAL_POSITION_INT" and valid_global_position_int(msg):
            self.poses.add(self.frame.pose_from_global_position_int(msg))
            self._pose_local = time.monotonic()
        elif mtype == "SYSTEM_TIME":
            self.utc.observe(msg.time_unix_usec, msg.time_boot_ms)


def _sleep_until(clock, t: float, stop: threading.Event, poll: float = 0.002, resets: int | None = None) -> bool:
    """Until the clock reads ``t`` (True), or ``stop`` (False), or the clock is reset: an
    autopilot reboot (True: the caller sees ``clock.resets`` change). ``resets``: the count the
    caller last saw (a reboot before the call returns at once, not at ``t`` of the new clock)."""
    resets = clock.resets if resets is None else resets
    while not stop.is_set():
        now = clock.now()
        if (now is not None and now >= t) or clock.resets != resets:
            return True
        time.sleep(poll)
    return False


class TruthAhead:
    """The truth world's states 0, 1, 2, ... (one per dt), computed ahead on a daemon thread and
    handed out in order by ``next()``; at most ``ahead`` are kept. A step that raises ends the
    thread and ``next()`` re-raises it in the caller."""

    def __init__(self, truth, ahead: int = 60):
        self.truth = truth
        self._q: queue.Queue = queue.Queue(maxsize=max(int(ahead), 1))
        self._stop = threading.Event()
        self._error: BaseException | None = None
        self.step_ms: deque[float] = deque(maxlen=3600)  # the last hour of steps (wall ms)
        self._thread = threading.Thread(target=self._run, name="feed-truth", daemon=True)

    def start(self) -> "TruthAhead":
        self._thread.start()
        return self

    def _put(self, states) -> bool:
        while not self._stop.is_set():
            try:
                self._q.put(states, timeout=0.1)
                return True
            except queue.Full:
                continue
        return False

    def _run(self) -> None:
        try:
            if not self._put(self.truth.states):
                return
            while not self._stop.is_set():
                t0 = time.perf_counter()
                states = self.truth.step()
                self.step_ms.append((time.perf_counter() - t0) * 1e3)
                if not self._put(states):
                    return
        except BaseException as exc:  # handed to the consumer
            self._error = exc

    def wait_ready(self, n: int, stop: threading.Event) -> bool:
        """Wait until ``n`` states are ready (the guidance's first solves are its slowest)."""
        n = min(n, self._q.maxsize)
        while not stop.is_set():
            if self._q.qsize() >= n:
                return True
            if self._error is not None:
                raise RuntimeError(f"truth world failed: {self._error!r}") from self._error
            time.sleep(0.01)
        return False

    def next(self, stop: threading.Event) -> np.ndarray | None:
        """The next state (M, 6); waits for it (None if ``stop`` is set first)."""
        while not stop.is_set():
            try:
                return self._q.get(timeout=0.05)
            except queue.Empty:
                if self._error is not None:
                    raise RuntimeError(f"truth world failed: {self._error!r}") from self._error
        return None

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5.0)


@dataclass(frozen=True)
class LiveFeedConfig:
    mavlink_url: str
    app_host: str = "127.0.0.1"
    app_port: int = 14600
    truth_path: str | None = None
    seed: int = 1
    duration_s: float | None = None  # None: the scenario's mission.duration_s
    # when the first scan goes out: "armed" (the vehicle arms: the scans then last the mission,
    # however long the autopilot takes to get ready), "altitude" (armed and within
    # AT_ALTITUDE_M of the mission altitude ``altitude_m``: the paper's mission, the UAV at h at
    # t = 0, without the take-off and climb) or "now" (the clock and a position known)
    start: str = "armed"
    altitude_m: float | None = None  # "altitude": h, ENU m (None: the scenario's uav.altitude_m)
    tlog_path: str | None = None
    ahead: int = 60  # truth states computed ahead of the scans (TruthAhead)
    signing_key: bytes | None = None  # MAVLink 2 signing on the feed's autopilot link
    kind: str = "nominal"  # how the true targets move (sim/truth/kinds.py TRUTH_KINDS)

    def __post_init__(self):
        if self.start not in START_MODES:
            raise ValueError(f"feed start must be one of {', '.join(START_MODES)}, got {self.start!r}")


def ready_to_scan(start: str, armed: bool, pose, altitude_m: float) -> bool:
    """Whether the first scan may go out (``LiveFeedConfig.start``): a position known and, for
    "armed", the vehicle armed; for "altitude", also within AT_ALTITUDE_M of ``altitude_m`` (ENU
    m), the app's own test of a take-off's end (onboard/app/autopilot/launch.py), so the world starts with
    the UAV at h as the paper's mission does. The app starts monitoring only with DF data, so the
    feed cannot wait for the monitoring itself. ``start`` is one of START_MODES (LiveFeedConfig
    checks it)."""
    if pose is None:
        return False
    if start == "now":
        return True
    return armed and (start == "armed" or float(pose.pos[2]) >= altitude_m - AT_ALTITUDE_M)


class LiveFeed:
    def __init__(self, cfg: LiveFeedConfig, scenario, log: Callable[[str], None] = print):
        from sim.truth.sensors import DirectionFinder
        from sim.truth.kinds import truth_world

        self.cfg = cfg
        self.sc = scenario
        self.frame = Frame(scenario.origin.lat_deg, scenario.origin.lon_deg, scenario.origin.alt_m)
        seq = np.random.SeedSequence(cfg.seed)
        truth_seq, df_seq = seq.spawn(2)
        kind_seq = seq.spawn(1)[0]  # the truth kind's own choices: the nominal truth's streams unchanged
        self.rng = np.random.default_rng(df_seq)  # DF noise, clutter, detections (this thread)
        steps = int(round((cfg.duration_s or scenario.mission.duration_s) / scenario.dynamics.dt_s))
        self.truth = truth_world(scenario, np.random.default_rng(truth_seq), cfg.kind, np.random.default_rng(kind_seq),
                                 steps)
        self.df = DirectionFinder.from_config(scenario.sensor)
        self.log = log
        self.sent = 0
        self.scans = 0
        self.late_scans = 0  # scans sent more than LATE_S (autopilot) after their time
        self.max_send_lag_s = 0.0
        self.stop_event = threading.Event()
        self.seq = 0  # datagrams sent
        self.last_record: dict | None = None  # the truth of the last scan (all of them: truth_path)
        self.step_ms: deque[float] = deque(maxlen=3600)  # truth step times (wall ms), the last hour

    def run(self) -> int:
        ahead = TruthAhead(self.truth, self.cfg.ahead).start()  # warms up while we wait
        self.step_ms = ahead.step_ms
        tel = Telemetry(self.cfg.mavlink_url, self.frame, self.cfg.tlog_path, self.cfg.signing_key).start()
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        out = open(self.cfg.truth_path, "w", buffering=1) if self.cfg.truth_path else None
        dest = (self.cfg.app_host, self.cfg.app_port)
        n_scans = int(round(self.cfg.duration_s if self.cfg.duration_s is not None
                            else self.sc.mission.duration_s))
        try:
            if out is not None:
                out.write(json.dumps(self._truth_header(n_scans)) + "\n")
            # wait for the truth world's first steps (its warm-up: ~1 s for the first), the
            # clock and a position (and the arming, if asked); the first scan is the next whole
            # second after all that, so no scan is late because the simulator was still starting
            if not ahead.wait_ready(READY_STATES, self.stop_event) or not self._wait_for_vehicle(tel):
                return 130
            T = math.floor(tel.clock.now()) + 1.0
            resets = tel.clock.resets
            self.log(f"feed: first scan at autopilot t={T:.0f} s, {n_scans} scans to {self.destination(dest)}")
            for k in range(n_scans):
                states = ahead.next(self.stop_event)  # the truth at T (step k), normally ready
                if states is None or not _sleep_until(tel.clock, T, self.stop_event, resets=resets):
                    return 130
                if tel.clock.resets != resets:
                    restart = self._after_reboot(tel)
                    if restart is None:
                        return 130
                    T, resets = restart
                uav = self._uav_at(tel, T)
                if uav is None:  # the targets moved on all the same (their step k is used up)
                    self.log(f"feed: no UAV position at t={T:.1f}: scan skipped")
                    T += 1.0
                    continue
                bearings = self.scan(T, states, uav, tel)
                lag = (tel.clock.now() or T) - T
                self.deliver(T, bearings, sock, dest)
                self.max_send_lag_s = max(self.max_send_lag_s, lag)
                self.late_scans += lag > LATE_S
                rec = {"t": T, "k": k, "uav_enu": [round(float(x), 3) for x in uav],
                       "targets": np.round(states, 4).tolist(),
                       "bearings": [[float(x) for x in b] for b in bearings]}
                self.last_record = rec
                if out is not None:
                    out.write(json.dumps(rec) + "\n")
                self.scans += 1
                T += 1.0
            self.log(f"feed: done: {self.scans} scans, {self.sent} {self.sent_unit}, "
                     f"{self.late_scans} sent > {LATE_S:g} s late (max {self.max_send_lag_s:.2f} s autopilot), "
                     f"truth step median {np.median(self.step_ms) if self.step_ms else 0:.0f} ms")
            return 0
        finally:
            ahead.stop()
            tel.stop()
            sock.close()
            if out is not None:
                out.close()

    def _truth_header(self, n_scans: int) -> dict:
        """The truth JSONL's first line."""
        o = self.sc.origin
        return {"header": {"scenario": self.sc.name, "seed": self.cfg.seed, "origin": [o.lat_deg, o.lon_deg, o.alt_m],
                           "targets": [t.name for t in self.sc.targets], "scans": n_scans}}

    def _uav_at(self, tel, T: float):
        """The UAV's ENU position at autopilot time ``T`` (None if unknown), after waiting up to
        0.5 s for a telemetry sample at or after T: an interpolation, not a guess."""
        deadline = time.monotonic() + 0.5
        while (tel.poses.latest() is None or tel.poses.latest().t < T) \
                and time.monotonic() < deadline and not self.stop_event.is_set():
            time.sleep(0.001)
        return tel.poses.at(T)

    def _wait_for_vehicle(self, tel) -> bool:
        """Until the clock and a position are known and the vehicle is as ``start`` asks
        (``ready_to_scan``); False if stopped first."""
        altitude_m = self.sc.uav.altitude_m if self.cfg.altitude_m is None else self.cfg.altitude_m
        waiting_said = False
        while not self.stop_event.is_set():
            pose = tel.poses.latest()
            if tel.clock.now() is not None and ready_to_scan(self.cfg.start, tel.armed, pose, altitude_m):
                break
            if not waiting_said and self.cfg.start != "now" and tel.sysid is not None:
                waiting_said = True
                reach = f" and reach {altitude_m:g} m" if self.cfg.start == "altitude" else ""
                self.log(f"feed: waiting for the vehicle to arm{reach} (--start now: scan at once)")
            time.sleep(0.01)
        return not self.stop_event.is_set()

    def _after_reboot(self, tel) -> tuple[float, int] | None:
        """The autopilot rebooted: its clock starts again from 0, and so do the scan times (a DF
        stamps with the clock it has); the targets go on. Waits for its clock and until the next
        whole second: (that time, the clock's reset count), or None if stopped."""
        while tel.clock.now() is None and not self.stop_event.is_set():
            time.sleep(0.01)
        resets = tel.clock.resets
        T = math.floor(tel.clock.now() or 0.0) + 1.0
        self.log(f"feed: the autopilot rebooted: next scan at t={T:.0f} s")
        if not _sleep_until(tel.clock, T, self.stop_event):
            return None
        return T, resets

    sent_unit = "datagrams"  # what ``sent`` counts

    def destination(self, dest: tuple[str, int]) -> str:
        return f"{dest[0]}:{dest[1]}"

    def scan(self, T: float, states: np.ndarray, uav: np.ndarray, tel: Telemetry) -> tuple[np.ndarray, ...]:
        """The DF's bearings of the truth at T from ``uav`` (per channel): the DF model's."""
        from sim.truth.sensors import df_scan
        return df_scan(states[:, :2], uav[:2], self.df, self.rng)

    def deliver(self, T: float, bearings, sock: socket.socket, dest: tuple[str, int]) -> None:
        """Send a scan: one datagram per channel (docs/DATAGRAM.md). sim/stack/kraken.py writes
        KrakenSDR's output instead."""
        for ch, b in enumerate(bearings):
            sock.sendto(dg.encode(T, ch, b, self.seq), dest)
            self.seq += 1
            self.sent += 1
