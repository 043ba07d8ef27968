"""The noise reading checked against the second differences two reports apart
(:mod:`torchsvs.datasets.noise_lags`): noise and white acceleration read 1 at any report times,
motion between sparse reports (a van's corners and stops) reads far below it, and the run then
neither smooths that motion away nor stays silent."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import torch

from tests.conftest import simulate_cv
from torchsvs.datasets import estimate_noise
from torchsvs.datasets.noise_lags import LAG_ERRORS, lag_reading, motion_checked
from torchsvs.recipes import Settings


def _reference(z: np.ndarray, t: np.ndarray, var: np.ndarray) -> tuple[float, float]:
    """Σ u_i u_{i+2} c_i2 c_{i+2,0} / r over Σ (c_i2 c_{i+2,0})², and the same of
    u_i (u_{i+2} − u_{i+3}), written from the three-point residual (Gasser, Sroka &
    Jennen-Steinmetz 1986) track by track, axis by axis, in float64: pairs whose residuals are
    within 3 standard deviations (u_{i+3} too for the second) and none of u_{i-2} .. u_{i+5}
    beyond 4.5, the products over the truncated Gaussian's second moment squared."""
    kappa = 1.0 - 2 * 3.0 * math.exp(-4.5) / math.sqrt(2 * math.pi) / math.erf(3 / math.sqrt(2))
    sums = np.zeros(4)
    for b in range(z.shape[0]):
        for j in range(z.shape[2]):
            seen = np.isfinite(z[b, :, j])
            x, s = z[b, seen, j], t[b, seen]
            c, u = [], []
            for i in range(len(x) - 2):
                h1, h2 = s[i + 1] - s[i], s[i + 2] - s[i + 1]
                w = np.array([1 / (h1 * (h1 + h2)), -1 / (h1 * h2), 1 / (h2 * (h1 + h2))])
                w /= np.linalg.norm(w)
                c.append(w)
                u.append(w @ x[i : i + 3])
            n = np.abs(np.array(u)) / math.sqrt(var[j])
            for i in range(len(u) - 2):
                if n[i] > 3 or n[i + 2] > 3 or (n[max(i - 2, 0) : i + 5] > 4.5).any():
                    continue
                a = c[i][2] * c[i + 2][0]
                sums[:2] += (u[i] * u[i + 2] * a / var[j] / kappa**2, a * a)
                if i + 3 < len(u) and n[i + 3] <= 3 and not (n[i + 5 : i + 6] > 4.5).any():
                    third = u[i] * u[i + 3] * a / var[j] / kappa**2
                    sums[2:] += (u[i] * u[i + 2] * a / var[j] / kappa**2 - third, a * a)
    return sums[0] / sums[1], sums[2] / sums[3]


def test_lag_reading_is_the_numpy_references_with_gaps_and_irregular_times():
    gen = torch.Generator().manual_seed(3)
    B, T = 6, 60
    dt = 1.0 + 9.0 * torch.rand(B, T, generator=gen, dtype=torch.float64)
    z = 20.0 * torch.randn(B, T, 2, generator=gen, dtype=torch.float64)
    z[1, 10:14] = float("nan")  # a gap: the stencils run over the observed positions
    z[4, 30:, 1] = float("nan")
    var = torch.tensor([400.0, 150.0], dtype=torch.float64)  # (axis 1 trimmed: 20 m read as 12)
    lag = lag_reading(z, dt, var)
    assert lag is not None
    t = torch.cumsum(dt, 1).numpy()
    ratio, beyond = _reference(z.numpy(), t, var.numpy())
    assert abs(lag.ratio - ratio) < 1e-9 and abs(lag.beyond - beyond) < 1e-9


def test_noise_and_white_acceleration_read_one_at_irregular_times():
    """E[u_i u_{i+2}] is the noise's alone: white acceleration adds nothing (the stencils'
    Peano kernels do not overlap), whatever its level against the noise's."""
    for q, seed in ((0.01, 0), (1.0, 1)):
        gen = torch.Generator().manual_seed(seed)
        B, T, sigma = 60, 150, 10.0
        dt = 1.0 + 9.0 * torch.rand(B, T, generator=gen, dtype=torch.float64)
        _, z = simulate_cv(dt, q, sigma**2, gen, speed=10.0)
        lag = lag_reading(z, dt, torch.full((2,), sigma**2, dtype=torch.float64))
        assert lag is not None and lag.se < 0.25
        assert abs(lag.ratio - 1.0) < 3 * lag.se, (q, lag)
        noise = estimate_noise(z, dt)
        assert motion_checked(noise, z, dt) is noise  # nothing to say where the model fits


def _vans(seed: int = 0, vans: int = 120, reports: int = 80, sigma: float = 5.0):
    """Vans on a street grid reporting every 60 s: between two reports a van drove one to a
    few blocks along a street, turned at some corners, or stood at a light or a delivery."""
    rng = np.random.default_rng(seed)
    rows = []
    for v in range(vans):
        x = y = 0.0
        for k in range(reports):
            if rng.random() > 0.3:  # moving: a run of blocks along one street, then a turn
                dx, dy = rng.choice([-1, 1]) * rng.uniform(150, 600), 0.0
                if rng.random() < 0.5:
                    dx, dy = dy, dx
                x, y = x + dx, y + dy
            rows.append((f"van{v}", 60.0 * k, x, y))
    truth = pd.DataFrame(rows, columns=["track_id", "time", "x", "y"])
    frame = truth.copy()
    frame[["x", "y"]] += rng.normal(0.0, sigma, (len(frame), 2))
    return frame, truth[["x", "y"]].to_numpy()


def test_motion_between_sparse_reports_is_not_smoothed_away_without_a_word(tmp_path):
    """Positions 60 s apart whose changes of speed and direction read as 150 m of noise for a
    5 m sensor: the Kalman smoother ran at that reading at 8 times the measurements' error and
    said nothing. The second differences two reports apart covary negatively (a stop follows
    a start), the reading's uncertainty takes that in, the run takes the low end, and says
    why."""
    from torchsvs.datasets import Columns
    from torchsvs.tracking import track_file

    frame, truth = _vans()
    source, target = tmp_path / "vans.csv", tmp_path / "out.csv"
    frame.to_csv(source, index=False)
    run = track_file(source, target, Settings("ks"), columns=Columns(), progress=False)
    lowered = run.settings.noise_lowered_from
    assert lowered is not None and min(lowered) > 50.0  # (the reading: motion)
    lag = run.settings.noise_lag
    assert lag is not None and max(lag) < 1.0 - LAG_ERRORS * 0.1  # (both axes: one group)
    assert any("mostly motion between reports" in w for w in run.warnings)
    found = run.accuracy  # (no point estimate at a noise chosen low: the range stands)
    assert found is not None and found.noise_unknown and "unknown, within" in found.line()
    assert found.interval[0] < 7.0 < found.interval[1] < 21.0  # (ends at the smallest changes')
    assert run.settings.noise_ceiling is not None
    summary = run.summary_json()
    assert math.isnan(summary["estimated_position_rmse"])
    assert summary["estimated_position_rmse_interval"] == list(found.interval)
    assert all(math.isnan(t["estimated_position_rmse"]) for t in summary["tracks"].values())
    out = pd.read_csv(target)
    error = ((out[["x", "y"]].to_numpy() - truth) ** 2).sum(1).mean() ** 0.5
    raw = ((frame[["x", "y"]].to_numpy() - truth) ** 2).sum(1).mean() ** 0.5
    assert error < 1.1 * raw, (error, raw)


def test_ships_by_satellite_ais_are_not_smoothed_into_their_turns(tmp_path):
    """Ships reported 5-60 min apart (``experiments.vehicle_sets``' ``satship``), σ 10 m: the
    course changes between reports read as 400 m of noise with an uncertainty of its own, so the
    lag reading is not surely below it, but surely below a quarter of it (below zero, which no
    noise makes). Before, the Kalman smoother came out at several times the measurements'
    error (4.9 on 5,000 rows)."""
    from experiments.recorded_sets import build_sets
    from torchsvs.datasets import Columns
    from torchsvs.tracking import track_file

    (ships,) = build_sets(["satship"], rows=3000, sigmas=[10.0])
    source, target = ships.write(tmp_path)[0], tmp_path / "out.csv"
    run = track_file(source, target, Settings("ks"), columns=Columns(), progress=False)
    assert run.settings.noise_lag is not None and max(run.settings.noise_lag) < 0
    out = pd.read_csv(target).merge(ships.truth.rows, on=["track_id", "time"])
    raw = ships.measurements.merge(ships.truth.rows, on=["track_id", "time"])
    error = ((out.x_x - out.x_y) ** 2 + (out.y_x - out.y_y) ** 2).mean() ** 0.5
    measured = ((raw.x_x - raw.x_y) ** 2 + (raw.y_x - raw.y_y) ** 2).mean() ** 0.5
    assert error < 1.05 * measured, (error, measured)


def test_the_altitude_of_3d_positions_is_checked_apart(tmp_path):
    """Vans at 60 s whose altitude is a flat road's with a 3 m sensor: the horizontal reading
    is motion and is lowered; the altitude's is noise and stays (pooled, it was lowered too and
    passed through its noise)."""
    from torchsvs.datasets import Columns
    from torchsvs.tracking import track_file

    frame, _ = _vans()
    frame["z"] = 30.0 + np.random.default_rng(1).normal(0.0, 3.0, len(frame))
    source = tmp_path / "vans.csv"
    frame.to_csv(source, index=False)
    run = track_file(
        source, tmp_path / "out.csv", Settings("ks"), columns=Columns(), progress=False
    )
    lowered, ran = run.settings.noise_lowered_from, run.settings.meas_var
    assert lowered is not None and ran is not None
    assert max(ran[0] / lowered[0] ** 2, ran[1] / lowered[1] ** 2) < 1e-3
    assert abs(ran[2] ** 0.5 / 3.0 - 1.0) < 0.1
    lag = run.settings.noise_lag
    assert lag is not None and math.isnan(lag[2])
    # (the altitude's error estimate stands: its reading is not contradicted)
    parts = run.axes_parts()
    assert parts["horizontal"].noise_unknown and not parts["vertical"].noise_unknown
    assert "vertical unknown" not in run.summary() and "horizontal unknown" in run.summary()
