"""What each CLI command does over a connected ``GcsLink``. Each returns an ``Outcome`` (data for
--json, text for people) or raises ``GcsError`` with the one line that says why."""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

from groundstation import protocol as P
from groundstation.errors import FAILED, TIMEOUT, GcsError
from groundstation.gcs_link import Ack, GcsLink, _same
from onboard.app.mavlink_connection import mavlink

PARAMS_MIN_S = 1.0  # a status's parameter list gets at least this (the app answers in well under it)
STAT_WAIT_S = 2.5  # the app publishes PMON_STAT at 1 Hz: a status waits at most this for it


@dataclass(frozen=True)
class Outcome:
    text: str
    data: dict = field(default_factory=dict)


def _fmt(x, spec=".1f", none="-"):
    return none if x is None or (isinstance(x, float) and not math.isfinite(x)) else format(x, spec)


# ----------------------------------------------------------------------------- status
def status(gl: GcsLink, with_params: bool = True) -> Outcome:
    v = gl.v
    t0 = time.monotonic()
    app_heard, app_beating = _wait_for_status(gl)
    params = None
    if app_heard and with_params:
        try:  # --timeout bounds the whole status: the parameters get what the waits left (>= 1 s)
            params = gl.params_list(max(PARAMS_MIN_S, t0 + gl.timeout - time.monotonic()))
        except GcsError:
            params = None
    link = _link_status(gl)
    vehicle, landed, prearm = _vehicle_status(gl)
    st = v.app_status if app_heard else None
    app = None if st is None else _app_status(v.app_state, st, params)
    lines = [
        f"vehicle {v.sysid}: {vehicle['mode']}, {'ARMED' if v.armed else 'disarmed'}, {landed}"
        + ("" if prearm is None or v.armed else
           ", pre-arm checks " + ("passing" if prearm else "FAILING (not ready to arm)")),
        f"  position  {_fmt(vehicle['lat_deg'], '.6f')}, {_fmt(vehicle['lon_deg'], '.6f')}  "
        f"alt {_fmt(vehicle['alt_rel_m'])} m above home",
        f"  battery   {_fmt(vehicle['battery_v'], '.2f')} V  {_fmt(vehicle['battery_pct'], 'd')} %",
        f"  link      {gl.url}: heartbeat {_fmt(link['heartbeat_age_s'], '.1f')} s ago, "
        f"packet loss {link['packet_loss_pct']:.1f} %"
        + (f", rssi {link['rssi']}" if link["rssi"] is not None else ""),
    ]
    if app is None and app_beating:
        lines.append(f"onboard app: {v.app_state} (its HEARTBEAT; no PMON_STAT within {gl.timeout:g} s: lost on "
                     f"the way{_bad_signature_hint(gl) or ', ask again'})")
    elif app is None:
        lines.append("onboard app: not heard (no PMON_STAT within "
                     f"{min(gl.timeout, STAT_WAIT_S):g} s{_bad_signature_hint(gl)})")
    else:
        lines += _app_lines(app["state"], st, params)
    return Outcome("\n".join(lines), {"vehicle": vehicle, "link": link, "app": app,
                                       "app_heartbeat_state": v.app_state if app_beating else None})


def _wait_for_status(gl: GcsLink) -> tuple[bool, bool]:
    """Ask for the vehicle's status and wait for it and the app's PMON_STAT: (app heard, app's
    HEARTBEAT seen)."""
    v = gl.v
    gl.request(mavlink.MAVLINK_MSG_ID_SYS_STATUS, mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT,
               mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE)
    gl.wait_for(lambda: v.get("GLOBAL_POSITION_INT") is not None and v.get("SYS_STATUS") is not None,
                min(gl.timeout, 1.0))
    # every PMON_STAT on this connection is fresh: it was opened a moment ago
    app_heard = gl.wait_for(lambda: v.n_stat > 0, min(gl.timeout, STAT_WAIT_S))
    app_beating = ("HEARTBEAT", P.APP_COMPID) in v.seen_at
    if not app_heard and app_beating and gl.timeout > STAT_WAIT_S:
        # the app is there (its HEARTBEAT came) and its PMON_STAT was lost on the way: an
        # autopilot forwarding a tick's burst (4 PMON_TGT, then PMON_STAT) drops its tail under
        # load (PX4's forwarding queue, docs/MAVLINK.md); wait the rest of --timeout for the next
        app_heard = gl.wait_for(lambda: v.n_stat > 0, gl.timeout - STAT_WAIT_S)
    return app_heard, app_beating


def _vehicle_status(gl: GcsLink) -> tuple[dict, str, bool | None]:
    """The vehicle's part of a status: (its --json dict, landed state, pre-arm checks passing)."""
    v = gl.v
    gp, ss = v.get("GLOBAL_POSITION_INT"), v.get("SYS_STATUS")
    landed = {mavlink.MAV_LANDED_STATE_ON_GROUND: "on ground", mavlink.MAV_LANDED_STATE_IN_AIR: "in air",
              mavlink.MAV_LANDED_STATE_TAKEOFF: "taking off",
              mavlink.MAV_LANDED_STATE_LANDING: "landing"}.get(v.landed_state, "unknown")
    prearm = _prearm_ok(gl)
    vehicle = {
        "sysid": v.sysid, "mode": v.mode_name, "armed": v.armed, "landed_state": landed,
        "prearm_ok": prearm,
        "lat_deg": gp.lat * 1e-7 if gp else None, "lon_deg": gp.lon * 1e-7 if gp else None,
        "alt_rel_m": gp.relative_alt * 1e-3 if gp else None, "alt_amsl_m": gp.alt * 1e-3 if gp else None,
        "battery_v": ss.voltage_battery * 1e-3 if ss and ss.voltage_battery != 65535 else None,
        "battery_pct": ss.battery_remaining if ss and ss.battery_remaining >= 0 else None,
    }
    return vehicle, landed, prearm


def _link_status(gl: GcsLink) -> dict:
    v = gl.v
    hb_age = time.monotonic() - v.seen_at.get(("HEARTBEAT", v.autopilot_comp), -math.inf)
    ss = v.get("SYS_STATUS")
    radio = v.get("RADIO_STATUS", 68) or v.last.get(("RADIO_STATUS", 0))
    return {"url": gl.url, "heartbeat_age_s": round(hb_age, 2) if math.isfinite(hb_age) else None,
            "packet_loss_pct": round(gl.packet_loss_pct(), 1), "received": gl.received,
            "autopilot_drop_rate_pct": ss.drop_rate_comm / 100 if ss else None,
            "rssi": radio.rssi if radio is not None else None}


def _app_status(state: str, st: P.AppStatus, params: dict | None) -> dict:
    """The onboard app's part of a status's --json, from its PMON_STAT."""
    return {"state": state, "tick_rate_hz": round(st.tick_rate_hz, 2),
            "last_tick_time_s": st.last_tick_time_s, "tick_ms": st.tick_ms,
            "ticks": st.ticks, "ticks_skipped": st.ticks_skipped, "ticks_late": st.ticks_late,
            "overruns": st.overruns, "overrun_stage": st.overrun_stage,
            "datagrams_accepted": st.datagrams_accepted, "datagrams_rejected": st.datagrams_rejected,
            "setpoints_refused": st.setpoints_refused, "warnings": list(st.warnings),
            "launch": st.launch_phase, "limits": st.limits,
            "kraken": None if st.kraken is None else dict(zip(("frames", "rejected", "gated"), st.kraken)),
            "uav_enu_m": list(st.uav_enu) if st.uav_enu else None,
            "next_enu_m": list(st.next_enu) if st.next_enu else None,
            "advice_enu_m": list(st.advice_enu) if st.advice_enu else None,
            "params": params}


def _app_lines(state: str, st: P.AppStatus, params: dict | None) -> list[str]:
    """The onboard app's part of a status, for people."""
    lines = [
        f"onboard app: {state}, tick rate {st.tick_rate_hz:.2f} Hz, last tick "
        f"t={_fmt(st.last_tick_time_s)} s ({_fmt(st.tick_ms, '.0f')} ms), {st.ticks} ticks "
        f"({st.ticks_skipped} skipped, {st.ticks_late} late"
        + (f"; {st.overruns} over budget, the last in {st.overrun_stage}" if st.overrun_stage else "") + ")",
        f"  DF datagrams {st.datagrams_accepted} accepted, {st.datagrams_rejected} rejected; "
        f"setpoints refused {st.setpoints_refused}",
        *([] if st.kraken is None else [
            f"  KrakenSDR {st.kraken[0]} frames, {st.kraken[1]} rejected, {st.kraken[2]} gated"]),
        f"  UAV ENU   {_enu(st.uav_enu)}   next {_enu(st.next_enu)}   advised {_enu(st.advice_enu)}",
    ]
    if st.launch_phase:
        lines.append(f"  launch    {st.launch_phase}")
    if st.limits:
        lines.append(f"  speed     {st.limits}")
    lines += [f"  WARNING   {w}" for w in st.warnings]
    if params:
        lines.append("  params    " + " ".join(f"{k.removeprefix('PMON_')}={v_:g}" for k, v_ in params.items()))
    return lines


def _bad_signature_hint(gl: GcsLink) -> str:
    """Why the app may be unheard on a signed link: its packets fail their check."""
    from onboard.app.signing import bad_signatures
    n = bad_signatures(gl.link.mav).get((gl.v.sysid, P.APP_COMPID), 0) if gl.link.signing else 0
    if not n:
        return ""
    why = (f"{gl.v.profile.name} rewrites the signature of what it forwards" if not gl.v.profile.can_sign
           else "a wrong key?")
    return f"; {n} of its packets failed the signature check: {why}"


def _enu(p) -> str:
    return "-" if p is None else f"({p[0]:.1f}, {p[1]:.1f}, {p[2]:.1f}) m"


# ----------------------------------------------------------------------------- commands
def _ack_outcome(what: str, ack: Ack, by: str, context: str = "", why: str | None = None) -> Outcome:
    """``why``: what this command knows of the refusal beyond the autopilot's words (said after
    them, or instead of "no reason given")."""
    data = {"command": what, "result": ack.result, "attempts": ack.attempts,
            "elapsed_s": round(ack.elapsed_s, 3)}
    if ack.ok:
        note = "" if ack.result == "ACCEPTED" else " (acknowledgement lost; effect observed)"
        return Outcome(f"{what}: accepted by the {by}{note}", data)
    if by == "onboard app" and ack.reason_code in P.REASONS:
        why = P.REASONS[ack.reason_code]
    else:
        texts = [t.removeprefix("PMON: ") for t in ack.texts] + ([why] if why else [])
        why = "; ".join(texts[-2:]) if texts else "no reason given"
    later = " (try again later)" if ack.result == "TEMPORARILY_REJECTED" else ""
    raise GcsError(f"{what} refused by the {by} ({ack.result}): {why}{later}{context}", FAILED)


def _vehicle_context(gl: GcsLink) -> str:
    v = gl.v
    gp = v.get("GLOBAL_POSITION_INT")
    alt = f", {gp.relative_alt / 1000:.1f} m above home" if gp else ""
    return f" [vehicle: {v.mode_name}, {'armed' if v.armed else 'disarmed'}{alt}]"


def app_action(gl: GcsLink, action: str) -> Outcome:
    want = {"start": "monitoring", "resume": "monitoring", "pause": "paused", "stop": "idle",
            "advise": "advisory"}.get(action)
    done = (lambda: gl.v.app_state == want) if want else None
    ack = gl.command(P.APP_COMPID, P.APP_COMMAND, P.ACTIONS[action], done=done, name=action)
    out = _ack_outcome(action, ack, "onboard app")
    if want and ack.ok:  # report the state the app is in now (its heartbeat follows the ACK)
        gl.wait_for(lambda: gl.v.app_state == want, 1.0)
    return Outcome(out.text + (f"; app {gl.v.app_state}" if gl.v.app_state else ""),
                   {**out.data, "app_state": gl.v.app_state})


MODE_SHOWN_S = 3.0  # s after its ACK a mode change must show in HEARTBEAT (the ACK is not proof)


def set_mode(gl: GcsLink, what: str, name: str, cmd: int | None = None) -> Outcome:
    """A flight mode by its firmware's name (the autopilot's profile: ArduCopter's or PX4's),
    by its command (RTL, LAND) or by DO_SET_MODE. Done when HEARTBEAT shows it: PX4 ACKs a mode
    it cannot run (POSCTL with no RC or joystick) ACCEPTED and stays where it was."""
    profile = gl.v.profile
    if profile.mode_number(name) is None:
        raise GcsError(f"{what}: {profile.no_mode(name)}", FAILED)
    done = lambda: profile.in_mode(gl.v.mode, name)  # noqa: E731
    t0 = time.monotonic()
    if cmd is None:
        ack = gl.command(None, mavlink.MAV_CMD_DO_SET_MODE, *profile.set_mode_params(name), done=done, name=what)
    else:
        ack = gl.command(None, cmd, done=done, name=what)
    out = _ack_outcome(what, ack, "autopilot", _vehicle_context(gl))
    gl.request(mavlink.MAVLINK_MSG_ID_HEARTBEAT)  # the new mode now, not at the next 1 Hz beat
    if not gl.wait_for(done, max(MODE_SHOWN_S, min(gl.timeout, 10.0))):
        texts = gl.texts_since(t0, gl.v.autopilot_comp)[-1:]
        raise GcsError(f"{what}: accepted by the autopilot, but it is still in {gl.v.mode_name} "
                       f"({profile.name} keeps its mode when the new one cannot run"
                       f"{': ' + texts[0] if texts else ''})", FAILED)
    return Outcome(out.text + f"; mode {gl.v.mode_name}", {**out.data, "mode": gl.v.mode_name})


def _prearm_ok(gl: GcsLink) -> bool | None:
    """The autopilot's pre-arm checks from SYS_STATUS, as its profile reads them (None where it
    does not report them)."""
    return gl.v.profile.prearm_ok(gl.v.get("SYS_STATUS"))


ARM_RETRY_S = 2.0  # arm --wait: between attempts while the autopilot refuses


def arm(gl: GcsLink, wait: bool = False) -> Outcome:
    """The launch mode first (the profile's: ArduCopter's GUIDED, as it takes off by command only
    in a navigating mode and the app flies GUIDED; PX4's Hold, where it boots, arms and takes
    off), then arm. ``wait``: the autopilot may not be ready yet (~40 s after boot for ArduCopter,
    ~5 s for PX4): wait for its pre-arm checks (SYS_STATUS) and try again every ARM_RETRY_S while
    it refuses, up to --timeout in all. (ArduPilot's pre-arm bit can pass before GUIDED's own
    need for a position estimate does: measured on 4.4 SITL, so its refusals are waited out
    too.)"""
    v = gl.v
    t0 = time.monotonic()
    deadline = t0 + gl.timeout
    if wait and not v.armed:
        gl.stream(mavlink.MAVLINK_MSG_ID_SYS_STATUS, 2.0)
        gl.wait_for(lambda: v.get("SYS_STATUS") is not None, min(gl.timeout, 2.0))
    while True:
        if wait and not v.armed and not gl.wait_for(lambda: _prearm_ok(gl) is not False,
                                                     max(deadline - time.monotonic(), 0.0)):
            texts = [t for t in gl.texts_since(t0, v.autopilot_comp) if v.profile.arming_refusal(t)]
            why = f": {texts[-1]}" if texts else ""
            raise GcsError(f"arm: the autopilot's pre-arm checks still fail after {gl.timeout:g} s{why}",
                           TIMEOUT)
        launch_mode = v.profile.launch_mode
        if not v.profile.in_mode(v.mode, launch_mode) and not v.armed:
            _ack_outcome(launch_mode.lower(), gl.command(
                None, mavlink.MAV_CMD_DO_SET_MODE, *v.profile.set_mode_params(launch_mode),
                done=lambda: v.profile.in_mode(v.mode, launch_mode), name=f"mode {launch_mode}"),
                "autopilot", _vehicle_context(gl))
        ack = gl.command(None, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1, done=lambda: bool(v.armed), name="arm")
        if ack.ok or not wait or time.monotonic() + ARM_RETRY_S > deadline:
            break
        gl.wait_for(lambda: bool(v.armed), ARM_RETRY_S)  # refused: not ready yet
    out = _ack_outcome("arm", ack, "autopilot", _vehicle_context(gl))
    gl.request(mavlink.MAVLINK_MSG_ID_HEARTBEAT)
    gl.wait_for(lambda: bool(v.armed), 1.0)
    waited = time.monotonic() - t0
    note = f" (ready after {waited:.1f} s)" if wait and waited > 1.0 else ""
    return Outcome(out.text + f"; {v.mode_name}, {'armed' if v.armed else 'not armed yet'}{note}",
                   {**out.data, "mode": v.mode_name, "armed": v.armed, "wait_s": round(waited, 2)})


CLIMB_PROGRESS_M = 0.5  # --wait: the take-off fails when the height gains less than this in --timeout


def takeoff(gl: GcsLink, alt: float, wait: bool) -> Outcome:
    """MAV_CMD_NAV_TAKEOFF to ``alt`` m above home, in the form every firmware accepts
    (onboard/app/autopilot/profiles.py). ``wait``: until at ``alt`` and reported in the air; a
    climb takes as long as it takes, so --timeout bounds the time without progress (less
    than CLIMB_PROGRESS_M gained), not the whole climb."""
    from onboard.app.autopilot.pose import heading_from_global_position_int

    v = gl.v
    gl.stream(mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT, 4.0)
    gl.stream(mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE, 2.0)  # not in any ArduPilot default stream
    gl.request(mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT)
    if not gl.wait_for(lambda: v.get("GLOBAL_POSITION_INT") is not None, min(gl.timeout, 2.0)):
        raise GcsError(f"takeoff: no position from the autopilot within {min(gl.timeout, 2.0):g} s "
                       f"(a take-off is sent with the vehicle's own position){_vehicle_context(gl)}", TIMEOUT)
    gp = v.get("GLOBAL_POSITION_INT")
    params = v.profile.takeoff_params(gp.lat * 1e-7, gp.lon * 1e-7, heading_from_global_position_int(gp.hdg),
                                      alt, (gp.alt - gp.relative_alt) * 1e-3)
    climbing = (mavlink.MAV_LANDED_STATE_TAKEOFF, mavlink.MAV_LANDED_STATE_IN_AIR)
    ack = gl.command(None, mavlink.MAV_CMD_NAV_TAKEOFF, *params,
                     done=lambda: v.landed_state in climbing, name="takeoff")
    why = None if ack.ok else _why_disarmed(gl)
    out = _ack_outcome(f"takeoff to {alt:g} m", ack, "autopilot", _vehicle_context(gl), why)
    data = {**out.data, "alt_m": alt}
    if not wait:
        return Outcome(out.text, data)
    t0 = time.monotonic()
    in_air = [0]  # consecutive IN_AIR reports

    def count(mtype, msg):
        if mtype == "EXTENDED_SYS_STATE" and msg.get_srcComponent() == v.autopilot_comp:
            in_air[0] = in_air[0] + 1 if msg.landed_state == mavlink.MAV_LANDED_STATE_IN_AIR else 0
    gl.on_message(count)

    def height() -> float:
        g = v.get("GLOBAL_POSITION_INT")
        return -math.inf if g is None else g.relative_alt / 1000

    def there():
        # at altitude and the take-off reported complete twice: the onboard app (its own link,
        # same report) then knows it is flying too, and a start is not refused
        return height() >= alt - 1.0 and in_air[0] >= 2
    best = height()
    while not gl.wait_for(there, gl.timeout):
        if height() < best + CLIMB_PROGRESS_M:
            raise GcsError(f"takeoff: not at {alt:g} m: no climb in the last {gl.timeout:g} s"
                           f"{_vehicle_context(gl)}", TIMEOUT)
        best = height()
    data["climb_s"] = round(time.monotonic() - t0, 2)
    return Outcome(out.text + f"; at {alt:g} m after {data['climb_s']:.1f} s", data)


AUTO_DISARM_TOL_S = 1.5  # armed this close to the auto-disarm delay before a disarm: the autopilot's own


def _why_disarmed(gl: GcsLink) -> str | None:
    """Why a take-off found the vehicle disarmed, from what this connection heard: the armed
    bit's changes in its HEARTBEATs, its STATUSTEXT at the disarm, and its auto-disarm delay
    (ArduCopter's DISARM_DELAY, PX4's COM_DISARM_PRFLT), read now. A disarm that came that long
    after the arm is the autopilot's own; one before this command connected is said as such
    (the arm was another command's). None while armed."""
    v = gl.v
    if v.armed is not False:
        return None
    now = time.monotonic()
    param = v.profile.auto_disarm_param
    delay = gl.autopilot_param(param, min(gl.timeout, 1.5)) if param else None
    rule = (f"{v.profile.name} disarms a vehicle armed on the ground that has not taken off after "
            f"{param} = {delay:g} s" if delay is not None and delay > 0 else None)
    again = "arm again" + (f" and take off within {delay:g} s" if rule else "")
    changes = list(v.armed_changes)
    disarm = next((i for i in range(len(changes) - 1, 0, -1) if not changes[i][2]), None)
    if disarm is None:
        return (f"the vehicle was disarmed already when this command connected {now - gl.t0:.1f} s ago"
                + (f" ({rule})" if rule else "") + f": {again}")
    (t, boot, _), (armed_t, armed_boot, _) = changes[disarm], changes[disarm - 1]
    # armed for, on the autopilot's clock where known (DISARM_DELAY runs on it), else this one's
    armed_for = boot - armed_boot if boot is not None and armed_boot is not None else t - armed_t
    armed_s = f"{armed_for:.1f} s after it armed" if disarm > 1 else f"armed {armed_for:.1f} s or more"
    said = [text for at, c, _s, text in v.texts if c == v.autopilot_comp and abs(at - t) <= 1.5
            and "disarm" in text.lower()]
    words = f" ('{said[-1]}')" if said else ""
    if rule and disarm > 1 and abs(armed_for - delay) <= AUTO_DISARM_TOL_S:
        return f"the autopilot disarmed itself {now - t:.1f} s ago{words}, {armed_s}: {rule}; {again}"
    return f"the vehicle disarmed {now - t:.1f} s ago{words}, {armed_s}" + (f" ({rule})" if rule else "") + f"; {again}"


# ----------------------------------------------------------------------------- parameters
def params_list(gl: GcsLink) -> Outcome:
    from onboard.app.params import BY_NAME  # names, ranges and meanings (a light module)
    values = gl.params_list()
    rows = []
    for name, value in values.items():
        spec = BY_NAME.get(name)
        rng = f"[{spec.lo:g}, {spec.hi:g}]" if spec else ""
        rows.append(f"{name:16s} {value:>10g}  {rng:16s} {spec.doc if spec else ''}")
    return Outcome("\n".join(rows), {"params": values})


def params_get(gl: GcsLink, name: str) -> Outcome:
    value = gl.param_exchange(name.upper())
    return Outcome(f"{name.upper()} = {value:g}", {"name": name.upper(), "value": value})


def params_set(gl: GcsLink, name: str, value: float) -> Outcome:
    if not math.isfinite(value):
        raise GcsError(f"params set {name}: value must be a finite number", 2)
    got = gl.param_exchange(name.upper(), value)
    note = "" if _same(got, value) else f" (rounded from {value:g})"
    return Outcome(f"{name.upper()} = {got:g}{note}; takes effect at the next tick",
                   {"name": name.upper(), "value": got, "requested": value})
