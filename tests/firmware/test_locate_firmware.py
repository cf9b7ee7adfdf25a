"""``pmon locate`` on the firmware's own logs: a lawnmower flown by ArduCopter's SITL (its
DataFlash .bin) and by PX4's SIH SITL (its ULog), read by the well-kept readers
(groundstation/poses.py); a simulated KrakenSDR recording drawn along the flown poses, stamped
with the log's own UTC (sim/locate_recording.py); both emitters located within 15 m at 300-605 m.
The flights: sim/firmware_lawnmower.py."""
from __future__ import annotations

import csv

import numpy as np
import pytest

from groundstation.locate import main
from groundstation.poses import read
from onboard.app.pose import Frame
from sim import ardupilot, px4
from sim import firmware_lawnmower as fl
from sim import locate_recording as rec


def _check_log(path, kind: str) -> list:
    log = read(path, Frame(*rec.ORIGIN))
    assert log.kind == kind
    # its UTC, on which KrakenSDR's stamps are put: ArduPilot's GPS week and ms; PX4's SIH writes
    # none (time_utc_usec 0), so its recording is stamped from a boot time given (--unix-at-boot)
    assert (log.utc.unix_time(log.end) is not None) == (kind == "bin")
    airborne = [s for s in log.samples if s.pos[2] > 10.0 and s.yaw is not None]
    xy = np.array([s.pos[:2] for s in airborne])
    for e, n in fl.corners():  # the log's positions are the flown corners, in the mission frame
        assert np.hypot(xy[:, 0] - e, xy[:, 1] - n).min() < fl.REACH_M + 2.0, (e, n)
    return log, airborne


def _locate(tmp_path, log_path, kind: str, capsys) -> None:
    log, airborne = _check_log(log_path, kind)
    boot = [] if kind == "bin" else ["--unix-at-boot", str(rec.UNIX_AT_BOOT)]
    unix_of = log.utc.unix_time if kind == "bin" else (lambda t: rec.UNIX_AT_BOOT + t)
    r = rec.write_recording(tmp_path / "rec", seed=11, poses=airborne, unix_of=unix_of)
    base = tmp_path / "out"
    code = main([str(r["mydata"]), str(log_path), "--scenario", str(r["scenario"]), "--out", str(base),
                 "--format", "csv,png", *boot])
    out, err = capsys.readouterr()
    assert code == 0, err
    assert "Traceback" not in err and f"poses from {kind}" in out
    with open(base.with_suffix(".csv")) as f:
        rows = list(csv.DictReader(f))
    last = max(int(x["t_s"]) for x in rows)
    for j, name in enumerate(("T1", "T2")):
        row = next(x for x in rows if int(x["t_s"]) == last and x["target"] == name)
        err_m = np.hypot(float(row["east_m"]) - r["truth_m"][j][0], float(row["north_m"]) - r["truth_m"][j][1])
        assert err_m <= 15.0, (name, err_m, out)


@pytest.mark.ardupilot
@pytest.mark.sitl
@pytest.mark.timeout(600)
@pytest.mark.skipif(ardupilot.skip_reason() is not None, reason=ardupilot.skip_reason() or "")
def test_locate_from_ardupilots_dataflash_log(tmp_path, capsys):
    log_path = fl.fly_ardupilot(tmp_path / "sitl")
    _locate(tmp_path, log_path, "bin", capsys)


@pytest.mark.px4
@pytest.mark.sitl
@pytest.mark.timeout(600)
@pytest.mark.skipif(px4.skip_reason() is not None, reason=px4.skip_reason() or "")
def test_locate_from_px4s_ulog(tmp_path, capsys):
    log_path = fl.fly_px4(tmp_path / "sitl")
    _locate(tmp_path, log_path, "ulg", capsys)
