"""The noise reading checked against the positions' smallest changes
(:mod:`torchsvs.datasets.noise_ceiling`): motion only spreads the residuals (Anderson's
inequality), so noise whose level or shape differs from track to track or turns along a track
never reads above the bound, while buses whose stops and straight runs read as noise do, and
the run then neither smooths their motion away nor stays silent."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest
import torch
from scipy.stats import chi  # installed with the dev extras (filterpy, pykalman)

from tests.conftest import simulate_cv
from torchsvs.datasets import estimate_noise
from torchsvs.datasets.noise_ceiling import (
    LEAST_BELOW,
    ON_LINE,
    SHARES,
    WINDOW,
    _noise_radius,
    ceiling_reading,
)
from torchsvs.datasets.noise_lags import CEILING_RATIO, motion_checked
from torchsvs.datasets.track_noise import read_track_noise
from torchsvs.recipes import Settings


def _residuals(x: np.ndarray, t: np.ndarray, order: int) -> list[np.ndarray]:
    """Each divided difference of ``order`` over successive positions of one axis, as unit
    weights (``w_j = 1 / Π_{l≠j} (t_j − t_l)`` over their norm) and the residual they make."""
    out = []
    for i in range(len(x) - order):
        s = t[i : i + order + 1]
        w = np.array(
            [
                1 / np.prod([s[j] - s[k] for k in range(order + 1) if k != j])
                for j in range(order + 1)
            ]
        )
        out.append(w @ x[i : i + order + 1] / np.linalg.norm(w))
    return out


def _ratio(radius: np.ndarray, m: int) -> tuple[float, float] | None:
    """χ's quantile (SciPy's, m degrees of freedom) over the radius's, the largest share's."""
    found = [
        (chi.ppf(q, m) / np.quantile(radius, q), q)
        for q in SHARES
        if q * len(radius) >= LEAST_BELOW
    ]
    return max(found) if found else None


def _reference(z: np.ndarray, t: np.ndarray, var: np.ndarray, own: np.ndarray) -> float:
    """:func:`ceiling_reading` written from its definition, track by track in float64: the
    residuals of orders 1 and 2 of every axis over the reading's σ; their radius's smallest
    shares against χ's (the file's noise) and the same whitened by the covariance of the
    core (every axis within 3 σ of the track's own level) of the residuals of orders 2-4 that
    begin within 16 observed steps of it, over the truncated Gaussian's second moment; the
    lower of the two, the highest over the orders."""
    B, _, m = z.shape
    z = np.where(np.isnan(z).any(-1, keepdims=True), np.nan, z)
    kappa = 1.0 - 2 * 3.0 * math.exp(-4.5) / math.sqrt(2 * math.pi) / math.erf(3 / math.sqrt(2))
    sigma = np.sqrt(var)
    per = {}  # order -> (track, first, [m] residual)
    for b in range(B):
        seen = np.isfinite(z[b]).all(1)
        x, s = z[b, seen], t[b, seen]
        for order in (1, 2, 3, 4):
            columns = [_residuals(x[:, a], s, order) for a in range(m)]
            for i, u in enumerate(zip(*columns, strict=True)):
                per.setdefault(order, []).append((b, i, np.array(u) / sigma))
    core = [
        (b, i, u)
        for order in (2, 3, 4)
        for b, i, u in per[order]
        if (np.abs(u) <= 3 * own[b]).all()
    ]
    best = -math.inf
    for order in (1, 2):
        kept = [(b, i, u) for b, i, u in per[order] if np.linalg.norm(u) > ON_LINE]
        pooled = _ratio(np.array([np.linalg.norm(u) for _, _, u in kept]), m)
        local = []
        for b, i, u in kept:
            near = [v for c, j, v in core if c == b and i - WINDOW <= j <= i + WINDOW]
            if len(near) >= 10 * m:
                cov = sum(np.outer(v, v) for v in near) / len(near) / kappa
                u = np.linalg.solve(np.linalg.cholesky(cov), u)
            local.append(np.linalg.norm(u))
        found = _ratio(np.array(local), m)
        if pooled is not None and found is not None:
            best = max(best, min(pooled, found)[0])
    return best


def test_ceiling_reading_is_the_numpy_references_with_gaps_and_irregular_times():
    gen = torch.Generator().manual_seed(5)
    B, T = 12, 70
    dt = 1.0 + 9.0 * torch.rand(B, T, generator=gen, dtype=torch.float64)
    _, z = simulate_cv(dt, 0.5, 25.0, gen, speed=5.0)
    z[::2] *= 1.5  # (tracks at their own levels)
    z[1, 10:14] = float("nan")  # a gap: the stencils run over the observed positions
    z[3, 40:43] = z[3, 39]  # a still stretch: its first differences are left out (on a line)
    z[5, 9:] = float("nan")  # a short track: too few residuals about each to whiten them
    z[7, 20:25, 1] = float("nan")  # (positions with an axis missing are left out whole)
    var = torch.tensor([30.0, 20.0], dtype=torch.float64)
    found = ceiling_reading(z, dt, var)
    assert found is not None
    own = read_track_noise(z, dt, var.tolist()).log_ratio.exp().nan_to_num(1.0)
    t = torch.cumsum(dt, 1).numpy()
    expected = _reference(z.numpy(), t, var.numpy(), own.numpy())
    assert abs(found.ratio - expected) < 1e-9 * expected, (found, expected)


def _cv(seed: int, B: int = 80, T: int = 120, q: float = 0.1, sigma: float = 10.0):
    gen = torch.Generator().manual_seed(seed)
    dt = 1.0 + 9.0 * torch.rand(B, T, generator=gen, dtype=torch.float64)
    truth, z = simulate_cv(dt, q, sigma**2, gen, speed=10.0)
    return dt, truth[..., [0, 2]], z - truth[..., [0, 2]], gen


def _checked(z: torch.Tensor, dt: torch.Tensor) -> float:
    noise = estimate_noise(z, dt)
    found = ceiling_reading(z, dt, noise.meas_var)
    assert found is not None
    if found.ratio <= CEILING_RATIO:
        assert motion_checked(noise, z, dt) is noise
    return found.ratio


def test_noise_of_every_shape_is_not_taken_for_motion():
    """White noise on the model's own tracks, each track at its own level (a third to three
    times), heavy-tailed (Student's t, 3 degrees of freedom), with a fifth of the reports
    repeated (stale, on a line), and a radar's (range and cross-range errors 1:10, turning with
    the bearing along each track; read on the file's axes alone, 1.8) never read above the
    bound; two sensors interleaved row by row do, and the lag reading keeps the check off."""
    dt, path, noise, gen = _cv(0)
    assert _checked(path + noise, dt) < 1.15
    level = torch.exp(math.log(3.0) * (2 * torch.rand(noise.shape[0], 1, 1, generator=gen) - 1))
    assert _checked(path + level * noise, dt) < 1.15
    t3 = torch.distributions.StudentT(3.0).sample(noise.shape).double() * 10.0
    assert _checked(path + t3, dt) < 1.25
    stale = path + noise
    repeat = torch.rand(stale.shape[:2], generator=gen) < 0.2
    repeat[:, 0] = False
    for k in range(1, stale.shape[1]):  # (a stale report repeats the last one)
        stale[:, k] = torch.where(repeat[:, k, None], stale[:, k - 1], stale[:, k])
    assert _checked(stale, dt) < 1.25
    # two sensors interleaved row by row (half the rows at 80 m, half at 10 m): more residuals
    # near 0 than one level makes, but the lag reading says noise, and the check stays
    level = torch.where(torch.rand(noise.shape[:2], generator=gen) < 0.5, 8.0, 1.0)
    mixed = path + level.unsqueeze(-1).double() * noise
    read = estimate_noise(mixed, dt)
    found = ceiling_reading(mixed, dt, read.meas_var)
    assert found is not None and found.ratio > CEILING_RATIO
    assert motion_checked(read, mixed, dt) is read
    bearing = torch.atan2(path[..., 1], path[..., 0] + 200.0)  # (the radar beside the tracks)
    rng, cross = (
        2.0 * torch.randn(path.shape[:2], generator=gen),
        20.0 * torch.randn(path.shape[:2], generator=gen),
    )
    radar = torch.stack(
        [rng * bearing.cos() - cross * bearing.sin(), rng * bearing.sin() + cross * bearing.cos()],
        -1,
    )
    assert _checked(path.double() + radar.double(), dt) < 1.3


def test_buses_smallest_changes_contradict_their_reading(tmp_path):
    """City buses every 30 s with a 5 m sensor (``experiments.bus_routes``): their runs, stops
    and corners read as 40-50 m of noise, the check two reports apart does not see it, and the
    Kalman smoother at the reading was 6 times the measurements' error without a word. The
    stops and straight runs are stiller than such noise allows: the run keeps to the
    measurements, says why, and its error estimate is a range whose high end is the bound's."""
    from experiments.recorded_sets import build_sets
    from torchsvs.datasets import Columns
    from torchsvs.tracking import track_file

    (buses,) = build_sets(["bus"], rows=3000, sigmas=[5.0])
    source, target = buses.write(tmp_path)[0], tmp_path / "out.csv"
    run = track_file(source, target, Settings("ks"), columns=Columns(), progress=False)
    settings = run.settings
    assert settings.noise_lag is None and settings.noise_ceiling is not None
    lowered = settings.noise_lowered_from
    assert lowered is not None and min(lowered) > 30.0  # (the reading: motion)
    assert max(settings.noise_ceiling) < min(lowered) / CEILING_RATIO
    assert any("smallest changes are small" in w for w in run.warnings)
    out = pd.read_csv(target).merge(buses.truth.rows, on=["track_id", "time"])
    raw = buses.measurements.merge(buses.truth.rows, on=["track_id", "time"])
    error = ((out.x_x - out.x_y) ** 2 + (out.y_x - out.y_y) ** 2).mean() ** 0.5
    measured = ((raw.x_x - raw.x_y) ** 2 + (raw.y_x - raw.y_y) ** 2).mean() ** 0.5
    assert error < 1.02 * measured, (error, measured)
    found = run.accuracy
    assert found is not None and found.noise_unknown
    assert found.interval[0] < error < found.interval[1] < 4 * measured, found.interval
    summary = run.summary_json()
    assert math.isnan(summary["estimated_position_rmse"])
    # the sensor's σ given: the reading, motion, does not make it "well below the data", and
    # the error estimate is made at it (it was made at the reading: 61.7 m for a true 7.0 m)
    given = Settings("ks", meas_var=[25.0, 25.0], noise="given")
    run = track_file(source, target, given, columns=Columns(), progress=False)
    assert run.settings.noise_below_data is None
    out = pd.read_csv(target).merge(buses.truth.rows, on=["track_id", "time"])
    error = ((out.x_x - out.x_y) ** 2 + (out.y_x - out.y_y) ** 2).mean() ** 0.5
    found = run.accuracy
    assert found is not None and abs(found.estimated_rmse / error - 1.0) < 0.1, (found, error)


@pytest.mark.parametrize("m", [1, 3])
def test_one_axis_and_three_read_their_own_chi(m):
    """An altitude alone (one axis) and three axes together: white noise reads within its
    sampling error of 1 (χ with 1 and 3 degrees of freedom)."""
    gen = torch.Generator().manual_seed(m)
    z = 10.0 * torch.randn(200, 60, m, generator=gen, dtype=torch.float64)
    dt = torch.ones(200, 60, dtype=torch.float64)
    found = ceiling_reading(z, dt, torch.full((m,), 100.0, dtype=torch.float64))
    assert found is not None and 0.85 < found.ratio < 1.15, found


def test_a_noise_free_altitude_costs_the_horizontal_estimate_nothing(tmp_path):
    """ADS-B's barometric altitude comes in 25 ft steps, level between them: its noise reads at
    float rounding (1e-13 m), which the lag check contradicts, and the whole run's error
    estimate was unknown for it, with a warning of motion between reports. Its error cannot be
    read off it, so its part stays unknown, but the horizontal part, whose reading stands,
    keeps its point estimate and its noise, and the warning says what the altitude is."""
    from torchsvs.datasets import Columns
    from torchsvs.tracking import track_file

    dt, path, noise, gen = _cv(2)
    climb = torch.cumsum(dt, 1) * (5.0 * torch.rand(dt.shape[0], 1, generator=gen) - 2.5)
    altitude = torch.round((3000.0 + climb.clamp(-300.0, 300.0)) / 7.62) * 7.62
    z = (path + noise).numpy()
    t = torch.cumsum(dt, 1).numpy()
    frame = pd.DataFrame(
        {
            "track_id": np.repeat(np.arange(z.shape[0]), z.shape[1]),
            "time": t.reshape(-1),
            "x": z[..., 0].reshape(-1),
            "y": z[..., 1].reshape(-1),
            "z": altitude.numpy().reshape(-1),
        }
    )
    source = tmp_path / "flights.csv"
    frame.to_csv(source, index=False)
    run = track_file(
        source, tmp_path / "out.csv", Settings("ks"), columns=Columns(), progress=False
    )
    lowered, ran = run.settings.noise_lowered_from, run.settings.meas_var
    assert lowered is not None and ran is not None and lowered[2] < 1e-9
    assert ran[:2] == pytest.approx([v * v for v in lowered[:2]])  # (the horizontal reading stands)
    parts = run.axes_parts()
    assert not parts["horizontal"].noise_unknown and parts["vertical"].noise_unknown
    assert any("read no noise on axes [2]" in w for w in run.warnings)
    assert not any("mostly motion" in w for w in run.warnings)


def test_the_noise_radius_is_chis_quantile():
    """The radius unit white noise falls within with probability q: χ's quantile (SciPy's) on
    one to four axes (a Wilson-Hilferty approximation was 31% low on three at q = 0.005)."""
    for q in SHARES + (0.5,):
        for m in (1, 2, 3, 4):
            assert _noise_radius(q, m) == pytest.approx(chi.ppf(q, m), rel=1e-9)
