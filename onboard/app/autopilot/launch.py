"""The launch sequence (the ``launch`` command, ``pmon run --auto-launch``): wait until the
autopilot is ready, its launch mode (the profile's: ArduCopter's GUIDED, PX4's Hold), arm, take
off to h, start monitoring (which enters the mission mode: onboard/app/state_machine.py). Pure:
``step`` maps the sequence, a snapshot of the vehicle and the time to the next sequence and the
actions the app carries out, so it is tested with plain values.

What a real autopilot does that the sequence waits out (measured on ArduCopter 4.4 SITL):
- pre-arm checks refuse arming for ~40 s after boot (EKF, GPS), each refusal a STATUSTEXT;
  ArduPilot reports the checks' state in SYS_STATUS (MAV_SYS_STATUS_PREARM_CHECK): where it
  does, the sequence asks for GUIDED and arming only once they pass; where it does not, it
  asks every ``ARM_RETRY_S`` until armed. A refusal's reason is said once per reason.
- at boot the mode switch can set the flight mode again after a GUIDED request, so GUIDED is
  asked for right before arming, not at the start.
And on PX4 v1.16 SITL: it boots in Hold and arms there ~5 s after boot (SYS_STATUS's pre-arm
health bit set at the same time); its take-off is a mode of its own (AUTO.TAKEOFF) that ends in
Hold by itself (~24 s for 40 m), and only then does the sequence start (OFFBOARD asked from a
hovering vehicle).
There is no give-up: the sequence waits as long as the autopilot needs (a ``stop`` command
cancels it); it is aborted when the vehicle leaves the launch's modes after the sequence took it
there (a pilot took over) or disarms after arming, and by the app on a link loss.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

MODE_RETRY_S = 1.0  # autopilot s between requests of the launch mode
ARM_RETRY_S = 2.0  # autopilot s between ARM commands while refused
# autopilot s between take-off commands until the climb shows: ArduCopter spools its motors
# ~3.3 s after accepting one before it climbs (its 4.4 SITL), so a second is not sent sooner
TAKEOFF_RETRY_S = 5.0
TAKEOFF_TRIES = 5  # take-off commands without a climb before the sequence gives up
CLIMB_STARTED_M = 1.0  # m above home that show the take-off was taken
AT_ALTITUDE_M = 1.0  # within this of the mission altitude counts as there

PHASES = ("ready", "mode", "arm", "takeoff", "climb", "start")


@dataclass(frozen=True)
class VehicleView:
    """What the app knows of the vehicle now (heights in the ENU mission frame, m)."""

    position: bool  # a pose, the local origin and a geodetic fix are known
    in_launch_mode: bool  # in the profile's launch mode (GUIDED; PX4's Hold)
    armed: bool
    up_m: float | None  # the vehicle's height
    home_up_m: float | None  # home's height (vehicle height - relative altitude)
    prearm_ok: bool | None  # SYS_STATUS's pre-arm bit as the profile reads it; None: not reported
    climbing: bool = False  # the autopilot reports taking off or in the air (EXTENDED_SYS_STATE)
    prearm_text: str | None = None  # the autopilot's latest "PreArm: ..." / "Arm: ..." reason
    can_start: bool = False  # the app's start preconditions hold (flying, DF data, ...)
    start_blocker: str | None = None  # why not, when not
    in_own_mode: bool | None = None  # in a mode the autopilot takes by itself in a launch (None: in_launch_mode)
    mode_name: str = "?"  # the mode it is in, in words


@dataclass(frozen=True)
class Launch:
    altitude_m: float  # the mission altitude (uav.altitude_m) to climb to: m above the mission origin, ENU up
    phase: str = "ready"
    next_t: float = -math.inf  # autopilot s of the next attempt in this phase
    tries: int = 0
    mode_seen: bool = False  # the vehicle has been in the launch mode since the sequence asked
    launch_mode: str = "GUIDED"  # its name (the profile's), for what the sequence says


@dataclass(frozen=True)
class Say:
    text: str
    level: str = "info"  # info | warning | error
    once: str | None = None  # a key: said once per launch


# actions for the app: ("mode",) (the launch mode), ("arm",), ("takeoff", alt_above_home_m), ("start",), Say
Action = tuple | Say


def step(L: Launch, v: VehicleView, now: float) -> tuple[Launch | None, list[Action]]:
    """One look at the sequence; returns it (None: ended) and what to do now. A phase ends as
    soon as the vehicle shows it done; a retry waits for its time."""
    out: list[Action] = []
    own = v.in_launch_mode if v.in_own_mode is None else v.in_own_mode
    if L.mode_seen and not own and L.phase in ("arm", "takeoff", "climb", "start"):
        return None, [Say(f"launch aborted: the vehicle left {L.launch_mode} (now {v.mode_name})", "warning")]
    if L.phase in ("takeoff", "climb", "start") and not v.armed:
        return None, [Say("launch aborted: the vehicle disarmed", "warning")]
    # what the vehicle already shows done
    if L.phase == "mode" and v.in_launch_mode:
        L = replace(L, phase="arm", next_t=-math.inf, tries=0, mode_seen=True)
    if L.phase == "arm" and v.armed:
        L = replace(L, phase="takeoff", next_t=-math.inf, tries=0)
        out.append(Say("launch: armed"))
    climbed = v.up_m is not None and v.home_up_m is not None and v.up_m - v.home_up_m > CLIMB_STARTED_M
    if L.phase == "takeoff" and (v.climbing or climbed):
        L = replace(L, phase="climb", next_t=-math.inf, tries=0)
        out.append(Say(f"launch: climbing to {L.altitude_m:g} m"))
    if L.phase == "climb" and v.up_m is not None and v.up_m >= L.altitude_m - AT_ALTITUDE_M:
        L = replace(L, phase="start")
    if now < L.next_t:
        return L, out
    # what to ask for now
    if L.phase == "ready":
        if not v.position:
            return L, out + [Say("launch: waiting for the autopilot's position", once="position")]
        if v.prearm_ok is False and not v.armed:
            why = f" ({v.prearm_text})" if v.prearm_text else ""
            return L, out + [Say(f"launch: waiting for the autopilot's pre-arm checks{why}",
                                 once=f"prearm:{v.prearm_text}")]
        L = replace(L, phase="arm" if v.in_launch_mode else "mode", mode_seen=v.in_launch_mode)
    if L.phase == "mode":
        return replace(L, next_t=now + MODE_RETRY_S, tries=L.tries + 1), out + [("mode",)]
    if L.phase == "arm":
        if v.prearm_ok is False:  # its pre-arm bit can pass for a moment and fail again: wait
            return L, out
        if L.tries and v.prearm_text:
            out.append(Say(f"launch: arming refused: {v.prearm_text}", "warning", once=f"arm:{v.prearm_text}"))
        return replace(L, next_t=now + ARM_RETRY_S, tries=L.tries + 1), out + [("arm",)]
    if L.phase == "takeoff":
        if L.tries >= TAKEOFF_TRIES:
            return None, out + [Say(f"launch failed: {TAKEOFF_TRIES} take-off commands without a climb",
                                    "error")]
        if v.up_m is None or v.home_up_m is None:
            return L, out
        return replace(L, next_t=now + TAKEOFF_RETRY_S, tries=L.tries + 1), \
            out + [("takeoff", L.altitude_m - v.home_up_m)]
    if L.phase == "start":
        if not v.in_launch_mode:  # the autopilot's own take-off is not over (PX4: back in Hold)
            return L, out + [Say(f"launch: at altitude, waiting for the autopilot to end its take-off "
                                 f"({v.mode_name})", once="start:own")]
        if v.can_start:
            return None, out + [("start",)]
        if v.start_blocker:
            out.append(Say(f"launch: at altitude, waiting: {v.start_blocker}", once=f"start:{v.start_blocker}"))
    return L, out
