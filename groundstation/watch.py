"""``watch``: a live table of every target the app tracks, one update per PMON_STAT (each tick,
or 1 Hz while the app is not ticking); optionally a PNG rewritten at most once a second."""
from __future__ import annotations

import json
import math
import time

from groundstation import protocol as P
from groundstation.gcs_commands import Outcome, _enu
from groundstation.errors import TIMEOUT, GcsError
from groundstation.gcs_link import GcsLink
from groundstation.plot import Estimate, Flight, draw


def _f(x, spec=".1f"):
    return "-" if x is None or not math.isfinite(x) else format(x, spec)


def snapshot(gl: GcsLink) -> dict:
    v = gl.v
    st = v.app_status
    goals = tuple(getattr(gl, "goal_names", ()) or ())
    never = st is None or st.datagrams_accepted == 0

    def since(e):
        # the app reports t(tick) - t(newest scan), negative when a newer scan has already
        # arrived (.notes/h4_app_requests.md): that target was just detected
        if e.since_detection_s is None:
            return None if never else 0.0
        return max(e.since_detection_s, 0.0)
    return {
        "app_state": v.app_state, "tick_time_s": st.last_tick_time_s if st else None,
        "tick_rate_hz": round(st.tick_rate_hz, 2) if st else None,
        "mode": v.mode_name, "armed": v.armed,
        "uav_enu_m": list(st.uav_enu) if st and st.uav_enu else None,
        "next_enu_m": list(st.next_enu) if st and st.next_enu else None,
        # the plan's next point: in advisory the advised waypoint (nothing is sent)
        "advice_enu_m": list(st.advice_enu) if st and st.advice_enu else None,
        "targets": [{"name": e.name, "x_m": e.x, "y_m": e.y, "vx_mps": e.vx, "vy_mps": e.vy,
                     "sigma_x_m": e.sigma_x, "sigma_y_m": e.sigma_y,
                     "since_detection_s": since(e), "tick_time_s": e.tick_time_s, "doing": e.mode_text(goals)}
                    for _, e in sorted(v.targets.items())],
    }


def table(snap: dict, n: int):
    from rich.table import Table

    t = Table(title=f"pmon watch: app {snap['app_state']}, tick t={_f(snap['tick_time_s'])} s "
                    f"({_f(snap['tick_rate_hz'], '.2f')} Hz); vehicle {snap['mode']}"
                    f"{' armed' if snap['armed'] else ' disarmed'}",
              caption=f"UAV {_enu(snap['uav_enu_m'])}   next waypoint {_enu(snap['next_enu_m'])}   "
                      f"advised {_enu(snap.get('advice_enu_m'))}   update {n}")
    for col in ("target", "E m", "N m", "vE m/s", "vN m/s", "1σ E m", "1σ N m", "last DF", "doing"):
        t.add_column(col, justify="right")
    for tg in snap["targets"]:
        since = tg["since_detection_s"]
        t.add_row(tg["name"], _f(tg["x_m"]), _f(tg["y_m"]), _f(tg["vx_mps"]), _f(tg["vy_mps"]),
                  _f(tg["sigma_x_m"]), _f(tg["sigma_y_m"]), "never" if since is None else f"{since:.1f} s",
                  tg.get("doing", "-"))
    return t


class _Updates:
    """What watch counts and draws, fed every message: an update is a tick seen whole (its
    PMON_TGTs, then its PMON_STAT), or, while the app does not tick, each PMON_STAT (1 Hz)."""

    def __init__(self, v):
        self.v = v
        self.n = 0
        self.uav_path: list = []
        self.tracks: dict = {}
        self._shown_tick = None
        self._last_tgt = time.monotonic()  # give the first tick 2 s to arrive whole

    def on_msg(self, mtype, msg) -> None:
        v = self.v
        if mtype == "PMON_STAT":
            st = P.AppStatus.from_msg(msg)
            tick_t = st.last_tick_time_s
            whole = bool(v.targets) and tick_t is not None and tick_t != self._shown_tick and all(
                e.tick_time_s == tick_t for e in v.targets.values())
            if whole or time.monotonic() - self._last_tgt > 2.0:
                self.n += 1
                self._shown_tick = tick_t
                if st.uav_enu:
                    self.uav_path.append(st.uav_enu[:2])
        elif mtype == "PMON_TGT":
            self._last_tgt = time.monotonic()
            e = P.TargetEstimate.from_msg(msg)
            hist = self.tracks.setdefault(e.index, [])
            if not hist or hist[-1].t != e.tick_time_s:
                hist.append(Estimate(e.tick_time_s, e.x, e.y, e.sigma_x, e.sigma_y, e.cov_xy))

    def draw(self, snap: dict, png: str, scenario) -> None:
        p = snap["next_enu_m"] or snap.get("advice_enu_m")  # advisory: the advised waypoint
        nxt = tuple(p[:2]) if p else None
        draw(Flight(tuple(self.uav_path), {k: list(h) for k, h in self.tracks.items()}, {}, nxt, "live"),
             png, title=f"pmon watch: t={_f(snap['tick_time_s'])} s, app {snap['app_state']}",
             scenario=scenario)


def watch(gl: GcsLink, count: int | None, duration: float | None, png: str | None, as_json: bool,
          console, scenario=None) -> Outcome:
    """``scenario``: the scene the PNG draws (area, goal, obstacles)."""
    updates = _Updates(gl.v)
    gl.on_message(updates.on_msg)
    t0 = time.monotonic()
    shown, last_update, last_png = 0, time.monotonic(), -math.inf
    live = None
    if not as_json and console.is_terminal:
        from rich.live import Live
        live = Live(console=console, auto_refresh=False, transient=False)
        live.start()
    try:
        while (count is None or shown < count) and (duration is None or time.monotonic() - t0 < duration):
            gl.pump(0.05)
            now = time.monotonic()
            if updates.n > shown:
                shown = updates.n
                last_update = now
                snap = snapshot(gl)
                _show(snap, shown, as_json, console, live)
                if png and now - last_png >= 1.0:
                    last_png = now
                    updates.draw(snap, png, scenario)
            elif now - last_update > gl.timeout:
                raise GcsError(f"watch: no update from the onboard app for {gl.timeout:g} s "
                               f"({'never heard' if not shown else f'after {shown} updates'})", TIMEOUT)
    except KeyboardInterrupt:
        pass  # the operator stops watching: not a failure
    finally:
        if live is not None:
            live.stop()
    return Outcome("", {"updates": shown, "targets": len(gl.v.targets)})


def _show(snap: dict, n: int, as_json: bool, console, live) -> None:
    """Update ``n``: a JSON line, the live table redrawn, or (not a terminal) the table printed."""
    if as_json:
        console.file.write(json.dumps({"update": n, **snap}) + "\n")
        console.file.flush()
    elif live is not None:
        live.update(table(snap, n), refresh=True)
    else:
        console.print(table(snap, n))
