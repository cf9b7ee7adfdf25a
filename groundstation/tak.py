"""Target estimates and the UAV as Cursor-on-Target (CoT) events for TAK (ATAK, WinTAK, iTAK,
a TAK server), sent with pytak over UDP (unicast, multicast: the SA mesh), TCP or TLS.

One event per estimate (uid ``pmon-<sysid>-T1``...), built with pytak's ``cot_event`` and
``cot_point``:

* ``type`` ``a-u-G`` (unknown, ground: a tracked vehicle whose affiliation the UAV cannot tell),
  ``how`` ``m-f`` (machine, fused: an estimate from bearings), callsign ``PMON T1``...;
* ``point``: latitude, longitude (7 decimals: 1 cm), ``hae`` the mission origin's altitude plus
  the estimate's height (MAVLink AMSL, the ground the targets move on), ``ce`` the CoT "circular
  1-sigma" (MITRE CoT event schema): the radius of the circle about the estimate that holds the
  1-sigma ellipse the live view draws (``estimates.radius_1sigma_m``), ``le`` 9999999
  (unknown: bearings measure no height, PMON_TGT carries no vertical variance);
* ``detail``: ``track`` course and speed, ``contact`` callsign, ``remarks`` with the 1-sigma
  east/north, the estimate's age and tick time;
* ``time``/``start``: when sent (UTC); ``stale``: when the estimate's data will be
  ``lost_after_s`` old, at most ``refresh_s`` ahead (a link that stops makes the marker stale
  within that). A target whose last DF scan is ``lost_after_s`` old gets a last event that is
  already stale, so TAK clients drop it instead of keeping it frozen.

The UAV is a track of its own (uid ``pmon-<sysid>-uav``, type ``a-f-A-M-F-Q``: friendly,
air, UAV) from the autopilot's GLOBAL_POSITION_INT at 1 Hz at most.

``TakSender`` runs pytak's client in a thread of its own with a bounded queue (oldest dropped,
counted): a slow or absent TAK server never stalls the ground station; TCP and TLS reconnect.
"""
from __future__ import annotations

import asyncio
import datetime as dt
import math
import threading
import xml.etree.ElementTree as ET
from configparser import ConfigParser
from dataclasses import dataclass

import pytak

from groundstation.estimates import OutputEstimate
from groundstation.hub_options import check_url

TARGET_TYPE = "a-u-G"
UAV_TYPE = "a-f-A-M-F-Q"
UNKNOWN = 9999999.0  # CoT's "unknown" ce/le
TIME_FMT = "%Y-%m-%dT%H:%M:%S.%fZ"


def _iso(t: dt.datetime) -> str:
    return t.strftime(TIME_FMT)[:-4] + "Z"  # milliseconds


@dataclass(frozen=True)
class _Marker:
    """What a CoT event says of one thing: who and what it is, and its ``point``."""
    uid: str
    cot_type: str
    how: str
    callsign: str
    lat: float
    lon: float
    hae: float
    ce: float
    le: float = UNKNOWN


def _event(m: _Marker, now: dt.datetime, stale: dt.datetime, detail_children=()) -> ET.Element:
    point = pytak.cot_point(m.lat, m.lon, round(m.ce, 2), round(m.hae, 2), m.le, precision=7)
    detail = pytak.cot_detail(*detail_children, flow_tag=False)
    ev = pytak.cot_event(uid=m.uid, cot_type=m.cot_type, how=m.how, point=point, detail=detail,
                         callsign=m.callsign)
    ev.set("time", _iso(now))
    ev.set("start", _iso(now))
    ev.set("stale", _iso(max(stale, now)))
    return ev


def _target(est: OutputEstimate, sysid: int) -> _Marker:
    return _Marker(uid(sysid, est.name), TARGET_TYPE, "m-f", f"PMON {est.name}", est.lat_deg, est.lon_deg,
                   est.alt_m, est.radius_1sigma_m)


def _track(course_deg: float, speed_mps: float) -> ET.Element:
    el = ET.Element("track")
    el.set("course", f"{course_deg:.1f}")
    el.set("speed", f"{speed_mps:.2f}")
    return el


def target_event(est: OutputEstimate, sysid: int, now: dt.datetime, lost_after_s: float,
                 refresh_s: float) -> ET.Element:
    left = max(min(lost_after_s - est.age_s, refresh_s), 0.0)
    remarks = ET.Element("remarks")
    remarks.text = (f"pmon estimate {est.name}: 1-sigma E {est.sigma_x_m:.0f} m, N {est.sigma_y_m:.0f} m; "
                    f"last DF scan {est.age_s:.1f} s before tick t={est.tick_time_s:.1f} s"
                    + ("; degenerate update (prior kept)" if est.degenerate else "")
                    + (f"; {est.doing}" if est.doing != "-" else ""))
    return _event(_target(est, sysid), now, now + dt.timedelta(seconds=left),
                  (_track(est.course_deg, est.speed_mps), remarks))


def lost_event(est: OutputEstimate, sysid: int, now: dt.datetime) -> ET.Element:
    """The target's last event: stale at once (TAK clients drop it)."""
    remarks = ET.Element("remarks")
    remarks.text = f"pmon estimate {est.name}: lost (no DF scan for {est.age_s:.0f} s)"
    return _event(_target(est, sysid), now, now, (remarks,))


def uav_event(gp, sysid: int, now: dt.datetime, stale_s: float, eph_m: float | None = None) -> ET.Element | None:
    """The UAV from a GLOBAL_POSITION_INT; None if it holds no position (ArduPilot sends 0, 0
    before its fix)."""
    lat, lon, alt = gp.lat * 1e-7, gp.lon * 1e-7, gp.alt * 1e-3
    if (gp.lat == 0 and gp.lon == 0) or not (abs(lat) <= 90 and abs(lon) <= 180):
        return None
    vn, ve = gp.vx / 100.0, gp.vy / 100.0
    course = math.degrees(math.atan2(ve, vn)) % 360.0
    ce = eph_m if eph_m is not None and math.isfinite(eph_m) else UNKNOWN
    return _event(_Marker(f"pmon-{sysid}-uav", UAV_TYPE, "m-g", f"PMON UAV {sysid}", lat, lon, alt, ce),
                  now, now + dt.timedelta(seconds=stale_s), (_track(course, math.hypot(vn, ve)),))


def uid(sysid: int, name: str) -> str:
    return f"pmon-{sysid}-{name}"


def to_bytes(ev: ET.Element) -> bytes:
    return pytak.serialize_cot(ev, xml_declaration=False) + b"\n"


def config(url: str, proto: int = 0, tls: dict | None = None, extra: dict | None = None):
    """pytak's configuration section: COT_URL, TAK_PROTO (0 XML, 1 TAK protobuf) and the
    PYTAK_TLS_* settings (client certificate, key, CA file, ...)."""
    scheme, sep, rest = url.partition("://")
    if scheme.lower().startswith("udp") and "+wo" not in scheme.lower():
        url = f"{scheme}+wo{sep}{rest}"  # send only: pytak would also bind the port on every interface to read
    cp = ConfigParser(interpolation=None)
    cp["pmon"] = {"COT_URL": url, "TAK_PROTO": str(int(proto)),
                  **{k: str(v) for k, v in (tls or {}).items() if v is not None},
                  **{k: str(v) for k, v in (extra or {}).items() if v is not None}}
    return cp["pmon"]


class TakSender:
    """pytak's TXWorker on an asyncio loop in a daemon thread; ``put`` never blocks."""

    QUEUE = 256
    RETRY_S = 2.0

    def __init__(self, cfg):
        self.cfg = cfg
        self.url = cfg.get("COT_URL")
        check_url(self.url)  # a malformed URL fails here, in the caller
        self.sent = 0
        self.dropped = 0
        self.connects = 0
        self.errors = 0
        self.last_error: str | None = None
        self._loop = asyncio.new_event_loop()
        self._queue: asyncio.Queue | None = None
        self._ready = threading.Event()
        self._stop = False
        self._thread = threading.Thread(target=self._run, name="pmon-tak", daemon=True)
        self._thread.start()
        self._ready.wait(5.0)

    def put(self, data: bytes) -> None:
        if self._queue is None or self._stop:
            self.dropped += 1
            return
        self._loop.call_soon_threadsafe(self._put, data)

    def _put(self, data: bytes) -> None:
        if self._queue.full():
            self._queue.get_nowait()
            self.dropped += 1
        self._queue.put_nowait(data)

    def _run(self) -> None:
        asyncio.set_event_loop(self._loop)
        self._queue = asyncio.Queue(self.QUEUE)
        self._ready.set()
        try:
            self._loop.run_until_complete(self._main())
        finally:
            self._loop.close()

    async def _main(self) -> None:
        while not self._stop:
            try:
                _, writer = await pytak.protocol_factory(self.cfg)
            except Exception as exc:  # refused, TLS failure, bad certificate: say so, retry
                self.errors += 1
                self.last_error = f"{type(exc).__name__}: {exc}"
                await asyncio.sleep(self.RETRY_S)
                continue
            self.connects += 1
            worker = pytak.TXWorker(self._queue, self.cfg, writer)
            try:
                while not self._stop:
                    data = await self._queue.get()
                    if data is None:
                        break
                    await worker.send_data(data)
                    self.sent += 1
            except Exception as exc:  # the server went away: reconnect
                self.errors += 1
                self.last_error = f"{type(exc).__name__}: {exc}"
            finally:
                close = getattr(writer, "close", None)
                if close is not None:
                    try:
                        res = close()
                        if asyncio.iscoroutine(res):
                            await res
                    except Exception:
                        pass

    def close(self, timeout: float = 2.0) -> None:
        """Send what is queued (within ``timeout``), then stop."""
        if self._queue is not None and not self._stop:
            done = threading.Event()

            async def drain():
                deadline = self._loop.time() + timeout
                while not self._queue.empty() and self._loop.time() < deadline:
                    await asyncio.sleep(0.02)
                self._stop = True
                self._queue.put_nowait(None) if not self._queue.full() else None
                done.set()
            asyncio.run_coroutine_threadsafe(drain(), self._loop)
            done.wait(timeout + 1.0)
        self._stop = True
        self._thread.join(timeout=timeout + 1.0)
