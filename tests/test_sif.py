"""The sliding innovation filter (Gadsden & Al-Shabi 2020) against a NumPy oracle written from
the paper, its reduction to the SVSF without memory, the step protocol, gradients."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import torchsvs as ts
from tests.conftest import assert_close
from torchsvs.kernels import general_path


def _sif_numpy(z, x0, P0, F, Q, H, R, delta):
    """Eqs. (9)-(13) of the paper, one track, float64, missing components skipped."""
    x, P, means, covs = x0.copy(), P0.copy(), [], []
    for z_t in z:
        x, P = F @ x, F @ P @ F.T + Q
        seen = ~np.isnan(z_t)
        e = np.where(seen, z_t - H @ x, 0.0)
        Hm = H * seen[:, None]
        K = np.linalg.pinv(Hm) @ np.diag(np.clip(np.abs(e) / delta, -1, 1))
        A = np.eye(len(x)) - K @ H
        x, P = x + K @ e, A @ P @ A.T + K @ R @ K.T
        means.append(x)
        covs.append(P)
    return np.array(means), np.array(covs)


def _problem():
    sc = ts.scenarios.atc_scenario(num_runs=3, generator=torch.Generator().manual_seed(0))
    z = sc.z[:, :120].clone()
    z[0, 30:35, 0] = float("nan")
    z[1, 50] = float("nan")
    return sc.model.double(), z, sc.x0, sc.P0


def test_sif_matches_the_numpy_oracle():
    model, z, x0, P0 = _problem()
    delta = np.array([600.0, 900.0])
    sif = ts.SlidingInnovationFilter(model, delta=delta).double()
    out = sif(z, x0, P0)
    F, Q = model.transition().numpy(), model.process_noise().numpy()
    H, R = model.meas_matrix().numpy(), model.meas_cov().numpy()
    for b in range(z.shape[0]):
        prior = x0[b] if x0.ndim == 2 else x0
        cov = P0[b] if P0.ndim == 3 else P0
        mean, covs = _sif_numpy(z[b].numpy(), prior.numpy(), cov.numpy(), F, Q, H, R, delta)
        assert_close(out.mean[b], mean, atol=1e-8)
        assert_close(out.cov[b], covs, atol=1e-6, rtol=1e-9)


def test_sif_is_the_svsf_without_memory():
    model, z, x0, P0 = _problem()
    sif = ts.SlidingInnovationFilter(model, delta=[700.0, 800.0]).double()
    svsf = ts.SVSF(model, psi=[700.0, 800.0], gamma=0.0, learn=False, artificial=None).double()
    with general_path():
        a, b = sif(z, x0, P0), svsf(z, x0, P0)
    assert_close(a.mean, b.mean, atol=1e-9)
    assert_close(a.cov, b.cov, atol=1e-6)


def test_sif_runs_online_and_learns_delta():
    model, z, x0, P0 = _problem()
    sif = ts.SlidingInnovationFilter(model, delta=800.0).double()
    whole = sif(z, x0, P0)
    state = sif.init(x0.expand(3, 4), P0)
    for t in range(0, z.shape[1], 7):
        state, part = sif.scan(state, z[:, t : t + 7])
        assert_close(part.mean, whole.mean[:, t : t + 7], atol=1e-12, rtol=1e-12)
    whole.mean.square().mean().backward()
    assert sif.layer.raw.grad is not None and bool(torch.isfinite(sif.layer.raw.grad).all())


def test_bad_delta():
    model = ts.models.ConstantVelocity()
    with pytest.raises(ValueError, match=r"^delta: expected finite values > 0"):
        ts.SlidingInnovationFilter(model, delta=-1.0)
    with pytest.raises(ValueError, match=r"^delta: expected a scalar or 2 widths"):
        ts.SlidingInnovationFilter(model, delta=[1.0, 2.0, 3.0])
