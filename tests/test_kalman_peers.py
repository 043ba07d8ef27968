"""KF and RTS against peer libraries (filterpy, pykalman) on identical random systems."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from filterpy.kalman import KalmanFilter as FPKalmanFilter
from pykalman import KalmanFilter as PKKalmanFilter

import torchsvs as ts
from tests.conftest import assert_close


def _filterpy(sys, b):
    kf = FPKalmanFilter(dim_x=sys.F.shape[0], dim_z=sys.H.shape[0])
    kf.x, kf.P = sys.x0.copy(), sys.P0.copy()
    kf.F, kf.H, kf.Q, kf.R = sys.F, sys.H, sys.Q, sys.R
    means, covs, means_p, covs_p = kf.batch_filter(list(sys.z[b]))
    xs, Ps, _, _ = kf.rts_smoother(means, covs)
    return means, covs, means_p, covs_p, xs, Ps


def _pykalman(sys):
    # pykalman's prior is at the first measurement's time: predict our x0 one step first.
    return PKKalmanFilter(
        transition_matrices=sys.F,
        observation_matrices=sys.H,
        transition_covariance=sys.Q,
        observation_covariance=sys.R,
        initial_state_mean=sys.F @ sys.x0,
        initial_state_covariance=sys.F @ sys.P0 @ sys.F.T + sys.Q,
    )


def test_kalman_filter_and_full_rts_equal_filterpy(system):
    z, x0, P0 = system.tensors()
    model = system.model()
    smoothed = ts.RTSSmoother(ts.KalmanFilter(model)).double()(z, x0, P0)
    filtered = smoothed.filtered
    for b in range(z.shape[0]):
        means, covs, means_p, covs_p, xs, Ps = _filterpy(system, b)
        assert_close(filtered.mean[b], means)
        assert_close(filtered.cov[b], covs)
        assert_close(filtered.pred_mean[b], means_p)
        assert_close(filtered.pred_cov[b], covs_p)
        assert_close(smoothed.mean[b], xs)
        assert_close(smoothed.cov[b], Ps)


def test_rts_and_loglikelihood_equal_pykalman(system):
    z, x0, P0 = system.tensors()
    smoothed = ts.RTSSmoother(ts.KalmanFilter(system.model())).double()(z, x0, P0)
    pk = _pykalman(system)
    for b in range(z.shape[0]):
        means, covs = pk.smooth(system.z[b])
        assert_close(smoothed.mean[b], means)
        assert_close(smoothed.cov[b], covs)
        assert_close(smoothed.filtered.log_likelihood[b], pk.loglikelihood(system.z[b]))


@pytest.mark.parametrize("missing_steps", [[0], [3, 4, 11]])
def test_all_missing_steps_equal_pykalman_masked(system, missing_steps):
    z, x0, P0 = system.tensors()
    z = z.clone()
    z[:, missing_steps] = float("nan")
    smoothed = ts.RTSSmoother(ts.KalmanFilter(system.model())).double()(z, x0, P0)
    pk = _pykalman(system)
    for b in range(z.shape[0]):
        masked = np.ma.masked_invalid(z[b].numpy())
        means, covs = pk.smooth(masked)
        assert_close(smoothed.mean[b], means)
        assert_close(smoothed.cov[b], covs)
        assert_close(smoothed.filtered.log_likelihood[b], pk.loglikelihood(masked))
    # A pure prediction step: posterior equals prior.
    t = missing_steps[-1]
    assert_close(smoothed.filtered.mean[:, t], smoothed.filtered.pred_mean[:, t])
    assert_close(smoothed.filtered.cov[:, t], smoothed.filtered.pred_cov[:, t])


def test_kalman_filter_equals_reference_with_missing_components(system):
    from tests.reference import svs_numpy as ref

    z, x0, P0 = system.tensors()
    z = z.clone()
    gen = torch.Generator().manual_seed(1)
    z[torch.rand(z.shape, generator=gen) < 0.25] = float("nan")
    out = ts.KalmanFilter(system.model()).double()(z, x0, P0)
    for b in range(z.shape[0]):
        r = ref.kalman_filter(
            z[b].numpy(), system.x0, system.P0, system.F, system.H, system.Q, system.R
        )
        for key in ("mean", "cov", "pred_mean", "pred_cov", "innovation"):
            assert_close(getattr(out, key)[b], r[key], msg=key)
