"""Multiple models: the CA and CT motion models, the IMM and its fixed-lag smoother."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from torch.func import jacrev, vmap

import torchsvs as ts
from tests.conftest import assert_close
from tests.reference.imm_numpy import imm as numpy_imm
from tests.reference.imm_numpy import kim_smoother as numpy_kim
from torchsvs.models.motion import turn_coefficients
from torchsvs.scenarios import Segment, simulate_segments

F64 = torch.float64
DEG = math.pi / 180
NAN = float("nan")

#: ConstantVelocity [x, vx, y, vy] inside ConstantAcceleration [x, vx, ax, y, vy, ay]
CV_IN_CA = [[0, 1, 3, 4], [0, 1, 2, 3, 4, 5]]
#: ConstantVelocity inside CoordinatedTurn [x, vx, y, vy, ω]
CV_IN_CT = [[0, 1, 2, 3], [0, 1, 2, 3, 4]]


def _track(segments, batch=3, seed=0, r=100.0):
    """Noise-free truth ``[B, T, 4]`` of a segment sequence from (0, 0) at 100 m/s along x, and
    its position measurements with variance ``r`` (seeded)."""
    truth = simulate_segments(torch.tensor([0.0, 100.0, 0.0, 0.0], dtype=F64), segments, 1.0)
    truth = truth.expand(batch, -1, -1)
    noise = r**0.5 * torch.randn(
        *truth.shape[:2], 2, generator=torch.Generator().manual_seed(seed), dtype=F64
    )
    return truth, truth[..., [0, 2]] + noise


TURN = [Segment(30.0), Segment(20.0, turn_rate=4 * DEG), Segment(30.0)]
ACCELERATE = [Segment(25.0), Segment(15.0, accel=(3.0, -2.0)), Segment(25.0)]
CV_PRIOR = (
    torch.tensor([0.0, 90.0, 0.0, 5.0], dtype=F64),
    torch.diag(torch.tensor([100.0, 100.0, 100.0, 100.0], dtype=F64)),
)
CA_PRIOR = (
    torch.tensor([0.0, 90.0, 0.0, 0.0, 5.0, 0.0], dtype=F64),
    torch.diag(torch.tensor([100.0, 100.0, 1.0, 100.0, 100.0, 1.0], dtype=F64)),
)
CT_PRIOR = (
    torch.tensor([0.0, 90.0, 0.0, 5.0, 0.0], dtype=F64),
    torch.diag(torch.tensor([100.0, 100.0, 100.0, 100.0, 1e-3], dtype=F64)),
)
STICKY = [[0.95, 0.05], [0.1, 0.9]]


def _cv(q=0.05):
    return ts.models.ConstantVelocity(q=q, r=100.0).double()


def _ca(q=0.5):
    return ts.models.ConstantAcceleration(q=q, r=100.0).double()


def _ct():
    return ts.models.CoordinatedTurn(q=0.05, q_turn=1e-4, r=100.0).double()


def _position_rmse(mean, truth, pos=(0, 2)):
    return float((mean[..., list(pos)] - truth[..., [0, 2]]).square().sum(-1).mean().sqrt())


# --- Models ---


def test_constant_acceleration_is_the_wiener_process_acceleration_model():
    T, q = 2.0, 0.3
    model = ts.models.ConstantAcceleration(ndim=2, dt=T, q=q, r=[4.0, 9.0])
    F = torch.tensor([[1, T, T**2 / 2], [0, 1, T], [0, 0, 1]], dtype=F64)
    Q = q * torch.tensor(
        [
            [T**5 / 20, T**4 / 8, T**3 / 6],
            [T**4 / 8, T**3 / 3, T**2 / 2],
            [T**3 / 6, T**2 / 2, T],
        ],
        dtype=F64,
    )
    assert_close(model.transition(), torch.block_diag(F, F))
    assert_close(model.process_noise(), torch.block_diag(Q, Q))
    H = torch.zeros(2, 6, dtype=F64)
    H[0, 0] = H[1, 3] = 1.0
    assert_close(model.meas_matrix(), H)
    assert_close(model.meas_cov(), torch.diag(torch.tensor([4.0, 9.0])))
    assert model.position_index == [0, 3] and model.velocity_index == [1, 4]
    assert model.acceleration_index == [2, 5]
    dt = torch.tensor([[1.0, 2.0]], dtype=F64)
    assert_close(model.transition(dt)[0, 1], model.transition())
    assert_close(model.process_noise(dt)[0, 1], model.process_noise())
    # Q is the integral of e^{As} b bᵀ e^{Aᵀs} q over the interval (b the jerk input).
    s = torch.linspace(0, T, 20001, dtype=F64)
    phi = torch.stack([s**2 / 2, s, torch.ones_like(s)], -1)  # e^{As} b
    integrand = q * phi.unsqueeze(-1) * phi.unsqueeze(-2)
    assert_close(torch.trapezoid(integrand, s, dim=0), Q, rtol=1e-7, atol=1e-9)


def test_coordinated_turn_reduces_to_constant_velocity_without_turn():
    T = 1.5
    ct = ts.models.CoordinatedTurn(dt=T, q=0.7, q_turn=0.01, r=4.0)
    cv = ts.models.ConstantVelocity(dt=T, q=1.0, r=4.0)
    x = torch.tensor([[10.0, 3.0, -5.0, 4.0, 0.0]], dtype=F64)
    assert_close(ct.f(x)[0, :4], cv.transition() @ x[0, :4], atol=1e-12)
    assert_close(ct.f_jacobian(x)[0, :4, :4], cv.transition(), atol=1e-12)
    # A quarter turn at ω = π/2 / T: the velocity rotates by 90°, the arc's chord is travelled.
    w = math.pi / 2 / T
    turned = ct.f(torch.tensor([[0.0, 2.0, 0.0, 0.0, w]], dtype=F64))[0]
    radius = 2.0 / w
    assert_close(turned, torch.tensor([radius, 0.0, radius, 2.0, w], dtype=F64), atol=1e-12)
    gain = torch.tensor(
        [[T**2 / 2, 0, 0], [T, 0, 0], [0, T**2 / 2, 0], [0, T, 0], [0, 0, T]], dtype=F64
    )
    expected = gain @ torch.diag(torch.tensor([0.7, 0.7, 0.01], dtype=F64)) @ gain.T
    assert_close(ct.process_noise(), expected, atol=1e-12)
    assert ct.process_noise(torch.ones(3, 4, dtype=F64)).shape == (3, 4, 5, 5)


@pytest.mark.parametrize("omega", [0.0, 1e-12, -3e-7, 4e-4, 9.999e-3, 1.0001e-2, -0.05, 0.3, 1.2])
def test_coordinated_turn_jacobian_matches_autograd_and_finite_differences(omega):
    ct = _ct()
    gen = torch.Generator().manual_seed(1)
    x = torch.randn(4, 5, generator=gen, dtype=F64) * torch.tensor([100, 50, 100, 50, 0])
    x[:, 4] = omega
    dt = torch.tensor([0.5, 1.0, 2.0, 3.0], dtype=F64)  # per track, as a filter step passes it
    J = ct.f_jacobian(x, dt)
    auto = vmap(jacrev(lambda s, d: ct.f(s.unsqueeze(0), d).squeeze(0)))(x, dt)
    assert bool(torch.isfinite(J).all())
    assert_close(J, auto, atol=1e-9, rtol=1e-9)
    h = 1e-6
    eye = torch.eye(5, dtype=F64)
    central = torch.stack(
        [(ct.f(x + h * eye[k], dt) - ct.f(x - h * eye[k], dt)) / (2 * h) for k in range(5)], -1
    )
    assert_close(J, central, atol=1e-6, rtol=1e-6)


def test_turn_coefficients_are_smooth_through_zero():
    a = torch.tensor([-2e-2, -1.0001e-2, -9.999e-3, -1e-6, 0.0, 1e-6, 9.999e-3, 1.0001e-2, 0.5])
    a = a.to(F64).requires_grad_()
    s, c, ds, dc = turn_coefficients(a)
    exact = a.detach()
    safe = torch.where(exact == 0, torch.ones_like(exact), exact)
    closed = torch.where(exact == 0, torch.ones_like(exact), torch.sin(safe) / safe)
    assert_close(s, closed, atol=1e-15, rtol=1e-14)
    assert_close(c[4], torch.tensor(0.0), atol=0)
    assert_close(dc[4], torch.tensor(0.5), atol=0)
    # Their autograd derivatives are the closed-form ones, finite at 0 and across the switch.
    (grad_s,) = torch.autograd.grad(s.sum(), a, create_graph=True)
    (grad_c,) = torch.autograd.grad(c.sum(), a, create_graph=True)
    assert_close(grad_s, ds, atol=1e-12)
    assert_close(grad_c, dc, atol=1e-12)
    (second,) = torch.autograd.grad(grad_s.sum() + grad_c.sum(), a)
    assert bool(torch.isfinite(second).all())


def test_ekf_and_ukf_track_a_simulated_coordinated_turn_with_per_step_dt():
    ct = ts.models.CoordinatedTurn(q=0.01, q_turn=1e-6, r=25.0).double()
    B, T = 4, 60
    gen = torch.Generator().manual_seed(3)
    dt = 0.5 + torch.rand(B, T, generator=gen, dtype=F64)
    start = torch.tensor([0.0, 100.0, 0.0, 0.0, 3 * DEG], dtype=F64).expand(B, 5)
    truth, z = ct.simulate(start, T, gen, dt=dt)  # Q has rank 3: drawn through eigh
    P0 = torch.diag(torch.tensor([100.0, 100.0, 100.0, 100.0, 1e-3], dtype=F64))
    x0 = start + torch.tensor([10.0, -5.0, -10.0, 5.0, -1 * DEG], dtype=F64)
    cv_rmse = _position_rmse(
        ts.KalmanFilter(ts.models.ConstantVelocity(q=0.01, r=25.0).double())(
            z, x0[:, :4], P0[:4, :4], dt=dt
        ).mean,
        truth,
    )
    for filt in (ts.ExtendedKalmanFilter(ct), ts.UnscentedKalmanFilter(ct)):
        out = filt(z, x0, P0, dt=dt)
        assert _position_rmse(out.mean, truth) < 5.0 < cv_rmse
        turn_error = (out.mean[:, T // 2 :, 4] - truth[:, T // 2 :, 4]).abs().mean()
        assert float(turn_error) < 0.25 * DEG


# --- The IMM ---


@pytest.mark.parametrize("kind", ["kf", "ekf-ct", "ukf-ct", "svsf", "svsf-h+"])
def test_imm_with_one_mode_is_that_filter(kind):
    truth, z = _track(TURN)
    z = z.clone()
    z[0, 10] = NAN
    z[1, 20, 0] = NAN
    x0, P0 = CV_PRIOR
    if kind == "kf":
        filt = ts.KalmanFilter(_cv())
    elif kind in ("ekf-ct", "ukf-ct"):
        x0, P0 = CT_PRIOR
        kind_class = ts.ExtendedKalmanFilter if kind == "ekf-ct" else ts.UnscentedKalmanFilter
        filt = kind_class(_ct())
    elif kind == "svsf":  # finite-difference velocities (artificial="auto")
        filt = ts.SVSF(_cv(), psi=[400.0, 300.0, 400.0, 300.0], gamma=0.1)
    else:
        filt = ts.SVSF(_cv(), psi=[400.0, 400.0], gamma=0.1, artificial=None)
    expected = filt(z, x0, P0)
    out = ts.IMM([filt], transition=[[1.0]])(z, x0, P0)
    assert_close(out.mean, expected.mean, atol=1e-10, rtol=1e-10)
    assert_close(out.cov, expected.cov, atol=1e-10, rtol=1e-10)
    assert_close(out.modes[0].mean, expected.mean, atol=1e-10, rtol=1e-10)
    assert_close(out.mode_probs, torch.ones_like(out.mode_probs), atol=0)
    if expected.log_likelihood is not None:
        assert_close(out.log_likelihood, expected.log_likelihood, atol=1e-9, rtol=1e-10)


def test_imm_with_identical_modes_is_one_of_them():
    truth, z = _track(TURN)
    x0, P0 = CV_PRIOR
    expected = ts.KalmanFilter(_cv())(z, x0, P0)
    imm = ts.IMM([ts.KalmanFilter(_cv()), ts.KalmanFilter(_cv())], transition=STICKY)
    out = imm(z, x0, P0, mode_probs=[0.3, 0.7])
    assert_close(out.mean, expected.mean, rtol=1e-12, atol=1e-9)
    assert_close(out.cov, expected.cov, rtol=1e-10, atol=1e-9)
    assert_close(out.log_likelihood, expected.log_likelihood, rtol=1e-12, atol=1e-9)
    # Equal likelihoods: the mode probabilities follow the Markov chain alone.
    mu = torch.tensor([0.3, 0.7], dtype=F64)
    for t in range(z.shape[1]):
        mu = mu @ torch.tensor(STICKY, dtype=F64)
        assert_close(out.mode_probs[:, t], mu.expand(3, 2), atol=1e-12)


def _filterpy_imm(models, Pi, mu0, z, x0, P0):
    from filterpy.kalman import IMMEstimator
    from filterpy.kalman import KalmanFilter as FilterpyKF

    filters = []
    for model in models:
        f = FilterpyKF(dim_x=model.state_dim, dim_z=model.meas_dim)
        f.F, f.H = model.transition().numpy(), model.meas_matrix().numpy()
        f.Q, f.R = model.process_noise().numpy(), model.meas_cov().numpy()
        f.x, f.P = x0.numpy().copy(), P0.numpy().copy()
        filters.append(f)
    estimator = IMMEstimator(filters, np.array(mu0), np.array(Pi))
    means, covs, probs = [], [], []
    for z_t in z:
        estimator.predict()
        estimator.update(z_t)
        means.append(estimator.x.copy())
        covs.append(estimator.P.copy())
        probs.append(estimator.mu.copy())
    return np.array(means), np.array(covs), np.array(probs)


def test_imm_matches_filterpy_imm_estimator():
    """Peer oracle: filterpy's IMMEstimator on the same data, two CV modes (quiet, agile)."""
    truth, z = _track(TURN, batch=2, seed=4)
    x0, P0 = CV_PRIOR
    models = [_cv(0.01), _cv(20.0)]
    Pi = [[0.97, 0.03], [0.05, 0.95]]
    out = ts.IMM([ts.KalmanFilter(m) for m in models], Pi, initial_probs=[0.6, 0.4])(z, x0, P0)
    for b in range(2):
        mean, cov, mu = _filterpy_imm(models, Pi, [0.6, 0.4], z[b].numpy(), x0, P0)
        assert_close(out.mean[b], mean, rtol=1e-10, atol=1e-8)
        assert_close(out.cov[b], cov, rtol=1e-9, atol=1e-8)
        assert_close(out.mode_probs[b], mu, rtol=1e-9, atol=1e-10)
    # The agile mode takes over during the turn (steps 30-49) and gives way after it.
    agile = out.mode_probs[..., 1]
    assert float(agile[:, 38:50].mean()) > 0.7 > 0.3 > float(agile[:, 15:30].mean())
    assert float(agile[:, 65:].mean()) < 0.3
    assert_close(out.mode_probs.sum(-1), torch.ones(2, z.shape[1], dtype=F64), atol=1e-12)


def _linear_modes(models, embedding):
    return [
        dict(
            F=m.transition().numpy(),
            Q=m.process_noise().numpy(),
            H=m.meas_matrix().numpy(),
            R=m.meas_cov().numpy(),
            index=ix,
        )
        for m, ix in zip(models, embedding, strict=True)
    ]


def _cv_ca_imm():
    models = [_cv(0.05), _ca(0.5)]
    imm = ts.IMM(
        [ts.KalmanFilter(m) for m in models],
        transition=[[0.9, 0.1], [0.2, 0.8]],
        embedding=CV_IN_CA,
        initial_probs=[0.7, 0.3],
    )
    return imm, models


def test_imm_of_unequal_states_matches_the_numpy_reference():
    """CV inside CA: unbiased mixing (the CV mode lends the CA mode's own acceleration), the
    combination with zero acceleration for the CV mode, missing data, against an independent
    float64 NumPy IMM."""
    truth, z = _track(ACCELERATE, batch=2, seed=5)
    z = z.clone()
    z[0, 5] = NAN
    z[1, 7, 0] = NAN
    x0, P0 = CA_PRIOR
    imm, models = _cv_ca_imm()
    out = imm(z, x0, P0)
    assert out.mean.shape == (2, 65, 6) and out.modes[0].mean.shape == (2, 65, 4)
    for b in range(2):
        ref = numpy_imm(z[b].numpy(), x0.numpy(), P0.numpy(), _linear_modes(models, CV_IN_CA),
                        [[0.9, 0.1], [0.2, 0.8]], [0.7, 0.3])  # fmt: skip
        assert_close(out.mean[b], ref["mean"], rtol=1e-10, atol=1e-8)
        assert_close(out.cov[b], ref["cov"], rtol=1e-9, atol=1e-8)
        assert_close(out.mode_probs[b], ref["mu"], rtol=1e-9, atol=1e-10)
        for j in range(2):
            assert_close(out.modes[j].mean[b], ref["means"][j], rtol=1e-10, atol=1e-8)
        assert_close(out.log_likelihood[b], ref["log_likelihood"], rtol=1e-12, atol=1e-8)
    # The combined acceleration is the CA mode's, weighted by its probability.
    assert_close(out.mean[..., 2], out.mode_probs[..., 1] * out.modes[1].mean[..., 2], atol=1e-12)
    # The CA mode's probability (1/3 at the chain's equilibrium) rises while the target
    # accelerates (steps 25-39) and falls back after.
    ca = out.mode_probs[..., 1]
    assert float(ca[:, 28:42].mean()) > 0.45 > 0.3 > float(ca[:, 10:25].mean())
    assert float(ca[:, 45:60].mean()) < 0.3


def test_mixing_pads_a_missing_component_with_the_receiving_modes_own():
    imm, _ = _cv_ca_imm()
    B = 2
    gen = torch.Generator().manual_seed(0)
    A = torch.randn(B, 6, 6, generator=gen, dtype=F64)
    P_ca = A @ A.mT + torch.eye(6, dtype=F64)
    x_ca = torch.randn(B, 6, generator=gen, dtype=F64)
    A = torch.randn(B, 4, 4, generator=gen, dtype=F64)
    P_cv, x_cv = A @ A.mT + torch.eye(4, dtype=F64), torch.randn(B, 4, generator=gen, dtype=F64)
    x, P = imm.embedding.into(0, 1, x_cv, P_cv, x_ca, P_ca)
    acc, other = [2, 5], [0, 1, 3, 4]
    assert_close(x[:, acc], x_ca[:, acc], atol=0)
    assert_close(x[:, other], x_cv, atol=0)
    assert_close(P[:, acc][:, :, acc], P_ca[:, acc][:, :, acc], atol=0)
    assert_close(P[:, other][:, :, other], P_cv, atol=0)
    assert bool((P[:, acc][:, :, other] == 0).all())
    x, P = imm.embedding.into(1, 0, x_ca, P_ca, x_cv, P_cv)  # CA into CV: its own components
    assert_close(x, x_ca[:, other], atol=0)
    assert_close(P, P_ca[:, other][:, :, other], atol=0)


def test_turn_mode_probability_rises_during_a_coordinated_turn():
    truth, z = _track(TURN, batch=3, seed=6)
    x0, P0 = CT_PRIOR
    imm = ts.IMM(
        [ts.KalmanFilter(_cv(0.01)), ts.ExtendedKalmanFilter(_ct())],
        transition=STICKY,
        embedding=CV_IN_CT,
    )
    out = imm(z, x0, P0)
    turn = out.mode_probs[..., 1]
    assert float(turn[:, 35:50].mean()) > 0.7 > 0.3 > float(turn[:, 10:30].mean())
    assert_close(out.mode_probs.sum(-1), torch.ones_like(turn), atol=1e-12)
    # The combined turn rate follows the 4°/s turn while the CT mode dominates.
    assert abs(float(out.mean[:, 40:50, 4].mean()) - 4 * DEG) < 1.0 * DEG
    ukf = ts.IMM(
        [ts.KalmanFilter(_cv(0.01)), ts.UnscentedKalmanFilter(_ct())],
        transition=STICKY,
        embedding=CV_IN_CT,
    )(z, x0, P0)
    turn = ukf.mode_probs[..., 1]
    assert float(turn[:, 35:50].mean()) > 0.7 > 0.3 > float(turn[:, 10:30].mean())


def test_imm_batch_is_its_rows_run_one_by_one():
    truth, z = _track(TURN, batch=3, seed=7)
    z = z.clone()
    z[1, 4:6] = NAN
    z[2, 9, 1] = NAN
    dt = torch.ones(3, z.shape[1], dtype=F64)
    dt[0, 40:] = 1.5
    x0 = CT_PRIOR[0] + torch.tensor([[0.0], [3.0], [-2.0]], dtype=F64)
    P0 = CT_PRIOR[1]
    probs = torch.tensor([[0.5, 0.5], [0.9, 0.1], [0.2, 0.8]], dtype=F64)
    imm = ts.IMM(
        [ts.KalmanFilter(_cv()), ts.ExtendedKalmanFilter(_ct())],
        transition=STICKY,
        embedding=CV_IN_CT,
    )
    batch = imm(z, x0, P0, dt=dt, mode_probs=probs)
    for b in range(3):
        row = imm(z[b], x0[b], P0, dt=dt[b], mode_probs=probs[b])
        assert_close(batch.mean[b], row.mean, atol=1e-10, rtol=1e-12)
        assert_close(batch.cov[b], row.cov, atol=1e-10, rtol=1e-12)
        assert_close(batch.mode_probs[b], row.mode_probs, atol=1e-12)
        assert_close(batch.modes[1].mean[b], row.modes[1].mean, atol=1e-10, rtol=1e-12)
        assert_close(batch.log_likelihood[b], row.log_likelihood, atol=1e-9, rtol=1e-12)


def test_scan_in_chunks_and_steps_equal_the_whole_run_exactly():
    truth, z = _track(ACCELERATE, batch=2, seed=8)
    z = z.clone()
    z[0, 30] = NAN
    x0, P0 = CA_PRIOR
    imm, _ = _cv_ca_imm()
    whole = imm(z, x0, P0)
    state = imm.init(x0.expand(2, 6), P0)
    parts = []
    for start, stop in [(0, 1), (1, 23), (23, 40), (40, 65)]:
        state, part = imm.scan(state, z[:, start:stop])
        parts.append(part)
    assert_close(torch.cat([p.mean for p in parts], 1), whole.mean, atol=0, rtol=0)
    assert_close(torch.cat([p.cov for p in parts], 1), whole.cov, atol=0, rtol=0)
    assert_close(torch.cat([p.mode_probs for p in parts], 1), whole.mode_probs, atol=0, rtol=0)
    assert_close(state.log_likelihood, whole.log_likelihood, atol=0, rtol=0)
    # One track, one step at a time: the results drop the batch axis.
    state = imm.init(x0, P0)
    for t in range(z.shape[1]):
        state, step = imm.step(state, z[1, t])
        assert_close(step.mean, whole.mean[1, t], atol=0, rtol=0)
        assert_close(step.modes[0].mean, whole.modes[0].mean[1, t], atol=0, rtol=0)
    assert step.mode_probs.shape == (2,) and step.cov.shape == (6, 6)
    assert_close(state.log_likelihood, whole.log_likelihood[1:], atol=0, rtol=0)
    single = imm(z[1], x0, P0)
    assert single.mean.shape == (65, 6) and single.modes[1].cov.shape == (65, 6, 6)
    assert_close(single.mean, whole.mean[1], atol=0, rtol=0)


def test_a_step_without_measurement_says_nothing_about_the_mode():
    truth, z = _track(TURN, batch=2, seed=9)
    z = z.clone()
    z[:, 40] = NAN
    imm = ts.IMM([ts.KalmanFilter(_cv(0.01)), ts.KalmanFilter(_cv(20.0))], transition=STICKY)
    out = imm(z, *CV_PRIOR)
    assert_close(out.mode_log_likelihood[:, 40], torch.zeros(2, 2, dtype=F64), atol=0)
    assert_close(out.mode_probs[:, 40], out.pred_mode_probs[:, 40], atol=1e-15)
    assert_close(out.mode_probs[:, 39] @ imm.transition, out.mode_probs[:, 40], atol=1e-15)


def test_keep_trims_the_result_but_not_the_mode_probabilities():
    truth, z = _track(TURN, batch=2)
    imm = ts.IMM([ts.KalmanFilter(_cv(0.01)), ts.KalmanFilter(_cv(20.0))], transition=STICKY)
    whole = imm(z, *CV_PRIOR)
    moments = imm(z, *CV_PRIOR, keep="moments")
    assert moments.pred_mode_probs is None and moments.modes[0].gain is None
    assert_close(moments.cov, whole.cov, atol=0)
    assert_close(moments.modes[1].cov, whole.modes[1].cov, atol=0)
    mean = imm(z, *CV_PRIOR, keep="mean")
    assert mean.cov is None and mean.modes[0].cov is None
    assert_close(mean.mode_probs, whole.mode_probs, atol=0)
    assert_close(mean.log_likelihood, whole.log_likelihood, atol=0)


def test_gradients_flow_through_the_imm_and_gradcheck_the_transition_logits():
    truth, z = _track(TURN, batch=2, seed=10)
    cv = ts.models.ConstantVelocity(q=0.05, r=100.0, learn_q=True).double()
    imm = ts.IMM(
        [ts.KalmanFilter(cv), ts.ExtendedKalmanFilter(_ct())],
        transition=STICKY,
        embedding=CV_IN_CT,
        learn_transition=True,
    )
    assert {n for n, _ in imm.named_parameters()} == {"transition_logits", "filters.0.model.q.raw"}
    assert_close(imm.transition, torch.tensor(STICKY, dtype=F64), atol=1e-15)
    x0 = CT_PRIOR[0].clone().requires_grad_()
    out = imm(z[:, :30], x0, CT_PRIOR[1])
    (-out.log_likelihood.sum() + out.mean.square().mean()).backward()
    for grad in (imm.transition_logits.grad, cv.q.raw.grad, x0.grad):
        assert grad is not None and bool(torch.isfinite(grad).all()) and bool(grad.abs().sum() > 0)
    imm.zero_grad()
    smoothed = ts.IMMSmoother(imm, lag=3)(z[:, :30], CT_PRIOR[0], CT_PRIOR[1])
    (smoothed.mean[..., [0, 2]] - truth[:, :30, [0, 2]]).square().mean().backward()
    for grad in (imm.transition_logits.grad, cv.q.raw.grad):
        assert grad is not None and bool(torch.isfinite(grad).all()) and bool(grad.abs().sum() > 0)
    # The gradient of the log-likelihood w.r.t. x0 is that of finite differences.
    h = 1e-5
    for k in (1, 2):
        shift = torch.zeros(5, dtype=F64)
        shift[k] = h
        with torch.no_grad():
            plus = imm(z[:, :30], CT_PRIOR[0] + shift, CT_PRIOR[1]).log_likelihood.sum()
            minus = imm(z[:, :30], CT_PRIOR[0] - shift, CT_PRIOR[1]).log_likelihood.sum()
        x0 = CT_PRIOR[0].clone().requires_grad_()
        (grad,) = torch.autograd.grad(imm(z[:, :30], x0, CT_PRIOR[1]).log_likelihood.sum(), x0)
        assert_close(grad[k], (plus - minus) / (2 * h), rtol=1e-5, atol=1e-7)

    # gradcheck on a tiny float64 case, w.r.t. the transition logits.
    gen = torch.Generator().manual_seed(0)
    quiet = ts.models.LinearGaussian(
        torch.tensor([[1.0, 1.0], [0.0, 1.0]]), torch.tensor([[1.0, 0.0]]),
        0.01 * torch.eye(2), torch.tensor([[0.5]]),
    ).double()  # fmt: skip
    agile = ts.models.LinearGaussian(
        torch.tensor([[1.0, 1.0], [0.0, 1.0]]), torch.tensor([[1.0, 0.0]]),
        torch.eye(2), torch.tensor([[0.5]]),
    ).double()  # fmt: skip
    tiny = ts.IMM(
        [ts.KalmanFilter(quiet), ts.KalmanFilter(agile)],
        transition=[[0.8, 0.2], [0.3, 0.7]],
        learn_transition=True,
    )
    zt = torch.randn(2, 4, 1, generator=gen, dtype=F64)
    x0t, P0t = torch.zeros(2, dtype=F64), torch.eye(2, dtype=F64)

    def run(logits):
        out = torch.func.functional_call(tiny, {"transition_logits": logits}, (zt, x0t, P0t))
        return out.log_likelihood, out.mean, out.mode_probs

    logits = tiny.transition_logits.detach().clone().requires_grad_()
    assert torch.autograd.gradcheck(run, (logits,))


def test_float32_runs_stay_finite():
    truth, z = _track(TURN, batch=2, seed=11)
    imm = ts.IMM(
        [ts.KalmanFilter(_cv(0.01)), ts.ExtendedKalmanFilter(_ct())],
        transition=STICKY,
        embedding=CV_IN_CT,
    )
    out = imm(z.float(), CT_PRIOR[0].float(), CT_PRIOR[1].float())
    assert out.mean.dtype == torch.float32
    assert bool(torch.isfinite(out.cov).all()) and bool(torch.isfinite(out.mode_probs).all())
    ref = imm(z, *CT_PRIOR)
    assert_close(out.mean, ref.mean, atol=0.05, rtol=1e-3)


class _Recorder(ts.IMM):
    """A subclass using the interaction hooks: ``aux`` keeps the measurements seen so far, and
    ``adjust_modes`` resets the CA mode's accelerations to zero before each interaction."""

    def __init__(self, *args, reset: bool, **kwargs):
        super().__init__(*args, **kwargs)
        self.reset = reset
        self.calls = 0

    def adjust_modes(self, state):
        self.calls += 1
        if not self.reset:
            return state
        ca = state.modes[1]
        mean = ca.mean.clone()
        mean[:, [2, 5]] = 0.0
        return state._replace(modes=(state.modes[0], ca._replace(mean=mean)))

    def update_aux(self, state, z, dt, u):
        assert state.steps >= 1 and state.modes[1].mean.shape == (2, 6)
        seen = z.unsqueeze(1)
        return seen if state.aux is None else torch.cat([state.aux, seen], 1)


def test_interaction_hooks_see_every_step_and_carry_aux_through_chunks():
    truth, z = _track(ACCELERATE, batch=2, seed=12)
    _, models = _cv_ca_imm()
    kwargs = dict(transition=[[0.9, 0.1], [0.2, 0.8]], embedding=CV_IN_CA)
    plain = ts.IMM([ts.KalmanFilter(m) for m in models], **kwargs)(z, *CA_PRIOR)
    same = _Recorder([ts.KalmanFilter(m) for m in models], reset=False, **kwargs)
    state = same.init(CA_PRIOR[0].expand(2, 6), CA_PRIOR[1])
    state, first = same.scan(state, z[:, :20])
    state, second = same.scan(state, z[:, 20:])
    assert same.calls == z.shape[1]
    assert_close(state.aux, z, atol=0)
    assert_close(torch.cat([first.mean, second.mean], 1), plain.mean, atol=0)
    reset = _Recorder([ts.KalmanFilter(m) for m in models], reset=True, **kwargs)(z, *CA_PRIOR)
    assert float((reset.mean - plain.mean).abs().max()) > 1.0  # the reset changed the mixing


def test_bad_imm_arguments_raise_naming_them():
    cv, ca = _cv(), _ca()
    kf = ts.KalmanFilter(cv)
    cases = [
        (TypeError, "^filters:", lambda: ts.IMM(kf, [[1.0]])),
        (TypeError, "^filters: mode 1", lambda: ts.IMM([kf, cv], STICKY)),
        (ValueError, "^filters: expected at least one", lambda: ts.IMM([], [])),
        (
            ValueError,
            "^filters: the modes measure different sizes",
            lambda: ts.IMM([kf, ts.KalmanFilter(ts.models.ConstantVelocity(ndim=3))], STICKY),
        ),
        (ValueError, r"^transition: .*shape \[2, 2\]", lambda: ts.IMM([kf, kf], [[1.0]])),
        (ValueError, "^transition: .*sum to 1", lambda: ts.IMM([kf, kf], [[0.5, 0.4], [0, 1]])),
        (ValueError, "^transition: .*>= 0", lambda: ts.IMM([kf, kf], [[1.5, -0.5], [0, 1]])),
        (ValueError, "^transition:", lambda: ts.IMM([kf, kf], [[NAN, 1.0], [0, 1]])),
        (TypeError, "^transition:", lambda: ts.IMM([kf, kf], "sticky")),
        (
            ValueError,
            "^transition: a learnable",
            lambda: ts.IMM([kf, kf], [[1.0, 0.0], [0.5, 0.5]], learn_transition=True),
        ),
        (ValueError, "^initial_probs:", lambda: ts.IMM([kf, kf], STICKY, initial_probs=[1, 1])),
        (ValueError, "^initial_probs:", lambda: ts.IMM([kf, kf], STICKY, initial_probs=[1.0])),
        (ValueError, "^embedding: the modes' state sizes differ", lambda: ts.IMM(
            [kf, ts.KalmanFilter(ca)], STICKY)),
        (ValueError, "^embedding: expected 2 index lists", lambda: ts.IMM(
            [kf, ts.KalmanFilter(ca)], STICKY, embedding=[[0, 1, 2, 3]])),
        (ValueError, "^embedding: mode 0: expected 4 distinct", lambda: ts.IMM(
            [kf, ts.KalmanFilter(ca)], STICKY, embedding=[[0, 1, 1, 3], list(range(6))])),
        (ValueError, r"^embedding: common components \[5, 6\] belong to no mode", lambda: ts.IMM(
            [kf, ts.KalmanFilter(ca)], STICKY, embedding=[[0, 1, 3, 4], [0, 1, 2, 3, 4, 7]])),
        (TypeError, "^embedding: mode 1", lambda: ts.IMM(
            [kf, ts.KalmanFilter(ca)], STICKY, embedding=[[0, 1, 3, 4], "012345"])),
        (TypeError, "^imm:", lambda: ts.IMMSmoother(kf, lag=2)),
        (ValueError, "^lag:", lambda: ts.IMMSmoother(ts.IMM([kf, kf], STICKY), lag=0)),
    ]  # fmt: skip
    for error, pattern, make in cases:
        with pytest.raises(error, match=pattern):
            make()


def test_bad_imm_call_inputs_raise_naming_them():
    truth, z = _track(TURN, batch=2)
    x0, P0 = CV_PRIOR
    cv = _cv()
    imm = ts.IMM([ts.KalmanFilter(cv), ts.KalmanFilter(_cv(20.0))], STICKY)
    svsf = ts.SVSF(cv, psi=[400.0, 300.0, 400.0, 300.0], gamma=0.1)  # measures 4 components
    mixed = ts.IMM([ts.KalmanFilter(cv), svsf], STICKY)
    fixed = ts.models.LinearGaussian(cv.transition(), cv.meas_matrix(), cv.process_noise(), cv.R())
    cases = [
        (ValueError, "^mode_probs: .*sum to 1", lambda: imm(z, x0, P0, mode_probs=[0.5, 0.6])),
        (ValueError, r"^mode_probs: .*shape \[2, 2\]", lambda: imm(z, x0, P0, mode_probs=[[1.0]])),
        (ValueError, "^mode_probs:", lambda: imm(z[0], x0, P0, mode_probs=[[0.5, 0.5]] * 2)),
        (ValueError, "^mode_probs:", lambda: imm.init(x0, P0, mode_probs=[-0.5, 1.5])),
        (ValueError, "^z:", lambda: imm(z[..., :1], x0, P0)),
        (ValueError, "^x0:", lambda: imm(z, x0[:3], P0)),
        (ValueError, "^P0: expected a positive definite", lambda: imm(z, x0, -P0)),
        (ValueError, "^dt:", lambda: imm(z, x0, P0, dt=-1.0)),
        (ValueError, "^psi:", lambda: imm(z, x0, P0, psi=torch.ones(2, 80, 2, dtype=F64))),
        (ValueError, "^filters: the modes' correctors measure different things",
         lambda: mixed(z, x0, P0)),
        (ValueError, "^dt: LinearGaussian has fixed matrices",
         lambda: ts.IMM([ts.KalmanFilter(cv), ts.KalmanFilter(fixed.double())], STICKY)(
             z, x0, P0, dt=1.0)),
        (TypeError, "^state:", lambda: imm.scan(ts.KalmanFilter(cv).init(x0, P0), z)),
        (ValueError, "^keep:", lambda: imm(z, x0, P0, keep="everything")),
        (ValueError, "^keep:", lambda: ts.IMMSmoother(imm, lag=2)(z, x0, P0, keep="nothing")),
    ]  # fmt: skip
    for error, pattern, make in cases:
        with pytest.raises(error, match=pattern):
            make()


def test_an_unreachable_mode_keeps_its_state_and_stays_improbable():
    truth, z = _track(TURN, batch=2)
    imm = ts.IMM(
        [ts.KalmanFilter(_cv(0.01)), ts.KalmanFilter(_cv(20.0))],
        transition=[[1.0, 0.0], [0.0, 1.0]],
        initial_probs=[1.0, 0.0],
    )
    out = imm(z, *CV_PRIOR)
    assert bool(torch.isfinite(out.mean).all()) and bool(torch.isfinite(out.modes[1].mean).all())
    assert_close(out.mode_probs[..., 1], torch.zeros(2, 80, dtype=F64), atol=0)
    assert_close(out.mean, ts.KalmanFilter(_cv(0.01))(z, *CV_PRIOR).mean, atol=1e-9, rtol=1e-12)


# --- The smoother ---


@pytest.mark.parametrize("lag", [None, 1, 4])
def test_imm_smoother_with_one_mode_is_the_rts_smoother(lag):
    truth, z = _track(TURN, batch=2, seed=13)
    z = z.clone()
    z[0, 12] = NAN
    expected = ts.RTSSmoother(ts.KalmanFilter(_cv()), lag=lag)(z, *CV_PRIOR)
    out = ts.IMMSmoother(ts.IMM([ts.KalmanFilter(_cv())], [[1.0]]), lag=lag)(z, *CV_PRIOR)
    assert_close(out.mean, expected.mean, atol=1e-9, rtol=1e-10)
    assert_close(out.cov, expected.cov, atol=1e-9, rtol=1e-10)


@pytest.mark.parametrize("lag", [None, 3])
def test_imm_smoother_matches_the_numpy_kim_smoother(lag):
    truth, z = _track(ACCELERATE, batch=2, seed=14)
    z = z.clone()
    z[0, 5] = NAN
    z[1, 50, 1] = NAN
    x0, P0 = CA_PRIOR
    imm, models = _cv_ca_imm()
    out = ts.IMMSmoother(imm, lag=lag)(z, x0, P0)
    modes = _linear_modes(models, CV_IN_CA)
    for b in range(2):
        filtered = numpy_imm(z[b].numpy(), x0.numpy(), P0.numpy(), modes,
                             [[0.9, 0.1], [0.2, 0.8]], [0.7, 0.3])  # fmt: skip
        ref = numpy_kim(filtered, z[b].numpy(), modes, [[0.9, 0.1], [0.2, 0.8]], lag=lag)
        assert_close(out.mean[b], ref["mean"], rtol=1e-10, atol=1e-8)
        assert_close(out.cov[b], ref["cov"], rtol=1e-9, atol=1e-8)
        assert_close(out.mode_probs[b], ref["mu"], rtol=1e-9, atol=1e-10)


def test_a_lag_past_the_track_end_is_the_fixed_interval():
    truth, z = _track(TURN, batch=2, seed=15)
    x0, P0 = CT_PRIOR
    imm = ts.IMM(
        [ts.KalmanFilter(_cv(0.01)), ts.ExtendedKalmanFilter(_ct())],
        transition=STICKY,
        embedding=CV_IN_CT,
    )
    whole = ts.IMMSmoother(imm, lag=None)(z, x0, P0)
    long = ts.IMMSmoother(imm, lag=z.shape[1] + 5)(z, x0, P0)
    assert_close(long.mean, whole.mean, atol=1e-10, rtol=1e-12)
    assert_close(long.cov, whole.cov, atol=1e-10, rtol=1e-12)
    assert_close(long.mode_probs, whole.mode_probs, atol=1e-12)
    assert_close(whole.mean[:, -1], whole.filtered.mean[:, -1], atol=0)
    single = ts.IMMSmoother(imm, lag=3)(z[1], x0, P0, keep="mean")
    assert single.mean.shape == (80, 5) and single.cov is None
    assert_close(single.mean, ts.IMMSmoother(imm, lag=3)(z, x0, P0).mean[1], atol=1e-10)
    # keep="mean" skips the smoothed covariances (the means never depend on them)
    means_only = ts.IMMSmoother(imm, lag=None)(z, x0, P0, keep="mean")
    assert means_only.cov is None and all(m.cov is None for m in means_only.modes)
    assert_close(means_only.mean, whole.mean, atol=1e-10, rtol=1e-12)


def test_imm_smoother_beats_the_filter_on_maneuvering_tracks():
    """Seeded scenario: straight, a 4°/s turn, straight (20 tracks); a CV and a CT mode."""
    truth, z = _track(TURN, batch=20, seed=16)
    x0, P0 = CT_PRIOR
    imm = ts.IMM(
        [ts.KalmanFilter(_cv(0.01)), ts.ExtendedKalmanFilter(_ct())],
        transition=STICKY,
        embedding=CV_IN_CT,
    )
    filtered = _position_rmse(imm(z, x0, P0).mean, truth)
    for lag in (2, 5):
        smoothed = ts.IMMSmoother(imm, lag=lag)(z, x0, P0)
        assert _position_rmse(smoothed.mean, truth) < 0.8 * filtered
        turn = smoothed.mode_probs[..., 1]
        assert float(turn[:, 35:50].mean()) > 0.7 > 0.3 > float(turn[:, 10:28].mean())
