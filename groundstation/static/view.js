// pmon gcs view: draws /scene.json once and every snapshot of /events (groundstation/view.py).
// Map units are metres of the mission ENU frame: x = east - min east, y = max north - north,
// so north is up; the SVG's viewBox is the area and the browser fits it to the box (meet).
"use strict";
(() => {
  const NS = "http://www.w3.org/2000/svg";
  const $ = (id) => document.getElementById(id);
  const map = $("map");
  let scene = null, snap = null, lastAt = 0, scale = 1, W = 1, H = 1;

  function el(tag, attrs, parent) {
    const e = document.createElementNS(NS, tag);
    for (const [k, v] of Object.entries(attrs || {})) e.setAttribute(k, v);
    if (parent) parent.appendChild(e);
    return e;
  }
  const X = (east) => east - scene.area.min_m[0];
  const Y = (north) => scene.area.max_m[1] - north;
  const px = (n) => n / scale; // n screen pixels in map units
  const f = (v, d = 1) => (v === null || v === undefined || !isFinite(v)) ? "—" : Number(v).toFixed(d);
  const ll = (p) => p ? `${f(p[1], 6)}, ${f(p[0], 6)}` : "—";
  const pts = (list) => list.map(([e, n]) => `${X(e).toFixed(2)},${Y(n).toFixed(2)}`).join(" ");

  function text(s, x, y, cls, size, parent) {
    const t = el("text", { x, y, class: cls, "font-size": px(size), "stroke-width": px(3) }, parent);
    t.textContent = s;
    return t;
  }

  // the n-sigma ellipse: (x, y) + k A [cos t, sin t], A the lower Cholesky factor of the
  // covariance (groundstation/scene.py covariance_ellipse: its east-west extent is k sigma_x)
  function ellipse(t, k, n = 120) {
    const sx = t.sigma_x, sy = t.sigma_y;
    const c = Math.max(-sx * sy, Math.min(sx * sy, t.cov_xy || 0));
    const a21 = sx > 1e-9 ? c / sx : 0, a22 = Math.sqrt(Math.max(sy * sy - a21 * a21, 0));
    const out = [];
    for (let i = 0; i < n; i++) {
      const th = 2 * Math.PI * i / n, co = Math.cos(th), si = Math.sin(th);
      out.push([t.x + k * sx * co, t.y + k * (a21 * co + a22 * si)]);
    }
    return out;
  }

  function niceStep(span) {
    const raw = span / 5, p = Math.pow(10, Math.floor(Math.log10(raw)));
    return [1, 2, 5, 10].map((m) => m * p).find((s) => s >= raw);
  }

  function measure() {
    const r = map.getBoundingClientRect();
    scale = Math.min(r.width / W, r.height / H) || 1;
  }

  function drawScene() {
    const g = $("scene");
    g.replaceChildren();
    const a = scene.area;
    el("rect", { x: 0, y: 0, width: W, height: H, class: "area", "stroke-width": px(1.5) }, g);
    const step = niceStep(Math.max(W, H));
    for (let e = Math.ceil(a.min_m[0] / step) * step; e <= a.max_m[0]; e += step)
      el("line", { x1: X(e), y1: 0, x2: X(e), y2: H, class: "grid", "stroke-width": px(1) }, g);
    for (let n = Math.ceil(a.min_m[1] / step) * step; n <= a.max_m[1]; n += step)
      el("line", { x1: 0, y1: Y(n), x2: W, y2: Y(n), class: "grid", "stroke-width": px(1) }, g);
    for (const goal of scene.goals) {
      el("polygon", { points: pts(goal.footprint), class: "goal", fill: scene.colours.goal }, g);
      const c = centre(goal.footprint);
      text(`goal ${goal.name}`, X(c[0]), Y(c[1]), "label", 12, g).setAttribute("fill", scene.colours.goal);
    }
    scene.obstacles.forEach((ob, i) => {
      el("polygon", { id: `obs-${i}`, points: pts(ob.footprint), class: "obstacle", "stroke-width": px(1) }, g);
      const c = centre(ob.footprint);
      const t = text(`${ob.name} ${f(ob.top_m, 0)} m`, X(c[0]), Y(c[1]), "label", 11, g);
      t.setAttribute("id", `obs-label-${i}`);
    });
    for (const t of g.querySelectorAll("text")) { t.setAttribute("text-anchor", "middle"); t.setAttribute("dominant-baseline", "middle"); }
    paintObstacles();
    drawOverlay(step);
  }

  function drawOverlay(step) {
    const g = $("overlay");
    g.replaceChildren();
    // scale bar (bottom left) and north arrow (top left), sized in screen pixels
    const x0 = px(12), y0 = H - px(14);
    el("path", { d: `M${x0},${y0 - px(5)} V${y0} H${x0 + step} V${y0 - px(5)}`, fill: "none", stroke: "#000",
                 "stroke-width": px(2) }, g);
    text(`${step} m`, x0 + step / 2, y0 - px(8), "label", 12, g).setAttribute("text-anchor", "middle");
    el("path", { d: `M${px(20)},${px(10)} l${px(7)},${px(18)} h${-px(14)} z`, fill: "#000" }, g);
    text("N", px(20), px(42), "label", 13, g).setAttribute("text-anchor", "middle");
  }

  function centre(fp) {
    const s = fp.reduce((a, p) => [a[0] + p[0], a[1] + p[1]], [0, 0]);
    return [s[0] / fp.length, s[1] / fp.length];
  }

  function paintObstacles() {
    const h = snap ? snap.altitude_m : scene.altitude_m;
    scene.obstacles.forEach((ob, i) => {
      // dark: the UAV cannot overfly it at h (the planner's rule: inflated by the UAV's margin)
      const blocked = snap ? snap.blocked[i]
        : (ob.bottom_m - scene.uav_margin_m < h && h < ob.top_m + scene.uav_margin_m);
      const p = $(`obs-${i}`), t = $(`obs-label-${i}`);
      p.setAttribute("fill", blocked ? scene.colours.blocking : scene.colours.overflown);
      p.setAttribute("data-blocks-uav", blocked ? "1" : "0");
      t.setAttribute("class", blocked ? "label dark" : "label");
    });
    const items = [["goal region", scene.colours.goal], [`obstacle above h = ${f(h, 0)} m`, scene.colours.blocking],
                   ["obstacle the UAV overflies", scene.colours.overflown]];
    $("legend").replaceChildren(...items.map(([name, c]) => {
      const li = document.createElement("li");
      li.innerHTML = `<span class="box" style="background:${c}"></span>`;
      li.append(name);
      return li;
    }), ...["UAV ▲, trail, setpoint ✕, advised waypoint ◇ (not sent)", "marker: estimate; filled 1σ, outline 3σ; line: recent track"].map((s) => {
      const li = document.createElement("li");
      li.textContent = s;
      return li;
    }));
  }

  function drawLive() {
    const g = $("live");
    g.replaceChildren();
    if (!snap) return;
    if (snap.trail.length > 1)
      el("polyline", { points: pts(snap.trail), class: "trail", "stroke-width": px(1.5) }, g);
    for (const t of snap.targets) {
      if (t.x === null || t.y === null) continue;
      const stale = t.since_detection_s === null || t.since_detection_s > 3;
      if (t.track.length > 1)
        el("polyline", { points: pts(t.track), class: "track", stroke: t.colour, "stroke-width": px(1.5),
                         "stroke-dasharray": `${px(4)} ${px(3)}` }, g);
      if (t.sigma_x !== null && t.sigma_y !== null) {
        el("polygon", { id: `ell3-${t.index}`, points: pts(ellipse(t, 3)), class: "ell3", stroke: t.colour,
                        "stroke-width": px(1), "stroke-dasharray": `${px(3)} ${px(3)}` }, g);
        el("polygon", { id: `ell1-${t.index}`, points: pts(ellipse(t, 1)), class: "ell1", stroke: t.colour,
                        fill: t.colour, "stroke-width": px(1.5) }, g);
      }
      el("circle", { id: `tgt-${t.index}`, cx: X(t.x), cy: Y(t.y), r: px(6), fill: t.colour, stroke: t.colour,
                     class: stale ? "target-marker stale" : "target-marker", "stroke-width": px(stale ? 3 : 1.5),
                     "data-tick": t.tick_time_s }, g);
      const lab = text(stale && t.since_detection_s !== null ? `${t.name} (${f(t.since_detection_s, 0)} s)` : t.name,
                       X(t.x) + px(9), Y(t.y) - px(7), "label", 13, g);
      lab.setAttribute("fill", t.colour);
    }
    if (snap.uav) {
      const [e, n] = snap.uav.enu;
      if (snap.setpoint) {
        const [se, sn] = snap.setpoint.enu, d = px(6);
        el("line", { x1: X(e), y1: Y(n), x2: X(se), y2: Y(sn), class: "setpoint", "stroke-width": px(1),
                     "stroke-dasharray": `${px(2)} ${px(2)}` }, g);
        el("path", { id: "setpoint", d: `M${X(se) - d},${Y(sn) - d} l${2 * d},${2 * d} m0,${-2 * d} l${-2 * d},${2 * d}`,
                     class: "setpoint", "stroke-width": px(2.5) }, g);
      }
      if (snap.advice && !snap.setpoint) {  // advisory (or a pilot flying): the plan's next point, not sent
        const [ae, an] = snap.advice.enu, d = px(7);
        el("line", { x1: X(e), y1: Y(n), x2: X(ae), y2: Y(an), class: "advice", "stroke-width": px(1),
                     "stroke-dasharray": `${px(4)} ${px(3)}` }, g);
        el("path", { id: "advice", d: `M${X(ae)},${Y(an) - d} l${d},${d} l${-d},${d} l${-d},${-d} z`,
                     class: "advice", "stroke-width": px(2) }, g);
      }
      el("path", { id: "uav", d: `M${X(e)},${Y(n) - px(10)} l${px(7)},${px(16)} h${-px(14)} z`, class: "uav",
                   "stroke-width": px(1.5) }, g);
    }
  }

  function chip(id, label, cls) {
    const c = $(id);
    c.textContent = label;
    c.className = "chip" + (cls ? " " + cls : "");
  }

  function drawPanel() {
    const app = snap.app, v = snap.vehicle;
    const state = app ? app.state : null;
    chip("app-state", `app ${state || "not heard"}`,
         { monitoring: "ok", idle: "", paused: "warn", "pilot override": "bad", fault: "bad" }[state] ?? "warn");
    const clock = $("clock");
    clock.textContent = app && app.tick_time_s !== null
      ? `t = ${f(app.tick_time_s, 0)} s · ${f(app.tick_rate_hz, 2)} Hz` : "t —";
    clock.setAttribute("data-tick", app && app.tick_time_s !== null ? app.tick_time_s : "");
    chip("vehicle", v.mode ? `${v.mode} · ${v.armed ? "armed" : "disarmed"}` : "vehicle —", v.armed ? "ok" : "");
    const rows = snap.targets.map((t) => {
      const tr = document.createElement("tr");
      const speed = Math.hypot(t.vx || 0, t.vy || 0);
      const since = t.since_detection_s;
      const stale = since === null || since > 3;
      tr.innerHTML = `<td><span class="swatch" style="background:${t.colour}"></span>${t.name}</td>` +
        `<td>${ll(t.lonlat)}</td><td>${f(t.sigma_x, 0)} / ${f(t.sigma_y, 0)}</td><td>${f(speed, 1)}</td>` +
        `<td class="${stale ? "stale" : ""}">${since === null ? "never" : f(since, 1) + " s"}</td>`;
      if (!t.doing || t.doing === "-") return [tr];
      // what the target most likely does, on a row of its own: the table keeps its width
      const doing = document.createElement("tr");
      const td = document.createElement("td");
      td.colSpan = 5;
      td.className = "doing";
      td.textContent = `${t.name}: ${t.doing}`;
      doing.appendChild(td);
      return [tr, doing];
    });
    $("targets").tBodies[0].replaceChildren(...rows.flat());
    $("uav").textContent = snap.uav
      ? `UAV ${ll(snap.uav.lonlat)} · ${f(snap.uav.enu[2], 1)} m up · next ${snap.setpoint ? ll(snap.setpoint.lonlat) : "—"}${snap.advice && !snap.setpoint ? ` · advised ${ll(snap.advice.lonlat)}` : ""} · h ${f(snap.altitude_m, 0)} m`
      : "UAV: no position yet";
    $("texts").replaceChildren(...snap.texts.slice().reverse().map((m) => {
      const li = document.createElement("li");
      li.className = m.severity <= 3 ? "sev-bad" : m.severity === 4 ? "sev-warn" : "";
      li.textContent = `${m.t_s === null ? "" : "t=" + f(m.t_s, 0) + " s · "}${m.source}: ${m.text.replace(/^PMON: /, "")}`;
      return li;
    }));
    $("counters").textContent = app
      ? `ticks ${app.ticks} (${app.ticks_skipped} skipped, ${app.ticks_late} late) · tick ${f(app.tick_ms, 0)} ms · ` +
        `DF ${app.datagrams_accepted} accepted, ${app.datagrams_rejected} rejected · setpoints refused ${app.setpoints_refused}`
      : `link ${snap.link}: no PMON_STAT from the onboard app yet`;
  }

  function freshness() {
    if (!snap) return;
    const age = (performance.now() - lastAt) / 1000 + (snap.app_silent_s || 0);
    if (!snap.app) chip("fresh", "app not heard", "bad");
    else chip("fresh", age < 2.5 ? "live" : `no update for ${f(age, 0)} s`, age < 2.5 ? "ok" : age < 5 ? "warn" : "bad");
  }

  function render() {
    if (!scene || !snap) return;
    paintObstacles();
    drawLive();
    drawPanel();
    freshness();
  }

  map.addEventListener("mousemove", (ev) => {
    const m = map.getScreenCTM();
    if (!m || !scene) return;
    const p = new DOMPoint(ev.clientX, ev.clientY).matrixTransform(m.inverse());
    const u = p.x / W, v = 1 - p.y / H; // interpolated between the area's corners (SW, SE, NE, NW)
    if (u < 0 || u > 1 || v < 0 || v > 1) return;
    const c = scene.area.corners_lonlat;
    const w = [(1 - u) * (1 - v), u * (1 - v), u * v, (1 - u) * v];
    const lon = w.reduce((s, wi, i) => s + wi * c[i][0], 0), lat = w.reduce((s, wi, i) => s + wi * c[i][1], 0);
    $("pointer").textContent = `pointer ${f(lat, 6)}, ${f(lon, 6)} · E ${f(p.x + scene.area.min_m[0], 0)} N ${f(scene.area.max_m[1] - p.y, 0)} m`;
  });

  window.addEventListener("resize", () => { if (scene) { measure(); drawScene(); render(); } });
  setInterval(freshness, 500);

  fetch("/scene.json").then((r) => r.json()).then((s) => {
    scene = s;
    W = s.area.max_m[0] - s.area.min_m[0];
    H = s.area.max_m[1] - s.area.min_m[1];
    map.setAttribute("viewBox", `0 0 ${W} ${H}`);
    document.title = `pmon view: ${s.name}`;
    const c = s.area.corners_lonlat;
    $("areainfo").textContent = `scenario ${s.name} · area SW ${ll(c[0])}, NE ${ll(c[2])} · origin ` +
      `${f(s.origin.lat_deg, 6)}, ${f(s.origin.lon_deg, 6)}, ${f(s.origin.alt_m, 0)} m`;
    measure();
    drawScene();
    const es = new EventSource("/events");
    es.onmessage = (ev) => {
      snap = JSON.parse(ev.data);
      lastAt = performance.now();
      if (snap) render();
    };
    es.onerror = () => chip("fresh", "ground station not reachable: retrying", "bad");
  });
})();
