"""``pmon gcs view``: the mission live in the operator's browser, served by this process on
127.0.0.1 from the same MAVLink connection as every other ``pmon gcs`` command.

The main thread pumps the link (``GcsLink``) and, at each PMON_STAT (every app tick, 1 Hz
otherwise), turns what it heard into one JSON snapshot; HTTP threads only hand out the static
page (groundstation/static/: HTML, JS, CSS, no external resource), the scenario's scene and the
snapshots as Server-Sent Events. No map tiles: the map is the mission area drawn to scale,
north up, with geodetic coordinates in the tables.

Endpoints: ``/`` (the page), ``/view.js``, ``/view.css``, ``/scene.json`` (area, obstacles,
goals, origin, colours), ``/state.json`` (the latest snapshot), ``/events`` (text/event-stream,
one ``data:`` line per snapshot).
"""
from __future__ import annotations

import json
import math
import socket
import sys
import threading
import time
from collections import OrderedDict, deque
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib import resources

from groundstation import protocol as P
from groundstation.gcs_commands import Outcome
from groundstation.export import lonlat
from groundstation.errors import FAILED, GcsError
from groundstation.gcs_link import GcsLink
from groundstation.scene import (BLOCKING_COLOUR, GOAL_COLOUR, OVERFLOWN_COLOUR, UAV_COLOUR, area_outline,
                                 blocks_uav, footprint, target_colour)

ASSETS = {"/": ("view.html", "text/html; charset=utf-8"),
          "/view.js": ("view.js", "text/javascript; charset=utf-8"),
          "/view.css": ("view.css", "text/css; charset=utf-8")}
TRAIL_N = 600  # UAV positions kept (one per snapshot: 10 min at 1 Hz)
TRACK_N = 60  # estimates kept per target (the recent track: a minute of ticks)
TEXTS_N = 12  # STATUSTEXTs shown
QUIET_S = 2.0  # no PMON_STAT for this long: a snapshot every QUIET_S all the same, saying how long
IDLE_S = 10.0  # a connection whose peer sends nothing (or reads nothing) for this long is closed
MAX_CLIENTS = 32  # connections served at once (a thread each); the next one pushes out the oldest
EVENT_IDLE_S = 15.0  # an event stream with nothing new gets a comment this often


def _num(x, nd=3):
    return None if x is None or not math.isfinite(x) else round(float(x), nd)


def assets() -> dict[str, tuple[bytes, str]]:
    """Path -> (bytes, content type) of the page, read once from the package."""
    root = resources.files("groundstation") / "static"
    return {path: ((root / name).read_bytes(), ctype) for path, (name, ctype) in ASSETS.items()}


def scene_json(sc) -> dict:
    """The scenario as the page draws it (mission ENU frame, m; lon/lat where shown)."""
    o = sc.origin
    origin = (o.lat_deg, o.lon_deg, o.alt_m)
    corners = area_outline(sc.area)
    return {
        "name": sc.name, "origin": {"lat_deg": o.lat_deg, "lon_deg": o.lon_deg, "alt_m": o.alt_m},
        "area": {"min_m": list(sc.area.min_m[:2]), "max_m": list(sc.area.max_m[:2]),
                 "corners_lonlat": lonlat(origin, corners).round(7).tolist()},
        "altitude_m": sc.uav.altitude_m, "uav_margin_m": sc.uav.obstacle_margin_m,
        "obstacles": [{"name": ob.name, "footprint": footprint(ob).round(3).tolist(),
                       "top_m": ob.center_m[2] + ob.size_m[2] / 2, "bottom_m": ob.center_m[2] - ob.size_m[2] / 2}
                      for ob in sc.obstacles],
        "goals": [{"name": g.name, "footprint": footprint(g).round(3).tolist()} for g in sc.goals],
        "targets": [t.name for t in sc.targets],
        "colours": {"targets": [target_colour(j) for j in range(max(len(sc.targets), 1))], "uav": UAV_COLOUR,
                    "goal": GOAL_COLOUR, "blocking": BLOCKING_COLOUR, "overflown": OVERFLOWN_COLOUR},
    }


class ViewState:
    """What the page shows, accumulated from the link's messages (the main thread's only)."""

    def __init__(self, gl: GcsLink, sc, publish):
        """``publish(snapshot)`` is called at each PMON_STAT, in the listener: the tick's
        PMON_TGTs came just before it, and the next tick's cannot have mixed in yet."""
        self.gl, self.sc, self.publish = gl, sc, publish
        o = sc.origin
        self.origin = (o.lat_deg, o.lon_deg, o.alt_m)
        self.trail: deque = deque(maxlen=TRAIL_N)
        self.tracks: dict[int, deque] = {}
        self.texts: deque = deque(maxlen=TEXTS_N)
        self.stat: P.AppStatus | None = None
        self.stat_raw = None
        self.stat_at = -math.inf  # local monotonic time of the last PMON_STAT
        self.seq = 0
        gl.on_message(self._on)

    def _on(self, mtype: str, msg) -> None:
        if mtype == "PMON_TGT":
            e = P.TargetEstimate.from_msg(msg)
            tr = self.tracks.setdefault(e.index, deque(maxlen=TRACK_N))
            if not tr or tr[-1][0] != e.tick_time_s:
                tr.append((e.tick_time_s, round(e.x, 2), round(e.y, 2)))
        elif mtype == "PMON_STAT":
            self.stat = P.AppStatus.from_msg(msg)
            self.stat_raw = msg.data
            self.stat_at = time.monotonic()
            if self.stat.uav_enu is not None:
                self.trail.append((round(self.stat.uav_enu[0], 2), round(self.stat.uav_enu[1], 2)))
            self.publish(self.snapshot())
        elif mtype == "STATUSTEXT":
            app = msg.get_srcComponent() == P.APP_COMPID or msg.text.startswith("PMON:")
            if app or msg.severity <= 4:  # the app's every event; the autopilot's warnings and worse
                st = self.stat
                self.texts.append({"t_s": _num(st.last_tick_time_s if st else None, 1),
                                   "severity": int(msg.severity), "source": "app" if app else "autopilot",
                                   "text": msg.text})

    def _vehicle(self) -> dict:
        v = self.gl.v
        if v.autopilot_comp is not None and v.get("HEARTBEAT") is not None:
            return {"mode": v.mode_name, "armed": v.armed, "from": "autopilot"}
        d = self.stat_raw
        if d is None:
            return {"mode": None, "armed": None, "from": None}
        from onboard.app.mavlink2 import mavutil
        mode = mavutil.mode_mapping_acm.get(int(d[12])) if math.isfinite(d[12]) and d[12] >= 0 else None
        return {"mode": mode or (None if d[12] < 0 else f"mode {int(d[12])}"), "armed": bool(d[13]),
                "from": "app"}  # the app's copy of the autopilot's heartbeat (a link to the companion)

    def _point(self, p) -> dict | None:
        return None if p is None else {"enu": [_num(c, 2) for c in p],
                                       "lonlat": lonlat(self.origin, p[:2]).round(7)[0].tolist()}

    def snapshot(self) -> dict:
        self.seq += 1
        st, v = self.stat, self.gl.v
        altitude_m = self.sc.uav.altitude_m
        if st is not None and st.next_enu is not None:
            altitude_m = st.next_enu[2]  # the app's setpoints are at the mission altitude (PMON_ALT, settable in flight)
        uav = st.uav_enu if st else None
        targets = []
        for j, e in sorted(v.targets.items()):
            since = e.since_detection_s
            targets.append({
                "index": j, "name": e.name, "colour": target_colour(j),
                "x": _num(e.x), "y": _num(e.y), "vx": _num(e.vx), "vy": _num(e.vy),
                "sigma_x": _num(e.sigma_x), "sigma_y": _num(e.sigma_y), "cov_xy": _num(e.cov_xy),
                "since_detection_s": None if since is None else max(round(since, 2), 0.0),
                "degenerate": e.degenerate, "tick_time_s": _num(e.tick_time_s, 3),
                "doing": e.mode_text(tuple(g.name for g in self.sc.goals)),
                "lonlat": lonlat(self.origin, [e.x, e.y]).round(7)[0].tolist()
                if math.isfinite(e.x) and math.isfinite(e.y) else None,
                "track": [[x, y] for _, x, y in self.tracks.get(j, ())],
            })
        return {
            "seq": self.seq,
            "app": None if st is None else {
                "state": v.app_state, "tick_time_s": _num(st.last_tick_time_s, 3),
                "tick_rate_hz": _num(st.tick_rate_hz, 2), "tick_ms": _num(st.tick_ms, 0),
                "ticks": st.ticks, "ticks_skipped": st.ticks_skipped, "ticks_late": st.ticks_late,
                "datagrams_accepted": st.datagrams_accepted, "datagrams_rejected": st.datagrams_rejected,
                "setpoints_refused": st.setpoints_refused},
            "app_silent_s": None if st is None else round(time.monotonic() - self.stat_at, 1),
            "vehicle": self._vehicle(),
            "link": self.gl.url,
            "altitude_m": altitude_m,
            "blocked": [blocks_uav(ob, altitude_m, self.sc.uav.obstacle_margin_m) for ob in self.sc.obstacles],
            "uav": None if uav is None else {"enu": [_num(c, 2) for c in uav],
                                             "lonlat": lonlat(self.origin, uav[:2]).round(7)[0].tolist()},
            "setpoint": self._point(None if st is None else st.next_enu),
            # the plan's next point (advisory: the advised waypoint, nothing is sent)
            "advice": self._point(None if st is None else st.advice_enu),
            "trail": [list(p) for p in self.trail],
            "targets": targets,
            "texts": list(self.texts),
        }


class Broadcaster:
    """The latest snapshot, handed from the main thread to every HTTP thread."""

    def __init__(self):
        self.cond = threading.Condition()
        self.data = b"null"
        self.seq = 0
        self.closed = False
        self.published_at = -math.inf  # local monotonic time

    def publish(self, snap: dict) -> None:
        data = json.dumps(snap, allow_nan=False, separators=(",", ":")).encode()
        with self.cond:
            self.data, self.seq = data, self.seq + 1
            self.published_at = time.monotonic()
            self.cond.notify_all()

    def wait(self, after: int, timeout: float) -> tuple[int, bytes]:
        with self.cond:
            self.cond.wait_for(lambda: self.seq > after or self.closed, timeout)
            return self.seq, self.data

    def close(self) -> None:
        with self.cond:
            self.closed = True
            self.cond.notify_all()


class _Handler(BaseHTTPRequestHandler):
    """One connection's requests; ``self.server.view`` is the ViewServer it serves."""

    protocol_version = "HTTP/1.1"

    @property
    def timeout(self) -> float:  # every read and write of the connection (read when it opens)
        return IDLE_S

    def log_message(self, *args):  # quiet: the terminal shows the mission, not requests
        pass

    def _send(self, code: int, body: bytes, ctype: str) -> None:
        self.send_response(code)
        self.send_header("Content-Type", ctype)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        self.send_header("X-Content-Type-Options", "nosniff")
        self.end_headers()
        if self.command != "HEAD":
            self.wfile.write(body)

    def do_HEAD(self):
        self.do_GET()

    def do_GET(self):
        server = self.server.view
        server.requests += 1
        path = self.path.split("?", 1)[0]
        if self.headers.get("Host", "") not in server.hosts:  # a rebound DNS name is not us
            self._send(403, b"forbidden host\n", "text/plain; charset=utf-8")
        elif path in server.files:
            self._send(200, *server.files[path])
        elif path == "/scene.json":
            self._send(200, server.scene, "application/json")
        elif path == "/state.json":
            self._send(200, server.bus.data, "application/json")
        elif path == "/events" and self.command == "GET":
            self._events()
        else:
            self._send(404, b"not found\n", "text/plain; charset=utf-8")

    def _events(self):
        server = self.server.view
        self.send_response(200)
        self.send_header("Content-Type", "text/event-stream")
        self.send_header("Cache-Control", "no-store")
        self.send_header("Connection", "close")
        self.end_headers()
        self.close_connection = True
        server._streaming(self.request)
        seen, wrote = 0, time.monotonic()
        self.wfile.write(b"retry: 1000\n\n")
        while not server.bus.closed and server._held(self.request):
            seq, data = server.bus.wait(seen, 1.0)  # short: a stream pushed out ends within 1 s
            if server.bus.closed:
                break
            if seq != seen:
                seen = seq
                self.wfile.write(b"data: " + data + b"\n\n")
            elif time.monotonic() - wrote < EVENT_IDLE_S:
                continue
            else:  # a comment keeps proxies and the browser's timer happy
                self.wfile.write(b": idle\n\n")
            self.wfile.flush()
            wrote = time.monotonic()


class _HttpServer(ThreadingHTTPServer):
    """The listener: a thread per connection, each counted in and out by its ViewServer."""

    daemon_threads = True
    allow_reuse_address = True  # a restart binds at once (TIME_WAIT); a live listener still refuses
    request_queue_size = 128  # a burst of connections waits in the kernel, not in SYN retries

    def __init__(self, address, view: "ViewServer"):
        self.view = view
        super().__init__(address, _Handler)

    def process_request(self, request, client_address):
        self.view._admit(request)
        super().process_request(request, client_address)

    def shutdown_request(self, request):  # the end of every connection's thread
        with self.view._lock:
            self.view._conns.pop(request, None)
        super().shutdown_request(request)

    def handle_error(self, request, client_address):
        server = self.view
        exc = sys.exc_info()[1]
        if isinstance(exc, OSError):  # a reset, a broken pipe, the idle timeout, a push-out
            server.hangups += 1
        else:  # a bug of ours: one line, the thread ends, the server goes on
            server.errors += 1
            print(f"view: {type(exc).__name__}: {exc} (client {client_address[0]})", file=sys.stderr)


class ViewServer:
    """The HTTP side: 127.0.0.1 only, a thread per client, stopped by ``close()``.

    Hostile or broken clients cost little: a client that hangs up mid-answer is counted
    (``hangups``), not printed; a connection idle for ``IDLE_S`` (no request byte, or its answer
    not read) is closed; at most ``MAX_CLIENTS`` are served at once, and the next one pushes out
    the oldest (one waiting for a request first, then the oldest event stream: a browser's page
    reconnects within a second), so a genuine request is always answered at once and held
    connections cost at most ``MAX_CLIENTS`` threads (``evicted`` counts those pushed out)."""

    def __init__(self, sc, port: int = 0, host: str = "127.0.0.1"):
        self.files = assets()
        self.scene = json.dumps(scene_json(sc)).encode()
        self.bus = Broadcaster()
        self.requests = 0
        self.hangups = 0
        self.evicted = 0
        self.errors = 0
        self._conns: OrderedDict = OrderedDict()  # socket -> streaming (an /events answer)
        self._lock = threading.Lock()
        self.httpd = _HttpServer((host, port), self)
        self.host, self.port = self.httpd.server_address[:2]
        self.hosts = {f"{self.host}:{self.port}", f"localhost:{self.port}"}
        self._thread = threading.Thread(target=self.httpd.serve_forever, kwargs={"poll_interval": 0.1},
                                        name="pmon-view-http", daemon=True)

    def _admit(self, request) -> None:
        """Count the connection in; at ``MAX_CLIENTS``, push out the oldest (not streaming first)."""
        with self._lock:
            out = None
            if len(self._conns) >= MAX_CLIENTS:
                out = next((s for s, streaming in self._conns.items() if not streaming), None)
                out = out if out is not None else next(iter(self._conns))
                del self._conns[out]
                self.evicted += 1
            self._conns[request] = False
        if out is not None:
            try:  # its thread's read returns, its write fails: the thread ends
                out.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass

    def _streaming(self, request) -> None:
        with self._lock:
            if request in self._conns:
                self._conns[request] = True

    def _held(self, request) -> bool:
        with self._lock:
            return request in self._conns

    @property
    def url(self) -> str:
        return f"http://{self.host}:{self.port}/"

    def start(self) -> "ViewServer":
        self._thread.start()
        return self

    def close(self) -> None:
        self.bus.close()
        self.httpd.shutdown()
        self.httpd.server_close()
        self._thread.join(timeout=5)


def open_in_browser(srv: ViewServer) -> None:
    """An ``on_ready`` of ``serve``: the page in the default browser (``pmon gcs view --open``)."""
    import webbrowser
    webbrowser.open(srv.url)


def serve(gl: GcsLink, sc, port: int, duration: float | None, as_json: bool, console,
          on_ready=None, stop: threading.Event | None = None) -> Outcome:
    """Serve the page until Ctrl-C, ``duration`` s or ``stop`` is set; one snapshot per PMON_STAT.
    ``on_ready(server)`` is called once the page is served (``open_in_browser``; tests: its
    ``url``)."""
    try:
        srv = ViewServer(sc, port).start()
    except OSError as exc:
        from groundstation.ports import bound_by
        who = bound_by("tcp", port) if port else None
        raise GcsError(f"view: cannot serve on 127.0.0.1:{port}: {exc.strerror or exc}"
                       + (f" (held by {who})" if who else ""), FAILED) from exc
    state = ViewState(gl, sc, srv.bus.publish)
    try:
        if as_json:
            console.file.write(json.dumps({"url": srv.url, "scenario": sc.name}) + "\n")
            console.file.flush()
        else:
            console.print(f"view: {srv.url}  (scenario {sc.name}, MAVLink {gl.url}; Ctrl-C stops)", soft_wrap=True)
        if on_ready is not None:
            on_ready(srv)
        srv.bus.publish(state.snapshot())
        t0 = time.monotonic()
        try:
            while (duration is None or time.monotonic() - t0 < duration) and not (stop and stop.is_set()):
                gl.pump(0.05)
                if time.monotonic() - max(state.stat_at, srv.bus.published_at) >= QUIET_S:
                    srv.bus.publish(state.snapshot())  # the app is silent: say for how long
        except KeyboardInterrupt:
            pass  # the operator closes the view: not a failure
    finally:
        srv.close()
    return Outcome(f"view: stopped after {state.seq} updates, {srv.requests} requests"
                   + (f", {srv.hangups} connections ended by their client or the idle timeout" if srv.hangups else ""),
                   {"url": srv.url, "updates": state.seq, "requests": srv.requests, "hangups": srv.hangups,
                    "evicted": srv.evicted})
