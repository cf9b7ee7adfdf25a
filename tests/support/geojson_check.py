"""RFC 7946 checks of a flight's GeoJSON (pmon gcs export, pmon demo's flight.geojson)."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pymap3d


def assert_geojson_in_area(path, sc, tol_m: float = 0.05) -> dict:
    """RFC 7946 checks of a FeatureCollection file, and every position inside the scenario's
    area: converted back to the mission frame here with pymap3d's own inverse (geodetic ->
    ENU), so [lat, lon] order or a wrong origin lands outside. Returns the parsed document."""
    import geojson
    from shapely.geometry import shape

    text = Path(path).read_text()
    doc = geojson.loads(text)
    assert doc.is_valid, doc.errors()
    raw = json.loads(text)
    assert raw["type"] == "FeatureCollection" and "crs" not in raw and raw["features"]
    o = sc.origin
    (x0, y0), (x1, y1) = sc.area.min_m[:2], sc.area.max_m[:2]
    for f in raw["features"]:
        g = f["geometry"]
        shp = shape(g)
        assert shp.is_valid, (f["properties"], shp)
        if g["type"] == "Polygon":  # the right-hand rule: exterior counter-clockwise
            assert shp.exterior.is_ccw, f["properties"]
            assert len(g["coordinates"]) == 1 and g["coordinates"][0][0] == g["coordinates"][0][-1]
        pts = np.array(shp.exterior.coords if g["type"] == "Polygon" else shp.coords)
        lon, lat = pts[:, 0], pts[:, 1]
        assert np.all(np.abs(lon) <= 180) and np.all(np.abs(lat) <= 90)
        e, n, _ = pymap3d.geodetic2enu(lat, lon, o.alt_m, o.lat_deg, o.lon_deg, o.alt_m)
        kind = f["properties"]["kind"]
        if kind in ("ellipse", "estimate", "estimate_track"):
            continue  # an estimate may stray outside the area; its features need not be inside
        assert np.all((e >= x0 - tol_m) & (e <= x1 + tol_m) & (n >= y0 - tol_m) & (n <= y1 + tol_m)), \
            (kind, f["properties"].get("name"), e.min(), e.max(), n.min(), n.max())
    return raw
