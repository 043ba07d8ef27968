"""The robust Student's t based Kalman filter: reductions and robustness."""

from __future__ import annotations

import pytest
import torch

import torchsvs as ts
from tests.conftest import assert_close, atc_batch, random_system


@pytest.mark.parametrize("shapes", ["derived", "swapped"])
def test_large_dof_and_tau_reduce_to_kalman_filter(system, shapes):
    z, x0, P0 = system.tensors()
    z = z.clone()
    z[0, 3, 0] = float("nan")
    big = 1e13
    rstkf = ts.RobustStudentTKalmanFilter(
        system.model(), dof_state=big, dof_meas=big, tau=big, scale_shapes=shapes
    )
    out = rstkf(z, x0, P0)
    kf = ts.KalmanFilter(system.model())(z, x0, P0)
    assert_close(out.mean, kf.mean, atol=1e-6, rtol=1e-6)
    assert_close(out.cov, kf.cov, atol=1e-6, rtol=1e-6)
    assert_close(out.gain, kf.gain, atol=1e-6, rtol=1e-6)


def test_measurement_outlier_is_downweighted():
    system = random_system(4, 2, T=12, B=1, seed=8)
    z, x0, P0 = system.tensors()
    clean_kf = ts.KalmanFilter(system.model())(z, x0, P0).mean
    clean_rst = ts.RobustStudentTKalmanFilter(system.model(), tau=1e6)(z, x0, P0).mean
    z_out = z.clone()
    z_out[0, 6] += 200.0  # ~100σ
    kf_shift = (ts.KalmanFilter(system.model())(z_out, x0, P0).mean - clean_kf)[0, 6].norm()
    rst = ts.RobustStudentTKalmanFilter(system.model(), tau=1e6)(z_out, x0, P0).mean
    rst_shift = (rst - clean_rst)[0, 6].norm()
    assert rst_shift < 0.1 * kf_shift


def test_iterations_and_batches_are_consistent():
    sc = atc_batch(3, seed=2)
    est = ts.RobustStudentTKalmanFilter(sc.model, scale_shapes="swapped")
    batch = est(sc.z[:, :60], sc.x0, sc.P0)
    for b in range(3):
        assert_close(batch.mean[b], est(sc.z[b, :60], sc.x0, sc.P0).mean)
    assert bool(torch.isfinite(batch.cov).all())
    assert bool((torch.linalg.eigvalsh(batch.cov) > 0).all())
    one = ts.RobustStudentTKalmanFilter(sc.model, iterations=1)(sc.z[:, :60], sc.x0, sc.P0)
    assert (one.mean - est(sc.z[:, :60], sc.x0, sc.P0).mean).abs().max() > 1e-3


@pytest.mark.parametrize("shapes", ["derived", "swapped"])
def test_all_missing_step_is_a_prediction(shapes):
    sc = atc_batch(2, seed=3)
    z = sc.z[:, :20].clone()
    z[:, 5] = float("nan")
    z[0, 9, 1] = float("nan")
    z[1, 12:] = float("nan")  # a short track padded in the batch: predictions only
    out = ts.RobustStudentTKalmanFilter(sc.model, scale_shapes=shapes)(z, sc.x0, sc.P0)
    assert_close(out.mean[:, 5], out.pred_mean[:, 5])
    assert_close(out.cov[:, 5], out.pred_cov[:, 5])
    # Swapped shapes once shrank E[ξ] at every empty step and P grew to inf.
    assert bool(torch.isfinite(out.cov).all())
    assert bool(torch.isfinite(out.mean).all())


@pytest.mark.parametrize(
    "kwargs, pattern",
    [
        ({"dof_state": 0.0}, "^dof_state: expected a number > 0"),
        ({"dof_meas": -1.0}, "^dof_meas: expected a number > 0"),
        ({"tau": 0}, "^tau: expected a number > 0"),
        ({"iterations": 0}, "^iterations: expected an integer >= 1"),
        ({"scale_shapes": "other"}, "^scale_shapes: expected 'derived' or 'swapped'"),
    ],
)
def test_bad_settings(kwargs, pattern):
    with pytest.raises(ValueError, match=pattern):
        ts.RobustStudentTKalmanFilter(ts.models.ConstantVelocity(), **kwargs)
