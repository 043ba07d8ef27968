"""Batch invariance, precision, single tracks, gradients, long runs, per-step ψ."""

from __future__ import annotations

import pytest
import torch
from torch.func import functional_call

import torchsvs as ts
from tests.conftest import assert_close, atc_batch, random_system


def _estimators(model, psi, gamma=0.2):
    """The H⁺-mode SVSF family at ``psi`` (one width per position) and, with the default
    ``artificial="auto"`` (finite-difference velocity for a ConstantVelocity model), the same
    widths for each position and velocity."""
    hplus = {"psi": psi, "gamma": gamma, "artificial": None}
    per_state = isinstance(psi, float) or not hasattr(model, "velocity_index")
    velocity = {"psi": psi if per_state else [p for p in psi for _ in (0, 1)], "gamma": gamma}
    return {
        "KF": ts.KalmanFilter(model),
        "KS": ts.RTSSmoother(ts.KalmanFilter(model)),
        "SVSF": ts.SVSF(model, **hplus),
        "SVSTPS": ts.RTSSmoother(ts.SVSF(model, **hplus), lag=1),
        "SVSS": ts.SVSS(ts.SVSF(model, **hplus), lag=2),
        "SVSS-interval": ts.SVSS(ts.SVSF(model, **hplus), lag=None),
        "SVSF-velocity": ts.SVSF(model, **velocity),
        "SVSS-velocity": ts.SVSS(ts.SVSF(model, **velocity), lag=2),
    }


@pytest.mark.parametrize("name", list(_estimators(ts.models.ConstantVelocity(), 1.0)))
def test_batch_equals_rows_run_one_by_one(name):
    system = random_system(4, 2, T=20, B=4, seed=3)
    z, x0, P0 = system.tensors()
    z = z.clone()
    z[1, 4, 0] = float("nan")
    est = _estimators(system.model(), [1.0, 2.0])[name].double()
    batch = est(z, x0, P0)
    for b in range(z.shape[0]):
        single = est(z[b], x0, P0)  # [T, m]: the result drops the batch axis
        assert single.mean.shape == (20, 4) and single.cov.shape == (20, 4, 4)
        assert_close(batch.mean[b], single.mean)
        assert_close(batch.cov[b], single.cov)


@pytest.mark.parametrize("name", ["KF", "SVSF", "SVSTPS", "SVSS"])
def test_float32_agrees_with_float64(name):
    sc = atc_batch(3, seed=1)
    est = _estimators(sc.model, [800.0, 800.0], gamma=0.1)[name]
    out64 = est(sc.z, sc.x0, sc.P0)
    out32 = est(sc.z.float(), sc.x0.float(), sc.P0.float())
    assert out32.mean.dtype == torch.float32
    # Positions are ~1e4 m: float32 resolves ~1e-3 m there.
    assert_close(out32.mean, out64.mean, atol=0.05, rtol=1e-5)
    # Covariance entries reach ~1e4 m²; smoothing subtracts such numbers, so compare at float32's
    # resolution of the largest entry.
    assert_close(out32.cov, out64.cov, atol=1e-5 * out64.cov.abs().max().item(), rtol=1e-4)


def test_single_track_result_drops_batch_axis():
    sc = atc_batch(1)
    out = ts.SVSS(ts.SVSF(sc.model, psi=800.0, gamma=0.1, artificial=None))(sc.z[0], sc.x0, sc.P0)
    T = sc.z.shape[1]
    assert out.mean.shape == (T, 4) and out.cov.shape == (T, 4, 4)
    assert out.filtered.innovation.shape == (T, 2)
    assert out.filtered.transition.shape == (1, 4, 4)


def _param_fn(est, z, x0, P0, output):
    names = ["boundary_layer.raw", "memory.raw"]
    prefix = "filter." if isinstance(est, ts.RTSSmoother) else ""

    def fn(log_psi, logit_gamma, z_):
        params = {prefix + names[0]: log_psi, prefix + names[1]: logit_gamma}
        out = functional_call(est, params, (z_, x0, P0))
        return getattr(out, output)

    return fn


@pytest.mark.parametrize("smoother_lag", [None, 1, 2, "interval"])
def test_gradcheck_wrt_psi_gamma_z(smoother_lag):
    system = random_system(4, 2, T=8, B=2, seed=5)
    z, x0, P0 = system.tensors()
    svsf = ts.SVSF(system.model(), psi=[1.0, 1.6], gamma=0.3).double()
    if smoother_lag is None:
        est = svsf
    else:
        est = ts.SVSS(svsf, lag=None if smoother_lag == "interval" else smoother_lag)
    log_psi = svsf.boundary_layer.raw.detach().clone().requires_grad_(True)
    logit_gamma = svsf.memory.raw.detach().clone().requires_grad_(True)
    zz = z.clone().requires_grad_(True)
    for output in ("mean", "cov"):
        fn = _param_fn(est, zz, x0, P0, output)
        assert torch.autograd.gradcheck(fn, (log_psi, logit_gamma, zz), eps=1e-6, atol=1e-5)


def test_gradients_finite_when_innovation_is_exactly_zero():
    model = ts.models.ConstantVelocity(dt=1.0, q=0.5, r=4.0).double()
    x0 = torch.tensor([1.0, 0.5, -2.0, 0.25], dtype=torch.float64)
    P0 = torch.eye(4, dtype=torch.float64)
    z = torch.randn(2, 6, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    z[:, 0] = (model.meas_matrix() @ model.transition() @ x0).detach()  # e_{1|0} = 0 exactly
    z.requires_grad_(True)
    svss = ts.SVSS(ts.SVSF(model, psi=[2.0, 3.0], gamma=0.1, artificial=None), lag=2)
    out = svss(z, x0, P0)
    assert bool((out.filtered.innovation[:, 0] == 0).all())
    (out.mean.square().sum() + out.cov.sum()).backward()
    params = [svss.filter.boundary_layer.raw, svss.filter.memory.raw]
    for g in [z.grad, *(p.grad for p in params)]:
        assert g is not None and bool(torch.isfinite(g).all())


def test_per_step_psi_override_equals_constant_psi_and_drives_output():
    sc = atc_batch(2)
    B, T = sc.z.shape[:2]
    svss = ts.SVSS(ts.SVSF(sc.model, psi=[800.0, 800.0], gamma=0.1, artificial=None))
    base = svss(sc.z, sc.x0, sc.P0)
    same = svss(sc.z, sc.x0, sc.P0, psi=torch.full((B, T, 2), 800.0, dtype=sc.z.dtype))
    assert_close(same.mean, base.mean)
    psi_bt = torch.full((B, T, 2), 800.0, dtype=sc.z.dtype, requires_grad=True)
    other = svss(sc.z, sc.x0, sc.P0, psi=psi_bt * 0.25)
    assert (other.mean - base.mean).abs().max() > 1.0
    other.mean.sum().backward()
    assert psi_bt.grad is not None and psi_bt.grad.abs().sum() > 0


def test_learn_false_holds_buffers():
    model = ts.models.ConstantVelocity()
    svsf = ts.SVSF(model, psi=[3.0, 4.0], gamma=0.0, learn=False, artificial=None)
    assert list(svsf.parameters()) == []
    assert float(svsf.gamma) == 0.0
    assert_close(svsf.psi, torch.tensor([3.0, 4.0]))
    learnable = ts.SVSF(model, psi=[3.0, 4.0], gamma=0.25, artificial=None)
    assert {n for n, _ in learnable.named_parameters()} == {"boundary_layer.raw", "memory.raw"}
    assert_close(learnable.gamma, torch.tensor(0.25), atol=1e-12)


@pytest.mark.parametrize("name", ["KF", "SVSF", "SVSS", "SVSTPS"])
def test_ten_thousand_float32_steps_stay_finite_and_pd(name):
    model = ts.models.ConstantVelocity(dt=1.0, q=0.16, r=200.0**2)
    gen = torch.Generator().manual_seed(0)
    x0 = torch.tensor([0.0, 10.0, 0.0, -5.0])
    truth, z = model.simulate(x0.expand(2, 4), 10_000, generator=gen)
    z = z.float()
    est = _estimators(model, [800.0, 800.0], gamma=0.1)[name]
    with torch.no_grad():
        out = est(z, x0, torch.diag(torch.tensor([1e4, 1e3, 1e4, 1e3])))
    assert out.mean.dtype == torch.float32
    assert bool(torch.isfinite(out.mean).all()) and bool(torch.isfinite(out.cov).all())
    assert bool((torch.linalg.eigvalsh(out.cov).amin(-1) > 0).all())
    assert_close(out.cov, out.cov.mT, atol=0, rtol=0)


def test_psi_sweep_equals_one_run_per_psi():
    from torchsvs.evaluation import psi_sweep
    from torchsvs.metrics import accumulative_rmse

    sc = atc_batch(3, seed=7)
    svss = ts.SVSS(ts.SVSF(sc.model, psi=1.0, gamma=0.1, artificial=None))
    grid = [(300.0, 300.0), (800.0, 1200.0), (2000.0, 2000.0)]
    scores = psi_sweep(svss, sc.z, sc.x0, sc.P0, sc.truth, grid, accumulative_rmse, max_tracks=6)
    for psi, (filtered, smoothed) in zip(grid, scores, strict=True):
        one = ts.SVSS(ts.SVSF(sc.model, psi=list(psi), gamma=0.1, artificial=None))(
            sc.z, sc.x0, sc.P0
        )
        assert_close(filtered, accumulative_rmse(one.filtered.mean, sc.truth))
        assert_close(smoothed, accumulative_rmse(one.mean, sc.truth))


@pytest.mark.parametrize("lag", [1, 3, None])
def test_shared_covariances_are_smoothed_once_and_equal_per_track_ones(lag):
    system = random_system(4, 2, T=15, B=5, seed=9)
    z, x0, P0 = system.tensors()
    ks = ts.RTSSmoother(ts.KalmanFilter(system.model()), lag=lag)
    shared = ks(z, x0, P0)  # P0 [n, n]: one covariance recursion for all tracks
    per_track = ks(z, x0, P0.expand(5, 4, 4).contiguous())
    assert shared.cov.stride(0) == 0 and per_track.cov.stride(0) != 0
    assert_close(shared.mean, per_track.mean)
    assert_close(shared.cov, per_track.cov)
    svss = ts.SVSS(ts.KalmanFilter(system.model()), lag=lag)(z, x0, P0)
    assert_close(svss.mean, shared.mean)


def test_the_gaussian_log_density_is_torchs_multivariate_normal():
    """The library's one Gaussian log-density (KF log-likelihood, NLL loss, particle weights)
    against torch.distributions, with a batch, and with missing components left out."""
    from torchsvs.linalg import gaussian_log_density

    gen = torch.Generator().manual_seed(0)
    A = torch.randn(5, 3, 3, generator=gen, dtype=torch.float64)
    S = A @ A.mT + 0.5 * torch.eye(3, dtype=torch.float64)
    r = torch.randn(5, 3, generator=gen, dtype=torch.float64)
    expected = torch.distributions.MultivariateNormal(torch.zeros(3, dtype=r.dtype), S).log_prob(r)
    assert_close(gaussian_log_density(r, torch.linalg.cholesky(S), 3.0), expected, atol=1e-12)
    # A missing third component: zero residual, unit variance, not counted.
    masked = S.clone()
    masked[:, 2, :] = masked[:, :, 2] = 0.0
    masked[:, 2, 2] = 1.0
    r2 = r.clone()
    r2[:, 2] = 0.0
    two = torch.distributions.MultivariateNormal(torch.zeros(2, dtype=r.dtype), S[:, :2, :2])
    got = gaussian_log_density(r2, torch.linalg.cholesky(masked), 2.0)
    assert_close(got, two.log_prob(r[:, :2]), atol=1e-12)
