"""The per-axis kernel of the constant-velocity model equals the general path, values and
gradients, and steps aside where the problem does not decouple by axis."""

from __future__ import annotations

import pytest
import torch

import torchsvs as ts
from tests.conftest import assert_close
from torchsvs.kernels import general_path

FIELDS = ("mean", "cov", "pred_mean", "pred_cov", "innovation", "mask", "gain")
FIELDS += ("post_innovation", "innovation_cov", "log_likelihood", "meas_cov", "transition")


def _problem(seed=0, B=3, T=30, missing=0.2):
    gen = torch.Generator().manual_seed(seed)
    z = torch.randn(B, T, 2, generator=gen, dtype=torch.float64) * 3
    z = z + torch.arange(T, dtype=torch.float64)[None, :, None] * torch.tensor([2.0, -1.0])
    z[torch.rand(B, T, 2, generator=gen) < missing] = float("nan")
    z[:, 7] = float("nan")
    dt = torch.rand(B, T, generator=gen, dtype=torch.float64) + 0.5
    x0 = torch.randn(B, 4, generator=gen, dtype=torch.float64)
    P0 = torch.diag(torch.tensor([9.0, 2.0, 9.0, 2.0], dtype=torch.float64)).repeat(B, 1, 1)
    P0[:, 0, 1] = P0[:, 1, 0] = 1.0  # within an axis: allowed
    return z, dt, x0, P0


def _estimators(model):
    fd, hplus = [3.0, 2.0, 4.0, 1.5], [3.0, 4.0]
    return {
        "KF": ts.KalmanFilter(model),
        "KS": ts.RTSSmoother(ts.KalmanFilter(model)),
        "KS lag 2": ts.RTSSmoother(ts.KalmanFilter(model), lag=2),
        "SVSF": ts.SVSF(model, psi=fd, gamma=0.2),
        "SVSF H+": ts.SVSF(model, psi=hplus, gamma=0.2, artificial=None),
        "SVSF adjacent": ts.SVSF(
            model, psi=fd, gamma=0.2, artificial=ts.FiniteDifferenceVelocity(bridge_gaps=False)
        ),
        "SVSS lag 2": ts.SVSS(ts.SVSF(model, psi=fd, gamma=0.2), lag=2),
        "SVSS H+ lag 3": ts.SVSS(ts.SVSF(model, psi=hplus, gamma=0.2, artificial=None), lag=3),
        "SVSS interval": ts.SVSS(ts.SVSF(model, psi=fd, gamma=0.2), lag=None),
        "SVSTPS": ts.RTSSmoother(ts.SVSF(model, psi=3.0, gamma=0.2), lag=1),
    }


NAMES = list(_estimators(ts.models.ConstantVelocity()))


def _filtered(out):
    return out.filtered if isinstance(out, ts.SmootherResult) else out


@pytest.mark.parametrize("name", NAMES)
@pytest.mark.parametrize("per_step_dt", [True, False], ids=["dt-per-step", "dt-model"])
def test_kernel_equals_general_path(name, per_step_dt):
    z, dt, x0, P0 = _problem()
    model = ts.models.ConstantVelocity(dt=1.5, q=0.5, r=[4.0, 2.0]).double()
    est = _estimators(model)[name].double()
    step = dt if per_step_dt else None
    fast = est(z, x0, P0, dt=step)
    assert _filtered(fast).axes is not None
    with general_path():
        slow = est(z, x0, P0, dt=step)
    assert _filtered(slow).axes is None
    assert_close(fast.mean, slow.mean, atol=1e-9)
    assert_close(fast.cov, slow.cov, atol=1e-9)
    for key in FIELDS:
        a, b = getattr(_filtered(fast), key), getattr(_filtered(slow), key)
        assert (a is None) == (b is None), key
        if a is not None:
            assert_close(a.double(), b.double(), atol=1e-9, msg=key)


@pytest.mark.parametrize("name", ["KS", "SVSS lag 2", "SVSTPS"])
def test_kernel_gradients_equal_general_path(name):
    z, dt, x0, P0 = _problem(seed=1, T=15)
    model = ts.models.ConstantVelocity(dt=1.0, q=0.5, r=[4.0, 2.0], learn_q=True).double()
    est = _estimators(model)[name].double()
    z = z.clone().requires_grad_(True)

    def grads():
        out = est(z, x0, P0, dt=dt)
        loss = out.mean.square().sum() + out.cov.diagonal(dim1=-2, dim2=-1).sum()
        params = [p for p in est.parameters() if p.requires_grad]
        return torch.autograd.grad(loss, [z, *params])

    fast = grads()
    with general_path():
        slow = grads()
    for a, b in zip(fast, slow, strict=True):
        assert_close(a, b, atol=1e-8, rtol=1e-8)


def test_single_track_and_psi_override_go_through_the_kernel():
    z, dt, x0, P0 = _problem(seed=2, B=2)
    model = ts.models.ConstantVelocity(q=0.5, r=[4.0, 2.0]).double()
    svss = ts.SVSS(ts.SVSF(model, psi=[3.0, 2.0, 4.0, 1.5], gamma=0.2), lag=2).double()
    psi = torch.rand(2, z.shape[1], 4, dtype=torch.float64) * 4 + 0.5
    fast = svss(z, x0, P0, dt=dt, psi=psi)
    one = svss(z[1], x0[1], P0[1], dt=dt[1], psi=psi[1])
    with general_path():
        slow = svss(z, x0, P0, dt=dt, psi=psi)
    assert_close(fast.mean, slow.mean, atol=1e-9)
    assert_close(one.mean, slow.mean[1], atol=1e-9)
    assert one.filtered.axes is None  # internals are not part of a single track's result


def test_kernel_steps_aside_when_axes_are_coupled():
    z, dt, x0, P0 = _problem(seed=3)
    correlated = ts.models.ConstantVelocity(q=0.5, r=[[4.0, 1.0], [1.0, 2.0]]).double()
    assert ts.KalmanFilter(correlated)(z, x0, P0, dt=dt).axes is None
    model = ts.models.ConstantVelocity(q=0.5, r=[4.0, 2.0]).double()
    coupled = P0.clone()
    coupled[:, 0, 2] = coupled[:, 2, 0] = 0.5
    assert ts.KalmanFilter(model)(z, x0, coupled, dt=dt).axes is None
    assert ts.ExtendedKalmanFilter(model)(z, x0, P0, dt=dt).axes is None
    assert ts.KalmanFilter(model)(z, x0, P0, dt=dt).axes is not None


def test_associative_scan_is_a_prefix_product():
    from torchsvs.kernels.scan import associative_scan

    gen = torch.Generator().manual_seed(0)
    for steps in (1, 2, 7, 64, 129):
        x = torch.randn(3, steps, 2, generator=gen, dtype=torch.float64)
        (total,) = associative_scan(lambda a, b: (a[0] + b[0],), (x,))
        assert_close(total, x.cumsum(dim=1))
        # A non-commutative one: products of 2x2 matrices, later ones on the left.
        M = torch.randn(2, steps, 2, 2, generator=gen, dtype=torch.float64)
        (prod,) = associative_scan(lambda a, b: (b[0] @ a[0],), (M,))
        expected, running = [], torch.eye(2, dtype=torch.float64).expand(2, 2, 2)
        for k in range(steps):
            running = M[:, k] @ running
            expected.append(running)
        assert_close(prod, torch.stack(expected, 1), atol=1e-9)


@pytest.mark.parametrize("name", ["KF", "KS"])
def test_time_scan_on_few_long_tracks_equals_general_path(name):
    """Two tracks of 300 steps take the associative scan over time."""
    from torchsvs.kernels.axes import prefer_scan

    z, dt, x0, P0 = _problem(seed=4, B=2, T=300)
    assert prefer_scan(2 * 2, 300)
    model = ts.models.ConstantVelocity(q=0.5, r=[4.0, 2.0]).double()
    est = _estimators(model)[name].double()
    fast = est(z, x0, P0, dt=dt)
    with general_path():
        slow = est(z, x0, P0, dt=dt)
    assert_close(fast.mean, slow.mean, atol=1e-8)
    assert_close(fast.cov, slow.cov, atol=1e-8)
    for key in FIELDS:
        a, b = getattr(_filtered(fast), key), getattr(_filtered(slow), key)
        if a is not None:
            assert_close(a.double(), b.double(), atol=1e-8, msg=key)
