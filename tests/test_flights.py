"""Recorded ADS-B flights in local frames, and the dirty samples through loader and estimators."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torchsvs.datasets import padded_batch, with_prior
from torchsvs.datasets.adsb import sample_files, samples_dir
from torchsvs.datasets.flights import flight_steps
from torchsvs.fitting.defaults import complete_settings
from torchsvs.recipes import Settings, make_estimator, make_model
from torchsvs.step_estimates import centred

try:
    samples_dir()
except ImportError as err:
    pytest.skip(str(err), allow_module_level=True)


def _files(folder: str) -> list:
    return [p for p in sample_files() if p.parent.name == folder]


def test_calibration_flights_are_24_tracks_with_every_row_accounted_for():
    steps, report = flight_steps(_files("calibration"))
    assert report.files == report.track_files == 24
    assert steps.num_tracks == 24
    rows = report.rows
    rows.check()
    assert rows.total == 52154 and not rows.set_aside
    assert rows.prediction == rows.notes["repeated_position"] == 72  # sydney's repeats


def test_reported_velocity_is_rotated_into_each_flight_frame():
    steps, _ = flight_steps(_files("calibration")[:2])
    speed = np.hypot(steps.extra["ve"], steps.extra["vn"])
    reported = steps.extra["groundspeed_kt"] * 1852 / 3600
    ok = np.isfinite(speed)
    # The frame's "up" leans against the aircraft's by the distance over the Earth's radius
    # (0.016 rad at 100 km): a horizontal speed loses up to 1 − cos of that into the frame's
    # vertical.
    assert np.allclose(speed[ok], reported[ok], rtol=1e-3, atol=1e-9)
    assert not np.allclose(speed[ok], reported[ok], rtol=1e-12)


@pytest.mark.parametrize("path", _files("noisy"), ids=lambda p: p.name)
def test_dirty_samples_run_through_loader_and_estimators(path):
    """Spoofing, outliers and time problems: no crash, no NaN where a row was placed, and the
    report says what happened to every row."""
    steps, report = flight_steps([path])
    report.rows.check()
    assert report.rows.total > 0 and steps.num_tracks >= 1
    tracks = padded_batch(steps, np.arange(steps.num_tracks), torch.float64)
    base = complete_settings(Settings(estimator="svss", lag=2), tracks)
    for name in ("ks", "svss"):
        settings = Settings(**{**base.__dict__, "estimator": name})
        est = make_estimator(settings, make_model(settings)).double()
        moved, _ = centred(tracks)
        moved = with_prior(moved, torch.tensor(settings.meas_var).sqrt())
        with torch.no_grad():
            out = est(moved.z, moved.x0, moved.P0, dt=moved.dt)
        assert bool(torch.isfinite(out.mean[moved.mask]).all()), name
