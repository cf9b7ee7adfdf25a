"""The vehicle's poses from a flight log, for ``pmon locate`` (docs/LOCATE.md): a MAVLink tlog, an
ArduPilot DataFlash log (.bin) or a PX4 ULog (.ulg), read with the well-kept readers (pymavlink's
``mavutil`` and ``DFReader``, pyulog).

Every format gives the same ``PoseLog``: samples on the autopilot's own timeline (seconds since
its boot: ``time_boot_ms``, DataFlash's ``TimeUS``, ULog's ``timestamp``), in the ENU mission
frame (``onboard.app.autopilot.pose.Frame`` at the scenario's origin), with the heading; and the map from
Unix time to that timeline the log itself holds (its UTC: SYSTEM_TIME, the GPS's week and
milliseconds, ULog's ``time_utc_usec``), the app's ``UtcMap``. A file that is none of these, or
holds no position, is a ``PoseError``: one line naming the file and what is missing.
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass, field

import numpy as np

from onboard.app.autopilot.clock import UtcMap
from onboard.app.autopilot.pose import Frame, PoseHistory, PoseSample, valid_global_position_int
from onboard.core.bearings import wrap

GPS_EPOCH_UNIX_S = 315964800  # 1980-01-06, the GPS week's origin, in Unix s
GPS_LEAP_S = 18  # GPS minus UTC since 2017 (ArduPilot's GPS_LEAPSECONDS_MILLIS)
WEEK_S = 604800
GAP_S = 2.0  # poses further apart than this leave a gap in the record (bearings there are not aligned)
ULOG_MAGIC = b"ULog\x01\x12\x35"
DATAFLASH_MAGIC = b"\xa3\x95"
KINDS = ("tlog", "bin", "ulg")


class PoseError(ValueError):
    """A pose log that cannot be used; the message names the file and says why."""


@dataclass
class PoseLog:
    path: str
    kind: str  # tlog | bin | ulg
    samples: list[PoseSample]  # autopilot s, ENU, increasing in time
    utc: UtcMap = field(default_factory=UtcMap)

    @property
    def start(self) -> float:
        return self.samples[0].t

    @property
    def end(self) -> float:
        return self.samples[-1].t

    def history(self) -> PoseHistory:
        """The app's pose history over the whole log (interpolated positions and headings; no
        extrapolation past the last sample)."""
        h = PoseHistory(keep_s=math.inf, max_extrapolation_s=0.0)
        for s in self.samples:
            h.add(s)
        return h

    def gaps(self, longer_than: float = GAP_S) -> list[tuple[float, float]]:
        """(start, end) autopilot s of each stretch without a pose longer than ``longer_than``."""
        t = np.array([s.t for s in self.samples])
        i = np.flatnonzero(np.diff(t) > longer_than)
        return [(float(t[k]), float(t[k + 1])) for k in i]


def kind_of(path: str) -> str:
    """The log's format, by its first bytes (a ULog's and a DataFlash log's magic), else a tlog."""
    from onboard.files import open_regular

    with open_regular(path) as f:
        head = f.read(8)
    if head.startswith(ULOG_MAGIC):
        return "ulg"
    if head.startswith(DATAFLASH_MAGIC):
        return "bin"
    return "tlog"


def read(path: str | os.PathLike, frame: Frame, kind: str | None = None) -> PoseLog:
    """The poses of the log at ``path`` (format ``kind``, or found from its bytes)."""
    path = os.fspath(path)
    try:
        kind = kind or kind_of(path)
    except ValueError as exc:  # onboard.files.FileRefused: not a regular file, unreadable
        raise PoseError(str(exc)) from None
    reader = {"tlog": _read_tlog, "bin": _read_dataflash, "ulg": _read_ulog}[kind]
    try:
        log = reader(path, frame)
    except PoseError:
        raise
    except Exception as exc:  # a third-party reader on a corrupt file: its error, in one line
        raise PoseError(f"{path}: not a readable {kind} ({type(exc).__name__}: {str(exc)[:80]})") from None
    if len(log.samples) < 2:
        raise PoseError(f"{path}: {len(log.samples)} position(s) in this {kind}: not a pose record "
                        f"({'GLOBAL_POSITION_INT' if kind == 'tlog' else 'POS' if kind == 'bin' else 'vehicle_global_position'})")
    return log


def _sorted(samples: list[PoseSample]) -> list[PoseSample]:
    """In time order, one sample per time (the first), times that go back dropped."""
    out: list[PoseSample] = []
    for s in samples:
        if not out or s.t > out[-1].t:
            out.append(s)
    return out


def _with_velocity(t, pos, yaw) -> list[PoseSample]:
    """Samples from times (s), ENU positions (N, 3) and headings (rad, or NaN), the velocity by
    central differences (DataFlash's POS and the ULog's global position carry none)."""
    t, pos = np.asarray(t, float), np.asarray(pos, float)
    vel = np.gradient(pos, t, axis=0) if len(t) > 1 else np.zeros_like(pos)
    return [PoseSample(float(a), p, v, None if not math.isfinite(y) else float(wrap(y)))
            for a, p, v, y in zip(t, pos, vel, yaw)]


# ----------------------------------------------------------------------------- tlog
def _read_tlog(path: str, frame: Frame) -> PoseLog:
    from onboard.app.mavlink2 import mavutil

    conn = mavutil.mavlink_connection(path, dialect="ardupilotmega")
    log, src = PoseLog(path, "tlog", []), None
    try:
        while (m := conn.recv_match(type=["GLOBAL_POSITION_INT", "SYSTEM_TIME"])) is not None:
            who = (m.get_srcSystem(), m.get_srcComponent())
            if src is None:
                src = who
            if who != src:  # another system's (a ground station's, the app's) messages
                continue
            if m.get_type() == "SYSTEM_TIME":
                log.utc.observe(m.time_unix_usec, m.time_boot_ms)
            elif valid_global_position_int(m):
                log.samples.append(frame.pose_from_global_position_int(m))
    finally:
        conn.close()
    log.samples = _sorted(log.samples)
    return log


# ----------------------------------------------------------------------------- DataFlash
def _read_dataflash(path: str, frame: Frame) -> PoseLog:
    from pymavlink import DFReader

    df = DFReader.DFReader_binary(path, zero_time_base=True)
    pos, yaw_t, yaw = [], [], []
    log = PoseLog(path, "bin", [])
    while (m := df.recv_match(type=["POS", "ATT", "GPS"])) is not None:
        kind = m.get_type()
        if kind == "POS":
            pos.append((m.TimeUS / 1e6, *frame.enu_from_geodetic(m.Lat, m.Lng, m.Alt)))
        elif kind == "ATT":
            yaw_t.append(m.TimeUS / 1e6)
            yaw.append(math.radians(m.Yaw))
        elif kind == "GPS" and m.Status >= 3 and m.GWk > 0:
            unix = GPS_EPOCH_UNIX_S + m.GWk * WEEK_S + m.GMS / 1000.0 - GPS_LEAP_S
            log.utc.observe(int(round(unix * 1e6)), int(round(m.TimeUS / 1000.0)))
    log.samples = _sorted(_samples(pos, yaw_t, yaw))
    return log


def _samples(pos: list, yaw_t: list, yaw: list) -> list[PoseSample]:
    """Positions [(t, e, n, u)] with the heading interpolated (the short way round) from
    [(t)] and [yaw rad]."""
    if not pos:
        return []
    p = np.array(pos, float)
    if len(yaw_t) >= 2:
        unwrapped = np.unwrap(np.asarray(yaw, float))
        h = np.interp(p[:, 0], yaw_t, unwrapped, left=np.nan, right=np.nan)
    else:
        h = np.full(len(p), np.nan)
    return _with_velocity(p[:, 0], p[:, 1:], h)


# ----------------------------------------------------------------------------- ULog
def _read_ulog(path: str, frame: Frame) -> PoseLog:
    from pyulog import ULog

    topics = ["vehicle_global_position", "vehicle_local_position", "vehicle_gps_position", "sensor_gps"]
    ulog = ULog(path, topics, parse_header_only=False)
    data = {d.name: d.data for d in ulog.data_list if d.multi_id == 0}
    log = PoseLog(path, "ulg", [])
    g = data.get("vehicle_global_position")
    if g is None:
        raise PoseError(f"{path}: no vehicle_global_position in this ULog: not a pose record")
    t = g["timestamp"] / 1e6
    ok = np.isfinite(g["lat"]) & np.isfinite(g["lon"]) & ((g["lat"] != 0) | (g["lon"] != 0))
    pos = [(a, *frame.enu_from_geodetic(la, lo, al)) for a, la, lo, al, k in
           zip(t, g["lat"], g["lon"], g["alt"], ok) if k]
    lp = data.get("vehicle_local_position")
    yaw_t, yaw = ([], []) if lp is None else (list(lp["timestamp"] / 1e6), list(lp["heading"]))
    finite = [(a, y) for a, y in zip(yaw_t, yaw) if math.isfinite(y)]
    log.samples = _sorted(_samples(pos, [a for a, _ in finite], [y for _, y in finite]))
    gps = data.get("vehicle_gps_position", data.get("sensor_gps"))
    if gps is not None and "time_utc_usec" in gps:
        for ts, utc in zip(gps["timestamp"], gps["time_utc_usec"]):
            if utc > 0:
                log.utc.observe(int(utc), int(ts // 1000))
    return log
