"""Cursor-on-Target as a TAK client reads it (the TAK tests and bench/tak_server.py)."""
from __future__ import annotations

import math

import numpy as np

SIGMA = (40.0, 25.0, 300.0)  # sigma_x, sigma_y, cov_xy of sim.stack.gcs_fake_vehicle.target_values


def one_sigma_radius_m(sx, sy, cxy) -> float:
    """The semi-major axis of the 1-sigma ellipse (the live view's ellipse, groundstation/
    static/view.js): the square root of the covariance's largest eigenvalue."""
    return float(math.sqrt(np.linalg.eigvalsh(np.array([[sx * sx, cxy], [cxy, sy * sy]])).max()))


def split_xml(stream: bytes) -> tuple[list[bytes], bytes]:
    out = []
    while b"</event>" in stream:
        end = stream.index(b"</event>") + len(b"</event>")
        start = stream.find(b"<event")
        out.append(stream[start:end])
        stream = stream[end:]
    return out, stream
