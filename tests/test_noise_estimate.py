"""The noise levels read off the data: ``estimate_noise`` (measurement noise, robust to
maneuvers, with a standard error) and ``smoother_q`` (the Kalman smoother's q).

Tracks come from ``experiments/noise_estimate.py`` (seeded simulations: coordinated turns, ships,
fast aircraft at long scans, irregular times, the project's random maneuvers, the CV model).
Statistical bounds: any estimator of σ from ``n`` Gaussian samples per axis has a standard error
of at least ``σ/√(2n)`` (Cramér-Rao, known mean); the bounds below are checked to be several of
the estimator's own standard errors wide, so a failure is not chance.
"""

from __future__ import annotations

import math
from dataclasses import replace

import pytest
import torch

import torchsvs as ts
from experiments.noise_estimate import (
    KINDS,
    Simulated,
    best_grid_q,
    drop_rows,
    ks_rmse,
    raw_rmse,
    simulate,
)
from tests.conftest import assert_close, simulate_cv
from torchsvs.datasets import estimate_noise, noise_estimate, track_noise, two_point_prior
from torchsvs.datasets.differences import difference_residuals
from torchsvs.fitting.noise import Q_FACTORS, q_curves, smoother_q, track_q_factors

#: The specification: within 20% of the true σ.
WITHIN = 0.2
#: ... and that bound at least this many standard errors wide (not a chance failure).
SE_MARGIN = 4.0


def small(name: str, tracks: int = 4) -> object:
    return replace(KINDS[name], tracks=tracks)


@pytest.mark.parametrize(
    "name, sigma",
    [
        ("turns 10 s", 10.0),  # the former estimator: 108 m
        ("turns 10 s", 50.0),  # former: 118 m
        ("turns irregular", 10.0),  # former: 41 m
        ("turns 1 s", 200.0),
        ("fast 60 s", 50.0),  # former: 294 m
        ("ships 9 s", 10.0),
        ("ships 9 s", 200.0),
        ("maneuvers 5 s", 50.0),  # former: 166 m
        ("CV q=0.05, 1-10 s", 50.0),
    ],
)
def test_measurement_noise_within_20_percent(name, sigma):
    sim = simulate(small(name), sigma, seed=7)
    noise = estimate_noise(sim.z, sim.dt)
    ratio = noise.meas_var.sqrt() / sigma
    assert noise.meas_std_se is not None
    se = noise.meas_std_se / sigma
    assert bool((se * SE_MARGIN <= WITHIN).all()), f"standard error {se.tolist()} too wide"
    assert bool(((ratio - 1).abs() <= WITHIN).all()), f"σ̂/σ = {ratio.tolist()}"


@pytest.mark.parametrize("name", ["turns 10 s", "maneuvers 5 s"])
def test_dropping_one_percent_of_rows_barely_moves_it(name):
    """Dropping 1% of the rows re-forms about 4% of the residuals (each row is in k + 1
    stencils of each order), which moves σ̂ by about √(2·0.04) ≈ 0.3 of its standard error
    (≤ 2.5% here): 3% is over three times that."""
    sim = simulate(small(name, tracks=8), 50.0, seed=3)
    base = float(estimate_noise(sim.z, sim.dt).meas_var.sqrt().mean())
    for seed in range(3):
        fewer = drop_rows(sim, 0.01, seed)
        moved = float(estimate_noise(fewer.z, fewer.dt).meas_var.sqrt().mean()) / base - 1
        assert abs(moved) <= 0.03, f"dropping 1% of the rows moved σ̂ by {100 * moved:.1f}%"


def test_standard_error_is_calibrated():
    """Over 12 seeds, ±2 jackknife standard errors (20 groups: t with 19 degrees of freedom,
    94%) cover σ at least 9 times (a calibrated error fails this with probability 0.6%), and the
    mean standard error is within a factor 2 of the seeds' spread (a sample standard deviation
    of 12 values is within 0.6-1.4 of the truth 98% of the time)."""
    kind = replace(KINDS["turns irregular"], tracks=3, duration=1500.0)
    sigma = 50.0
    estimates, errors = [], []
    for seed in range(12):
        sim = simulate(kind, sigma, seed=100 + seed)
        noise = estimate_noise(sim.z, sim.dt)
        assert noise.meas_std_se is not None
        estimates.append(float(noise.meas_var[0].sqrt()))
        errors.append(float(noise.meas_std_se[0]))
    est, err = torch.tensor(estimates), torch.tensor(errors)
    covered = int(((est - sigma).abs() <= 2 * err).sum())
    assert covered >= 9, f"±2 se covered σ in {covered} of 12 seeds"
    ratio = float(err.mean() / est.std())
    assert 0.5 <= ratio <= 2.0, f"mean se / spread of the estimates = {ratio:.2f}"


def test_white_acceleration_is_fitted_where_the_data_show_it():
    """Tracks of the CV model itself with q h³ ~ r: only the fit with white acceleration is
    unbiased (the noise-alone fit reads r + b q, 10% high in σ here), and it is chosen
    (8,000 rows show it by about ten standard errors); on turning tracks the noise-alone fit is
    kept."""
    gen = torch.Generator().manual_seed(5)
    B, T, q, r = 20, 400, 2.0, 25.0
    dt = 1.0 + 4.0 * torch.rand(B, T, generator=gen, dtype=torch.float64)
    _, z = simulate_cv(dt, q, r, gen)
    noise = estimate_noise(z, dt)
    assert noise.white_acceleration == 1.0
    assert_close(noise.meas_var.sqrt(), torch.full((2,), math.sqrt(r)), rtol=0.05)
    sim = simulate(small("turns 10 s"), 50.0, seed=7)
    assert estimate_noise(sim.z, sim.dt).white_acceleration == 0.0


def test_difference_residuals_annihilate_polynomials_and_give_the_white_acceleration_variance():
    """A path of degree below the order leaves no residual; white acceleration of density q
    gives each residual the variance b·q, checked against the covariance of the integrated
    Wiener process, Cov(X_s, X_t) = q (s³/3 + (t - s) s²/2) for s ≤ t."""
    gen = torch.Generator().manual_seed(0)
    dt = 0.5 + 3.0 * torch.rand(1, 12, generator=gen, dtype=torch.float64)
    t = torch.cumsum(dt, 1)[0]
    for k in (2, 3, 4):
        coeffs = torch.randn(k, generator=gen, dtype=torch.float64)
        path = sum(c * t**j for j, c in enumerate(coeffs))
        res = difference_residuals(path.view(1, -1, 1) * 1e3, dt, (k,))
        assert float(res.u.abs().max()) < 1e-6 * float(path.abs().max() * 1e3)
    # The residual's coefficients: u is linear in z, so read them off unit vectors.
    T = t.numel()
    s, u = t.view(-1, 1), t.view(1, -1)
    lo, hi = torch.minimum(s, u), torch.maximum(s, u)
    cov = lo**3 / 3 + (hi - lo) * lo**2 / 2
    for k in (2, 3, 4):
        basis = torch.eye(T, dtype=torch.float64).view(T, T, 1)  # T tracks, each one unit z
        coeff = difference_residuals(basis, dt.expand(T, T), (k,))
        C = torch.zeros(T - k, T, dtype=torch.float64)
        # Residual i of track j is coefficient j of stencil i (first step i).
        C[coeff.first, coeff.track] = coeff.u
        b = difference_residuals(torch.zeros(1, T, 1, dtype=torch.float64), dt, (k,)).b
        assert_close((C.square().sum(1)), torch.ones(T - k), rtol=1e-12)  # unit noise gain
        assert_close(torch.einsum("ij,jk,ik->i", C, cov, C), b, rtol=1e-9)


def test_three_point_residual_is_the_gasser_sroka_jennen_steinmetz_one():
    dt = torch.tensor([[1.0, 2.0, 5.0, 0.5]], dtype=torch.float64)
    z = torch.tensor([[[0.0], [3.0], [1.0], [7.0]]], dtype=torch.float64)
    res = difference_residuals(z, dt, (2,))
    t = torch.cumsum(dt[0], 0)
    for i in range(2):
        h1, h2 = t[i + 1] - t[i], t[i + 2] - t[i + 1]
        H = h1 + h2
        rho = z[0, i + 1, 0] - (h2 * z[0, i, 0] + h1 * z[0, i + 2, 0]) / H
        a = 1 + (h1 / H) ** 2 + (h2 / H) ** 2
        assert float(res.u[i].abs()) == pytest.approx(float(rho.abs() / a.sqrt()))
        assert float(res.b[i]) == pytest.approx(float(h1**2 * h2**2 / (3 * H) / a))


def test_large_data_are_fitted_on_a_sample_of_blocks(monkeypatch):
    sim = simulate(small("turns 1 s"), 50.0, seed=1)
    monkeypatch.setattr(noise_estimate, "MAX_RESIDUALS", 4000)
    noise = estimate_noise(sim.z, sim.dt)
    assert noise.triplets <= 4000 * 1.05
    assert bool(((noise.meas_var.sqrt() / 50.0 - 1).abs() <= WITHIN).all())


def test_bad_inputs_are_named():
    z = torch.zeros(1, 2, 2, dtype=torch.float64)
    with pytest.raises(ValueError, match="^z: too few"):
        estimate_noise(z, torch.ones(1, 2, dtype=torch.float64))
    line = torch.arange(20.0, dtype=torch.float64).view(1, 20, 1).expand(1, 20, 2)
    with pytest.raises(ValueError, match="^z: most positions lie exactly"):
        estimate_noise(line, torch.ones(1, 20, dtype=torch.float64))
    with pytest.raises(ValueError, match="^z, dt:"):
        estimate_noise(line, torch.ones(1, 19, dtype=torch.float64))
    with pytest.raises(ValueError, match="^orders:"):
        estimate_noise(line, torch.ones(1, 20, dtype=torch.float64), orders=(1, 2))
    with pytest.raises(ValueError, match="^criterion:"):
        smoother_q(line, torch.ones(1, 20, dtype=torch.float64), 1.0, criterion="mse")
    with pytest.raises(ValueError, match="^meas_var:"):
        smoother_q(line, torch.ones(1, 20, dtype=torch.float64), -1.0)


def test_likelihood_q_recovers_the_true_q_within_its_standard_error():
    """Tracks of the CV model itself: the innovation likelihood's q is the maximum-likelihood
    estimate, within three of its standard errors of the truth."""
    gen = torch.Generator().manual_seed(2)
    q, r = 0.5, 100.0
    dt = torch.full((8, 300), 2.0, dtype=torch.float64)
    _, z = simulate_cv(dt, q, r, gen, speed=20.0)
    fit = smoother_q(z, dt, r, criterion="nll")
    assert 0 < fit.log_se < 0.3
    assert abs(math.log(fit.q / q)) <= 3 * fit.log_se


@pytest.mark.parametrize(
    "name, sigma",
    [
        ("turns 1 s", 50.0),  # the likelihood's q: 1.09 of the best; the former: 1.11
        ("ships 9 s", 50.0),
        ("CV q=1, 1 s", 50.0),
    ],
)
def test_sure_q_is_near_the_best_of_a_grid_scanned_with_the_truth(name, sigma):
    """The smoother with the estimated noise and the SURE q is within 5% of the best RMSE of a
    grid of q scanned with the truth and the true noise (the RMSE is flat near its optimum:
    SURE's statistical error on q costs about 1% here), and below the raw measurements."""
    sim = simulate(small(name), sigma, seed=11)
    noise = estimate_noise(sim.z, sim.dt)
    fit = smoother_q(sim.z, sim.dt, noise.meas_var)
    rmse = ks_rmse(sim, float(noise.meas_var.mean()), fit.q)
    _, best = best_grid_q(sim, sigma**2, points=19)
    assert rmse <= 1.05 * best, f"KS RMSE {rmse:.2f} m, grid's best {best:.2f} m"
    assert rmse < raw_rmse(sim)


def test_sure_q_never_worse_than_the_measurements_when_nothing_can_be_smoothed():
    """Fast turns at 60 s scans (30-90° per scan): smoothing cannot help; SURE's q lets the
    smoother follow the measurements instead of cutting the corners."""
    sim = simulate(small("fast 60 s"), 10.0, seed=0)
    noise = estimate_noise(sim.z, sim.dt)
    fit = smoother_q(sim.z, sim.dt, noise.meas_var)
    assert ks_rmse(sim, float(noise.meas_var.mean()), fit.q) <= 1.02 * raw_rmse(sim)


def test_smoother_q_uses_a_sample_of_large_data():
    sim = simulate(small("ships 9 s", tracks=2), 50.0, seed=0)
    fit = smoother_q(sim.z, sim.dt, 2500.0, max_steps=512, window=256)
    assert fit.steps <= 512
    assert isinstance(sim, Simulated)


def test_noise_spread_tells_one_sensor_from_two():
    """Between-track spread of the per-track noise reading: near 0 for one sensor (its excess
    over the tracks' own standard errors), near the log-ratio's half-width for two sensors of
    σ 20 and 60 (log 3 / 2 = 0.55), None with fewer than 4 usable tracks."""
    gen = torch.Generator().manual_seed(4)
    dt = 1.0 + 9.0 * torch.rand(12, 120, generator=gen, dtype=torch.float64)
    _, z = simulate_cv(dt, q=0.5, r=40.0**2, generator=gen, speed=30.0)
    one = track_noise.noise_spread(z, dt)
    assert one is not None and one < 0.08
    _, z20 = simulate_cv(dt[:6], q=0.5, r=20.0**2, generator=gen, speed=30.0)
    _, z60 = simulate_cv(dt[6:], q=0.5, r=60.0**2, generator=gen, speed=30.0)
    mixed = torch.cat([z20, z60])
    two = track_noise.noise_spread(mixed, dt)
    assert two is not None and 0.4 < two < 0.7
    assert track_noise.noise_spread(z[:3], dt[:3]) is None
    short = z.clone()
    short[:, track_noise.SPREAD_POINTS - 1 :] = float("nan")  # no track has enough points
    assert track_noise.noise_spread(short, dt) is None


@pytest.mark.parametrize("smoothed", [False, True])
def test_filter_sure_leverage_is_the_filters_own_derivative(smoothed):
    """SURE scores H x̂_{t|t} (smoothed=False) or H x̂_{t|T} with the leverage H P Hᵀ / r of the
    same pass: it is the estimate's derivative in z_t (central differences of the float64
    filter or RTS smoother, exact for a linear map)."""
    gen = torch.Generator().manual_seed(2)
    dt = 1.0 + 4.0 * torch.rand(1, 30, generator=gen, dtype=torch.float64)
    _, z = simulate_cv(dt, q=2.0, r=25.0, generator=gen, speed=10.0)
    model = ts.models.ConstantVelocity(q=2.0, r=25.0).double()
    kf = ts.KalmanFilter(model)
    estimator = ts.RTSSmoother(kf) if smoothed else kf
    x0 = torch.tensor([[z[0, 0, 0], 0.0, z[0, 0, 1], 0.0]], dtype=torch.float64)
    P0 = torch.diag(torch.tensor([25.0, 100.0, 25.0, 100.0], dtype=torch.float64))
    out = estimator(z, x0, P0, dt=dt)
    for t, axis in ((5, 0), (17, 1), (29, 0)):
        up, down = z.clone(), z.clone()
        up[0, t, axis] += 1e-3
        down[0, t, axis] -= 1e-3
        slope = (estimator(up, x0, P0, dt=dt).mean - estimator(down, x0, P0, dt=dt).mean)[
            0, t, 2 * axis
        ] / 2e-3
        assert_close(slope, out.cov[0, t, 2 * axis, 2 * axis] / 25.0, atol=1e-9, rtol=1e-7)


def test_filter_q_serves_a_filter_on_turns():
    """On hard turns a Kalman filter with the smoother's q cuts corners (it cannot look ahead):
    the filter's own SURE q is larger, and its filter is below the raw measurements."""
    sim = simulate(small("turns 10 s"), 50.0, seed=3)
    smoother_fit = smoother_q(sim.z, sim.dt, 2500.0)
    filter_fit = smoother_q(sim.z, sim.dt, 2500.0, smoothed=False)
    assert filter_fit.q > smoother_fit.q

    def kf_rmse(q: float) -> float:
        model = ts.models.ConstantVelocity(ndim=2, q=q, r=2500.0).double()
        prior = two_point_prior(sim.z, sim.dt, 2500.0)
        with torch.no_grad():
            out = ts.KalmanFilter(model)(sim.z, prior.x0, prior.P0, dt=sim.dt, keep="mean")
        ok = ~torch.isnan(sim.z[..., 0])
        return float((out.mean[..., [0, 2]] - sim.truth)[ok].square().sum(-1).mean().sqrt())

    assert kf_rmse(filter_fit.q) < kf_rmse(smoother_fit.q)
    assert kf_rmse(filter_fit.q) < raw_rmse(sim)


def _two_kinds(
    tracks: int = 6, steps: int = 300
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Tracks of the CV model, half quiet (q 0.01) and half maneuvering (q 10), σ 20 m, 2 s
    scans: truth positions, measurements, intervals."""
    gen = torch.Generator().manual_seed(5)
    dt = torch.full((tracks, steps), 2.0, dtype=torch.float64)
    half = tracks // 2
    quiet, zq = simulate_cv(dt[:half], q=0.01, r=400.0, generator=gen, speed=10.0)
    busy, zb = simulate_cv(dt[half:], q=10.0, r=400.0, generator=gen, speed=10.0)
    return torch.cat([quiet, busy])[..., [0, 2]], torch.cat([zq, zb]), dt


def test_q_curves_pooled_value_is_smoother_q_sure():
    """The pooled curve at factor 1 is the SURE smoother_q minimised (whole tracks shorter than
    its window are its windows)."""
    _, z, dt = _two_kinds(steps=200)
    fit = smoother_q(z, dt, 400.0)
    curves = q_curves(z, dt, 400.0, fit.q)
    assert curves.pooled()[Q_FACTORS.index(1.0)] == pytest.approx(fit.value, rel=1e-9)
    assert curves.counts.tolist() == [2.0 * 198] * 6


def test_track_q_factors_split_quiet_from_maneuvering_tracks_and_beat_one_q():
    """Each track's own q: the quiet half below the file's and below the maneuvering half's, the
    smoother's RMSE against the truth lower than with one q for all; without shrinkage room
    (shrink → ∞) every track keeps the file's."""
    truth, z, dt = _two_kinds()
    q = smoother_q(z, dt, 400.0).q
    curves = q_curves(z, dt, 400.0, q)
    factors = track_q_factors(curves, curves.pooled())
    assert factors[:3].max() < 1 and factors[:3].max() < factors[3:].min(), factors.tolist()
    assert (track_q_factors(curves, curves.pooled(), shrink=1e12) == 1).all()

    def rmse(per_track_q: torch.Tensor) -> float:
        prior = two_point_prior(z, dt, 400.0)
        errors = []
        for b in range(len(z)):
            model = ts.models.ConstantVelocity(q=float(per_track_q[b]), r=400.0).double()
            ks = ts.RTSSmoother(ts.KalmanFilter(model))
            with torch.no_grad():
                out = ks(z[b : b + 1], prior.x0[b : b + 1], prior.P0[b : b + 1], dt=dt[b : b + 1])
            errors.append((out.mean[0][:, [0, 2]] - truth[b]).square().sum(-1))
        return float(torch.cat(errors).mean().sqrt())

    assert rmse(q * factors) < 0.95 * rmse(torch.full((6,), q))
    with pytest.raises(ValueError, match="^pooled, curves:"):
        track_q_factors(curves, curves.pooled()[:3])


def test_settings_q_factors_only_rise_for_the_student_t_filter():
    """The same quiet and maneuvering tracks: the Kalman filter's quiet tracks get a factor below
    1, the robust Student-t filter's none (``recipes.UPWARD_Q_ONLY``), while its maneuvering
    tracks keep theirs."""
    from torchsvs.datasets import RecordedTracks
    from torchsvs.estimating import settings_q_factors
    from torchsvs.fitting.defaults import complete_settings, with_q_curve
    from torchsvs.recipes import Settings

    _, z, dt = _two_kinds()
    tracks = RecordedTracks(
        z=z, dt=dt, time=dt.cumsum(1), lengths=torch.full((6,), 300), ids=list("abcdef")
    )
    factors = {}
    for name in ("kf", "rstkf"):
        settings = with_q_curve(complete_settings(Settings(name, meas_var=[400.0]), tracks), tracks)
        factors[name] = settings_q_factors(settings, tracks)
    assert factors["kf"][:3].max() < 1
    assert (factors["rstkf"] >= 1).all()
    assert torch.equal(factors["rstkf"][3:], factors["kf"][3:].clamp_min(1.0))


def _turning_at_irregular_times(sigma: float, B: int = 20, T: int = 250, seed: int = 0):
    """Aircraft (200 m/s) turning at up to 3 deg/s, a new rate every minute or so, reported
    2-35 s apart: motion between reports that the white-acceleration fit does not extrapolate."""
    gen = torch.Generator().manual_seed(seed)
    gaps = torch.tensor([2.0, 4.0, 10.0, 20.0, 35.0], dtype=torch.float64)
    dt = gaps[torch.randint(0, 5, (B, T), generator=gen)]
    dt[:, 0] = 0.0
    t = dt.cumsum(1)
    fine = torch.arange(0.0, float(t.max()) + 1.0, 1.0, dtype=torch.float64)
    z = torch.empty(B, T, 2, dtype=torch.float64)
    for b in range(B):
        rate = torch.repeat_interleave(
            (torch.rand(len(fine) // 60 + 1, generator=gen, dtype=torch.float64) * 2 - 1)
            * math.radians(3.0),
            60,
        )[: len(fine)]
        heading = rate.cumsum(0)
        path = torch.stack([heading.cos(), heading.sin()], -1).cumsum(0) * 200.0
        at = t[b].long()
        z[b] = path[at] + sigma * torch.randn(T, 2, generator=gen, dtype=torch.float64)
    return z, dt


def test_a_maneuver_read_as_noise_far_apart_widens_the_readings_uncertainty(monkeypatch):
    """Reports far apart of a maneuvering target: both fits read part of the motion as noise,
    with a jackknife error that knows nothing of it; the shortest stencils read less, and the
    difference joins the standard error, so the reading's interval reaches the truth (the
    guards then act on it). On a regular grid nothing changes."""
    z, dt = _turning_at_irregular_times(25.0)
    found = estimate_noise(z, dt)
    monkeypatch.setattr(noise_estimate, "_short_stencils", lambda *args: None)
    plain = estimate_noise(z, dt)
    assert_close(found.meas_var, plain.meas_var)  # the estimate stands
    sigma, se = plain.meas_var.sqrt(), plain.meas_std_se
    # read 30.5-31.2 m ± 0.9-1.7 for 25 m (32 m before the lowest order's maneuver was left to
    # the higher orders): the truth beyond two of its standard errors
    assert bool((sigma > 1.2 * 25.0).all()) and bool((sigma - 2 * se > 1.05 * 25.0).all())
    wide = found.meas_std_se
    assert bool((sigma - wide < 1.15 * 25.0).all()) and bool((wide > 2.5 * se).all())  # ± 6.4-6.6
    regular_dt = torch.full((20, 200), 5.0, dtype=torch.float64)
    _, regular = simulate_cv(regular_dt, 1.0, 25.0**2, torch.Generator().manual_seed(1), 100.0)
    alike = estimate_noise(regular, regular_dt)
    monkeypatch.undo()
    found = estimate_noise(regular, regular_dt)
    assert torch.equal(found.meas_var, alike.meas_var)
    assert torch.equal(found.meas_std_se, alike.meas_std_se)


def test_between_spread_is_dersimonian_and_lairds_moment_estimator():
    """Worked by hand: values 0 and 2 of unit weight have mean 1, Q = 2 and one degree of
    freedom, so τ² = (Q − 1) / (Σw − Σw²/Σw) = 1; values within their own errors give τ = 0;
    one value leaves no degree of freedom."""
    from torchsvs.datasets.track_noise import between_spread

    one = torch.ones(2, dtype=torch.float64)
    assert between_spread(torch.tensor([0.0, 2.0], dtype=torch.float64), one) == (1.0, 1.0)
    mean, tau = between_spread(torch.tensor([1.0, 3.0], dtype=torch.float64), one * 0.25)
    assert mean == 2.0 and tau == 0.0  # (Q = 0.5 < 1 degree of freedom)
    assert between_spread(torch.tensor([5.0], dtype=torch.float64), one[:1])[1] is None
    # each group about its own mean: two groups (0, 2) and (10, 12) are the first pair twice,
    # Q = 4 over 2 degrees of freedom, Σw − Σw²/Σw = 1 + 1: τ² = 1
    y = torch.tensor([0.0, 2.0, 10.0, 12.0], dtype=torch.float64)
    four, group = torch.ones(4, dtype=torch.float64), torch.tensor([0, 0, 1, 1])
    assert between_spread(y, four, group)[1] == 1.0
    assert between_spread(y, four)[1] > 5.0  # (pooled: the groups' levels read as a spread)


def test_axes_of_different_noise_are_no_spread_between_tracks():
    """A drone's 5, 5 and 10 m on x, y and altitude, every track alike: pooled about one level
    the axes read as tracks that differ by a third (an outside probe: a warning, and the error
    estimate's range 0-11 m); each axis about its own, no spread."""
    gen = torch.Generator().manual_seed(3)
    dt = torch.full((30, 200), 1.0, dtype=torch.float64)
    sigma = torch.tensor([5.0, 5.0, 10.0], dtype=torch.float64)
    speed = 3.0 + 0.3 * torch.randn(30, 200, 3, generator=gen, dtype=torch.float64).cumsum(1)
    z = speed.cumsum(1) + sigma * torch.randn(30, 200, 3, generator=gen, dtype=torch.float64)
    spread = track_noise.noise_spread(z, dt)
    assert spread is not None and spread < 0.1  # (all axes 5 m: 0-0.06 on three seeds; pooled 0.3)


def _turning_aircraft(seed: int, sigma: float, tracks: int = 12, steps: int = 240):
    """Aircraft at 200 m/s on 5 s reports, alternating straight legs and standard-rate turns
    (1.5-3 deg/s, rolled into over 5 s): ``z [B, T, 2]``, ``dt [B, T]``."""
    gen = torch.Generator().manual_seed(seed)
    fine, h = 0.05, 5.0
    n = int(steps * h / fine)
    rate = torch.zeros(tracks, n, dtype=torch.float64)
    for b in range(tracks):
        at, turn = 0, bool(torch.rand(1, generator=gen) < 0.5)
        while at < n:
            span = int(float(40 + 110 * torch.rand(1, generator=gen)) / fine)
            if turn:
                sign = 1.0 if float(torch.rand(1, generator=gen)) < 0.5 else -1.0
                degrees = 1.5 + 1.5 * float(torch.rand(1, generator=gen))
                rate[b, at : at + span] = sign * math.radians(degrees)
            turn, at = not turn, at + span
    width = int(h / fine) + 1  # (odd: centred)
    kernel = torch.ones(1, 1, width, dtype=torch.float64) / width
    rate = torch.nn.functional.conv1d(rate.unsqueeze(1), kernel, padding="same").squeeze(1)
    heading = 6.28 * torch.rand(tracks, 1, generator=gen, dtype=torch.float64)
    heading = heading + rate.cumsum(1) * fine
    path = torch.stack([heading.cos(), heading.sin()], -1).cumsum(1) * 200.0 * fine
    every = int(h / fine)
    z = path[:, every - 1 :: every][:, :steps]
    z = z + sigma * torch.randn(z.shape, generator=gen, dtype=torch.float64)
    return z, torch.full(z.shape[:2], h, dtype=torch.float64)


def test_a_maneuver_the_lowest_order_reads_is_left_to_the_higher_orders():
    """Standard-rate turns on 5 s reports at 200 m/s (1 g): the second differences read the
    turn (50 m where σ is 30), and the fit of orders 2-4 read 36 m, five standard errors off,
    so the error estimate came out at 0.4-0.65 times the truth without a warning (an outside
    probe). Where the lowest order reads surely and clearly above the others, the noise is read
    off those: within 5% of σ, and within three standard errors; tracks that only go straight
    read as before."""
    for seed in (1, 2):
        z, dt = _turning_aircraft(seed, 30.0)
        orders = [float(estimate_noise(z, dt, orders=(k,)).meas_var.sqrt().mean()) for k in (2, 4)]
        assert orders[0] > 1.3 * orders[1]  # (the turns at the lowest order)
        found = estimate_noise(z, dt)
        sigma = found.meas_var.sqrt()
        assert found.meas_std_se is not None
        assert bool(((sigma / 30.0 - 1).abs() < 0.05).all()), sigma.tolist()
        assert bool(((sigma - 30.0).abs() < 3 * found.meas_std_se + 0.3).all())
    straight = simulate(small("turns 10 s"), 50.0, seed=7)
    plain = estimate_noise(straight.z, straight.dt)
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(noise_estimate, "_lowest_reads_motion", lambda *a: False)
        assert torch.equal(estimate_noise(straight.z, straight.dt).meas_var, plain.meas_var)
        # without the check the turning aircraft read the turns as noise (36 m for 30)
        before = estimate_noise(z, dt).meas_var.sqrt()
        assert bool((before > 1.15 * 30.0).all()), before.tolist()
