"""How the real ArduCopter SITL follows GUIDED setpoints (PX4's SITL, OFFBOARD ones), and how
sim/mock/multicopter.py does on the same ones.

    python -m bench.sitl_response [--limits stock,demo] [--cases top,step20,step100,ramp,route90,route70]
                                  [--speedup 4] [--param NAME=VALUE ...] [--save FILE.json.gz]
    python -m bench.sitl_response --autopilot px4 [--speedup 2] [--save FILE.json.gz]
    python -m bench.sitl_response --replay tests/data/sitl_response.json.gz   # the model, no SITL
    python -m bench.sitl_response --fit tests/data/sitl_response.json.gz      # its airframe terms

Boots ArduPilot's own SITL firmware (sim/firmware/ardupilot.py; set PMON_ARDUPILOT_SITL) once per set of
limits, takes off in GUIDED to 20 m and flies each case from a settled hover where the last one
ended (its coordinates are relative to that point, local NED, metres):

- ``top``: a velocity-only command at 3x WPNAV_SPEED for 15 s: the airframe's top speed (the
  drag at ANGLE_MAX; ArduCopter does not cap a velocity command at WPNAV_SPEED);
- ``step20``, ``step100``: one position-only SET_POSITION_TARGET_LOCAL_NED 20 m / 100 m away;
- ``ramp``: a target moving in a straight line at half the lower of WPNAV_SPEED and the top
  speed, sent at 10 Hz as position + velocity (its position at the send time, its velocity);
- ``routeNN``: a planner-like route, one setpoint per second: from hover, accelerate at half
  WPNAV_ACCEL to NN % of the lower of WPNAV_SPEED and the top speed, then six legs with turns
  of 90, -120, 60, -150, 45 deg at 0.6x WPNAV_ACCEL. It is flown four times, each sending, at
  tick k (the plan's time k s, when the setpoint is sent d s after it), for p[k], v[k]: the
  plan's position and velocity at k, T = 1 s:
  ``pos``: p[k+1], position only (what the app sends today: the copter brakes to each point);
  ``posvel_next``: p[k+1] with v[k+1] (the point and the velocity to fly through it);
  ``ramp``: p[k] + d c with c = (p[k+1] - p[k]) / T (a target that reaches p[k+1] when the
  next setpoint is due);
  ``pva``: the plan's state at k + d: p[k] + d v[k] + d^2 a / 2, v[k] + d a, and a =
  (v[k+1] - v[k]) / T as acceleration (the firmware integrates it to p[k+1], v[k+1]); what the
  app sends, computed by the same function (onboard.core.setpoint.plan_setpoint).

PX4 (``--autopilot px4``: PX4 v1.16 SITL, SIH quad, sim/firmware/px4.py; set PMON_PX4_SITL): armed in
Hold, NAV_TAKEOFF to 20 m (AMSL), then OFFBOARD entered the way PX4 requires (setpoints first).
PX4 holds a setpoint as sent and leaves OFFBOARD 1 s after the last, so every setpoint is sent
again at 10 Hz of PX4's clock as the app does (PMON_SP_HZ): a fixed one as it was, a route's as
the plan's state at that moment. Limits: its stock parameters (``stock``); WPNAV_SPEED /
WPNAV_ACCEL read as MPC_XY_VEL_MAX / MPC_ACC_HOR. The routes are flown three ways: ``pos`` (the
next point, resent), ``posvel`` (the plan's position and velocity at the moment of sending) and
``pva`` (and its acceleration: what the app sends). ``--replay`` of a PX4 flight holds each
setpoint until the next, as PX4 does (sim.mock.guided.fly_timeline(offboard=True)).

Limits: ``stock`` is what the binary boots with (copter.parm over the firmware's defaults: read
back and printed), ``demo`` is sim/mock/multicopter.py's DEMO_VEHICLE_PARAMS. The copter's
LOCAL_POSITION_NED is recorded at ~40 Hz (50 Hz asked) on the firmware's clock (time_boot_ms);
a setpoint's time is the firmware time of the last message received when it was sent.

Printed per case: for routes and the ramp, the horizontal distance from the vehicle to the point
the plan puts it at, when the next 1-s setpoint is due (median, p95, max over the ticks); for
steps, the time to come within 1 m, the overshoot and the peak speed. Last line: JSON of these.
``--save`` writes the traces (10 Hz, horizontal) and every setpoint sent: the reference data of
tests/sim/test_vehicle.py. ``--replay`` gives a saved flight's setpoints to the model
(sim.mock.guided.fly_timeline at the firmware's 400 Hz) and prints its RMS position error on each
trace and its distance at the next tick beside the SITL's.

Its parts: sim/firmware/response_flight.py (the MAVLink client and a trace), sim/firmware/response_cases.py
(the cases and their figures), sim/firmware/response_model.py (the model on a saved flight, its fit).
"""
from __future__ import annotations


import argparse
import gzip
import json
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Mapping

import numpy as np

from sim.mock.multicopter import DEMO_VEHICLE_PARAMS
from sim.firmware import px4 as px4_sitl
from sim.firmware.ardupilot import ArduPilotSitl, SitlError, find_binary, param_item, skip_reason

from sim.firmware.response_cases import (
    distance_at_ticks, fly_ramp, fly_route, fly_step, fly_top, planner_route, stats, step_figures, top_speed,
)
from sim.firmware.response_flight import HOME, FlightError, SitlFlight, Trace
from sim.firmware.response_model import fit_airframe, in_envelope, limits_for, load, replay

READ_PARAMS = ("WPNAV_SPEED", "WPNAV_ACCEL", "WPNAV_SPEED_UP", "WPNAV_SPEED_DN", "PSC_JERK_XY",
               "PSC_POSXY_P", "PSC_VELXY_P", "PSC_VELXY_I", "PSC_VELXY_D", "ATC_ACCEL_R_MAX",
               "ATC_ACCEL_P_MAX", "ATC_RATE_FF_ENAB", "ATC_RATE_R_MAX", "ANGLE_MAX", "GUID_TIMEOUT",
               "GUID_OPTIONS", "FENCE_ENABLE", "SCHED_LOOP_RATE", "WP_YAW_BEHAVIOR")
PX4_READ_PARAMS = ("MPC_XY_VEL_MAX", "MPC_ACC_HOR", "MPC_ACC_HOR_MAX", "MPC_JERK_MAX", "MPC_JERK_AUTO",
                   "MPC_XY_CRUISE", "MPC_XY_P", "MPC_XY_VEL_P_ACC", "MPC_XY_VEL_I_ACC", "MPC_XY_VEL_D_ACC",
                   "MPC_TILTMAX_AIR", "MPC_Z_VEL_MAX_UP", "MPC_Z_VEL_MAX_DN", "MPC_ACC_UP_MAX", "MPC_ACC_DOWN_MAX",
                   "MPC_Z_P", "MPC_THR_HOVER", "SIH_MASS", "SIH_KDV", "SIH_L_ROLL", "COM_OF_LOSS_T")
LIMITS = {"stock": {}, "demo": dict(DEMO_VEHICLE_PARAMS)}
ROUTE_KINDS = ("pos", "posvel_next", "ramp", "pva")
PX4_ROUTE_KINDS = ("pos", "posvel", "pva")


# --------------------------------------------------------------------------- main

def _number(text: str) -> bool:
    try:
        return float(text) > 0
    except ValueError:
        return False


@dataclass(frozen=True)
class BenchRun:
    """What each set of limits is flown with, from the command line: the firmware, its speedup,
    the cases, the route setpoints' latency (s) and cruise speed (m/s; None: from the case's
    share), the parameters set over each set of limits, and which autopilot."""

    binary: Path
    speedup: float
    cases: tuple[str, ...]
    latency_s: float = 0.0
    route_speed: float | None = None
    extra: Mapping[str, float] = field(default_factory=dict)
    autopilot: str = "ardupilot"


def fly_limits(label: str, run: BenchRun, log=print) -> tuple[dict, dict, list[Trace]]:
    binary, speedup, cases, latency = run.binary, run.speedup, run.cases, run.latency_s
    route_speed, extra, px4 = run.route_speed, run.extra, run.autopilot == "px4"
    params_in = {**LIMITS[label], **(extra or {})}
    # PX4's ULog of a full run is ~200 MB: its working directory goes with the bench
    workdir = tempfile.TemporaryDirectory(prefix="pmon-px4-bench-") if px4 else None
    sitl = px4_sitl.Px4Sitl(binary, HOME, speed=speedup, params=params_in, workdir=Path(workdir.name)) if px4 else \
        ArduPilotSitl(binary, HOME, speedup=speedup, params=params_in)
    sitl.start()
    try:
        f = SitlFlight(sitl.talk_url("api") if px4 else sitl.url(0), speedup, run.autopilot)
        try:
            f.take_off_px4() if px4 else f.take_off()
            params = f.read_params(PX4_READ_PARAMS if px4 else READ_PARAMS)
            log(f"[{label}] parameters read back: {params}")
            if px4:
                vmax, amax = params["MPC_XY_VEL_MAX"], params["MPC_ACC_HOR"]
            else:
                vmax, amax = params["WPNAV_SPEED"] / 100.0, params["WPNAV_ACCEL"] / 100.0
            figures, traces = {}, []
            top = None
            for case in cases:
                if case == "top":
                    tr = fly_top(f, 3.0 * vmax, 45.0, 15.0)
                    top = top_speed(tr)
                    figures[tr.name] = {"top_speed_mps": round(top, 2)}
                    traces.append(tr)
                elif case.startswith("step"):
                    dist = float(case[4:])
                    tr = fly_step(f, dist, 0.0 if dist < 50 else 180.0, 8.0 + dist / vmax * 1.3)
                    figures[tr.name] = step_figures(tr, dist)
                    traces.append(tr)
                elif case == "ramp":
                    tr = fly_ramp(f, 0.5 * min(vmax, top or vmax), 90.0, 20.0)
                    figures[tr.name] = stats(distance_at_ticks(tr))
                    traces.append(tr)
                elif case.startswith("route"):
                    share = float(case[5:] or 90) / 100.0
                    cruise = route_speed or share * min(vmax, top or vmax)
                    figures[f"{case}_speed_mps"] = round(cruise, 2)
                    P, V = planner_route(cruise, amax)
                    for kind in PX4_ROUTE_KINDS if px4 else ROUTE_KINDS:
                        tr = fly_route(f, kind, P, V, latency, name=f"{case}_{kind}")
                        figures[tr.name] = stats(distance_at_ticks(tr))
                        traces.append(tr)
                log(f"[{label}] {case}: " + json.dumps({k: v for k, v in figures.items()
                                                          if k.startswith(case)}))
                if px4 and not f.in_offboard():
                    raise FlightError(f"PX4 left OFFBOARD during {case} (mode {f.heartbeat.custom_mode:#x})")
        finally:
            f.conn.close()
    finally:
        sitl.stop()
        if workdir is not None:
            workdir.cleanup()
    return params, figures, traces


def offline(path: str, fit: bool) -> int:
    try:
        data = load(path)
    except (OSError, ValueError) as exc:
        print(f"python -m bench.sitl_response: {path}: {exc}", file=sys.stderr)
        return 2
    if fit:
        print(json.dumps(fit_airframe(data)))
        return 0
    out = {}
    for lab in data:
        limits = limits_for(data[lab]["params"])
        for tr in data[lab]["traces"]:
            model = replay(tr, limits)
            rms = float(np.sqrt(np.mean(np.sum((model - np.asarray(tr["pos"])) ** 2, axis=1))))
            fig = {"rms_m": round(rms, 2), "in_envelope": in_envelope(lab, tr["name"])}
            if tr["plan"]:
                fig["sitl"] = stats(distance_at_ticks(tr))
                fig["model"] = stats(distance_at_ticks({**tr, "pos": model.tolist()}))
            out[f"{lab}:{tr['name']}"] = fig
            line = f"{lab:6s} {tr['name']:20s} rms={fig['rms_m']:5.2f} m"
            if "sitl" in fig:
                line += (f"  next tick: SITL median {fig['sitl']['median_m']:5.2f} p95 {fig['sitl']['p95_m']:5.2f}"
                         f"  model median {fig['model']['median_m']:5.2f} p95 {fig['model']['p95_m']:5.2f}")
            print(line + ("" if fig["in_envelope"] else "  (beyond the airframe's envelope)"))
    print(json.dumps(out))
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.sitl_response", description=__doc__.split("\n\n")[0])
    ap.add_argument("--autopilot", choices=("ardupilot", "px4"), default="ardupilot",
                    help="ArduCopter SITL (default) or PX4 SITL (SIH quad, OFFBOARD)")
    ap.add_argument("--limits", default=None, help="comma-separated: stock, demo (default stock,demo; PX4: stock)")
    ap.add_argument("--cases", default="top,step20,step100,ramp,route90,route70",
                    help="comma-separated cases (default top,step20,step100,ramp,route90,route70)")
    ap.add_argument("--route-speed", type=float, default=None,
                    help="the routes' cruise speed, m/s (default: routeNN flies at NN %% of the lower of "
                    "WPNAV_SPEED and the top speed measured by the case 'top')")
    ap.add_argument("--speedup", type=float, default=4.0, help="SITL speedup (default 4)")
    ap.add_argument("--latency-s", type=float, default=0.0,
                    help="route setpoints sent this long after their tick (default 0)")
    ap.add_argument("--param", action="append", default=[], metavar="NAME=VALUE", type=param_item,
                    help="a parameter over each set of limits at boot; repeatable (e.g. WPNAV_SPEED=400)")
    ap.add_argument("--save", help="write the traces here (gzipped JSON)")
    ap.add_argument("--replay", metavar="FILE", help="fly nothing: the model's RMS error (m) on each "
                    "trace of a saved flight, and its distance at the next tick beside the SITL's")
    ap.add_argument("--fit", metavar="FILE", help="fly nothing: fit sim.mock.multicopter's lean_tc and drag to "
                    "a saved flight's in-envelope traces (a few minutes)")
    args = ap.parse_args(argv)
    if args.replay or args.fit:
        return offline(args.replay or args.fit, fit=bool(args.fit))
    px4 = args.autopilot == "px4"
    labels = [x.strip() for x in (args.limits or ("stock" if px4 else "stock,demo")).split(",") if x.strip()]
    for lab in labels:
        if lab not in LIMITS:
            ap.error(f"--limits: unknown set {lab!r} (stock, demo)")
    cases = [x.strip() for x in args.cases.split(",") if x.strip()]
    extra = dict(args.param)
    for case in cases:
        if not (case in ("top", "ramp") or (case.startswith("step") and _number(case[4:]))
                or (case.startswith("route") and (case == "route" or _number(case[5:])))):
            ap.error(f"--cases: unknown case {case!r} (top, stepD, ramp, routeNN)")
    binary = px4_sitl.find_sitl() if px4 else find_binary()
    why = px4_sitl.skip_reason() if px4 else skip_reason()
    if why is not None:
        print(f"python -m bench.sitl_response: {why}", file=sys.stderr)
        return 2
    run = BenchRun(binary, args.speedup, tuple(cases), args.latency_s, args.route_speed, extra, args.autopilot)
    out, saved = {}, {}
    for lab in labels:
        try:
            params, figures, traces = fly_limits(lab, run)
        except (SitlError, px4_sitl.SitlError, FlightError) as exc:
            print(f"python -m bench.sitl_response: {lab}: {exc}", file=sys.stderr)
            return 1
        key = "px4" if px4 else lab  # PX4's stock parameters: their own label
        out[key] = {"params": params, "cases": figures}
        saved[key] = {"params": params, "traces": [t.as_dict() for t in traces]}
        for name, fig in figures.items():
            if isinstance(fig, dict):
                print(f"{key:6s} {name:18s} " + "  ".join(f"{k}={v}" for k, v in fig.items()))
    if args.save:
        with gzip.GzipFile(args.save, "wb", mtime=0) as fh:  # mtime 0: the same flight, the same bytes
            fh.write(json.dumps(saved, separators=(",", ":")).encode())
        print(f"traces saved to {args.save} ({Path(args.save).stat().st_size // 1024} kB)")
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
