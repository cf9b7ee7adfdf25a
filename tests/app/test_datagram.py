"""DF datagram parsing: every malformed input is refused with its reason; good ones round-trip."""
import json
import math

import numpy as np
import pytest

from onboard.app.df import datagram as dg


def raw(**kw):
    obj = {"v": 1, "t": 10.0, "ch": 0, "bearings_rad": [0.5, -3.0]}
    obj.update(kw)
    return json.dumps({k: v for k, v in obj.items() if v is not ...}).encode()


def test_round_trip():
    d = dg.parse(dg.encode(12.5, 3, [0.1, math.pi], seq=7), n_channels=4, now_s=12.6)
    assert (d.t, d.ch, d.seq) == (12.5, 3, 7)
    assert np.array_equal(d.bearings, [0.1, math.pi])


@pytest.mark.parametrize("data, reason", [
    (b"x" * 5000, "too_large"),
    (b"\xff\xfe", "not_utf8"),
    (b"{not json", "not_json"),
    (b"[1, 2]", "not_object"),
    (raw(v=2), "bad_version"),
    (raw(t=...), "missing_field"),
    (raw(extra=1), "unknown_field"),
    (raw(t="10"), "bad_type"),
    (raw(ch=1.0), "bad_type"),
    (raw(bearings_rad=[0.1, True]), "bad_type"),
    (b'{"v":1,"t":NaN,"ch":0,"bearings_rad":[]}', "not_finite"),
    (b'{"v":1,"t":1,"ch":0,"bearings_rad":[Infinity]}', "not_finite"),
    (raw(bearings_rad=[-math.pi]), "out_of_range"),
    (raw(bearings_rad=[3.2]), "out_of_range"),
    (raw(t=-1.0), "out_of_range"),
    (raw(ch=4), "unknown_channel"),
    (raw(ch=-1), "unknown_channel"),
    (raw(bearings_rad=[0.0] * 65), "too_many_bearings"),
    (raw(t=13.0), "future_time"),
    (raw(t=4.0), "stale_time"),
    # integers too large for a float: float() and math.isfinite() raise OverflowError on these
    (raw(t=10 ** 400), "out_of_range"),
    (raw(t=-10 ** 400), "out_of_range"),
    (raw(bearings_rad=[0.1, 10 ** 400]), "out_of_range"),
    (raw(bearings_rad=[-10 ** 309]), "out_of_range"),
    (raw(v=10 ** 400), "bad_version"),
    (raw(ch=10 ** 400), "unknown_channel"),
    (raw(seq=10 ** 400), "out_of_range"),
])
def test_bad_datagrams_are_refused_with_their_reason(data, reason):
    with pytest.raises(dg.DatagramError) as e:
        dg.parse(data, n_channels=4, now_s=10.5)
    assert e.value.reason == reason
    assert len(str(e.value)) < 120, "a huge value is shown cut, not whole"


def test_buffer_counts_rejections_and_keeps_the_first_of_duplicates():
    buf = dg.ScanBuffer(2)
    buf.offer(raw(ch=0, bearings_rad=[0.1]), 10.0)
    with pytest.raises(dg.DatagramError):
        buf.offer(raw(ch=0, bearings_rad=[0.2]), 10.0)
    with pytest.raises(dg.DatagramError):
        buf.offer(b"garbage", 10.0)
    assert not buf.complete(10.0)
    buf.offer(raw(ch=1, bearings_rad=[]), 10.0)
    assert buf.complete(10.0)
    assert buf.accepted == 2 and buf.rejected["duplicate"] == 1 and buf.rejected["not_json"] == 1
    (t, scan), = buf.take_until(10.0)
    assert scan[0].bearings.tolist() == [0.1]  # the first one was kept
    with pytest.raises(dg.DatagramError) as e:  # a scan for a tick already run is stale
        buf.offer(raw(ch=1, t=9.5), 10.0)
    assert e.value.reason == "stale_time"
