"""traffic's KalmanSmoother6D baseline, loaded without traffic/__init__; skipped when not installed.

Install with ``pip install --no-deps traffic==2.13 && pip install impunity pyproj``.
"""

from __future__ import annotations

import sys

import numpy as np
import pytest

from experiments.traffic_baseline import KT_TO_MS, available, smooth_flight, straight_flight

pytestmark = pytest.mark.skipif(
    not available(), reason="traffic==2.13, impunity or pyproj not installed"
)

SPEED = 200 * KT_TO_MS  # m/s
MID = slice(20, -20)  # away from the first and last rows, where the fusion weights differ


def _errors(track_deg: float, **kwargs):
    flight = straight_flight(track_deg, **kwargs)
    res = smooth_flight(**flight)
    east, north = np.sin(np.radians(track_deg)), np.cos(np.radians(track_deg))
    # traffic 2.13 fuses the forward estimate at row k with the backward one at row k + 1, so
    # mid-flight the smoothed position is the truth half a second ahead.
    t = flight["time_s"] + 0.5
    dx, dy = res["x"] - SPEED * east * t, res["y"] - SPEED * north * t
    return res, dx * east + dy * north, dx * north - dy * east


@pytest.mark.parametrize("track_deg", [90.0, 0.0])
def test_straight_flight_position_and_direction(track_deg: float) -> None:
    res, along, cross = _errors(track_deg)
    assert res["points_processed"] in (199, 200) and res["seconds"] > 0  # 1 s rows over ~199 s
    # km-sized errors here would mean the kts -> m/s conversion had not happened
    assert np.abs(along[MID]).max() < 8.0
    assert np.abs(cross[MID]).max() < 6.0
    assert np.abs(cross).max() < 12.0
    east, north = np.sin(np.radians(track_deg)), np.cos(np.radians(track_deg))
    vx, vy = np.median(res["vx"]), np.median(res["vy"])
    assert vx * east + vy * north == pytest.approx(SPEED, rel=0.03)
    assert abs(vx * north - vy * east) < 0.5
    assert np.median(res["groundspeed_kt"]) == pytest.approx(200, rel=0.03)
    assert np.median(res["altitude_ft"]) == pytest.approx(10000, abs=10)


def test_loaded_without_traffic_init() -> None:
    assert "traffic" not in sys.modules  # traffic/__init__.py pulls in a large dependency tree


def test_nan_samples_are_interpolated_before_smoothing() -> None:
    flight = straight_flight(90.0, irregular=False)
    flight["groundspeed_kt"][1::3] = np.nan  # a NaN in every 17-row window: R would be NaN
    flight["vertical_rate_fpm"][0] = np.nan  # a NaN in the first row would poison every row
    res = smooth_flight(**flight)
    assert np.isfinite(res["x"]).all() and np.isfinite(res["vx"]).all()
    gaps = smooth_flight(**flight, fill_gaps=False)
    assert np.isnan(gaps["x"]).all()


def test_noise_free_input_makes_r_singular() -> None:
    with pytest.raises(np.linalg.LinAlgError):
        smooth_flight(**straight_flight(90.0, noise=0.0, irregular=False))
