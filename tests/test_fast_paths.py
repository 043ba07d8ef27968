"""The fast paths run what a filter declares (``FastPathFilter.paths``), where the kernels can
carry it (``supports``); a filter that declares none runs its step loop."""

from __future__ import annotations

import torch

import torchsvs as ts
from tests.conftest import assert_close
from torchsvs.filters.fast_paths import NO_FAST_PATHS, FastPaths


def _problem():
    gen = torch.Generator().manual_seed(0)
    z = torch.randn(3, 20, 2, generator=gen, dtype=torch.float64).cumsum(1) * 4
    z[1, 5:8, 0] = float("nan")
    x0 = torch.zeros(3, 4, dtype=torch.float64)
    P0 = torch.eye(4, dtype=torch.float64) * 50
    return ts.models.ConstantVelocity(ndim=2, dt=1.0, q=0.5, r=[4.0, 2.0]).double(), z, x0, P0


def test_each_filter_declares_its_rules_and_the_kernels_limits_apply():
    cv = _problem()[0]
    filters = ts.filters
    declared = {
        filters.KalmanFilter(cv): FastPaths("kalman", "kalman"),
        filters.ExtendedKalmanFilter(cv): FastPaths(dense="kalman"),
        filters.UnscentedKalmanFilter(cv): NO_FAST_PATHS,
        filters.SVSF(cv, psi=30.0): FastPaths(axis="svsf"),  # finite-difference velocity
        filters.SVSF(cv, psi=30.0, artificial=None): FastPaths("svsf", "svsf"),
        filters.VariableBoundarySVSF(cv, psi=3.0): FastPaths(axis="vbl-innovation"),
        filters.ArtificialKalmanFilter(cv): NO_FAST_PATHS,
        # The kernels carry P in the Joseph form and take the model's constant R.
        filters.KalmanFilter(cv, adaptive_noise=filters.AdaptiveNoise(5)): NO_FAST_PATHS,
        filters.KalmanFilter(cv, covariance_form="sqrt"): NO_FAST_PATHS,
        filters.SVSF(cv, psi=30.0, covariance_form="ud"): NO_FAST_PATHS,
    }
    for est, paths in declared.items():
        assert est.supports() == paths, type(est).__name__


def test_a_filter_declaring_no_fast_path_runs_its_step_loop_to_the_same_numbers():
    class Plain(ts.filters.KalmanFilter):
        paths = NO_FAST_PATHS

    cv, z, x0, P0 = _problem()
    kf, plain = ts.filters.KalmanFilter(cv).double(), Plain(cv).double()
    with torch.no_grad():
        fast, slow = kf(z, x0, P0), plain(z, x0, P0)
        state = plain.init(x0, P0)
        assert plain.step_shortcut(state, z[:, 0], None, "all") is None
        state, _ = plain.step(state, z[:, 0])
    assert fast.axes is not None and slow.axes is None  # the per-axis kernel: the KF's only
    assert state.constants is None  # no compiled online step either
    for key in ("mean", "cov", "innovation_cov", "log_likelihood"):
        assert_close(getattr(fast, key), getattr(slow, key), atol=1e-10, rtol=1e-10, msg=key)
