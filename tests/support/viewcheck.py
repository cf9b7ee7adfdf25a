"""The live view (``pmon gcs view``) checked in a real browser, reusable by any SITL test:

    from tests.support.viewcheck import browser_unavailable, check_live_view
    if (why := browser_unavailable()):
        pytest.skip(why)
    report = check_live_view(gcs_url, "paper", seconds=15, screenshot=tmp_path / "view.png")

``check_live_view`` opens its own ``GcsLink`` on ``gcs_url`` (one client: a real ArduPilot TCP
port takes one), serves the view from it in a thread, exactly as ``pmon gcs view`` does, and
records every PMON_TGT it receives, decoded here from the raw DEBUG_FLOAT_ARRAY by the layout
in docs/MAVLINK.md, not through the view's code. Headless Chromium (Debian's chromium and
chromedriver, driven by selenium; nothing downloaded) loads the page; a MutationObserver the
test installs reads, after every redraw, each target marker's and ellipse's box on screen.
The test projects its own estimates with the page's documented projection (the area fitted to
the map's box, centred, north up, equal scales) from the map element's box and the scenario,
and requires: every marker within ``tol_px`` of its estimate of the same tick, 1-sigma and
3-sigma ellipses with the east/north extents of sigma_x, sigma_y (exact for the Cholesky
parametrisation both draw), updates at >= ``min_rate_hz`` of mission (tick) time, no console
error, every resource from the ground station itself, payload <= 200 kB, and the page readable
at 1280x800 and at a phone's 390x844. Raises AssertionError naming what failed.
"""
from __future__ import annotations

import io
import json
import math
import os
import shutil
import tempfile
import threading
import time
import urllib.request
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

CHROMIUM = os.environ.get("PMON_CHROMIUM", "/usr/bin/chromium")
CHROMEDRIVER = os.environ.get("PMON_CHROMEDRIVER", "/usr/bin/chromedriver")
FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync",
         "--disable-dev-shm-usage", "--hide-scrollbars")
PAYLOAD_MAX = 200_000  # bytes of HTML + JS + CSS

# after each redraw of the live layer: the clock's tick, the map's box, every marker's and
# ellipse's box (screen px), the page's width and the viewport's
OBSERVER = """
window.__frames = [];
const read = () => {
  const box = (e) => { const r = e.getBoundingClientRect(); return [r.left, r.top, r.width, r.height]; };
  const m = document.getElementById('map');
  const f = {wall_ms: performance.now(), tick: document.getElementById('clock').dataset.tick,
             map: box(m), targets: []};
  for (const c of document.querySelectorAll('circle.target-marker')) {
    const j = c.id.slice(4);
    const e1 = document.getElementById('ell1-' + j), e3 = document.getElementById('ell3-' + j);
    f.targets.push({index: Number(j), tick: c.dataset.tick, marker: box(c),
                    ell1: e1 ? box(e1) : null, ell3: e3 ? box(e3) : null});
  }
  window.__frames.push(f);
};
new MutationObserver(read).observe(document.getElementById('live'), {childList: true});
"""


def browser_unavailable() -> str | None:
    """Why the browser check cannot run here (one line), or None."""
    for path, what in ((CHROMIUM, "chromium"), (CHROMEDRIVER, "chromedriver")):
        if not (os.path.isfile(path) and os.access(path, os.X_OK)):
            return f"{what} not installed at {path} (apt-get install chromium chromium-driver)"
    try:
        import selenium  # noqa: F401
    except ImportError:
        return "selenium not installed (pip install -e '.[test]')"
    return None


@contextmanager
def chromium(width: int = 1280, height: int = 800, phone: bool = False):
    """A headless Chromium under selenium, its profile in a fresh temporary directory. A window
    of width x height; ``phone``: a phone's viewport of exactly width x height CSS px (touch,
    2x pixels; a headless window is never narrower than 500 px)."""
    os.environ.setdefault("SE_OFFLINE", "true")  # selenium-manager must never fetch a driver
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    profile = tempfile.mkdtemp(prefix="pmon-chromium-")
    opts = webdriver.ChromeOptions()
    opts.binary_location = CHROMIUM
    for a in FLAGS:
        opts.add_argument(a)
    if phone:
        opts.add_experimental_option("mobileEmulation", {"deviceMetrics": {"width": width, "height": height,
                                                                           "pixelRatio": 2.0}})
    else:
        opts.add_argument(f"--window-size={width},{height}")
    opts.add_argument(f"--user-data-dir={profile}")
    opts.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    # the browser only on idle CPU (chromedriver and the Chromium it starts in SCHED_IDLE, which
    # they inherit and, unlike a nice value, Chromium does not change): an operator's browser runs
    # on the ground station, not beside the onboard app, whose ticks it would otherwise delay on a
    # 2-core test machine (ArduPilot's flight A had a 688 ms tick, late, as the browser started)
    driver_sh = Path(profile) / "chromedriver-idle.sh"
    driver_sh.write_text(f'#!/bin/sh\nchrt --idle 0 true 2>/dev/null && exec chrt --idle 0 "{CHROMEDRIVER}" "$@"\n'
                         f'exec "{CHROMEDRIVER}" "$@"\n')
    driver_sh.chmod(0o700)
    driver = webdriver.Chrome(service=Service(str(driver_sh)), options=opts)
    try:
        driver.set_page_load_timeout(20)
        driver.set_script_timeout(20)
        yield driver
    finally:
        driver.quit()
        shutil.rmtree(profile, ignore_errors=True)


@dataclass
class ViewReport:
    url: str = ""
    frames: int = 0  # redraws seen
    checked_markers: int = 0
    max_marker_err_px: float = 0.0
    max_ellipse_err_px: float = 0.0
    ticks_shown: int = 0
    mission_s: float = 0.0
    rate_hz: float = 0.0
    payload_bytes: int = 0
    console: list = field(default_factory=list)
    screenshot: str | None = None
    phone: dict = field(default_factory=dict)
    state: dict = field(default_factory=dict)  # the view's last snapshot (/state.json)


def _projection(map_box, sc):
    """ENU (x, y) -> screen px, as the page must draw it: the area fitted to the map's box
    (SVG viewBox = area, preserveAspectRatio xMidYMid meet), north up."""
    left, top, w, h = map_box
    (x0, y0), (x1, y1) = sc.area.min_m[:2], sc.area.max_m[:2]
    W, H = x1 - x0, y1 - y0
    s = min(w / W, h / H)
    ox, oy = left + (w - W * s) / 2, top + (h - H * s) / 2
    return (lambda x, y: (ox + (x - x0) * s, oy + (y1 - y) * s)), s


def _centre(box):
    return box[0] + box[2] / 2, box[1] + box[3] / 2


def _check_frames(frames, estimates, sc, tol_px, report) -> None:
    errs, ell_errs = [], []
    for f in frames:
        proj, s = _projection(f["map"], sc)
        for t in f["targets"]:
            key = (t["index"], round(float(t["tick"]), 3))
            assert key in estimates, f"the page drew T{t['index'] + 1} at tick {t['tick']}, never received over MAVLink"
            x, y, sx, sy, _cxy = estimates[key]
            px, py = proj(x, y)
            cx, cy = _centre(t["marker"])
            errs.append(math.hypot(cx - px, cy - py))
            for box, k in ((t["ell1"], 1), (t["ell3"], 3)):
                assert box is not None, f"T{t['index'] + 1}: no {k}-sigma ellipse drawn"
                ex, ey = _centre(box)
                ell_errs += [abs(ex - px), abs(ey - py), abs(box[2] / 2 - k * sx * s), abs(box[3] / 2 - k * sy * s)]
    report.checked_markers = len(errs)
    report.max_marker_err_px = max(errs, default=0.0)
    report.max_ellipse_err_px = max(ell_errs, default=0.0)
    assert errs, "no target marker drawn"
    assert report.max_marker_err_px <= tol_px, \
        f"a target marker is {report.max_marker_err_px:.2f} px from its estimate's position (> {tol_px} px)"
    assert report.max_ellipse_err_px <= tol_px, \
        f"an ellipse's centre or extent is {report.max_ellipse_err_px:.2f} px off (> {tol_px} px)"


def _layout(driver) -> dict:
    return driver.execute_script("""
      const r = (id) => { const b = document.getElementById(id).getBoundingClientRect();
                          return [b.left, b.top, b.width, b.height]; };
      const fs = Math.min(...[...document.querySelectorAll('td, .chip, .info, li')]
                           .map((e) => parseFloat(getComputedStyle(e).fontSize)));
      return {vw: innerWidth, vh: innerHeight, scroll_w: document.documentElement.scrollWidth,
              map: r('map'), table: r('targets'), bar: r('bar'), min_font_px: fs};""")


def check_live_view(gcs_url: str, scenario: str = "paper", *, seconds: float = 15.0,
                    screenshot: str | Path | None = None, signing_key: bytes | None = None,
                    timeout: float = 10.0, tol_px: float = 1.0, min_rate_hz: float = 0.9,
                    phone: bool = True) -> ViewReport:
    """Serve the view of the mission on ``gcs_url`` and check what a browser draws of it for
    ``seconds`` (wall); the mission must be running (the app ticking)."""
    from rich.console import Console

    from groundstation.gcs_link import GcsLink
    from groundstation.view import serve
    from onboard.config import load_scenario

    sc = load_scenario(scenario)
    report = ViewReport()
    estimates: dict = {}  # (target index, tick time) -> (x, y, sigma_x, sigma_y, cov_xy)
    lock = threading.Lock()

    def record(mtype, msg):
        if mtype == "PMON_TGT":  # docs/MAVLINK.md: 0 x, 1 y, 6 sigma_x, 7 sigma_y, 9 cov_xy, 13 tick time
            d = msg.data
            with lock:
                estimates[(int(msg.array_id), round(float(d[13]), 3))] = (d[0], d[1], d[6], d[7], d[9])

    ready, stop = threading.Event(), threading.Event()
    server = []
    failure = []
    gl = GcsLink(gcs_url, timeout, signing_key=signing_key)
    gl.on_message(record)

    def run():
        try:
            gl.connect()
            serve(gl, sc, 0, None, False, Console(file=io.StringIO()),
                  on_ready=lambda srv: (server.append(srv), ready.set()), stop=stop)
        except BaseException as exc:  # shown by the caller
            failure.append(exc)
            ready.set()

    th = threading.Thread(target=run, name="pmon-view", daemon=True)
    th.start()
    try:
        assert ready.wait(timeout + 10), "the view did not start"
        assert not failure, f"the view failed: {failure[0]!r}"
        url = report.url = server[0].url
        report.payload_bytes = _check_payload(url)
        frames, lay, resources = _watch_desktop(url, seconds, timeout, screenshot, report)
        with urllib.request.urlopen(url + "state.json", timeout=5) as r:
            report.state = json.loads(r.read())
        with lock:
            est = dict(estimates)
        report.frames = len(frames)
        _check_frames(frames, est, sc, tol_px, report)
        _check_rate(frames, min_rate_hz, report)
        assert not report.console, f"browser console: {report.console}"
        foreign = [r for r in resources if not r.startswith(url)]
        assert not foreign, f"the page loaded resources from elsewhere: {foreign}"
        _check_desktop_layout(lay)
        if phone:
            def latest():
                with lock:
                    return dict(estimates)
            report.phone = _check_phone(url, latest, sc, tol_px)
        return report
    finally:
        stop.set()
        th.join(timeout=10)
        gl.close()


def _check_payload(url: str) -> int:
    """The page, its script and its style: nothing from outside the ground station, and small.
    Returns their size in bytes."""
    payload = 0
    for path in ("", "view.js", "view.css"):
        with urllib.request.urlopen(url + path, timeout=5) as r:
            body = r.read()
        payload += len(body)
        text = body.decode()
        ext = [w for w in ("http://", "https://", "//cdn", "@import") if w in text.replace(
            "http://www.w3.org/2000/svg", "")]
        assert not ext, f"/{path} refers to something outside the ground station: {ext}"
    assert payload <= PAYLOAD_MAX, f"payload {payload} B > {PAYLOAD_MAX} B"
    return payload


def _watch_desktop(url: str, seconds: float, timeout: float, screenshot, report: ViewReport):
    """The page at 1280x800 watched for ``seconds``: the frames drawn, the layout, the resources
    loaded (the console's warnings and the screenshot into ``report``)."""
    with chromium(1280, 800) as driver:
        driver.get(url)
        t0 = time.monotonic()
        while not driver.execute_script("return document.querySelectorAll('circle.target-marker').length"):
            assert time.monotonic() - t0 < timeout, f"no target drawn within {timeout:g} s of loading the page"
            time.sleep(0.1)
        driver.execute_script(OBSERVER)
        time.sleep(seconds)
        frames = driver.execute_script("return window.__frames")
        lay = _layout(driver)
        if screenshot is not None:
            driver.save_screenshot(str(screenshot))
            report.screenshot = str(screenshot)
        resources = driver.execute_script(
            "return performance.getEntriesByType('resource').map((e) => e.name)")
        report.console = [e for e in driver.get_log("browser") if e["level"] in ("SEVERE", "WARNING")]
    return frames, lay, resources


def _check_rate(frames, min_rate_hz: float, report: ViewReport) -> None:
    ticks = sorted({round(float(f["tick"]), 3) for f in frames if f["tick"]})
    report.ticks_shown = len(ticks)
    report.mission_s = ticks[-1] - ticks[0] if len(ticks) > 1 else 0.0
    report.rate_hz = (len(ticks) - 1) / report.mission_s if report.mission_s > 0 else 0.0
    assert report.rate_hz >= min_rate_hz, (f"the page showed {len(ticks)} ticks over {report.mission_s:.1f} s "
                                           f"of mission: {report.rate_hz:.2f} Hz < {min_rate_hz}")


def _check_desktop_layout(lay: dict) -> None:
    """Readable at 1280x800: map and target table wholly in the window, no horizontal scroll."""
    assert lay["scroll_w"] <= lay["vw"], f"horizontal scroll at 1280x800: {lay}"
    for name in ("map", "table"):
        left, top, w, h = lay[name]
        assert left >= 0 and top >= 0 and left + w <= lay["vw"] + 0.5 and top + h <= lay["vh"] + 0.5, \
            f"the {name} is not wholly visible at 1280x800: {lay}"
    assert lay["map"][3] >= 600 and lay["min_font_px"] >= 12, f"too small at 1280x800: {lay}"


def _check_phone(url, estimates_now, sc, tol_px) -> dict:
    """A phone-sized window: the map as wide as the screen, markers where they belong, no
    horizontal scroll."""
    with chromium(390, 844, phone=True) as driver:
        driver.get(url)
        t0 = time.monotonic()
        while not driver.execute_script("return document.querySelectorAll('circle.target-marker').length"):
            assert time.monotonic() - t0 < 10, "no target drawn on the phone-sized page"
            time.sleep(0.1)
        driver.execute_script(OBSERVER)
        time.sleep(1.5)
        frames = driver.execute_script("return window.__frames")
        lay = _layout(driver)
        console = [e for e in driver.get_log("browser") if e["level"] in ("SEVERE", "WARNING")]
    rep = ViewReport()
    _check_frames(frames, estimates_now(), sc, tol_px, rep)
    assert lay["vw"] == 390, f"not a phone's viewport: {lay}"
    assert lay["scroll_w"] <= lay["vw"], f"horizontal scroll on a phone: {lay}"
    assert lay["map"][2] >= lay["vw"] - 20 and lay["map"][3] >= 300, f"map too small on a phone: {lay}"
    assert lay["min_font_px"] >= 12, f"text below 12 px on a phone: {lay}"
    assert not console, f"browser console on a phone: {console}"
    return {"layout": lay, "frames": len(frames), "max_marker_err_px": rep.max_marker_err_px}


def summary(report: ViewReport) -> str:
    return json.dumps({k: v for k, v in report.__dict__.items() if k not in ("console", "phone", "state")})
