"""The compiled SURE curves and positions of the Kalman smoother (``kernels/cpp/curves.h``,
:mod:`torchsvs.kernels.curves`) against the estimator's own runs in tensor loops
(:func:`torchsvs.kernels.eager_loops`): the risks, the chosen factors, the kept passes, the
outlier screen's distances; per-track ``q``; threads; float32."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from torchsvs.datasets import two_point_prior
from torchsvs.datasets.priors import first_observed_two
from torchsvs.filters import KalmanFilter
from torchsvs.fitting import noise
from torchsvs.fitting.outliers import outlier_distances
from torchsvs.kernels import curves, eager_loops
from torchsvs.models import ConstantVelocity
from torchsvs.smoothers import RTSSmoother


def _ragged(B: int = 60, T: int = 80, m: int = 2, seed: int = 0) -> tuple[torch.Tensor, ...]:
    """Tracks with irregular intervals, missing positions (both axes and one), a padded tail
    after each track's end, one track of one row and a maneuver; float64."""
    g = torch.Generator().manual_seed(seed)
    dt = (torch.rand(B, T, generator=g, dtype=torch.float64) * 4.0 + 0.5).clone()
    t = dt.cumsum(1)
    speed = torch.randn(B, 1, m, generator=g, dtype=torch.float64) * 20.0
    turn = torch.where(t > 100.0, (t - 100.0) * 0.5, 0.0).unsqueeze(-1)
    z = t.unsqueeze(-1) * speed + turn * turn + 30.0 * torch.randn(B, T, m, generator=g)
    z[torch.rand(B, T, generator=g) < 0.1] = math.nan
    z[..., 1][torch.rand(B, T, generator=g) < 0.05] = math.nan
    lengths = torch.randint(3, T + 1, (B,), generator=g)
    lengths[0] = 1
    z[torch.arange(T).unsqueeze(0) >= lengths.unsqueeze(1)] = math.nan
    r = torch.tensor([900.0, 400.0], dtype=torch.float64)[:m]
    return z, dt, r


@pytest.mark.parametrize("smoothed", [True, False])
def test_curves_equal_the_estimators_passes(smoothed: bool) -> None:
    z, dt, r = _ragged()
    pooled = None

    def choose(found: noise.QCurves) -> torch.Tensor:
        nonlocal pooled
        pooled = pooled or found.pooled()
        off_grid = torch.where(torch.arange(found.risk.shape[1]) % 3 == 0, 1.7, 1.0)
        return noise.track_q_factors(found, pooled) * off_grid

    compiled = noise.q_curve_runs(z, dt, r, 0.3, smoothed, choose=choose, keep=True)
    with eager_loops():
        eager = noise.q_curve_runs(z, dt, r, 0.3, smoothed, choose=choose, keep=True)
    scale = eager[0].risk.abs().clamp_min(1.0)
    assert ((compiled[0].risk - eager[0].risk).abs() / scale).max() < 1e-10
    torch.testing.assert_close(compiled[0].counts, eager[0].counts, rtol=0, atol=0)
    assert compiled[1] is not None and torch.equal(compiled[1], eager[1])
    kept, reference = compiled[2], eager[2]
    assert kept is not None and reference is not None
    assert bool(kept.ran.all())  # every track at its own factor, on the grid or not
    on_grid = reference.ran
    assert bool(on_grid.any()) and not bool(on_grid.all())  # the case is exercised
    torch.testing.assert_close(
        kept.mean[on_grid], reference.mean[on_grid], rtol=1e-10, atol=1e-8, equal_nan=True
    )
    torch.testing.assert_close(
        kept.position_var[on_grid], reference.position_var[on_grid], rtol=1e-9, atol=0
    )


def test_positions_with_each_tracks_q_equal_the_estimator() -> None:
    z, dt, r = _ragged(B=12, seed=1)
    prior = two_point_prior(z, dt, r)
    q = torch.logspace(-2, 1, 12, dtype=torch.float64)
    found = curves.positions(z, dt, prior.x0, prior.P0, r, q)
    assert found is not None
    mean, var = found.mean, found.var
    for b in range(len(q)):
        model = ConstantVelocity(ndim=2, q=float(q[b]), r=r.tolist()).double()
        with eager_loops(), torch.no_grad():
            out = RTSSmoother(KalmanFilter(model))(
                z[b : b + 1], prior.x0[b : b + 1], prior.P0[b : b + 1], dt=dt[b : b + 1]
            )
        torch.testing.assert_close(mean[b], out.mean[0], rtol=1e-10, atol=1e-8)
        cov = out.cov[0].diagonal(dim1=-2, dim2=-1)[..., 0::2]
        torch.testing.assert_close(var[b], cov, rtol=1e-9, atol=0)


def test_positions_float32_and_threads() -> None:
    z, dt, r = _ragged(B=200, T=700, seed=2)  # 140,000 track-steps: the loop's threads
    prior = two_point_prior(z, dt, r)
    q = torch.full((200,), 0.2, dtype=torch.float64)
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one = curves.positions(z, dt, prior.x0, prior.P0, r, q)
        torch.set_num_threads(2)
        two = curves.positions(z, dt, prior.x0, prior.P0, r, q)
    finally:
        torch.set_num_threads(before)
    assert one is not None and two is not None
    assert torch.equal(one[0], two[0]) and torch.equal(one[1], two[1])
    low = curves.positions(
        z.float(), dt.float(), prior.x0.float(), prior.P0.float(), r.float(), q.float()
    )
    assert low is not None
    seen = ~torch.isnan(z)
    position = one[0][..., 0::2][seen]
    error = (low[0][..., 0::2].double()[seen] - position).abs().max()
    assert float(error) < 1e-6 * float(position.abs().max())  # a few float32 spacings


def test_positions_of_one_track_do_not_depend_on_the_batch() -> None:
    z, dt, r = _ragged(B=40, seed=3)
    prior = two_point_prior(z, dt, r)
    q = torch.full((40,), 0.5, dtype=torch.float64)
    whole = curves.positions(z, dt, prior.x0, prior.P0, r, q)
    part = curves.positions(z[7:9], dt[7:9], prior.x0[7:9], prior.P0[7:9], r, q[7:9])
    assert whole is not None and part is not None
    assert torch.equal(whole[0][7:9], part[0]) and torch.equal(whole[1][7:9], part[1])


def test_outlier_distances_equal_the_estimators() -> None:
    z, dt, r = _ragged(seed=4)
    full = (~torch.isnan(z)).all(-1).unfold(1, 7, 1).all(-1)  # rows t..t+6 observed
    b, start = (int(i) for i in torch.nonzero(full[:, 20:])[0])
    t = start + 23  # the middle of seven observed rows
    z[b, t] += 500.0
    compiled = outlier_distances(z, dt, r, 3.0)
    with eager_loops():
        eager = outlier_distances(z, dt, r, 3.0)
    torch.testing.assert_close(compiled, eager, rtol=1e-8, atol=1e-10, equal_nan=True)
    assert float(compiled[b, t]) > 50.0
    # rows not judged (a track of one row, rows between the ends of short tracks) are NaN alike
    high = torch.isnan(compiled) & (~torch.isnan(z)).all(-1)
    assert bool(high[0, 0]) and int(high.sum()) > 1


def test_curves_need_the_compiled_loops_else_none() -> None:
    z, dt, r = _ragged(B=4)
    prior = two_point_prior(z, dt, r)
    q = torch.full((4, 3), 0.5, dtype=torch.float64)
    counted = ~torch.isnan(z)
    with eager_loops():
        assert curves.sure_risks(z, dt, counted, prior.x0, prior.P0, r, q) is None
        assert curves.positions(z, dt, prior.x0, prior.P0, r, q[:, 0]) is None
        assert curves.studentized(z, dt, prior.x0, prior.P0, r, 0.5, 0.9) is None


@pytest.mark.parametrize("smoothed", [True, False])
def test_the_first_two_observations_divergence_is_autograds(smoothed: bool) -> None:
    """The estimate's derivative by each axis's first and second measurement, through the
    two-point prior too: the tangent runs of the compiled pass against autograd through the
    prior and the estimator's tensor loops (a late first observation, an axis seen once, a
    track of one row)."""
    z, dt, r = _ragged(B=8, T=30, seed=5)
    z[2, :5, 0] = math.nan
    z[3, :, 1] = math.nan
    z[3, 7, 1] = 5.0
    prior = two_point_prior(z, dt, r, speed_std=50.0)
    found = noise.kalman_positions(z, dt, prior.x0, prior.P0, r, 0.4, smoothed, chunk=8)
    assert found.first_two is not None
    first, second, has_first, has_second = first_observed_two(~torch.isnan(z))
    checked = 0
    for b in range(len(z)):
        for j in range(2):
            for i, (index, has) in enumerate(((first, has_first), (second, has_second))):
                value = float(found.first_two[b, j, i])
                if not has[b, j]:
                    assert math.isnan(value)
                    continue
                t = int(index[b, j])
                moved = z[b : b + 1].clone().requires_grad_(True)
                start = two_point_prior(moved, dt[b : b + 1], r, speed_std=50.0)
                with eager_loops():
                    out = noise.kalman(2, 0.4, r, smoothed)(
                        moved, start.x0, start.P0, dt=dt[b : b + 1]
                    )
                (grad,) = torch.autograd.grad(out.mean[0, t, 2 * j], moved)
                assert value == pytest.approx(float(grad[0, t, j]), abs=1e-12)
                checked += 1
    assert checked > 20


@pytest.mark.parametrize("smoothed", [True, False])
def test_the_passes_chunk_sums_are_sures_terms(smoothed: bool) -> None:
    """SURE's sums per chunk written by the compiled pass equal those of its outputs in
    tensors (accuracy.exact_risk_terms of the means, the exact divergence from the variances
    and the first two observations' tangents): the same chunks, the same sums to rounding."""
    from torchsvs.accuracy import CHUNK, exact_divergence, exact_risk_terms, terms_of_sums

    z, dt, r = _ragged(B=30, T=100, seed=6)  # ragged lengths: chunks past a track's end
    prior = two_point_prior(z, dt, r)
    found = noise.kalman_positions(z, dt, prior.x0, prior.P0, r, 0.3, smoothed, CHUNK)
    assert found.sums is not None and found.first_two is not None
    assert found.sums.shape == (30, -(-100 // CHUNK), 2, 3)
    compiled = terms_of_sums(found.sums)
    # the variances' divergence, with the tangents (held to autograd above) placed at each
    # axis's first two observations, where exact_divergence leaves NaN
    divergence = exact_divergence(z, found.var, r)
    first, second, has_first, has_second = first_observed_two(~torch.isnan(z))
    for index, has, i in ((first, has_first, 0), (second, has_second, 1)):
        for b, j in torch.nonzero(has).tolist():
            divergence[b, index[b, j], j] = found.first_two[b, j, i]
    tensors = exact_risk_terms(z, found.mean[..., 0::2], divergence)
    assert np.array_equal(compiled.track, tensors.track)
    assert np.array_equal(compiled.count, tensors.count)
    np.testing.assert_allclose(compiled.residual, tensors.residual, rtol=1e-10, atol=1e-6)
    np.testing.assert_allclose(compiled.divergence, tensors.divergence, rtol=1e-10, atol=1e-12)
    with pytest.raises(ValueError, match="chunk: expected steps >= 1 with the tangents"):
        curves.positions(z, dt, prior.x0, prior.P0, r, torch.ones(30, dtype=torch.float64), chunk=4)
