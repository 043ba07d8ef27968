"""Models and scenarios: the paper's matrices, per-step dt, learnable noise, seeded truth."""

from __future__ import annotations

import math

import torch

import torchsvs as ts
from tests.conftest import assert_close, atc_batch


def test_constant_velocity_matrices_are_eqs_43_to_48():
    T, L = 2.0, 0.16
    model = ts.models.ConstantVelocity(ndim=2, dt=T, q=L, r=200.0**2)
    F = torch.tensor([[1, T, 0, 0], [0, 1, 0, 0], [0, 0, 1, T], [0, 0, 0, 1]], dtype=torch.float64)
    q = torch.tensor([[T**3 / 3, T**2 / 2], [T**2 / 2, T]], dtype=torch.float64)
    Q = L * torch.block_diag(q, q)
    H = torch.tensor([[1.0, 0, 0, 0], [0, 0, 1.0, 0]], dtype=torch.float64)
    assert_close(model.transition(), F)
    assert_close(model.process_noise(), Q)
    assert_close(model.meas_matrix(), H)
    assert_close(model.meas_cov(), 200.0**2 * torch.eye(2))
    assert model.position_index == [0, 2] and model.velocity_index == [1, 3]
    three = ts.models.ConstantVelocity(ndim=3, dt=T, q=L, r=[1.0, 2.0, 3.0])
    assert_close(three.process_noise(), L * torch.block_diag(q, q, q))
    assert_close(three.meas_cov(), torch.diag(torch.tensor([1.0, 2.0, 3.0])))


def test_per_step_dt_uses_each_interval():
    model = ts.models.ConstantVelocity(dt=1.0, q=0.5, r=4.0)
    sc = atc_batch(2)
    z = sc.z[:, :30]
    dt = torch.full(z.shape[:2], 1.0, dtype=z.dtype)
    kf = ts.KalmanFilter(model)
    assert_close(kf(z, sc.x0, sc.P0, dt=dt).mean, kf(z, sc.x0, sc.P0).mean)
    dt[1] = 2.5  # track 1 sampled every 2.5 s: same as a model built with dt = 2.5
    varied = kf(z, sc.x0, sc.P0, dt=dt)
    slow = ts.KalmanFilter(ts.models.ConstantVelocity(dt=2.5, q=0.5, r=4.0))(z[1], sc.x0, sc.P0)
    assert_close(varied.mean[1], slow.mean)
    assert_close(varied.cov[1], slow.cov)
    assert varied.transition.shape == (2, 30, 4, 4)


def test_learnable_noise_round_trips_and_gets_gradients():
    Q = torch.tensor([[2.0, 0.3], [0.3, 1.0]], dtype=torch.float64)
    R = torch.tensor([[0.5]], dtype=torch.float64)
    model = ts.models.LinearGaussian(
        torch.eye(2), torch.tensor([[1.0, 0.0]]), Q, R, learn_noise=True
    )
    assert_close(model.process_noise(), Q, atol=1e-12)
    assert_close(model.meas_cov(), R, atol=1e-12)
    cv = ts.models.ConstantVelocity(q=0.16, r=[4.0, 9.0], learn_noise=True)
    assert {n for n, _ in cv.named_parameters()} == {"q.raw", "R.raw"}
    sc = atc_batch(1)
    out = ts.KalmanFilter(cv)(sc.z[:, :20], sc.x0, sc.P0)
    (-out.log_likelihood.sum()).backward()
    assert cv.q.raw.grad is not None and bool(torch.isfinite(cv.R.raw.grad).all())
    fixed = ts.models.ConstantVelocity()
    assert list(fixed.parameters()) == []


def test_sample_is_reproducible_with_a_generator():
    model = ts.models.ConstantVelocity(q=1.0, r=1.0)
    x0 = torch.zeros(3, 4, dtype=torch.float64)
    a = model.simulate(x0, 10, generator=torch.Generator().manual_seed(3))
    b = model.simulate(x0, 10, generator=torch.Generator().manual_seed(3))
    assert_close(a[0], b[0], atol=0, rtol=0)
    assert_close(a[1], b[1], atol=0, rtol=0)
    assert a[0].shape == (3, 10, 4) and a[1].shape == (3, 10, 2)


def test_simulate_is_eqs_1_2_drawn_step_by_step():
    """propagate/observe against a loop written from Eqs. (1)-(2) with the same draws: a
    nonlinear model, per-step dt, control inputs, and a process noise without a component."""
    model = ts.models.ElectrohydrostaticActuator()
    B, T = 3, 6
    gen = torch.Generator().manual_seed(1)
    u = torch.randn(B, T, 1, generator=gen, dtype=torch.float64)
    dt = 0.001 * (1 + torch.rand(B, T, generator=gen, dtype=torch.float64))
    x0 = torch.tensor([0.0, 0.0, 0.0, 2.1e8], dtype=torch.float64).expand(B, 4)
    Q = model.process_noise().clone()
    Q[3, :] = Q[:, 3] = 0.0
    truth = model.propagate(x0, T, torch.Generator().manual_seed(2), dt=dt, u=u, cov=Q)
    z = model.observe(truth, torch.Generator().manual_seed(3), noise_scale=0.5)
    draws = torch.Generator().manual_seed(2)
    L = torch.linalg.cholesky(Q[:3, :3])
    x, expected = x0, []
    for t in range(T):
        eps = torch.randn(B, 3, generator=draws, dtype=torch.float64)
        x = model.f(x, dt[:, t], u[:, t]) + torch.cat([eps @ L.mT, torch.zeros(B, 1)], -1)
        expected.append(x)
    assert_close(truth, torch.stack(expected, 1), atol=0, rtol=0)
    assert bool((truth[..., 3] == 2.1e8).all())  # the noiseless component was never drawn
    eps = torch.randn(B, T, 3, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    L_R = torch.linalg.cholesky(model.meas_cov())
    assert_close(z, model.h(truth) + 0.5 * eps @ L_R.mT, atol=1e-12, rtol=0)


def test_simulated_noise_has_the_model_covariances():
    """Sample covariances of the simulated noises match Q and R: with N = 40,000 draws an
    entry's standard error is at most sqrt(2/N) ≈ 0.7% of the diagonal scale, bounded at 5%
    (7σ; the four Q entries and three R entries fail together with probability < 1e-10)."""
    model = ts.models.ConstantVelocity(ndim=1, dt=0.5, q=2.0, r=3.0)
    N = 40_000
    x0 = torch.zeros(N, 2, dtype=torch.float64)
    truth, z = model.simulate(x0, 1, generator=torch.Generator().manual_seed(0))
    w = truth[:, 0]  # one step from zero: the process noise itself
    Q = model.process_noise()
    scale = Q.diagonal().sqrt()
    cov = w.T @ w / N
    assert float(((cov - Q) / (scale[:, None] * scale[None, :])).abs().max()) < 0.05
    v = z[:, 0] - model.h(truth[:, 0])
    assert abs(float(v.square().mean()) / 3.0 - 1) < 0.05
    still = model.simulate(x0[:2], 4, torch.Generator().manual_seed(0), process_noise=False)[0]
    assert bool((still == 0).all())


def test_atc_truth_follows_the_described_maneuvers():
    sc = atc_batch(3, seed=0)
    truth = sc.truth[0]
    assert truth.shape == (490, 4)
    speed = truth[:, [1, 3]].norm(dim=-1)
    assert_close(speed, torch.full((490,), 120.0, dtype=torch.float64), atol=1e-6)
    heading = torch.atan2(truth[:, 3], truth[:, 1]) * 180 / math.pi
    # straight along +x, 3°/s clockwise for 30 s, straight, 1°/s counter-clockwise for 90 s.
    assert_close(heading[124], torch.tensor(0.0, dtype=torch.float64), atol=1e-9)
    assert_close(heading[154], torch.tensor(-90.0, dtype=torch.float64), atol=1e-6)
    assert_close(heading[279], torch.tensor(-90.0, dtype=torch.float64), atol=1e-6)
    assert_close(heading[369], torch.tensor(0.0, dtype=torch.float64), atol=1e-6)
    # 125 s straight at 120 m/s from (−25000, −10000).
    assert_close(
        truth[124, [0, 2]],
        torch.tensor([-25000.0 + 125 * 120, -10000.0], dtype=torch.float64),
        atol=1e-6,
    )
    # Identical truth for every run, independent noise.
    assert_close(sc.truth[1], truth, atol=0, rtol=0)
    assert (sc.z[0] - sc.z[1]).abs().min() > 0
    again = atc_batch(3, seed=0)
    assert_close(again.z, sc.z, atol=0, rtol=0)
    noise = sc.z - sc.truth[..., [0, 2]]
    assert abs(noise.std().item() - 200.0) < 10.0


def test_turn_with_angular_acceleration_and_linear_acceleration():
    start = torch.tensor([0.0, 100.0, 0.0, 0.0], dtype=torch.float64)
    deg = math.pi / 180
    turning = ts.scenarios.simulate_segments(
        start, [ts.scenarios.Segment(10.0, turn_rate=1 * deg, turn_accel=0.5 * deg)], dt=1.0
    )
    heading = torch.atan2(turning[0, -1, 3], turning[0, -1, 1]) / deg
    assert abs(heading.item() - (1 * 10 + 0.5 * 0.5 * 100)) < 1e-6  # ω0 t + α t²/2 = 35°
    accel = ts.scenarios.simulate_segments(
        start, [ts.scenarios.Segment(4.0, accel=(2.0, -1.0))], dt=1.0
    )
    assert_close(
        accel[0, -1], torch.tensor([400 + 16, 108, -8, -4], dtype=torch.float64), atol=1e-9
    )


def test_random_maneuvers_are_seeded_varied_and_physical():
    ranges = ts.scenarios.ManeuverRanges(steps=120, speed=(80.0, 300.0), meas_std=(20.0, 60.0))
    a = ts.scenarios.random_maneuvers(400, ranges, torch.Generator().manual_seed(5))
    b = ts.scenarios.random_maneuvers(400, ranges, torch.Generator().manual_seed(5))
    assert_close(a.z, b.z, atol=0, rtol=0)
    assert a.truth.shape == (400, 120, 4) and a.z.shape == (400, 120, 2)
    speed = a.truth[..., [1, 3]].norm(dim=-1)
    assert speed.min() >= 80.0 - 1e-6 and speed.max() <= 300.0 + 1e-6
    # Every kind occurs, roughly in proportion to the weights (0.4, 0.3, 0.1, 0.2) of the steps.
    share = torch.bincount(a.kinds.flatten(), minlength=4).double() / a.kinds.numel()
    assert_close(share, torch.tensor([0.4, 0.3, 0.1, 0.2], dtype=torch.float64), atol=0.05, rtol=0)
    # Segments last 10-40 steps: kinds change at most every 10 steps (a change may keep the kind).
    changes = (a.kinds[:, 1:] != a.kinds[:, :-1]).sum(1)
    assert changes.max() <= 120 // 10
    # Per-track noise in range and as drawn.
    residual = a.z - a.truth[..., [0, 2]]
    ratio = residual.std(dim=(1, 2)) / a.meas_std
    assert a.meas_std.min() >= 20.0 and a.meas_std.max() <= 60.0
    assert (ratio - 1).abs().max() < 0.25
    # A constant-turn track's heading changes at its turn rate: kinds 1 steps turn, kind 0 do not.
    heading = torch.atan2(a.truth[..., 3], a.truth[..., 1])
    turn = torch.remainder(heading[:, 1:] - heading[:, :-1] + math.pi, 2 * math.pi) - math.pi
    straight = (a.kinds[:, 1:] == 0) & (a.kinds[:, :-1] == 0)
    assert turn[straight].abs().max() < 1e-9
    assert turn[(a.kinds[:, 1:] == 1) & (a.kinds[:, :-1] == 1)].abs().min() > 0.9 * math.pi / 180


def test_random_scenario_has_model_and_prior():
    ranges = ts.scenarios.ManeuverRanges(steps=30, meas_std=(100.0, 300.0))
    sc = ts.scenarios.random_scenario(
        2000, ranges, q=2.0, prior_std=(50.0, 5.0), generator=torch.Generator().manual_seed(1)
    )
    assert sc.truth.shape == (2000, 30, 4) and sc.z.shape == (2000, 30, 2)
    assert sc.x0.shape == (2000, 4) and sc.P0.shape == (4, 4) and sc.meas_std.shape == (2000,)
    assert_close(sc.model.meas_cov(), 200.0**2 * torch.eye(2, dtype=torch.float64))
    assert_close(sc.model.process_noise()[1, 1], torch.tensor(2.0, dtype=torch.float64))
    # x0 − initial truth ~ N(0, P0): initial truth is one step of the truth back along the velocity.
    start = torch.stack(
        [sc.truth[:, 0, 0] - sc.truth[:, 0, 1], sc.truth[:, 0, 2] - sc.truth[:, 0, 3]], -1
    )
    spread = (sc.x0[:, [0, 2]] - start).std(0)
    assert ((spread - 50.0).abs() < 5.0).all()
    out = ts.KalmanFilter(sc.model)(sc.z, sc.x0, sc.P0)
    assert out.mean.shape == (2000, 30, 4)
