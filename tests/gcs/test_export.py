"""Flights for map tools and pictures: ``pmon gcs export`` (GeoJSON checked against RFC 7946 with
geojson and shapely, KML against the OGC KML 2.2 schema with fastkml), ``plot`` / ``watch --png``
(the whole scene, the one palette, a legend that covers nothing). The demo's own flight.geojson
is checked in tests/sim/test_demo.py (``assert_geojson_in_area``)."""
from __future__ import annotations

import json
import math

import numpy as np
import pymap3d
import pytest

from groundstation.cli import main
from groundstation.plot import Estimate, Flight, figure, load
from groundstation.scene import (BLOCKING_COLOUR, OVERFLOWN_COLOUR, TARGET_COLOURS, covariance_ellipse,
                                 target_colour)
from tests.support.geojson_check import assert_geojson_in_area


def _flight(n: int = 25) -> Flight:
    t = np.arange(n, dtype=float) + 30.0
    tracks = {j: [Estimate(tk, 200 + 100 * j + 3 * k, 800 - 10 * k, 20 + k, 30 - k / 2, 150.0 * (-1) ** j)
                  for k, tk in enumerate(t)] for j in range(4)}
    truth = {j: [(205 + 100 * j + 3 * k, 795 - 10 * k) for k in range(n)] for j in range(4)}
    uav = tuple((10.0 + 4 * k, 20.0 + 6 * k) for k in range(n))
    return Flight(uav, tracks, truth, (120.0, 180.0), "test")


def test_covariance_ellipse_is_the_covariance_and_counter_clockwise():
    pts = covariance_ellipse(100.0, 50.0, 20.0, 10.0, 120.0, n_sigma=3.0, n=2000)
    d = pts - [100.0, 50.0]
    assert np.cov(d.T, bias=True) * 2 / 9 == pytest.approx(np.array([[400.0, 120.0], [120.0, 100.0]]), rel=1e-3)
    assert np.ptp(pts[:, 0]) / 2 == pytest.approx(60.0, abs=1e-9)  # exactly 3 sigma_x east-west
    assert np.ptp(pts[:, 1]) / 2 == pytest.approx(30.0, rel=1e-5)
    area2 = np.sum(d[:, 0] * np.roll(d[:, 1], -1) - np.roll(d[:, 0], -1) * d[:, 1])
    assert area2 > 0  # counter-clockwise
    assert covariance_ellipse(0, 0, math.nan, 1, 0) is None


def test_export_writes_valid_geojson_and_kml(tmp_path, paper):
    from fastkml.validator import validate

    run = tmp_path / "run.jsonl"
    with open(run, "w") as f:
        for k, tk in enumerate(np.arange(25.0) + 30.0):
            f.write(json.dumps({"t": tk, "uav_enu": [10 + 4 * k, 20 + 6 * k, 40.0], "next": [50, 60, 40],
                                "means": [[200 + 100 * j + 3 * k, 800 - 10 * k, 0, 3, -10, 0] for j in range(4)],
                                "sigmas_xy": [[20 + k, 30 - k / 2]] * 4, "cov_xy": [150.0, -150.0] * 2}) + "\n")
    (tmp_path / "truth.jsonl").write_text(
        json.dumps({"header": {"scenario": "paper"}}) + "\n"
        + "".join(json.dumps({"t": 30.0 + k, "uav_enu": [0, 0, 40], "targets": [[205 + 100 * j + 3 * k, 795 - 10 * k,
                                                                                   0, 0, 0, 0] for j in range(4)]}) + "\n"
                  for k in range(25)))
    rc = main(["--json", "export", str(run), "--at", "30,42.4,54"])
    assert rc == 0
    gj, kml = tmp_path / "run.geojson", tmp_path / "run.kml"
    raw = assert_geojson_in_area(gj, paper)
    kinds = [f["properties"]["kind"] for f in raw["features"]]
    assert kinds.count("obstacle") == 4 and kinds.count("goal") == len(paper.goals) == 3 and kinds.count("area") == 1
    assert kinds.count("uav_path") == 1 and kinds.count("true_track") == 4 and kinds.count("estimate_track") == 4
    ells = [f["properties"] for f in raw["features"] if f["properties"]["kind"] == "ellipse"]
    assert sorted({(e["t_s"], e["n_sigma"]) for e in ells}) == [(30.0, 1.0), (30.0, 3.0), (42.0, 1.0), (42.0, 3.0),
                                                                 (54.0, 1.0), (54.0, 3.0)]
    assert len(ells) == 4 * 6
    obst = {f["properties"]["name"]: f["properties"] for f in raw["features"] if f["properties"]["kind"] == "obstacle"}
    assert {k: v["blocks_uav"] for k, v in obst.items()} == {"O1": True, "O2": False, "O3": True, "O4": False}
    assert obst["O1"]["fill"] == BLOCKING_COLOUR and obst["O2"]["fill"] == OVERFLOWN_COLOUR
    t1 = next(f for f in raw["features"] if f["properties"].get("name") == "T1 estimated track")
    assert t1["properties"]["stroke"] == TARGET_COLOURS[0]
    # a 1-sigma ellipse in lon/lat is the estimate's: its centre and east-west half-width, in metres
    e1 = next(f for f in raw["features"] if f["properties"].get("name") == "T2 1-sigma at t=30 s")
    ring = np.array(e1["geometry"]["coordinates"][0])
    o = paper.origin
    e, n, _ = pymap3d.geodetic2enu(ring[:, 1], ring[:, 0], o.alt_m, o.lat_deg, o.lon_deg, o.alt_m)
    assert (e.max() + e.min()) / 2 == pytest.approx(300.0, abs=0.05) and (e.max() - e.min()) / 2 == \
        pytest.approx(20.0, abs=0.05)
    assert validate(file_to_validate=kml) is True
    assert kml.read_text().count("<Placemark>") == len(raw["features"])
    # only KML, no ellipse but the last
    rc = main(["export", str(run), "--format", "kml", "--every", "0", "--out", str(tmp_path / "k")])
    assert rc == 0 and (tmp_path / "k.kml").exists() and not (tmp_path / "k.geojson").exists()
    assert validate(file_to_validate=tmp_path / "k.kml") is True


def test_export_errors_are_one_line(tmp_path, capsys):
    run = tmp_path / "run.jsonl"
    run.write_text(json.dumps({"t": 1.0, "uav_enu": [0, 0, 40], "means": [[1, 2, 0, 0, 0, 0]],
                               "sigmas_xy": [[1, 1]]}) + "\n")
    for argv, code, msg in ((["export", str(run), "--at", "1,x"], 2, "export: --at: 'x' is not a number"),
                            (["export", str(run), "--every", "-1"], 2, "--every must be >= 0"),
                            (["export", str(run), "--scenario", "nope.yaml"], 2, "--scenario nope.yaml: cannot read"),
                            (["export", str(tmp_path / "none.jsonl")], 1, "no such file"),
                            (["export", str(run), "--out", str(tmp_path / "no" / "dir" / "x")], 1, "cannot write")):
        capsys.readouterr()
        rc = main(argv)
        err = capsys.readouterr().err.strip()
        assert rc == code and len(err.splitlines()) == 1 and msg in err, (argv, err)


def test_the_flight_picture_draws_the_scene_in_the_palette_with_the_legend_beside_it(paper):
    from matplotlib.colors import to_hex
    from matplotlib.patches import Polygon

    import sim.evaluation.figures as figs
    fig, ax = figure(_flight(), scenario=paper)
    fig.canvas.draw()
    r = fig.canvas.get_renderer()
    legend = ax.get_legend()
    assert legend is not None and not legend.get_window_extent(r).overlaps(ax.get_window_extent(r))
    labels = [t.get_text() for t in legend.get_texts()]
    assert {"T1 estimate", "T4 true", "UAV", "goal region", "obstacle above h = 40 m",
            "obstacle the UAV overflies"} <= set(labels)
    fills = [to_hex(p.get_facecolor()[:3]) for p in ax.patches if isinstance(p, Polygon) and p.get_fill()]
    assert fills.count(BLOCKING_COLOUR) == 2 and fills.count(OVERFLOWN_COLOUR) == 2  # O1, O3 dark; O2, O4 light
    lines = {ln.get_label(): to_hex(ln.get_color()) for ln in ax.get_lines()}
    for j in range(4):
        assert lines[f"T{j + 1} estimate"] == lines[f"T{j + 1} true"] == target_colour(j) == to_hex(figs._colour(j))
    assert ax.get_xlim()[0] <= paper.area.min_m[0] and ax.get_xlim()[1] >= paper.area.max_m[0]


def test_load_reads_the_run_logs_covariance(tmp_path):
    run = tmp_path / "run.jsonl"
    run.write_text(json.dumps({"t": 3.0, "uav_enu": [0, 0, 40], "means": [[1, 2, 0, 0, 0, 0]],
                               "sigmas_xy": [[3, 4]], "cov_xy": [-5.5]}) + "\n")
    (e,) = load(run).tracks[0]
    assert (e.sigma_x, e.sigma_y, e.cov_xy) == (3, 4, -5.5)
