"""onboard/core/doa.py on plain arrays: array angles to bearings, spectrum peaks, the convention a
main DoA is written in, the clutter rate the peaks show."""
from __future__ import annotations

import math

import numpy as np
import pytest

from onboard.core import doa


def lobes(centres_deg, heights_db, width_deg=4.0, floor_db=-40.0, ripple_db=0.0, rng=None):
    """A KrakenSDR-like dB spectrum: Gaussian lobes (linear power) over a noise floor, normalised
    to its maximum, floored at -100 dB and shifted up by its minimum (as DOA_plot_util and the
    writer do)."""
    theta = np.arange(360.0)
    p = np.full(360, 10 ** (floor_db / 10))
    if rng is not None and ripple_db:  # smooth, as an estimator's output over a 5-element array is
        k = np.arange(1, 6)[:, None]
        wave = (rng.normal(0, 1, (5, 1)) * np.cos(np.radians(theta) * k + rng.uniform(0, 2 * np.pi, (5, 1)))).sum(0)
        p = p * 10 ** (ripple_db * wave / np.abs(wave).max() / 10)
    for c, h in zip(centres_deg, heights_db):
        d = doa.circular_distance_deg(theta, c)
        p = p + 10 ** (h / 10) * np.exp(-0.5 * (d / width_deg) ** 2)
    db = np.maximum(10 * np.log10(p / p.max()), -100.0)
    return np.round(db - db.min(), 2)


def test_unit_circle_angles_turn_counterclockwise_from_the_array_reference():
    # the array's reference on the nose of a vehicle heading north: theta 90 (counterclockwise)
    # is west, 270 east, 0 ahead, 180 behind
    for theta, bearing_deg in ((0.0, 0.0), (90.0, -90.0), (270.0, 90.0), (180.0, 180.0), (45.0, -45.0)):
        assert math.degrees(doa.bearing_from_array(theta, 0.0)) == pytest.approx(bearing_deg)
    # heading east and the reference 30 degrees right of the nose: theta 0 is 120 degrees
    assert math.degrees(doa.bearing_from_array(0.0, math.radians(90), math.radians(30))) == pytest.approx(120)
    assert math.degrees(doa.bearing_from_array(10.0, math.radians(90), math.radians(30))) == pytest.approx(110)
    # bearings on (-pi, pi]
    assert doa.bearing_from_array(180.0, 0.0) == pytest.approx(math.pi)
    assert doa.bearing_from_array(180.0 + 1e-9, 0.0) > 3.14
    b = np.linspace(-math.pi + 1e-6, math.pi, 50)
    for h, m in ((0.3, 0.0), (-2.0, 1.1), (3.1, -0.4)):
        theta = doa.array_from_bearing(b, h, m)
        assert ((theta >= 0) & (theta < 360)).all()
        assert np.allclose(doa.bearing_from_array(theta, h, m), b)


def test_compass_is_360_minus_unit_circle():
    assert doa.unit_circle_deg(12.0, "compass") == pytest.approx(348.0)
    assert doa.unit_circle_deg(12.0, "unit_circle") == pytest.approx(12.0)
    with pytest.raises(ValueError, match="convention"):
        doa.unit_circle_deg(1.0, "math")


def test_peaks_are_found_between_bins_and_on_both_sides_of_zero(rng):
    s = lobes([120.3, 240.7, 359.6], [0.0, -3.0, -6.0], rng=rng, ripple_db=1.0)
    angles, heights = doa.spectrum_peaks(s, floor_db=20.0, prominence_db=3.0, max_peaks=8)
    assert len(angles) == 3, angles
    # strongest first, each within 0.1 degree of its lobe (the parabola through 3 dB bins of a
    # Gaussian lobe is exact up to the floor's ripple and the 0.01 dB rounding)
    assert doa.circular_distance_deg(angles, [120.3, 240.7, 359.6]).max() < 0.1, angles
    assert heights[0] == 0.0 and heights[1] == pytest.approx(-3.0, abs=0.1) and heights[2] == pytest.approx(-6, abs=0.1)


def test_peak_threshold_prominence_and_count(rng):
    s = lobes([100.0, 220.0], [0.0, -15.0], rng=rng, ripple_db=2.5)
    # the weak lobe is 15 dB down: outside a 12 dB floor, inside a 20 dB one
    assert len(doa.spectrum_peaks(s, 12.0, 3.0, 8)[0]) == 1
    assert len(doa.spectrum_peaks(s, 20.0, 3.0, 8)[0]) == 2
    # the floor's ripple makes local maxima; none is 3 dB prominent
    from scipy.signal import find_peaks
    assert len(find_peaks(s)[0]) > 2
    assert len(doa.spectrum_peaks(s, 100.0, 3.0, 100)[0]) == 2
    # at most max_peaks, the strongest
    angles, _ = doa.spectrum_peaks(s, 20.0, 3.0, 1)
    assert len(angles) == 1 and abs(angles[0] - 100.0) < 0.2


def test_no_peaks_in_flat_or_corrupt_spectra():
    assert len(doa.spectrum_peaks(np.zeros(360), 10, 3, 8)[0]) == 0
    bad = lobes([50.0], [0.0])
    bad = bad.astype(float)
    bad[3] = np.nan
    assert len(doa.spectrum_peaks(bad, 10, 3, 8)[0]) == 0
    assert len(doa.spectrum_peaks(np.zeros(2), 10, 3, 8)[0]) == 0


def test_the_convention_of_a_main_doa_is_read_from_its_spectrum():
    s = lobes([77.0], [0.0])
    assert doa.detect_convention(77.0, s) == "unit_circle"
    assert doa.detect_convention(283.0, s) == "compass"  # 360 - 77
    assert doa.detect_convention(120.0, s) is None
    s0 = lobes([0.0], [0.0])
    # at 0 (and 180) the two are the same angle: nothing to learn
    assert doa.detect_convention(0.0, s0) is None and doa.detect_convention(360.0, s0) is None
    s1 = lobes([359.0], [0.0])
    assert doa.detect_convention(1.0, s1) == "compass" and doa.detect_convention(359.0, s1) == "unit_circle"


def test_clutter_rate_follows_the_counts():
    assert doa.clutter_rate([], 0.95, 0.1, 10.0) == 0.1
    assert doa.clutter_rate([1] * 20, 0.95, 0.1, 10.0) == 0.1  # only the target: the floor
    assert doa.clutter_rate([3, 2, 4, 3], 0.9, 0.1, 10.0) == pytest.approx(2.1)
    assert doa.clutter_rate([60] * 5, 0.9, 0.1, 10.0) == 10.0
