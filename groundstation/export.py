"""A flight as geodetic features for map tools (QGIS, Google Earth, geojson.io): GeoJSON
(RFC 7946) and KML 2.2.

Features: the area, goal regions and obstacles of the scenario; the UAV path; per target the
estimated track, the true track (when a truth JSONL is given) and its 1-sigma and 3-sigma
ellipses at chosen tick times; the last estimate of each target as a point. The mission ENU
frame is turned into WGS 84 longitude, latitude at the scenario's origin with pymap3d (as the
onboard app does, onboard/app/autopilot/pose.py). GeoJSON: positions [lon, lat], exterior rings
counter-clockwise (the right-hand rule), no ``crs`` member; colours as simplestyle properties
(stroke, fill), which geojson.io draws.
"""
from __future__ import annotations

import json
import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pymap3d

from groundstation.plot import Estimate, Flight
from groundstation.scene import (BLOCKING_COLOUR, GOAL_COLOUR, OVERFLOWN_COLOUR, UAV_COLOUR, area_outline,
                                 blocks_uav, covariance_ellipse, footprint, target_colour)

DECIMALS = 7  # 1e-7 deg: ~1 cm, the precision of MAVLink's degE7
ELLIPSE_SIGMAS = (1.0, 3.0)


def lonlat(origin: tuple[float, float, float], xy) -> np.ndarray:
    """(N, 2) [lon, lat] degrees of ENU ground points (N, 2) in metres at ``origin`` (lat, lon,
    alt AMSL)."""
    p = np.asarray(xy, float).reshape(-1, 2)
    lat, lon, _ = pymap3d.enu2geodetic(p[:, 0], p[:, 1], np.zeros(len(p)), *origin)
    return np.stack([np.asarray(lon, float), np.asarray(lat, float)], axis=1).reshape(-1, 2)


@dataclass(frozen=True)
class Shape:
    """One feature in the mission frame: a Point (1, 2), LineString (N, 2) or Polygon (N, 2,
    counter-clockwise, not closed)."""

    geometry: str
    xy: np.ndarray
    props: dict = field(default_factory=dict)
    colour: str = "#000000"
    height_m: float | None = None  # obstacles: KML extrudes them to this height


def ellipse_times(flight: Flight, at: tuple[float, ...] | None = None, every_s: float = 10.0) -> list[float]:
    """Tick times (autopilot s) at which ellipses are drawn: ``at`` if given, else every
    ``every_s`` from the first tick, and the last tick (0: only the last)."""
    times = sorted({e.t for est in flight.tracks.values() for e in est})
    if not times:
        return []
    if at:
        return sorted(at)
    if every_s <= 0:
        return [times[-1]]
    n = int((times[-1] - times[0]) // every_s) + 1
    picked = {min(times, key=lambda t: abs(t - (times[0] + k * every_s))) for k in range(n)}
    return sorted(picked | {times[-1]})


def _nearest(est: list[Estimate], t: float, tol_s: float = 1.0) -> Estimate | None:
    best = min(est, key=lambda e: abs(e.t - t), default=None)
    return best if best is not None and abs(best.t - t) <= tol_s else None


def shapes(flight: Flight, sc, at: tuple[float, ...] | None = None, every_s: float = 10.0) -> list[Shape]:
    """Every feature of the flight and the scene, in the mission frame."""
    out = [Shape("Polygon", area_outline(sc.area), {"kind": "area", "name": f"area ({sc.name})"}, "#555555")]
    for g in sc.goals:
        out.append(Shape("Polygon", footprint(g), {"kind": "goal", "name": f"goal {g.name}"}, GOAL_COLOUR))
    altitude_m = sc.uav.altitude_m
    for ob in sc.obstacles:
        dark = blocks_uav(ob, altitude_m, sc.uav.obstacle_margin_m)
        top = ob.center_m[2] + ob.size_m[2] / 2
        out.append(Shape("Polygon", footprint(ob), {"kind": "obstacle", "name": ob.name, "top_m": top,
                                                    "blocks_uav": dark},
                         BLOCKING_COLOUR if dark else OVERFLOWN_COLOUR, height_m=top))
    if len(flight.uav) >= 2:
        out.append(Shape("LineString", np.array(flight.uav), {"kind": "uav_path", "name": "UAV path"}, UAV_COLOUR))
    if flight.uav:
        out.append(Shape("Point", np.array(flight.uav[-1:]), {"kind": "uav", "name": "UAV (last)"}, UAV_COLOUR))
    for j, pts in sorted(flight.truth.items()):
        if len(pts) >= 2:
            out.append(Shape("LineString", np.array(pts), {"kind": "true_track", "target": f"T{j + 1}",
                                                           "name": f"T{j + 1} true track"}, target_colour(j)))
    times = ellipse_times(flight, at, every_s)
    for j, est in sorted(flight.tracks.items()):
        c, name = target_colour(j), f"T{j + 1}"
        if len(est) >= 2:
            out.append(Shape("LineString", np.array([(e.x, e.y) for e in est]),
                             {"kind": "estimate_track", "target": name, "name": f"{name} estimated track",
                              "t_first_s": est[0].t, "t_last_s": est[-1].t}, c))
        last = est[-1]
        out.append(Shape("Point", np.array([[last.x, last.y]]),
                         {"kind": "estimate", "target": name, "name": f"{name} at t={last.t:g} s", "t_s": last.t,
                          "sigma_x_m": last.sigma_x, "sigma_y_m": last.sigma_y, "cov_xy_m2": last.cov_xy}, c))
        for t in times:
            e = _nearest(est, t)
            if e is None:
                continue
            for k in ELLIPSE_SIGMAS:
                pts = covariance_ellipse(e.x, e.y, e.sigma_x, e.sigma_y, e.cov_xy, k, n=72)
                if pts is not None:
                    out.append(Shape("Polygon", pts, {"kind": "ellipse", "target": name, "t_s": e.t,
                                                      "n_sigma": k, "name": f"{name} {k:g}-sigma at t={e.t:g} s"}, c))
    return out


# ----------------------------------------------------------------------------- GeoJSON
def _coords(origin, s: Shape) -> list:
    ll = np.round(lonlat(origin, s.xy), DECIMALS).tolist()
    if s.geometry == "Point":
        return ll[0]
    if s.geometry == "Polygon":
        return [ll + [ll[0]]]  # closed; counter-clockwise as given (lon/lat keeps east/north's sense)
    return ll


def _style(s: Shape) -> dict:
    if s.geometry == "Point":
        return {"marker-color": s.colour}
    st = {"stroke": s.colour, "stroke-width": 2 if s.props.get("kind") != "ellipse" else 1}
    if s.geometry == "Polygon":
        kind = s.props.get("kind")
        st.update({"fill": s.colour, "fill-opacity": {"obstacle": 0.8, "goal": 0.25}.get(kind, 0.0)})
    return st


def to_geojson(flight: Flight, sc, at: tuple[float, ...] | None = None, every_s: float = 10.0) -> dict:
    o = sc.origin
    origin = (o.lat_deg, o.lon_deg, o.alt_m)
    feats = [{"type": "Feature", "geometry": {"type": s.geometry, "coordinates": _coords(origin, s)},
              "properties": {**s.props, **_style(s)}} for s in shapes(flight, sc, at, every_s)]
    box = lonlat(origin, area_outline(sc.area))
    bbox = [round(float(v), DECIMALS) for v in (box[:, 0].min(), box[:, 1].min(), box[:, 0].max(), box[:, 1].max())]
    return {"type": "FeatureCollection", "bbox": bbox, "features": feats}


# ----------------------------------------------------------------------------- KML
KML_NS = "http://www.opengis.net/kml/2.2"


def _kml_colour(hex_rgb: str, alpha: float) -> str:
    """'#rrggbb' -> KML's aabbggrr."""
    r, g, b = hex_rgb[1:3], hex_rgb[3:5], hex_rgb[5:7]
    return f"{int(round(alpha * 255)):02x}{b}{g}{r}"


def _sub(parent: ET.Element, tag: str, text=None) -> ET.Element:
    el = ET.SubElement(parent, f"{{{KML_NS}}}{tag}")
    if text is not None:
        el.text = str(text)
    return el


def to_kml(flight: Flight, sc, at: tuple[float, ...] | None = None, every_s: float = 10.0,
           title: str = "pmon flight") -> str:
    o = sc.origin
    origin = (o.lat_deg, o.lon_deg, o.alt_m)
    ET.register_namespace("", KML_NS)
    root = ET.Element(f"{{{KML_NS}}}kml")
    doc = _sub(root, "Document")
    _sub(doc, "name", title)
    folders: dict[str, ET.Element] = {}
    styles: set[str] = set()
    for s in shapes(flight, sc, at, every_s):
        kind = s.props.get("kind", "")
        sid = f"{kind}-{s.colour[1:]}"
        if sid not in styles:
            styles.add(sid)
            doc.insert(1 + len(styles) - 1, _kml_style(s, kind, sid))  # styles before the folders (the schema's order)
        group = {"area": "scene", "goal": "scene", "obstacle": "scene", "uav_path": "UAV", "uav": "UAV"}.get(
            kind, s.props.get("target", kind))
        if group not in folders:
            folders[group] = _sub(doc, "Folder")
            _sub(folders[group], "name", group)
        _kml_placemark(folders[group], s, kind, sid, origin)
    ET.indent(root)
    return '<?xml version="1.0" encoding="UTF-8"?>\n' + ET.tostring(root, encoding="unicode") + "\n"


def _kml_style(s: Shape, kind: str, sid: str) -> ET.Element:
    """The Style ``sid`` of the shapes of ``kind`` in ``s``'s colour."""
    st = ET.Element(f"{{{KML_NS}}}Style", id=sid)
    if s.geometry == "Point":
        _sub(_sub(st, "IconStyle"), "color", _kml_colour(s.colour, 1.0))
    else:
        ls = _sub(st, "LineStyle")
        _sub(ls, "color", _kml_colour(s.colour, 1.0))
        _sub(ls, "width", 1 if kind == "ellipse" else 2)
        if s.geometry == "Polygon":
            ps = _sub(st, "PolyStyle")
            _sub(ps, "color", _kml_colour(s.colour, {"obstacle": 0.8, "goal": 0.25}.get(kind, 0.0)))
            _sub(ps, "fill", 1 if kind in ("obstacle", "goal") else 0)
    return st


def _kml_placemark(folder: ET.Element, s: Shape, kind: str, sid: str, origin: tuple[float, float, float]) -> None:
    """Shape ``s`` as a Placemark of ``folder``, in style ``sid``."""
    pm = _sub(folder, "Placemark")
    _sub(pm, "name", s.props.get("name", kind))
    desc = ", ".join(f"{k}={v}" for k, v in s.props.items() if k != "name")
    _sub(pm, "description", desc)
    _sub(pm, "styleUrl", f"#{sid}")
    ll = np.round(lonlat(origin, s.xy), DECIMALS)
    if s.geometry == "Polygon":
        ll = np.vstack([ll, ll[:1]])
    if s.height_m is not None:  # obstacles: a block of their height in 3D viewers
        text = " ".join(f"{lon:.7f},{lat:.7f},{s.height_m:g}" for lon, lat in ll)
    else:
        text = " ".join(f"{lon:.7f},{lat:.7f}" for lon, lat in ll)
    if s.geometry == "Point":
        _sub(_sub(pm, "Point"), "coordinates", text)
    elif s.geometry == "LineString":
        ls_ = _sub(pm, "LineString")
        _sub(ls_, "tessellate", 1)
        _sub(ls_, "coordinates", text)
    else:
        poly = _sub(pm, "Polygon")
        if s.height_m is not None:
            _sub(poly, "extrude", 1)
            _sub(poly, "altitudeMode", "relativeToGround")
        _sub(_sub(_sub(poly, "outerBoundaryIs"), "LinearRing"), "coordinates", text)


# ----------------------------------------------------------------------------- files
def write(flight: Flight, sc, base: str | Path, formats=("geojson", "kml"), at: tuple[float, ...] | None = None,
          every_s: float = 10.0) -> list[Path]:
    """Write BASE.geojson and/or BASE.kml; returns the paths written."""
    base = Path(base)
    out = []
    if "geojson" in formats:
        p = base.with_name(base.name + ".geojson")
        p.write_text(json.dumps(to_geojson(flight, sc, at, every_s), allow_nan=False, separators=(",", ":")) + "\n")
        out.append(p)
    if "kml" in formats:
        p = base.with_name(base.name + ".kml")
        p.write_text(to_kml(flight, sc, at, every_s, title=f"pmon flight: {flight.source or base.name}"))
        out.append(p)
    return out


def parse_times(text: str) -> tuple[float, ...]:
    """'30,60.5,90' -> (30.0, 60.5, 90.0); ValueError naming the bad item."""
    vals = []
    for item in text.split(","):
        try:
            v = float(item)
        except ValueError:
            raise ValueError(f"{item.strip()!r} is not a number") from None
        if not math.isfinite(v):
            raise ValueError(f"{item.strip()!r} is not finite")
        vals.append(v)
    return tuple(vals)
