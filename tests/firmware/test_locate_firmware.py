"""``pmon locate`` on the firmware's own logs: a lawnmower flown by ArduCopter's SITL (its
DataFlash .bin) and by PX4's SIH SITL (its ULog), read by the well-kept readers
(groundstation/poses.py); a simulated KrakenSDR recording drawn along the flown poses, stamped
with the log's own UTC (sim/stack/locate_recording.py); both emitters located within 15 m at 300-525 m
and the ellipses consistent (NEES). The flights (sim/stack/lawnmower.py) are the lawnmower's
three northern legs (``SHORT``), fast: their logs are what is tested, not the survey's length."""
from __future__ import annotations

import csv

import numpy as np
import pytest
from scipy.stats import chi2

from groundstation.locate import Request, locate, main
from groundstation.poses import read
from onboard.app.autopilot.pose import Frame
from onboard.config import load_scenario
from onboard.policy import DEFAULT, with_policy
from sim.firmware import ardupilot
from sim.firmware import px4
from sim.stack import lawnmower as fl
from sim.stack import locate_recording as rec

SHORT = fl.SHORT  # the three northern legs, 300-525 m from the emitters
RECORDINGS = 2  # drawn along the one flight, besides the command's own
NEES_P = 1e-3  # the mean NEES checked against its two-sided band at this false-alarm rate


def _check_log(path, kind: str) -> list:
    log = read(path, Frame(*rec.ORIGIN))
    assert log.kind == kind
    # its UTC, on which KrakenSDR's stamps are put: ArduPilot's GPS week and ms; PX4's SIH writes
    # none (time_utc_usec 0), so its recording is stamped from a boot time given (--unix-at-boot)
    assert (log.utc.unix_time(log.end) is not None) == (kind == "bin")
    airborne = [s for s in log.samples if s.pos[2] > 10.0 and s.yaw is not None]
    xy = np.array([s.pos[:2] for s in airborne])
    for e, n in fl.corners(SHORT):  # the log's positions are the flown corners, in the mission frame
        assert np.hypot(xy[:, 0] - e, xy[:, 1] - n).min() < fl.REACH_M + 2.0, (e, n)
    return log, airborne


def _locate(tmp_path, log_path, kind: str, capsys) -> None:
    log, airborne = _check_log(log_path, kind)
    boot = [] if kind == "bin" else ["--unix-at-boot", str(rec.UNIX_AT_BOOT)]
    unix_of = log.utc.unix_time if kind == "bin" else (lambda t: rec.UNIX_AT_BOOT + t)
    r = rec.write_recording(tmp_path / "rec", seed=11, cfg=SHORT, poses=airborne, unix_of=unix_of)
    base = tmp_path / "out"
    code = main([str(r["mydata"]), str(log_path), "--scenario", str(r["scenario"]), "--out", str(base),
                 "--format", "csv,png", *boot])
    out, err = capsys.readouterr()
    assert code == 0, err
    assert "Traceback" not in err and f"poses from {kind}" in out
    with open(base.with_suffix(".csv")) as f:
        final = {x["target"]: x for x in csv.DictReader(f) if x["estimate"] == "final"}
    nees = []
    for j, name in enumerate(("T1", "T2")):
        row = final[name]
        e = np.array([float(row["east_m"]), float(row["north_m"])]) - r["truth_m"][j]
        assert np.hypot(*e) <= 15.0, (name, e, out)
        c = float(row["cov_en_m2"])
        nees.append(float(e @ np.linalg.solve([[float(row["sigma_east_m"]) ** 2, c], [c, float(row["sigma_north_m"]) ** 2]], e)))
    # more recordings along the same flight, as bench/locate.py draws them with --poses
    for k in range(RECORDINGS):
        r = rec.write_recording(tmp_path / f"r{k}", 12 + k, SHORT, poses=airborne, unix_of=unix_of)
        sc = with_policy(load_scenario(str(r["scenario"])), DEFAULT)
        found, _ = locate(Request(str(r["mydata"]), str(log_path), sc, seed=12 + k,
                                  unix_at_boot=None if kind == "bin" else rec.UNIX_AT_BOOT))
        for j, truth in enumerate(r["truth_m"]):
            e = found.final_means[j][:2] - truth
            assert np.hypot(*e) <= 15.0, (k, j, e)
            nees.append(float(e @ np.linalg.solve(found.final_covs[j][:2, :2], e)))
    lo, hi = chi2.ppf([NEES_P / 2, 1 - NEES_P / 2], 2 * len(nees)) / len(nees)
    assert lo <= np.mean(nees) <= hi, nees


@pytest.mark.ardupilot
@pytest.mark.sitl
@pytest.mark.timeout(600)
@pytest.mark.skipif(ardupilot.skip_reason() is not None, reason=ardupilot.skip_reason() or "")
def test_locate_from_ardupilots_dataflash_log(tmp_path, capsys):
    log_path = fl.fly_ardupilot(tmp_path / "sitl", speedup=8.0, cfg=SHORT)
    _locate(tmp_path, log_path, "bin", capsys)


@pytest.mark.px4
@pytest.mark.sitl
@pytest.mark.timeout(600)
@pytest.mark.skipif(px4.skip_reason() is not None, reason=px4.skip_reason() or "")
def test_locate_from_px4s_ulog(tmp_path, capsys):
    log_path = fl.fly_px4(tmp_path / "sitl", cfg=SHORT)
    _locate(tmp_path, log_path, "ulg", capsys)
