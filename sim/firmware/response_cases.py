"""The cases bench/sitl_response.py flies (a step, the top speed, a ramp, a planner-like route and
the setpoints it is sent as) and the figures of each trace: the distance at the next tick, a
step's settling.
"""
from __future__ import annotations

import math

import numpy as np

from sim.firmware.response_flight import MASK_POS, MASK_POSVEL, MASK_PVA, MASK_VEL, SitlFlight, Trace
from onboard.core.setpoint import plan_setpoint

TICK_S = 1.0


def fly_step(f: SitlFlight, distance: float, heading_deg: float, duration: float) -> Trace:
    tr = f.start_case(f"step{distance:g}")
    h = math.radians(heading_deg)
    f.send(MASK_POS, (distance * math.cos(h), distance * math.sin(h), 0.0))
    t0 = f.t_ms / 1000.0
    f.wait_fw(t0 + duration)
    f.recording = None
    return tr


def fly_top(f: SitlFlight, speed: float, heading_deg: float, duration: float) -> Trace:
    """A velocity-only command far above what the airframe flies: its top speed at ANGLE_MAX."""
    tr = f.start_case("top")
    h = math.radians(heading_deg)
    v = (speed * math.cos(h), speed * math.sin(h), 0.0)
    t0 = f.t_ms / 1000.0
    k = 0
    while k * 0.5 <= duration:  # within GUID_TIMEOUT
        f.wait_fw(t0 + k * 0.5)
        f.send(MASK_VEL, (0.0, 0.0, 0.0), v)
        k += 1
    f.send(MASK_VEL, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
    f.wait_fw(t0 + duration + 6.0)
    f.recording = None
    return tr


def top_speed(tr: Trace) -> float:
    """The top speed held: the median speed over the last 3 s of the command."""
    d = tr.as_dict(every=1)
    t, v = np.asarray(d["t"]), np.linalg.norm(np.asarray(d["vel"]), axis=1)
    # the last send of the fast command (on PX4 the stop after it is resent to the trace's end)
    t_stop = max(x[0] for x in d["sends"] if x[3] is not None and math.hypot(*x[3][:2]) > 1.0)
    return float(np.median(v[(t > t_stop - 3.0) & (t <= t_stop)]))


def fly_ramp(f: SitlFlight, speed: float, heading_deg: float, duration: float) -> Trace:
    tr = f.start_case(f"ramp{speed:.0f}")
    h = math.radians(heading_deg)
    v = (speed * math.cos(h), speed * math.sin(h), 0.0)
    t0 = f.t_ms / 1000.0
    k = 0
    while k * 0.1 <= duration:
        f.wait_fw(t0 + k * 0.1)
        dt = f.t_ms / 1000.0 - t0
        f.send(MASK_POSVEL, (v[0] * dt, v[1] * dt, 0.0), v)
        if k % 10 == 0:
            tr.plan.append((f.t_ms / 1000.0, v[0] * dt, v[1] * dt))
        k += 1
    f.wait_fw(t0 + duration + 3.0)
    f.recording = None
    return tr


def planner_route(speed: float, accel: float, heading_deg: float = 0.0,
                  turns=((6, 90), (5, -120), (4, 60), (6, -150), (4, 45), (5, 0))) -> tuple[np.ndarray, np.ndarray]:
    """A route a vehicle with these limits can fly, sampled every TICK_S: from hover, accelerate at
    half the acceleration limit to ``speed``, then legs (seconds straight) each followed by a turn
    (degrees, + = clockwise) at 0.6x the acceleration limit. Returns p (K, 2) and v (K, 2)."""
    dt = 0.01
    a_t, a_n = 0.5 * accel, 0.6 * accel
    psi = math.radians(heading_deg)
    p, s = np.zeros(2), 0.0
    plan = [(p.copy(), np.zeros(2))]
    events, t = [], 0.0
    for leg_s, turn_deg in turns:
        events.append(("straight", leg_s))
        if turn_deg:
            events.append(("turn", math.radians(turn_deg)))
    t_next = TICK_S
    queue = list(events)
    mode, left = "accel", None
    while True:
        if mode == "accel":
            s = min(speed, s + a_t * dt)
            if s >= speed:
                if not queue:
                    break
                mode, left = queue.pop(0)
        elif mode == "straight":
            left -= dt
            if left <= 0:
                if not queue:
                    break
                mode, left = queue.pop(0)
        else:
            rate = a_n / max(s, 1e-6)
            step = math.copysign(min(rate * dt, abs(left)), left)
            psi += step
            left -= step
            if abs(left) < 1e-9:
                if not queue:
                    break
                mode, left = queue.pop(0)
        p = p + s * dt * np.array([math.cos(psi), math.sin(psi)])
        t += dt
        if t >= t_next - 1e-9:
            plan.append((p.copy(), s * np.array([math.cos(psi), math.sin(psi)])))
            t_next += TICK_S
    P = np.array([x[0] for x in plan])
    V = np.array([x[1] for x in plan])
    return P, V


def route_setpoint(kind: str, P: np.ndarray, V: np.ndarray, k: int, latency: float = 0.0):
    """What to send at tick k (the plan's time k TICK_S) for the route: (mask, pos, vel, acc), NED."""
    nxt = min(k + 1, len(P) - 1)
    if kind == "pos":
        return MASK_POS, (*P[nxt], 0.0), None, None
    if kind == "posvel":  # the plan's position and velocity ``latency`` s after tick k
        p, v, _ = plan_setpoint(P[k], V[k], V[nxt], TICK_S, min(latency, TICK_S))
        return MASK_POSVEL, (*p, 0.0), (*v, 0.0), None
    if kind == "posvel_next":
        return MASK_POSVEL, (*P[nxt], 0.0), (*V[nxt], 0.0), None
    if kind == "ramp":
        v = (P[nxt] - P[k]) / TICK_S
        p = P[k] + v * latency
        return MASK_POSVEL, (*p, 0.0), (*v, 0.0), None
    if kind == "pva":  # the app's setpoint (onboard.core.setpoint); the last tick: no acceleration
        p, v, a = plan_setpoint(P[k], V[k], V[nxt], TICK_S, min(latency, TICK_S))
        return MASK_PVA, (*p, 0.0), (*v, 0.0), (*a, 0.0)
    raise ValueError(kind)


def fly_route(f: SitlFlight, kind: str, P: np.ndarray, V: np.ndarray, latency: float = 0.0,
              name: str | None = None) -> Trace:
    tr = f.start_case(name or f"route_{kind}")
    t0 = f.t_ms / 1000.0
    for k in range(len(P)):
        f.wait_fw(t0 + k * TICK_S + latency)
        tr.plan.append((t0 + k * TICK_S, *P[k]))
        late = f.t_ms / 1000.0 - (t0 + k * TICK_S)  # the plan's state when it is sent
        mask, p, v, a = route_setpoint(kind, P, V, k, late)
        f.send(mask, p, v, a)
        if f.px4:  # resent as the app does: the plan's state at each send (the point, for pos)
            f.resend = f.resending((lambda k: lambda t: route_setpoint(kind, P, V, k, t - (t0 + k * TICK_S)))(k))
    f.wait_fw(t0 + len(P) * TICK_S + 2.0)
    f.recording = None
    return tr


# --------------------------------------------------------------------------- figures

def distance_at_ticks(tr: Trace | dict) -> np.ndarray:
    """Horizontal distance from the vehicle to the plan's point at each planned time after the first
    (the time the next 1-s setpoint is due), the vehicle's position interpolated on the firmware clock."""
    d = tr if isinstance(tr, dict) else tr.as_dict(every=1)
    t = np.asarray(d["t"])
    pos = np.asarray(d["pos"])
    out = []
    for tp, x, y in d["plan"][1:]:
        if tp > t[-1]:
            break
        px, py = np.interp(tp, t, pos[:, 0]), np.interp(tp, t, pos[:, 1])
        out.append(math.hypot(px - x, py - y))
    return np.asarray(out)


def step_figures(tr: Trace, distance: float) -> dict:
    d = tr.as_dict(every=1)
    t, pos = np.asarray(d["t"]), np.asarray(d["pos"])
    # the step itself (on PX4 the hold before it is resent into the trace's first half second)
    first = next(x for x in d["sends"] if math.hypot(*x[2][:2]) > 0.5 * distance)
    t_send = first[0]
    goal = np.asarray(first[2][:2])
    err = np.linalg.norm(pos[:, :2] - goal, axis=1)
    inside = np.nonzero((err < 1.0) & (t >= t_send))[0]
    along = pos[:, :2] @ (goal / np.linalg.norm(goal))
    return {"t_within_1m_s": None if not len(inside) else round(float(t[inside[0]] - t_send), 2),
            "overshoot_m": round(float(max(0.0, along.max() - distance)), 2),
            "peak_speed_mps": round(float(np.max(np.linalg.norm(np.asarray(d["vel"])[:, :2], axis=1))), 2)}


def stats(x: np.ndarray) -> dict:
    return {"median_m": round(float(np.median(x)), 2), "p95_m": round(float(np.percentile(x, 95)), 2),
            "max_m": round(float(np.max(x)), 2), "n": int(len(x))}

