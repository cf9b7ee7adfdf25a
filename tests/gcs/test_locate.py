"""``pmon locate``: a simulated KrakenSDR recording (and its datagrams) of a lawnmower over two
stationary emitters, poses in a tlog (sim/stack/locate_recording.py), located by the app's own filter;
the outputs read back; the mounting offset and the time alignment shown to matter; malformed and
misaligned recordings refused in one line naming the file and the line or time. The firmware's
own logs (DataFlash, ULog) of flight A of tests/firmware/test_ardupilot.py and test_px4.py:
tests/support/locate_check.py."""
from __future__ import annotations

import csv
import json
import shutil

import numpy as np
import pytest

from groundstation.locate import main
from onboard.app.autopilot.pose import Frame
from onboard.config import load_scenario
from sim.stack import locate_recording as rec
from tests.support.geojson_check import assert_geojson_in_area


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    folder = tmp_path_factory.mktemp("rec")
    return rec.write_recording(folder, seed=7)


def _final(csv_path) -> tuple[dict, list]:
    """Each target's final row, and the rows of every tick."""
    with open(csv_path) as f:
        rows = list(csv.DictReader(f))
    return {r["target"]: r for r in rows if r["estimate"] == "final"}, [r for r in rows if r["estimate"] == "tick"]


def _run(args, capsys) -> tuple[int, str, str]:
    code = main([str(a) for a in args])
    out, err = capsys.readouterr()
    assert "Traceback" not in err
    return code, out, err


@pytest.mark.parametrize("bearings", ["mydata", "datagrams"])
def test_locates_both_emitters_within_15_m_and_writes_every_output(recording, bearings, tmp_path, capsys):
    base = tmp_path / "out"
    code, out, err = _run([recording[bearings], recording["tlog"], "--scenario", recording["scenario"],
                           "--out", base], capsys)
    assert code == 0, err
    final, rows = _final(base.with_suffix(".csv"))
    assert len(rows) == 2 * len({r["t_s"] for r in rows}) and len(rows) > 2 * 300  # every tick, both targets
    for j, name in enumerate(("T1", "T2")):
        r = final[name]
        err_m = np.hypot(float(r["east_m"]) - recording["truth_m"][j][0], float(r["north_m"]) - recording["truth_m"][j][1])
        assert err_m <= 15.0, (name, err_m)
        prior_err = np.linalg.norm(recording["prior_m"][j] - recording["truth_m"][j])
        assert err_m < prior_err / 3  # the bearings, not the prior, placed it
        assert float(r["p_stationary"]) > 0.9  # the stationary mode won
        assert 0 < float(r["ellipse95_minor_m"]) <= float(r["ellipse95_major_m"]) < 100
        lat, lon, _ = Frame(*rec.ORIGIN).geodetic_from_enu([float(r["east_m"]), float(r["north_m"]), 0.0])
        assert float(r["lat_deg"]) == pytest.approx(lat, abs=1e-6) and float(r["lon_deg"]) == pytest.approx(lon, abs=1e-6)
    assert "T1: " in out and "T2: " in out and "stationary, fused over the recording" in out
    sc = load_scenario(str(recording["scenario"]))
    doc = assert_geojson_in_area(base.with_suffix(".geojson"), sc)
    kinds = {f["properties"].get("kind") for f in doc["features"]}
    assert {"estimate", "ellipse", "uav_path"} <= kinds
    assert base.with_suffix(".kml").read_text().startswith("<?xml")
    assert base.with_suffix(".png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_the_array_mounting_offset_is_the_configured_one(tmp_path, capsys):
    """Recorded with the array's 0 at 90 degrees right of the nose: located with that offset (the
    scenario's kraken.mount_offset_deg) both emitters are within 15 m; told 0, they are not."""
    cfg = rec.RecordingConfig(mount_offset_deg=90.0)
    r = rec.write_recording(tmp_path / "rec", seed=3, cfg=cfg)
    errors = {}
    for mount in (90.0, 0.0):
        base = tmp_path / f"m{mount:g}"
        code, _, err = _run([r["mydata"], r["tlog"], "--scenario", r["scenario"], "--out", base, "--format", "csv",
                             "--set", f"kraken.mount_offset_deg={mount}"], capsys)
        assert code == 0, err
        final, _ = _final(base.with_suffix(".csv"))
        errors[mount] = [np.hypot(float(final[n]["east_m"]) - t[0], float(final[n]["north_m"]) - t[1])
                         for n, t in zip(("T1", "T2"), r["truth_m"])]
    assert max(errors[90.0]) <= 15.0, errors
    assert min(errors[0.0]) > 50.0, errors


def _partial_tlog(recording, path, keep) -> None:
    poses = rec.lawnmower(rec.RecordingConfig(), np.random.default_rng(7))
    rec.write_tlog(path, [p for p in poses if keep(p.t)], Frame(*rec.ORIGIN))


def test_bearings_outside_the_pose_record_and_in_its_gaps_are_said_in_one_line_each(recording, tmp_path, capsys):
    tlog = tmp_path / "part.tlog"
    _partial_tlog(recording, tlog, lambda t: 100.0 <= t <= 300.0 and not 200.0 <= t <= 230.0)
    code, out, err = _run([recording["mydata"], tlog, "--scenario", recording["scenario"], "--out", tmp_path / "o",
                           "--format", "csv"], capsys)
    assert code == 0, err
    said = [ln for ln in out.splitlines() if ln.startswith("not aligned: ")]
    before = [ln for ln in said if "before the pose record starts" in ln]
    after = [ln for ln in said if "after the pose record ends" in ln]
    gap = [ln for ln in said if "in a gap of the pose record" in ln]
    assert len(before) == len(after) == len(gap) == 1, said
    assert "mydata.csv: 40 frame(s) before" in before[0]  # t 60..99: the first 40 seconds' frames
    assert any("no pose between autopilot t 199.9 and 230.1 s" in ln for ln in said), said
    _, rows = _final(tmp_path / "o.csv")
    assert min(int(r["t_s"]) for r in rows) == 100 and max(int(r["t_s"]) for r in rows) == 300


def test_a_recording_off_the_pose_record_is_one_line_naming_the_times(recording, tmp_path, capsys):
    code, out, err = _run([recording["mydata"], recording["tlog"], "--scenario", recording["scenario"],
                           "--time-offset", "5000", "--out", tmp_path / "o"], capsys)
    assert code == 2 and not out
    assert err.count("\n") == 1 and "no bearing falls on the pose record" in err and "--time-offset" in err
    assert "t 60.0..4" in err  # the log's span, named
    # a clock offset the option corrects: the bearings 2 s late against the poses
    code, out, err = _run([recording["mydata"], recording["tlog"], "--scenario", recording["scenario"],
                           "--time-offset", "2", "--out", tmp_path / "o2", "--format", "csv"], capsys)
    assert code == 0, err
    assert sum("after the pose record ends" in ln for ln in out.splitlines()) == 1


def _corrupt(src, dst, line_no: int, new: str) -> None:
    lines = open(src).read().splitlines(keepends=True)
    lines[line_no - 1] = new
    open(dst, "w").write("".join(lines))


@pytest.mark.parametrize("case", ["nan", "fields", "back_in_time", "datagram", "truncated_json"])
def test_a_malformed_recording_is_one_line_naming_file_and_line(recording, tmp_path, capsys, case):
    src = recording["datagrams"] if case in ("datagram", "truncated_json") else recording["mydata"]
    bad = tmp_path / ("bad.jsonl" if src == recording["datagrams"] else "bad.csv")
    lines = open(src).read().splitlines(keepends=True)
    if case == "nan":
        new = lines[9].replace(lines[9].split(", ")[1], "nan", 1)
    elif case == "fields":
        new = "1790000070218, 12, 3\n"
    elif case == "back_in_time":
        new = lines[0]
    elif case == "datagram":
        new = json.dumps({"v": 1, "t": 70.0, "ch": 0, "bearings_rad": [4.0]}) + "\n"
    else:
        new = lines[9][:20] + "\n"
    _corrupt(src, bad, 10, new)
    code, out, err = _run([bad, recording["tlog"], "--scenario", recording["scenario"], "--out", tmp_path / "o"], capsys)
    assert code == 2 and not out
    assert err.count("\n") == 1 and f"{bad}:10: " in err, err
    reason = {"nan": "not_finite", "fields": "field_count", "back_in_time": "time goes back",
              "datagram": "out_of_range", "truncated_json": "not JSON"}[case]
    assert reason in err


def test_a_bad_pose_log_is_one_line(recording, tmp_path, capsys):
    for poses, says in ((recording["mydata"], "not a pose record"), (tmp_path, "not a regular file"),
                        (tmp_path / "none.tlog", "cannot read")):
        code, out, err = _run([recording["mydata"], poses, "--scenario", recording["scenario"]], capsys)
        assert code == 2 and not out and err.count("\n") == 1 and says in err, err
    fake = tmp_path / "fake.ulg"
    fake.write_bytes(b"ULog\x01\x12\x35\x01" + b"\xff" * 64)
    code, _, err = _run([recording["mydata"], fake, "--scenario", recording["scenario"]], capsys)
    assert code == 2 and err.count("\n") == 1 and str(fake) in err, err
    fake_bin = tmp_path / "fake.bin"
    fake_bin.write_bytes(b"\xa3\x95\x80" + b"\x00" * 200)
    code, _, err = _run([recording["mydata"], fake_bin, "--scenario", recording["scenario"]], capsys)
    assert code == 2 and err.count("\n") == 1 and str(fake_bin) in err, err


def test_a_scenario_without_the_recordings_vfos_is_said(recording, tmp_path, capsys):
    shutil.copy(recording["mydata"], tmp_path / "m.csv")
    code, out, err = _run([tmp_path / "m.csv", recording["tlog"], "--scenario", recording["scenario"],
                           "--set", "kraken.vfos=[{target: T1, freq_hz: 433100000}]", "--out", tmp_path / "o",
                           "--format", "csv"], capsys)
    assert code == 0, err
    assert any("unknown_vfo: 433200000 Hz is no target's VFO" in ln for ln in out.splitlines()), out
    code, out, err = _run([tmp_path / "m.csv", recording["tlog"], "--format", "kml,svg"], capsys)
    assert code == 2 and "'svg'" in err


def test_a_reseed_on_the_last_ticks_keeps_the_converged_estimate_and_is_said(recording, tmp_path, capsys):
    """T1's last six scans 30 degrees off: the filter, surprised, re-seeds its belief at the end;
    the final estimate is still the recording's (the stationary hypothesis fused over it, where
    those bearings are clutter), and the re-seed is said."""
    from onboard.core.bearings import bearing, wrap

    lines = open(recording["datagrams"]).read().splitlines()
    last = max(json.loads(x)["t"] for x in lines)
    poses = {round(p.t, 1): p.pos[:2] for p in rec.lawnmower(rec.RecordingConfig(), np.random.default_rng(7))}
    bad = []
    for x in lines:
        d = json.loads(x)
        if d["ch"] == 0 and d["t"] > last - 6:
            b = bearing(np.asarray(recording["truth_m"][0])[None, :], poses[round(d["t"], 1)])[0]
            d["bearings_rad"] = [float(wrap(b + np.radians(30.0)))]
        bad.append(json.dumps(d))
    src = tmp_path / "late.jsonl"
    src.write_text("\n".join(bad) + "\n")
    code, out, err = _run([src, recording["tlog"], "--scenario", recording["scenario"], "--out", tmp_path / "o",
                           "--format", "csv", "--json"], capsys)
    assert code == 0, err
    doc = json.loads(out)
    t1 = doc["targets"][0]
    assert t1["reseeded_at_s"] and t1["reseeded_at_s"][-1] >= last - 6, t1
    assert t1["final"] == "stationary, fused over the recording"
    assert np.hypot(t1["east_m"] - recording["truth_m"][0][0], t1["north_m"] - recording["truth_m"][0][1]) <= 15.0
    e = np.array([t1["east_m"], t1["north_m"]]) - recording["truth_m"][0]
    assert e @ np.linalg.solve(t1["cov_en_m2"], e) < 13.8  # chi-square(2)'s 99.9 % quantile
