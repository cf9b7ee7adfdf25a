"""The documented procedure (docs/SITL.md), flown with the real programs against ArduPilot's own
SITL firmware: the conformance tests (tests/firmware/test_ardupilot.py) and bench/ardupilot.py use it.

    with Mission(MissionConfig(speedup=2), out_dir) as m:     # SITL boots, app and feed start
        m.gcs("launch")                                         # as the operator types it
        m.wait(lambda o: o.app_state == "monitoring", 120)
        ...
    figures = m.figures()

What runs, each as a process, as on a vehicle (the rig of sim/stack/rig.py, and the operator):
- ArduCopter SITL (sim/firmware/ardupilot.py) at the scenario's UAV start (its home), five MAVLink TCP
  ports: SERIAL0 the app, SERIAL1 the DF feed, SERIAL2 the operator's ``pmon gcs`` commands,
  SERIAL5 an observer, SERIAL6 a second ground station (``Mission.spare_url``: the live view);
  or (``autopilot="px4"``) PX4 SITL (sim/firmware/px4.py): the app on PX4's offboard/API link, the rest
  on its ground-station link (each a loopback port of its own through the driver's relay);
- ``pmon run`` (optionally through sim/stack/tcp_proxy.py's ``TcpProxy``, a telemetry link that a test
  can cut);
- ``pmon feed live``;
- ``pmon gcs ...`` per command (``Mission.gcs``; every call is kept: exit code, output, wall s).
The observer (this process, a MAVLink client of its own on SERIAL5, like a second ground
station: sim/stack/mission_clients.py) records what the autopilot says it does: its positions, the GUIDED target it holds
(POSITION_TARGET_LOCAL_NED: the setpoint it received), its modes, and what the app says through
ArduPilot's routing (PMON_TGT, PMON_STAT, STATUSTEXT).
"""
from __future__ import annotations

import json
import math
import os
import shutil
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Mapping

import numpy as np

from onboard.app.mavlink_connection import mavlink
from onboard.app.autopilot.pose import Frame
from sim.stack.app_tlog import app_mode, takeover_reactions
from sim.stack.mission_clients import Observer, Sticks
from sim.mock.multicopter import DEMO_VEHICLE_PARAMS
from sim.stack.rig import Rig, RigConfig
from sim.stack.tick_account import TickAccount, scan_times

OBSERVER_PORT, SPARE_PORT = 3, 4  # the autopilot's MAVLink ports after the rig's app, feed, GCS

# ArduCopter SITL's boot (no GPS fix, EKF origin, pre-arm: armable ~42.6 autopilot s after it,
# sim/mock/copter.py's BootTimeline) run at BOOT_SPEEDUP up to BOOT_FAST_UNTIL_S (Mission.fast_boot):
# ArduPilot reads SIM_SPEEDUP at run time (measured on ../shared/ardupilot: 2x -> 10.97x -> 2.17x
# within 0.3 s of each PARAM_SET); the arming, the take-off and the flight at the flight's speedup
BOOT_SPEEDUP = 10.0
BOOT_FAST_UNTIL_S = 35.0
REPORT_S = 0.2  # autopilot s: two periods of the observer's POSITION_TARGET_LOCAL_NED stream
# ArduCopter parameters a fast multicopter is set up with, as docs/SITL.md recommends for the
# paper's 20 m steps: the demo's vehicle's
RECOMMENDED_PARAMS = DEMO_VEHICLE_PARAMS


@dataclass(frozen=True)
class MissionConfig:
    autopilot: str = "ardupilot"  # ardupilot (the firmware's SITL) | px4 (PX4's SITL) | mock (python -m sim.mock.autopilot)
    speedup: float = 2.0  # SITL --speedup (simulated s per wall s)
    params: Mapping[str, float] = field(default_factory=dict)  # autopilot params over copter.parm
    scenario: str = "paper"
    seed: int = 1
    feed_duration_s: float = 120.0  # scans the feed sends (from arming)
    auto_launch: bool = False  # pmon run --auto-launch
    link_proxy: bool = False  # the app reaches SERIAL0 through a TcpProxy (Mission.proxy)
    app_args: tuple[str, ...] = ()


def _off_the_companion(argv: list[str]) -> list[str]:
    """The operator's ``pmon gcs`` runs on the ground, not on the companion computer: here it
    runs at nice 19 from its interpreter's start (by ``nice``; the program lowers itself too,
    groundstation/cli.py, but only once its interpreter has started), so it takes little of the
    CPU the app and the autopilot want: started at normal priority beside the app, its start had
    made ticks of 275-387 ms in the ArduPilot flight's run logs (of a 900 ms budget at 2x). Not
    SCHED_IDLE (``chrt --idle``): beside three nice-10 processes an idle-class command did not end
    within a test's 300 s (docs/DEPLOY.md, section 4)."""
    nice = shutil.which("nice")
    return [nice, "-n", "19", *argv] if nice else argv


@dataclass
class GcsCall:
    args: tuple[str, ...]
    rc: int
    stdout: str
    stderr: str
    wall_s: float
    t: float | None  # autopilot s when it returned


class Mission:
    """The rig (sim/stack/rig.py: SITL, app, feed, five autopilot ports) and an observer for one flight;
    ``out`` keeps every log; ``link_tap``: hears every byte the app sends its autopilot (with
    ``link_proxy``, Rig's)."""

    def __init__(self, cfg: MissionConfig, out: Path, binary: Path | None = None,
                 link_tap: Callable[[bytes], None] | None = None):
        self.cfg = cfg
        self.out = Path(out).resolve()  # the firmware runs in a directory of its own: no relative paths
        self.rig = Rig(RigConfig(scenario=cfg.scenario, seed=cfg.seed, autopilot_seed=1, autopilot=cfg.autopilot,
                                 binary=str(binary) if binary else None, speedup=cfg.speedup, params=cfg.params,
                                 ports=5, auto_launch=cfg.auto_launch, app_args=cfg.app_args,
                                 link_proxy=cfg.link_proxy, feed_duration_s=cfg.feed_duration_s
                                 ).records_in(self.out), link_tap=link_tap)
        self.sc = self.rig.sc
        o = self.sc.origin
        self.frame = Frame(o.lat_deg, o.lon_deg, o.alt_m)
        self.observer: Observer | None = None
        self.sticks: Sticks | None = None
        self.commands: list[GcsCall] = []
        self._booted = threading.Event()  # ends fast_boot's thread
        self._fast_boot: threading.Thread | None = None

    @property
    def sitl(self):
        """The autopilot: ArduPilotSitl, or the mock as a process (sim.firmware.processes.MockProcess)."""
        return self.rig.ap

    @property
    def app(self):
        return self.rig.app

    @property
    def proxy(self):
        return self.rig.proxy

    # ----- lifecycle
    def __enter__(self) -> "Mission":
        try:
            return self.start()
        except BaseException:
            self.stop()
            raise

    def __exit__(self, *exc) -> None:
        self.stop()

    def start(self) -> "Mission":
        """The autopilot, the observer from its boot on, then the app and the feed."""
        self.rig.start_autopilot()
        self.observer = Observer(self.rig.url(OBSERVER_PORT))
        self.rig.start_app()
        self.rig.start_feed()
        return self

    def fast_boot(self, until_s: float = BOOT_FAST_UNTIL_S) -> None:
        """ArduCopter SITL at BOOT_SPEEDUP from now until autopilot ``until_s``, then at the
        flight's speedup again (a thread sets SIM_SPEEDUP): for flights whose tests time nothing
        in wall s before the copter can arm; a no-op past ``until_s`` or on another autopilot."""
        if self.cfg.autopilot != "ardupilot" or (self.observer.t or 0.0) >= until_s:
            return

        def set_speedup(x: float) -> None:
            link = self.observer.link
            link.send(link.mav.param_set_encode(1, 1, b"SIM_SPEEDUP", x, mavlink.MAV_PARAM_TYPE_REAL32))

        def run() -> None:
            set_speedup(BOOT_SPEEDUP)
            while (self.observer.t or 0.0) < until_s and not self._booted.is_set() and self.rig.problem() is None:
                time.sleep(0.01)
            set_speedup(self.cfg.speedup)
        self._booted.clear()
        self._fast_boot = threading.Thread(target=run, name="fast boot", daemon=True)
        self._fast_boot.start()

    def take_sticks(self) -> Sticks:
        """A pilot's sticks from now on, on the observer's port (PX4's GCS link takes any number of
        clients that speak first; ArduPilot's TCP port takes one)."""
        if self.sticks is None:
            self.sticks = Sticks(self.rig.url(OBSERVER_PORT))
        return self.sticks

    def stop(self) -> None:
        self._booted.set()
        if self._fast_boot is not None:
            self._fast_boot.join(timeout=5)
        if self.sticks is not None:
            self.sticks.close()
        self.rig.stop_programs()
        if self.observer is not None:
            self.observer.close()
            with self.observer.lock, open(self.out / "observer.json", "w") as f:
                o = self.observer
                json.dump({"origin": o.origin, "boots": o.boots, "positions": o.positions,
                           "targets": o.targets, "modes": o.modes, "texts": o.texts,
                           "estimates": o.estimates}, f)
        self.rig.stop()

    @property
    def spare_url(self) -> str:
        """A MAVLink port of its own for a second ground station (one TCP client)."""
        return self.rig.url(SPARE_PORT)

    # ----- the operator
    def gcs(self, *args: str, timeout: float = 10.0, wall_limit: float = 300.0) -> GcsCall:
        """``pmon gcs --connect SERIAL2 --timeout T ARGS...`` as a process, run once."""
        argv = [sys.executable, "-m", "onboard.cli", "gcs", "--connect", self.rig.gcs_url,
                "--timeout", f"{timeout:g}", *args]
        t0 = time.monotonic()
        p = subprocess.run(_off_the_companion(argv), capture_output=True, text=True, timeout=wall_limit,
                           env=dict(os.environ, PYTHONUNBUFFERED="1"))
        call = GcsCall(tuple(args), p.returncode, p.stdout, p.stderr, time.monotonic() - t0, self.observer.t)
        self.commands.append(call)
        with open(self.out / "gcs.log", "a") as f:
            f.write(f"$ pmon gcs {' '.join(args)}  [t={call.t}, {call.wall_s:.1f} s, exit {p.returncode}]\n"
                    f"{p.stdout}{p.stderr}")
        return call

    def wait(self, pred: Callable[[Observer], bool], timeout: float, what: str = "") -> bool:
        """Wait (wall s) until ``pred(observer)``; also fails early when the app or the autopilot
        ended (the feed may: its scans ran out)."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if pred(self.observer):
                return True
            if (why := self.rig.problem()):
                raise RuntimeError(f"{why} (while waiting for {what})")
            time.sleep(0.05)
        return False

    def sim_sleep(self, seconds: float) -> None:
        """Sleep ``seconds`` of autopilot time."""
        t0 = self.observer.t or 0.0
        self.wait(lambda o: (o.t or 0.0) >= t0 + seconds, seconds / self.cfg.speedup * 3 + 10, "time")

    # ----- reading back
    def app_log(self) -> str:
        return (self.out / "app.log").read_text(errors="replace")

    def run_log(self) -> list[dict]:
        path = self.out / "run.jsonl"
        return [json.loads(line) for line in open(path) if line.strip()] if path.exists() else []

    def mission_ned(self, x: float, y: float, z: float) -> tuple[float, float, float]:
        """An autopilot local NED position (at its EKF origin) as NED at the mission origin."""
        e, n, u = self.frame.enu_from_ned((x, y, z), self.observer.origin)
        return (float(n), float(e), float(-u))

    def tick_account(self, budget_s: float = 0.9) -> dict:
        """docs/SITL.md's misses (sim.stack.tick_account.TickAccount) from the app's run log and the
        GUIDED targets the autopilot reported holding (its receipt of each setpoint)."""
        acc = TickAccount()
        with self.observer.lock:
            targets = list(self.observer.targets)
        # in time order, as they happened (the account keeps only recent receipts to match)
        events = [(t, 1, (x, y, z)) for t, x, y, z in targets if t is not None]
        for rec in self.run_log():
            # a setpoint sent after a pilot took over, before the app heard of it, is not taken
            # (ArduPilot ignores it outside GUIDED, PX4 outside OFFBOARD) and is not the app's
            # miss; nor one sent within a target report (0.1 s) of the takeover: its receipt
            # cannot be seen. The observer times a mode change to its heartbeats, so a change it
            # saw may have come up to one heartbeat period earlier (PX4 sends HEARTBEAT at 1 Hz
            # and refuses another rate; ArduPilot at the 4 Hz asked)
            window = REPORT_S + self.observer.heartbeat_period_s()
            if rec["planned"] and rec["sent_t"] is not None and not (
                    self.guided_at(rec["sent_t"]) and self.guided_at(rec["sent_t"] + window)):
                rec = {**rec, "planned": False}
            events.append((rec["t"], 0, rec))
        for t, kind, item in sorted(events, key=lambda e: (e[0], e[1])):
            if kind == 0:
                acc.on_tick(item, budget_s)
            else:
                acc.on_setpoint(t, self.mission_ned(*item))
        return acc.finish(scan_times(self.out / "truth.jsonl"))

    def guided_at(self, t: float) -> bool:
        """The autopilot was in GUIDED at autopilot time t (the observer's heartbeats)."""
        with self.observer.lock:
            modes = [m for m in self.observer.modes if m[0] is not None and m[0] <= t]
        return bool(modes) and app_mode(self.cfg.autopilot)(modes[-1][1])

    def follow_errors_m(self) -> list[float]:
        """How well the vehicle flies the plan (``follow_errors_m`` of the run log)."""
        return follow_errors_m(self.run_log())

    def containment(self) -> dict:
        """The vehicle's reported positions against the area and the obstacles (3D: the UAV may
        overfly the low ones)."""
        from onboard.core.obstacles import Obstacles

        with self.observer.lock:
            pos = list(self.observer.positions)
        if not pos:
            return {"samples": 0, "outside_area": 0, "in_obstacle": 0}
        enu = np.array([self.frame.enu_from_geodetic(lat, lon, alt) for _, lat, lon, alt, _ in pos])
        lo, hi = np.asarray(self.sc.area.min_m), np.asarray(self.sc.area.max_m)
        outside = np.any((enu[:, :2] < lo[:2]) | (enu[:, :2] > hi[:2]), axis=1)
        obs = Obstacles.from_boxes(self.sc.obstacles)
        inside = obs.contains(enu).any(axis=1) if len(obs) else np.zeros(len(enu), bool)
        return {"samples": len(enu), "outside_area": int(outside.sum()), "in_obstacle": int(inside.sum()),
                "min_xy_m": enu[:, :2].min(axis=0).round(1).tolist(),
                "max_xy_m": enu[:, :2].max(axis=0).round(1).tolist()}

    def estimate_errors(self) -> dict:
        """The app's estimates against the feed's truth at the same scan times (sim.stack.demo)."""
        from sim.stack.demo import score
        return score(self.out / "run.jsonl", self.out / "truth.jsonl", self.sc)

    def takeover_reactions(self) -> list[float]:
        """For each time the vehicle left GUIDED (the observer's heartbeats): autopilot s from
        the mode change to the last setpoint the app sent before it came back (0 when it sent
        none), from the app's own tlog (its setpoints carry its autopilot clock)."""
        with self.observer.lock:
            modes = list(self.observer.modes)
        return takeover_reactions(self.out / "app.tlog", modes, app_mode(self.cfg.autopilot))

    def autopilot_crashes(self) -> int:
        """Floating point exceptions and other aborts the firmware printed (the mock: the
        defects that crash ArduCopter, which it counts)."""
        log = (self.out / "autopilot.log").read_text(errors="replace")
        return sum(log.count(s) for s in ("Floating point exception", "Segmentation fault", "abort",
                                          "defect that crashes"))


def follow_errors_m(recs: list[dict]) -> list[float]:
    """How well the vehicle flies the plan: for each monitoring tick (app tick records, in
    order) that sent a setpoint, the distance (m, horizontal) from its planned point to where
    the vehicle was at the next tick's scan (the app's own telemetry; ticks a pilot or a link
    loss interrupted are left out: the next record must also be a monitoring tick one second on)."""
    return [math.hypot(b["uav_enu"][0] - a["next"][0], b["uav_enu"][1] - a["next"][1])
            for a, b in zip(recs, recs[1:])
            if a["sent"] and a["next"] and b["planned"] and b["uav_enu"] and abs(b["t"] - a["t"] - 1.0) < 1e-6]


def fly_launch_procedure(m: Mission, monitor_s: float, during: Callable[[Mission, dict], None] | None = None,
                         takeovers: tuple[tuple[str, ...], ...] = (("mode", "LOITER"), ("hold",)),
                         fast_boot: bool = False) -> dict:
    """docs/SITL.md's procedure from the autopilot's boot, as tests/firmware/test_ardupilot.py (flight A)
    and bench/ardupilot.py fly it: ``pmon gcs launch`` at once; ``monitor_s`` autopilot s of
    monitoring (``during(m, rec)`` runs at its start, inside that time); then each takeover (a
    pilot's mode change), 3 s, ``pmon gcs resume``, 6 s; ``fast_boot``: the rest of the boot
    after the launch command at BOOT_SPEEDUP (Mission.fast_boot). Returns each command's GcsCall
    and the app's state after it, keyed by what it was."""
    rec: dict = {"boot_t": m.observer.t}
    rec["launch"] = m.gcs("launch")  # at once: the autopilot is still booting
    if fast_boot:
        m.fast_boot()
    if not m.wait(lambda o: o.app_state == "monitoring", 150 + 60 / m.cfg.speedup, "monitoring"):
        raise RuntimeError(f"not monitoring; the app said {m.observer.app_texts()}")
    rec["start_t"] = t0 = m.observer.t
    if during is not None:
        during(m, rec)
    m.sim_sleep(monitor_s - ((m.observer.t or t0) - t0))
    for cmd in takeovers:
        key = cmd[-1]
        rec[key] = m.gcs(*cmd)
        m.wait(lambda o: o.app_state == "pilot override", 10, "pilot override")
        rec[f"{key}_app"] = m.observer.app_state
        m.sim_sleep(3.0)
        rec[f"{key}_resume"] = m.gcs("resume")
        m.sim_sleep(6.0)
    rec["end_state"] = m.observer.app_state
    return rec


def figures(m: Mission) -> dict:
    """The procedure's figures (docs/SITL.md): misses, receipts, takeovers, error, containment."""
    acc = m.tick_account()
    err = m.estimate_errors()
    follow = m.follow_errors_m()
    reactions = m.takeover_reactions()
    return {
        "autopilot": m.cfg.autopilot, "params": dict(m.cfg.params), "speedup": m.cfg.speedup,
        "scans": acc["scans"], "ticks": acc["ticks"], "monitoring_ticks": acc["monitoring_ticks"],
        "ticks_skipped": acc["ticks_skipped"], "scans_unticked": acc["scans_unticked"],
        "ticks_late": acc["ticks_late"], "setpoint_delay_s_median": acc["setpoint_delay_s_median"],
        "setpoint_delay_s_max": acc["setpoint_delay_s_max"], "latency_ms_median": acc["latency_ms_median"],
        "takeover_reaction_s": [round(r, 3) for r in reactions],
        "from_plan_at_next_tick_m_median": round(float(np.median(follow)), 2) if follow else None,
        "from_plan_at_next_tick_m_p95": round(float(np.percentile(follow, 95)), 2) if follow else None,
        "rmse_m": err["rmse_m"], "containment": m.containment(), "autopilot_crashes": m.autopilot_crashes(),
        "gcs_commands": [" ".join(c.args) + f" -> {c.rc}" for c in m.commands],
    }
