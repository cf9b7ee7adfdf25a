"""``pmon locate`` on a firmware's own log of a flight the firmware tests fly anyway: flight A of
tests/firmware/test_ardupilot.py (ArduCopter's DataFlash .bin) and of tests/firmware/test_px4.py
(PX4's ULog), read by the well-kept readers (groundstation/poses.py).

* The log is the flight's: its poses are the positions the autopilot reported over MAVLink during
  the flight (the observer's GLOBAL_POSITION_INT, sim/stack/mission_clients.py), at the same
  autopilot times, within ``POSE_MATCH_M``; its UTC is there (ArduPilot's GPS week and ms) or
  not (PX4's SIH writes none: the recording is stamped from a boot time given, --unix-at-boot).
* A simulated KrakenSDR recording is drawn along the flown poses, stamped with that UTC
  (sim/stack/locate_recording.py), over ``RecordingConfig``'s two emitters, from which every
  airborne pose of the flight must be ``EMITTER_RANGE_M`` away: both located within 15 m in three recordings (the command's own, with its CSV, and two
  more), the ellipses consistent (the NEES' mean within its two-sided band).
"""
from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
from scipy.stats import chi2

from groundstation.locate import Request, locate, main
from groundstation.poses import read
from onboard.app.autopilot.pose import Frame
from onboard.config import load_scenario
from onboard.policy import DEFAULT, with_policy
from sim.stack import locate_recording as rec

CFG = rec.RecordingConfig()  # its emitters and DF model (its lawnmower is not flown here)
RECORDINGS = 2  # drawn along the one flight, besides the command's own
NEES_P = 1e-3  # the mean NEES checked against its two-sided band at this false-alarm rate
LOCATED_M = 15.0
# the log's position at a reported time against the report: 50 ms of flight at 9 m/s (the logs
# and the reports are of one estimator on one clock)
POSE_MATCH_M = 0.5
EMITTER_RANGE_M = (250.0, 600.0)  # every airborne pose from each emitter: located from afar


def firmware_log(m) -> Path:
    """The firmware's own log of a Mission's flight (the largest: one boot, one log)."""
    if m.cfg.autopilot == "ardupilot":
        logs = sorted(Path(m.sitl.workdir, "logs").glob("*.BIN"))
    else:
        logs = m.sitl.ulogs()
    assert logs, f"{m.sitl.workdir}: no firmware log written"
    return max(logs, key=lambda p: p.stat().st_size)


def _check_log(m, path: Path, kind: str, airborne_s: float):
    """The log read, checked against what the autopilot said; (the log, its airborne poses)."""
    frame = Frame(*rec.ORIGIN)
    log = read(path, frame)
    assert log.kind == kind
    assert (log.utc.unix_time(log.end) is not None) == (kind == "bin")
    airborne = [s for s in log.samples if s.pos[2] > 10.0 and s.yaw is not None]
    assert airborne and airborne[-1].t - airborne[0].t >= airborne_s, (path, len(airborne))
    t = np.array([s.t for s in log.samples])
    pos = np.array([s.pos for s in log.samples])
    with m.observer.lock:
        said = [(ts, frame.enu_from_geodetic(lat, lon, alt)) for ts, lat, lon, alt, _ in m.observer.positions
                if ts is not None and airborne[0].t <= ts <= airborne[-1].t]
    assert len(said) >= airborne_s, len(said)  # reported at >= 1 Hz over the airborne time
    ts = np.array([x for x, _ in said])
    logged = np.stack([np.interp(ts, t, pos[:, k]) for k in range(3)], axis=1)
    off = np.linalg.norm(logged - np.array([p for _, p in said]), axis=1)
    worst = int(np.argmax(off))
    assert off[worst] <= POSE_MATCH_M, (f"the log {off[worst]:.2f} m from the reported position at "
                                        f"t = {ts[worst]:.2f} s", logged[worst], said[worst])
    xy = np.array([s.pos[:2] for s in airborne])
    for em in CFG.emitters_m:
        r = np.hypot(*(xy - em).T)
        assert EMITTER_RANGE_M[0] <= r.min() and r.max() <= EMITTER_RANGE_M[1], (em, r.min(), r.max())
    return log, airborne


def _nees(e: np.ndarray, cov: np.ndarray) -> float:
    return float(e @ np.linalg.solve(cov, e))


def locate_from_flight(m, kind: str, tmp_path: Path, capsys, airborne_s: float) -> None:
    """``pmon locate`` on the Mission ``m``'s own firmware log (``kind`` bin or ulg), the flight
    airborne for at least ``airborne_s`` (autopilot s); raises AssertionError on any miss."""
    log_path = firmware_log(m)
    log, airborne = _check_log(m, log_path, kind, airborne_s)
    boot = [] if kind == "bin" else ["--unix-at-boot", str(rec.UNIX_AT_BOOT)]
    unix_of = log.utc.unix_time if kind == "bin" else (lambda t: rec.UNIX_AT_BOOT + t)
    r = rec.write_recording(tmp_path / "rec", seed=11, cfg=CFG, poses=airborne, unix_of=unix_of)
    assert r["frames"] >= airborne_s * 0.9, r["frames"]
    base = tmp_path / "out"
    code = main([str(r["mydata"]), str(log_path), "--scenario", str(r["scenario"]), "--out", str(base),
                 "--format", "csv,png", *boot])
    out, err = capsys.readouterr()
    assert code == 0, err
    assert "Traceback" not in err and f"poses from {kind}" in out
    assert base.with_suffix(".png").stat().st_size > 0
    with open(base.with_suffix(".csv")) as f:
        final = {x["target"]: x for x in csv.DictReader(f) if x["estimate"] == "final"}
    nees = []
    for j, name in enumerate(("T1", "T2")):
        row = final[name]
        e = np.array([float(row["east_m"]), float(row["north_m"])]) - r["truth_m"][j]
        assert np.hypot(*e) <= LOCATED_M, (name, e, out)
        c = float(row["cov_en_m2"])
        nees.append(_nees(e, np.array([[float(row["sigma_east_m"]) ** 2, c], [c, float(row["sigma_north_m"]) ** 2]])))
    # more recordings along the same flight, as bench/locate.py draws them with --poses
    for k in range(RECORDINGS):
        r = rec.write_recording(tmp_path / f"r{k}", 12 + k, CFG, poses=airborne, unix_of=unix_of)
        sc = with_policy(load_scenario(str(r["scenario"])), DEFAULT)
        found, _ = locate(Request(str(r["mydata"]), str(log_path), sc, seed=12 + k,
                                  unix_at_boot=None if kind == "bin" else rec.UNIX_AT_BOOT))
        for j, truth in enumerate(r["truth_m"]):
            e = found.final_means[j][:2] - truth
            assert np.hypot(*e) <= LOCATED_M, (k, j, e)
            nees.append(_nees(e, found.final_covs[j][:2, :2]))
    lo, hi = chi2.ppf([NEES_P / 2, 1 - NEES_P / 2], 2 * len(nees)) / len(nees)
    assert lo <= np.mean(nees) <= hi, nees
