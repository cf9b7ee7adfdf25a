"""The vehicle model (sim.mock.multicopter, sim.mock.guided) on the setpoints of a saved flight of
bench/sitl_response.py: its positions, its RMS error against the SITL's, and the fit of its
airframe terms.
"""
from __future__ import annotations

import gzip
import json
from dataclasses import replace

import numpy as np


def guided_setpoint(mask: int, pos, vel, acc):
    """A recorded SET_POSITION_TARGET_LOCAL_NED as sim.mock.guided reads it (the type_mask's fields)."""
    from sim.mock.guided import GuidedSetpoint

    return GuidedSetpoint(pos=None if mask & 0b111 else tuple(pos),
                          vel=None if mask & 0b111000 or vel is None else tuple(vel),
                          acc=None if mask & 0b111000000 or acc is None else tuple(acc))


def replay(trace: dict, limits=None, rate_hz: float = 400.0) -> np.ndarray:
    """The model (sim.mock.multicopter, sim.mock.guided) given the trace's setpoints at their firmware times,
    from the trace's first sample (hovering at its start, GUIDED position-only): its horizontal
    positions at the trace's sample times, (N, 2)."""
    from sim.mock.guided import fly_timeline
    from sim.mock.multicopter import VehicleLimits, VehicleState

    limits = limits or VehicleLimits()
    t = np.asarray(trace["t"], float)
    p0, v0 = trace["pos"][0], trace["vel"][0]
    state = VehicleState(pos=(p0[0], p0[1], 0.0), vel=(v0[0], v0[1], 0.0))
    sends = [(s[0] - t[0], guided_setpoint(s[1], s[2], s[3], s[4])) for s in trace["sends"]]
    states = fly_timeline(state, sends, t - t[0], limits, rate_hz, submode="pos", hold=(0.0, 0.0, 0.0),
                          offboard=not limits.shaping)
    return np.array([s.pos[:2] for s in states])


def rms_error(trace: dict, limits=None, rate_hz: float = 400.0) -> float:
    """RMS horizontal distance (m) between the model's positions and the SITL's over the trace."""
    model = replay(trace, limits, rate_hz)
    return float(np.sqrt(np.mean(np.sum((model - np.asarray(trace["pos"])) ** 2, axis=1))))


IN_ENVELOPE = ("not the demo's route90: its plan asks more than the airframe's lean gives at 9 m/s; "
               "not PX4's top: 15 s at the tilt limit, which two SITL runs flew 11 m apart")


def in_envelope(label: str, name: str) -> bool:
    """The traces the model is fitted and held to (the rest: see IN_ENVELOPE)."""
    return not ((label == "demo" and name.startswith("route90")) or (label == "px4" and name == "top"))


def model_errors(data: dict, rate_hz: float = 400.0, **airframe) -> dict:
    """{(limits label, trace name): RMS error of the model, m} over a saved flight."""
    return {(lab, tr["name"]): rms_error(tr, limits_for(data[lab]["params"], **airframe), rate_hz)
            for lab in data for tr in data[lab]["traces"]}


def fit_airframe(data: dict, rate_hz: float = 400.0, evaluations: int = 60) -> dict:
    """The airframe terms minimising the RMS over the in-envelope traces of their RMS errors
    (Nelder-Mead from the model's current values): lean_tc and drag (quadratic) for ArduCopter's
    SITL, lean_tc and drag_lin (linear, as SIH's) for PX4's."""
    from scipy.optimize import minimize

    from sim.mock.multicopter import is_px4

    px4 = any(is_px4(data[lab]["params"]) for lab in data)
    names = ("lean_tc", "drag_lin") if px4 else ("lean_tc", "drag")
    start = limits_for(next(iter(data.values()))["params"])

    def cost(x):
        if x[0] < 0.0 or x[1] <= 0.0:
            return 1e9
        e = model_errors(data, rate_hz, **dict(zip(names, x)))
        return float(np.sqrt(np.mean([v * v for k, v in e.items() if in_envelope(*k)])))

    r = minimize(cost, [getattr(start, n) for n in names], method="Nelder-Mead",
                 options=dict(maxfev=evaluations, xatol=1e-3, fatol=1e-4))
    return {names[0]: round(float(r.x[0]), 3), names[1]: round(float(r.x[1]), 4), "rms_m": round(r.fun, 3)}


def load(path: str) -> dict:
    with gzip.open(path, "rt") as fh:
        return json.load(fh)


def limits_for(params: dict, **airframe):
    """sim.mock.multicopter's limits for the parameters a flight read back (and airframe terms, if given)."""
    from sim.mock.multicopter import limits_from_params

    return replace(limits_from_params(params), **airframe)

