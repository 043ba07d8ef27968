"""SVSF, SVSTPS and SVSS against the float64 NumPy reference written from the paper."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import torchsvs as ts
from tests.conftest import assert_close, atc_batch, random_system
from tests.reference import svs_numpy as ref

FILTER_KEYS = ("mean", "cov", "pred_mean", "pred_cov", "innovation", "post_innovation")
LAGS = [1, 2, 3, None]


def _psi(m: int) -> np.ndarray:
    # Widths near the innovation scale, so both the linear and the saturated branch of Eq. (6) run.
    return np.linspace(0.8, 2.5, m)


def _svsf(system, gamma=0.3, **kw):
    psi = torch.from_numpy(_psi(system.H.shape[0]))
    return ts.SVSF(system.model(), psi=psi, gamma=gamma, **kw).double()


def _ref_svsf(system, z, gamma=0.3):
    m = system.H.shape[0]
    return ref.svsf(z, system.x0, system.P0, system.F, system.H, system.Q, system.R, _psi(m), gamma)


def _both_branches_exercised(result, psi):
    ratio = result.innovation.abs() / torch.as_tensor(psi)
    assert bool((ratio < 1).any()) and bool((ratio > 1).any())


@pytest.mark.parametrize("missing", [False, True], ids=["complete", "missing"])
def test_svsf_equals_reference(system, missing):
    z, x0, P0 = system.tensors()
    if missing:
        z = z.clone()
        z[torch.rand(z.shape, generator=torch.Generator().manual_seed(2)) < 0.25] = float("nan")
        z[:, 5] = float("nan")
    out = _svsf(system)(z, x0, P0)
    _both_branches_exercised(out, _psi(system.H.shape[0]))
    for b in range(z.shape[0]):
        r = _ref_svsf(system, z[b].numpy())
        for key in FILTER_KEYS:
            assert_close(getattr(out, key)[b], r[key], msg=key)


@pytest.mark.parametrize("lag", LAGS)
@pytest.mark.parametrize("missing", [False, True], ids=["complete", "missing"])
def test_svss_equals_direct_eq42(system, lag, missing):
    """The O(T·L) / O(T) recursions equal Eq. (42) evaluated literally, product by product."""
    z, x0, P0 = system.tensors()
    if missing:
        z = z.clone()
        z[torch.rand(z.shape, generator=torch.Generator().manual_seed(3)) < 0.3] = float("nan")
    out = ts.SVSS(_svsf(system), lag=lag)(z, x0, P0)
    for b in range(z.shape[0]):
        r = _ref_svsf(system, z[b].numpy())
        d = ref.smooth_direct(r, system.F, system.H, system.R, lag=lag, increment="svss")
        assert_close(out.mean[b], d["mean"])
        if lag == 1:
            # At lag 1 the paper's projection covariance is the exact one; at larger lags it is
            # not (Eq. (38) holds for the Kalman gain only): see test_smoother_covariance_*.
            assert_close(out.cov[b], d["cov"])


@pytest.mark.parametrize("lag", LAGS)
def test_svstps_equals_rts_windows_over_svsf(system, lag):
    z, x0, P0 = system.tensors()
    out = ts.RTSSmoother(_svsf(system), lag=lag)(z, x0, P0)
    for b in range(z.shape[0]):
        r = _ref_svsf(system, z[b].numpy())
        w = ref.rts_window(r, system.F, lag=lag)
        assert_close(out.mean[b], w["mean"])
        # Eq. (17)'s covariance is exact for any filter gain: C_k makes the parts uncorrelated.
        assert_close(out.cov[b], w["cov"], atol=1e-8)


@pytest.mark.parametrize("lag", LAGS)
def test_svss_over_kalman_filter_equals_rts(system, lag):
    """With the Kalman gain forward, B_N is the Kalman gain and SVSS reduces to RTS."""
    z, x0, P0 = system.tensors()
    kf = ts.KalmanFilter(system.model())
    svss = ts.SVSS(kf, lag=lag)(z, x0, P0)
    rts = ts.RTSSmoother(kf, lag=lag)(z, x0, P0)
    assert_close(svss.mean, rts.mean)
    assert_close(svss.cov, rts.cov, atol=1e-8)


def test_svss_differs_from_svstps_over_svsf(system):
    z, x0, P0 = system.tensors()
    svsf = _svsf(system)
    a = ts.SVSS(svsf, lag=1)(z, x0, P0).mean
    b = ts.RTSSmoother(svsf, lag=1)(z, x0, P0).mean
    assert (a - b).abs().max() > 1e-3


def test_atc_svsf_never_corrects_velocity():
    """Sec. 4.1: H⁺ = Hᵀ for position-only H, so the velocity keeps its prior value."""
    sc = atc_batch(2)
    out = ts.SVSF(sc.model, psi=[800.0, 800.0], gamma=0.1, artificial=None)(sc.z, sc.x0, sc.P0)
    assert_close(out.mean[..., [1, 3]], sc.x0[[1, 3]].expand(2, out.mean.shape[1], 2))
    F, H, Q, R = (
        sc.model.transition().numpy(),
        sc.model.meas_matrix().numpy(),
        sc.model.process_noise().numpy(),
        sc.model.meas_cov().numpy(),
    )
    r = ref.svsf(
        sc.z[0].numpy(), sc.x0.numpy(), sc.P0.numpy(), F, H, Q, R, np.array([800.0, 800.0]), 0.1
    )
    for key in FILTER_KEYS:
        assert_close(getattr(out, key)[0], r[key], msg=key)


def test_artificial_velocity_equals_reference():
    """SVSF with Eq. (51) pseudo-measurements equals the reference run on y with H = I."""
    sc = atc_batch(2, seed=4)
    z = sc.z.clone()
    z[0, 7, 1] = float("nan")
    dt = 1.0
    svsf = ts.SVSF(
        sc.model,
        psi=[500.0, 600.0, 500.0, 600.0],
        gamma=0.1,
        artificial=ts.FiniteDifferenceVelocity(bridge_gaps=False),  # Eq. (51) as printed
    ).double()
    out = svsf(z, sc.x0, sc.P0)
    r_pos = sc.model.meas_cov()[0, 0].item()
    R_axis = np.array([[r_pos, r_pos / dt], [r_pos / dt, 2 * r_pos / dt**2]])
    R_y = np.kron(np.eye(2), R_axis)
    F, Q = sc.model.transition().numpy(), sc.model.process_noise().numpy()
    for b in range(2):
        y = ref.finite_difference_velocity(z[b].numpy(), dt)
        assert_close(torch.isnan(torch.from_numpy(y)), ~out.mask[b])
        r = ref.svsf(
            y,
            sc.x0.numpy(),
            sc.P0.numpy(),
            F,
            np.eye(4),
            Q,
            R_y,
            np.array([500.0, 600, 500, 600]),
            0.1,
        )
        for key in FILTER_KEYS:
            assert_close(getattr(out, key)[b], r[key], msg=key)
        d = ref.smooth_direct(r, F, np.eye(4), R_y, lag=2)
        assert_close(ts.SVSS(svsf, lag=2)(z, sc.x0, sc.P0).mean[b], d["mean"])


@pytest.mark.parametrize("per_step_dt", [False, True], ids=["scalar-dt", "per-step-dt"])
def test_gap_bridging_velocity_and_noise_equal_reference(per_step_dt):
    """Velocities across missing positions difference against the axis' last observation."""
    sc = atc_batch(2, seed=6)
    z = sc.z.clone()
    hide = torch.rand(z.shape, generator=torch.Generator().manual_seed(1)) < 0.3
    z[hide] = float("nan")
    z[:, 3] = float("nan")
    R = torch.tensor([[4.0e4, 1.0e4], [1.0e4, 2.5e4]], dtype=z.dtype)
    model = ts.models.ConstantVelocity(dt=2.0, q=0.16, r=R).double()
    dt = torch.full(z.shape[:2], 2.0, dtype=z.dtype) if per_step_dt else None
    y, H, R_y = ts.FiniteDifferenceVelocity()(z, model, dt)
    assert_close(H, torch.eye(4))
    for b in range(2):
        assert_close(y[b], ref.finite_difference_velocity(z[b].numpy(), 2.0, bridge_gaps=True))
        expected = ref.finite_difference_noise(z[b].numpy(), 2.0, R.numpy())
        seen = ~torch.isnan(y[b])
        both = (seen.unsqueeze(-1) & seen.unsqueeze(-2)).numpy()  # masked entries are free
        assert_close(np.where(both, R_y[b].numpy(), 0.0), np.where(both, expected, 0.0))
    bridged = ~torch.isnan(y[..., [1, 3]])
    adjacent = ~torch.isnan(
        ts.FiniteDifferenceVelocity(bridge_gaps=False)(z, model, dt)[0][..., [1, 3]]
    )
    assert bool((bridged & ~adjacent).any()) and not bool((adjacent & ~bridged).any())


def test_artificial_velocity_with_per_step_dt_matches_scalar_dt():
    sc = atc_batch(2, seed=5)
    svsf = ts.SVSF(
        sc.model, psi=[500.0, 600.0, 500.0, 600.0], artificial=ts.FiniteDifferenceVelocity()
    )
    a = svsf(sc.z, sc.x0, sc.P0)
    b = svsf(sc.z, sc.x0, sc.P0, dt=torch.ones(sc.z.shape[:2], dtype=sc.z.dtype))
    assert_close(a.mean, b.mean)
    assert_close(a.cov, b.cov)


def test_gamma_memory_matters():
    system = random_system(3, 3, seed=7)
    z, x0, P0 = system.tensors()
    a = _svsf(system, gamma=0.0, learn=False)(z, x0, P0).mean
    b = _svsf(system, gamma=0.6)(z, x0, P0).mean
    assert (a - b).abs().max() > 1e-2
    r = _ref_svsf(system, z[0].numpy(), gamma=0.0)
    assert_close(a[0], r["mean"])


@pytest.mark.parametrize("lag", LAGS)
@pytest.mark.parametrize("kind", ["svss", "rts"])
def test_smoother_covariance_equals_dense_exact_covariance(system, lag, kind):
    """The O(T) covariance recursion equals Cov(x_k − x̂ˢ_k) built as a dense linear map of all
    noises, given the SVSF's gains, with missing components and an all-missing step."""
    z, x0, P0 = system.tensors()
    z = z.clone()
    z[torch.rand(z.shape, generator=torch.Generator().manual_seed(6)) < 0.2] = float("nan")
    z[:, 9] = float("nan")
    svsf = _svsf(system)
    est = ts.SVSS(svsf, lag=lag) if kind == "svss" else ts.RTSSmoother(svsf, lag=lag)
    out = est(z, x0, P0)
    m = system.H.shape[0]
    for b in range(z.shape[0]):
        zb = z[b].numpy()
        gains = ref.svsf_gains(
            zb, system.x0, system.P0, system.F, system.H, system.Q, system.R, _psi(m), 0.3
        )
        assert_close(out.filtered.gain[b], gains)
        dense = ref.dense_smoother_covariance(
            system.F,
            system.H,
            system.Q,
            system.R,
            system.P0,
            gains,
            ~np.isnan(zb),
            lag=lag,
            kind=kind,
        )
        assert_close(out.cov[b], dense["cov"], atol=1e-8, rtol=1e-8)
        assert bool((torch.linalg.eigvalsh(out.cov[b]) > -1e-9).all())


@pytest.mark.parametrize("bridge_gaps", [True, False])
def test_finite_differences_without_gaps_equal_reference(bridge_gaps):
    """Gap-free measurements on one interval take the one-pass adjacent differences; they
    equal the NumPy reference exactly as the gap path does."""
    sc = atc_batch(3, seed=8)
    art = ts.FiniteDifferenceVelocity(bridge_gaps=bridge_gaps)
    velocity, (r, cross, vv) = art.per_axis(sc.z, sc.model, None)
    dt = float(sc.model.dt)
    for b in range(3):
        expected = ref.finite_difference_velocity(sc.z[b].numpy(), dt, bridge_gaps=bridge_gaps)
        assert_close(velocity[b], torch.from_numpy(expected[:, 1::2]), atol=0, rtol=0)
    assert torch.isnan(velocity[:, 0]).all() and not torch.isnan(velocity[:, 1:]).any()
    r_pos = sc.model.meas_cov().diagonal()
    assert_close(vv, 2 * r_pos / dt**2)
