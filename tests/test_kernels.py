"""The per-axis kernel of the constant-velocity model equals the general path, values and
gradients, and steps aside where the problem does not decouple by axis."""

from __future__ import annotations

import subprocess

import pytest
import torch

import torchsvs as ts
from tests.conftest import assert_close
from torchsvs.kernels import build, eager_loops, fused_axes, fused_dense, general_path

FIELDS = ("mean", "cov", "pred_mean", "pred_cov", "innovation", "mask", "gain")
FIELDS += ("post_innovation", "innovation_cov", "log_likelihood", "meas_cov", "transition")


def _problem(seed=0, B=3, T=30, missing=0.2):
    gen = torch.Generator().manual_seed(seed)
    z = torch.randn(B, T, 2, generator=gen, dtype=torch.float64) * 3
    z = z + torch.arange(T, dtype=torch.float64)[None, :, None] * torch.tensor([2.0, -1.0])
    z[torch.rand(B, T, 2, generator=gen) < missing] = float("nan")
    z[:, 7:8] = float("nan")
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
        "KS lag 1": ts.RTSSmoother(ts.KalmanFilter(model), lag=1),
        "KS lag 2": ts.RTSSmoother(ts.KalmanFilter(model), lag=2),
        "SVSF": ts.SVSF(model, psi=fd, gamma=0.2),
        "SVSF H+": ts.SVSF(model, psi=hplus, gamma=0.2, artificial=None),
        "SVSF adjacent": ts.SVSF(
            model, psi=fd, gamma=0.2, artificial=ts.FiniteDifferenceVelocity(bridge_gaps=False)
        ),
        "SVSS lag 1": ts.SVSS(ts.SVSF(model, psi=fd, gamma=0.2), lag=1),
        "SVSS lag 2": ts.SVSS(ts.SVSF(model, psi=fd, gamma=0.2), lag=2),
        "SVSS H+ lag 3": ts.SVSS(ts.SVSF(model, psi=hplus, gamma=0.2, artificial=None), lag=3),
        "SVSS interval": ts.SVSS(ts.SVSF(model, psi=fd, gamma=0.2), lag=None),
        "SVSTPS": ts.RTSSmoother(ts.SVSF(model, psi=3.0, gamma=0.2), lag=1),
        # The variable boundary layer, its limit low enough to inflate at a third of the steps.
        "VBL": ts.VariableBoundarySVSF(model, psi=[1.2, 0.9], gamma=0.2),
        "VBL SVSS lag 1": ts.SVSS(ts.VariableBoundarySVSF(model, psi=1.1, gamma=0.2), lag=1),
        "VBL SVSS lag 2": ts.SVSS(ts.VariableBoundarySVSF(model, psi=1.1, gamma=0.2), lag=2),
        "VBL SVSS interval": ts.SVSS(ts.VariableBoundarySVSF(model, psi=1.1), lag=None),
        "VBL SVSTPS": ts.RTSSmoother(ts.VariableBoundarySVSF(model, psi=1.1), lag=1),
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
    """Two tracks of 300 steps take the associative scan over time (where the compiled loops
    are not used)."""
    from torchsvs.kernels.scan import prefer_scan

    z, dt, x0, P0 = _problem(seed=4, B=2, T=300)
    assert prefer_scan(2 * 2, 300)
    model = ts.models.ConstantVelocity(q=0.5, r=[4.0, 2.0]).double()
    est = _estimators(model)[name].double()
    with eager_loops():
        fast = est(z, x0, P0, dt=dt)
    with general_path():
        slow = est(z, x0, P0, dt=dt)
    assert_close(fast.mean, slow.mean, atol=1e-8)
    assert_close(fast.cov, slow.cov, atol=1e-8)
    for key in FIELDS:
        a, b = getattr(_filtered(fast), key), getattr(_filtered(slow), key)
        if a is not None:
            assert_close(a.double(), b.double(), atol=1e-8, msg=key)


needs_compiler = pytest.mark.skipif(
    build._compiler() is None, reason="no C++ compiler: the compiled loops cannot be built"
)


@pytest.fixture
def spy(monkeypatch):
    """Counts the compiled loops' calls: the forward pass, the smoother passes together, and
    the dense linear steps."""
    calls = {"forward": 0, "adjoint": 0, "backward": 0, "dense": 0, "together": 0}
    for module, function, counter in (
        (fused_axes, "forward", "forward"),
        (fused_axes, "filter_smoother", "together"),
        (fused_axes, "adjoint", "adjoint"),
        (fused_axes, "backward_adjoint", "adjoint"),
        (fused_axes, "backward", "backward"),
        (fused_axes, "rts_interval", "backward"),
        (fused_dense, "dense_run", "dense"),
    ):
        original = getattr(module, function)

        def counted(*args, _original=original, _counter=counter, **kwargs):
            calls[_counter] += 1
            return _original(*args, **kwargs)

        monkeypatch.setattr(module, function, counted)
    online_step = fused_dense.OnlineStep.__call__

    def counted_step(self, *args, **kwargs):  # an online step: dense_run's one-step form
        calls["dense"] += 1
        return online_step(self, *args, **kwargs)

    monkeypatch.setattr(fused_dense.OnlineStep, "__call__", counted_step)
    return calls


@pytest.fixture
def on_two_threads(monkeypatch):
    """Runs a test with 2 intra-op threads; yields the thread count of every compiled call."""
    counts = []
    threads = build.threads

    def counted(*args):
        counts.append(threads(*args))
        return counts[-1]

    monkeypatch.setattr(build, "threads", counted)
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        yield counts
    finally:
        torch.set_num_threads(before)


@needs_compiler
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["f64", "f32"])
@pytest.mark.parametrize("name", NAMES)
def test_compiled_loops_equal_tensor_loops(name, dtype, spy):
    """Without gradients the per-axis kernel runs its compiled loops: the same numbers as the
    tensor loops (which the tests above hold to the general path), every field."""
    assert build.library() is not None, build.failure()
    z, dt, x0, P0 = (x.to(dtype) for x in _problem(seed=5, B=4, T=40))
    model = ts.models.ConstantVelocity(dt=1.5, q=0.5, r=[4.0, 2.0])
    est = _estimators(model)[name].to(dtype)
    with torch.no_grad():
        compiled = est(z, x0, P0, dt=dt)
        assert spy["forward"] == 1
        # lag 1 runs inside the forward loop; other smoothers over its record
        assert spy["backward"] == int(isinstance(est, ts.RTSSmoother) and est.lag != 1)
        with eager_loops():
            eager = est(z, x0, P0, dt=dt)
    assert spy["forward"] == 1
    tol = {"atol": 1e-10, "rtol": 1e-10} if dtype == torch.float64 else {"atol": 1e-3, "rtol": 1e-4}
    assert_close(compiled.mean, eager.mean, **tol)
    assert_close(compiled.cov, eager.cov, **tol)
    for key in FIELDS:
        a, b = getattr(_filtered(compiled), key), getattr(_filtered(eager), key)
        assert (a is None) == (b is None), key
        if a is not None:
            assert a.dtype in (dtype, torch.bool), key
            assert_close(a, b, msg=key, **tol)


@needs_compiler
@pytest.mark.parametrize("ndim", [1, 3, 4])
def test_compiled_loops_for_any_axis_count_on_threads(ndim, spy, on_two_threads):
    """The compiled loops unroll 1-3 axes and take any other count at run time, and split
    large batches over threads (here 2): every case equals the tensor loops to 1e-10."""
    B, T = 1100, 100  # ≥ 100k track-steps and B·n² ≥ 4096: the loops run on threads
    gen = torch.Generator().manual_seed(ndim)
    z = torch.randn(B, T, ndim, generator=gen, dtype=torch.float64) * 3
    z = z + torch.arange(T, dtype=torch.float64)[None, :, None]
    z[torch.rand(B, T, ndim, generator=gen) < 0.1] = float("nan")
    dt = torch.rand(B, T, generator=gen, dtype=torch.float64) + 0.5
    x0 = torch.randn(B, 2 * ndim, generator=gen, dtype=torch.float64)
    P0 = torch.eye(2 * ndim, dtype=torch.float64) * 4
    model = ts.models.ConstantVelocity(ndim=ndim, q=0.5, r=[2.0 + i for i in range(ndim)])
    model = model.double()
    fd = [3.0, 2.0] * ndim
    estimators = {
        "KF": ts.KalmanFilter(model),
        "KS": ts.RTSSmoother(ts.KalmanFilter(model)),
        "SVSF H+": ts.SVSF(model, psi=[3.0] * ndim, gamma=0.2, artificial=None),
        "SVSS lag 2": ts.SVSS(ts.SVSF(model, psi=fd, gamma=0.2), lag=2),
    }
    for name, est in estimators.items():
        with torch.no_grad():
            compiled = est(z, x0, P0, dt=dt)
            with eager_loops():
                eager = est(z, x0, P0, dt=dt)
        assert_close(compiled.mean, eager.mean, atol=1e-10, rtol=1e-10, msg=name)
        assert_close(compiled.cov, eager.cov, atol=1e-10, rtol=1e-10, msg=name)
        for key in FIELDS:
            a, b = getattr(_filtered(compiled), key), getattr(_filtered(eager), key)
            if a is not None:
                assert_close(a, b, atol=1e-10, rtol=1e-10, msg=f"{name} {key}")
    assert spy["forward"] == 4 and spy["backward"] == 2
    assert on_two_threads == [2] * 6


@needs_compiler
@pytest.mark.parametrize("scale", [1e-12, 1e-7, 1.0, 1e7, 1e12])
def test_compiled_log_likelihood_at_any_scale_of_S(scale, spy):
    """The compiled loop takes the logarithm of S once per 16 steps, through a product of the
    factors in (1e-15, 1e15), and of any other factor at once: the log-likelihood equals the
    tensor loops' to 1e-12 relative whether S is tiny, ordinary or huge, over many flushes."""
    z, dt, x0, P0 = _problem(seed=9, B=3, T=70)
    # S ≈ r ≈ scale²: 1e±24 go straight in; 1e±14 multiply, and overflow without the flushes.
    variance = scale**2
    model = ts.models.ConstantVelocity(q=0.5 * variance, r=[4.0 * variance, 2.0 * variance])
    kf = ts.KalmanFilter(model.double())
    z, x0, P0 = z * scale, x0 * scale, P0 * variance
    with torch.no_grad():
        compiled = kf(z, x0, P0, dt=dt)
        with eager_loops():
            eager = kf(z, x0, P0, dt=dt)
    assert spy["forward"] == 1
    assert compiled.log_likelihood is not None and eager.log_likelihood is not None
    assert_close(compiled.log_likelihood, eager.log_likelihood, atol=0, rtol=1e-12)


@needs_compiler
def test_compiled_loops_take_per_step_psi_and_lags_beyond_the_track(spy):
    z, dt, x0, P0 = _problem(seed=6, B=3, T=12)
    model = ts.models.ConstantVelocity(q=0.5, r=[4.0, 2.0]).double()
    psi = torch.rand(3, 12, 4, dtype=torch.float64) * 4 + 0.5
    for lag in (1, 11, 50):
        svss = ts.SVSS(ts.SVSF(model, psi=[3.0, 2.0, 4.0, 1.5], gamma=0.2), lag=lag).double()
        with torch.no_grad():
            compiled = svss(z, x0, P0, dt=dt, psi=psi)
            with general_path():
                general = svss(z, x0, P0, dt=dt, psi=psi)
        assert_close(compiled.mean, general.mean, atol=1e-9)
        assert_close(compiled.cov, general.cov, atol=1e-9)
    assert spy["forward"] == 3 and spy["backward"] == 2  # lag 1 smooths in the forward loop


LAG_ONE = {
    "KS": lambda model: ts.RTSSmoother(ts.KalmanFilter(model), lag=1),
    "SVSTPS": lambda model: ts.RTSSmoother(ts.SVSF(model, psi=[3.0, 2.0], artificial=None), lag=1),
    "SVSS H+": lambda model: ts.SVSS(ts.SVSF(model, psi=[3.0, 4.0], gamma=0.2, artificial=None)),
    "SVSS": lambda model: ts.SVSS(ts.SVSF(model, psi=[3.0, 2.0, 4.0, 1.5], gamma=0.2)),
}


@needs_compiler
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["f64", "f32"])
@pytest.mark.parametrize("name", list(LAG_ONE))
def test_lag_one_smoothing_in_the_forward_loop_equals_the_backward_pass(name, dtype, spy):
    """A one-step-lag smoother runs inside the compiled forward loop (each step smooths the one
    before it from the lanes' registers) and gives exactly what the backward pass over the
    stored record gives: every track of a batch wider than a block of lanes, steps across
    the loop's chunk boundaries, gaps, per-step intervals, tracks of one and two steps, and
    whatever the call keeps."""
    model = ts.models.ConstantVelocity(dt=1.5, q=0.5, r=[4.0, 2.0]).to(dtype)
    est = LAG_ONE[name](model).to(dtype)
    for B, T in ((70, 40), (3, 1), (3, 2), (40, 17)):
        z, dt, x0, P0 = (x.to(dtype) for x in _problem(seed=T, B=B, T=T))
        with torch.no_grad():
            record = est.filter(z, x0, P0, dt=dt)
            calls = spy["backward"]
            reference = est.smooth(record)
            assert spy["backward"] == calls + (T > 1)
            # The same recursion to the bit; over two steps the RTS's backward pass is Eq. (17)
            close = 1e-12 if dtype == torch.float64 else 1e-5
            same = est.projection_gain or T != 2
            tol = {"atol": 0, "rtol": 0} if same else {"atol": close, "rtol": close}
            for keep in ("all", "moments", "mean"):
                fused_pass = est(z, x0, P0, dt=dt, keep=keep)
                assert spy["backward"] == calls + (T > 1), "the smoothing ran in the forward loop"
                assert_close(fused_pass.mean, reference.mean, **tol)
                if keep != "mean":
                    assert_close(fused_pass.cov, reference.cov, **tol)
                    assert_close(fused_pass.filtered.cov, record.cov, atol=0, rtol=0)
                assert_close(fused_pass.filtered.mean, record.mean, atol=0, rtol=0)
                if keep == "all":
                    for key in FIELDS:
                        a, b = getattr(fused_pass.filtered, key), getattr(record, key)
                        if a is not None:
                            assert_close(a, b, atol=0, rtol=0, msg=key)


@needs_compiler
def test_lag_one_smoothing_in_the_forward_loop_on_threads(spy, on_two_threads):
    """Tracks split over threads smooth in the forward loop like one thread does."""
    z, dt, x0, P0 = _problem(seed=11, B=1100, T=100, missing=0.1)
    model = ts.models.ConstantVelocity(q=0.5, r=[4.0, 2.0]).double()
    svss = LAG_ONE["SVSS"](model).double()
    with torch.no_grad():
        whole = svss(z, x0, P0, dt=dt)
        reference = svss.smooth(svss.filter(z, x0, P0, dt=dt))
    assert_close(whole.mean, reference.mean, atol=0, rtol=0)
    assert_close(whole.cov, reference.cov, atol=0, rtol=0)
    assert spy["forward"] == 2 and spy["backward"] == 1
    assert on_two_threads == [2] * 3


@needs_compiler
@pytest.mark.parametrize("name", list(LAG_ONE))
def test_lag_one_smoothing_with_gradients_runs_in_the_forward_loop(name, spy):
    """Training a one-step-lag smoother runs the smoothing inside the compiled forward loop and
    takes it back in that loop's adjoint (no smoother pass): the numbers are those without
    gradients, and the gradients of every smoothed and filtered output equal those of the
    smoother's own general recursion over the filter's whole record (its compiled reverse
    mode, a separate implementation)."""
    z, dt, x0, P0 = _problem(seed=12, B=5, T=30)
    model = ts.models.ConstantVelocity(q=0.5, r=[4.0, 2.0], learn_noise=True).double()
    smoother = LAG_ONE[name](model).double()
    params = [p for p in smoother.parameters() if p.requires_grad]

    def grads(out):
        weights = torch.linspace(-1.0, 1.0, out.cov.numel(), dtype=torch.float64)
        loss = out.mean.square().sum() * 1e-2 + (out.cov * weights.reshape(out.cov.shape)).sum()
        loss = loss + out.filtered.mean.sum() + out.filtered.cov.diagonal(0, -2, -1).sum()
        return torch.autograd.grad(loss, [*params, zz, xx, PP])

    zz, xx, PP = (x.clone().requires_grad_(True) for x in (z, x0, P0))
    fused_run = smoother(zz, xx, PP, dt=dt)
    assert (spy["forward"], spy["backward"]) == (1, 0) and fused_run.mean.requires_grad
    fused_grads = grads(fused_run)
    assert spy["adjoint"] == 1
    general_run = smoother.smooth(smoother.filter(zz, xx, PP, dt=dt))
    general_grads = grads(general_run)
    assert (spy["backward"], spy["adjoint"]) == (1, 3)
    assert_close(fused_run.mean, general_run.mean, atol=1e-12, rtol=0)
    assert_close(fused_run.cov, general_run.cov, atol=1e-12, rtol=0)
    for i, (a, b) in enumerate(zip(fused_grads, general_grads, strict=True)):
        assert a.abs().sum() > 0, i
        assert_close(a, b, atol=1e-10, rtol=1e-10, msg=f"gradient {i}")
    with torch.no_grad():
        inferred = smoother(z, x0, P0, dt=dt)
    assert_close(fused_run.mean.detach(), inferred.mean, atol=0, rtol=0)
    assert_close(fused_run.cov.detach(), inferred.cov, atol=0, rtol=0)


@needs_compiler
@pytest.mark.parametrize("name", ["KS", "KS lag 2", "SVSS lag 2", "SVSS H+ lag 3", "SVSS interval"])
@pytest.mark.parametrize("keep", ["mean", "moments"])
def test_training_a_smoother_keeping_less_runs_filter_and_smoother_together(name, keep, spy):
    """Training a smoother of another lag while keeping less than all runs the filter and the
    smoother's recursion in one compiled pass (fused_axes.filter_smoother: no record written, no
    smoother pass of its own) and its reverse mode: its numbers and gradients equal those of
    the whole record's pass through the smoother's own recursion and reverse mode (and the
    inference pass runs them together too, whatever the batch's size)."""
    z, dt, x0, P0 = _problem(seed=13, B=4, T=30)
    model = ts.models.ConstantVelocity(q=0.5, r=[4.0, 2.0], learn_noise=True).double()
    smoother = _estimators(model)[name].double()
    params = [p for p in smoother.parameters() if p.requires_grad]
    zz, xx, PP = (x.clone().requires_grad_(True) for x in (z, x0, P0))

    def grads(out):
        loss = out.mean.square().sum() * 1e-2 + out.filtered.mean.sum()
        if keep == "moments":  # else the smoothed and filtered covariances are not kept
            weights = torch.linspace(-1.0, 1.0, out.cov.numel(), dtype=torch.float64)
            loss = loss + (out.cov * weights.reshape(out.cov.shape)).sum()
            loss = loss + out.filtered.cov.diagonal(0, -2, -1).square().sum()
        return torch.autograd.grad(loss, [*params, zz, xx, PP])

    together = smoother(zz, xx, PP, dt=dt, keep=keep)
    assert (spy["forward"], spy["backward"], spy["together"]) == (0, 0, 1)
    assert (together.filtered.cov is None) == (keep == "mean")
    fused_grads = grads(together)
    assert spy["adjoint"] == 1
    whole = smoother(zz, xx, PP, dt=dt)
    assert (spy["forward"], spy["backward"]) == (1, 1)
    whole_grads = grads(whole)
    assert_close(together.mean, whole.mean, atol=1e-12, rtol=0)
    if keep == "moments":
        assert_close(together.cov, whole.cov, atol=1e-12, rtol=0)
    for i, (a, b) in enumerate(zip(fused_grads, whole_grads, strict=True)):
        assert a.abs().sum() > 0, i
        assert_close(a, b, atol=1e-10, rtol=1e-10, msg=f"gradient {i}")
    with torch.no_grad():  # 4 tracks × 2 axes: together too (not chosen by the batch's size)
        inferred = smoother(z, x0, P0, dt=dt, keep=keep)
    assert (spy["forward"], spy["backward"], spy["together"]) == (1, 1, 2)
    assert_close(inferred.mean, together.mean.detach(), atol=0, rtol=0)
    assert_close(inferred.mean, whole.mean.detach(), atol=1e-12, rtol=0)
    assert_close(inferred.filtered.mean, whole.filtered.mean.detach(), atol=0, rtol=0)


def _gradients(est, dtype, z, dt, x0, P0):
    """The gradients of a loss of every output field with respect to every learnable parameter
    and to ``z``, ``x0`` and ``P0``."""
    z, x0, P0 = (x.clone().requires_grad_(True) for x in (z, x0, P0))
    out = est(z, x0, P0, dt=dt)
    filtered = _filtered(out)
    loss = torch.zeros((), dtype=dtype)
    for i, key in enumerate(FIELDS):
        value = getattr(filtered, key)
        if value is not None and value.is_floating_point() and value.requires_grad:
            weights = torch.linspace(-1.0, 1.0, value.numel(), dtype=dtype).reshape(value.shape)
            loss = loss + (value * weights).sum() / (i + 1)
    loss = loss + (out.mean * out.mean).sum() * 1e-3 + out.cov.diagonal(dim1=-2, dim2=-1).sum()
    params = [p for p in est.parameters() if p.requires_grad]
    return torch.autograd.grad(loss, [*params, z, x0, P0], allow_unused=True)


@needs_compiler
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["f64", "f32"])
@pytest.mark.parametrize("name", NAMES)
def test_compiled_gradients_equal_tensor_loop_gradients(name, dtype, spy):
    """With gradients the per-axis forward loop runs compiled and its reverse mode too
    (axes._CompiledAxes): the gradients of every output field (with weights, so that no term
    cancels) with respect to ψ, γ, q, R, the measurements and the prior equal those of the
    differentiable tensor loops, with gaps and a per-step interval."""
    z, dt, x0, P0 = (x.to(dtype) for x in _problem(seed=11, B=3, T=25))
    model = ts.models.ConstantVelocity(q=0.5, r=[4.0, 2.0], learn_q=True, learn_r=True)
    est = _estimators(model)[name].to(dtype)
    for p in est.parameters():
        p.requires_grad_(True)
    compiled = _gradients(est, dtype, z, dt, x0, P0)
    # Smoothers of lag 1 train inside the forward loop and its adjoint; the others through the
    # general backward recursion and its reverse mode (the RTS fixed interval too: with Γ = K
    # it is the RTS); the eager run calls neither.
    smoother = isinstance(est, ts.RTSSmoother) and est.lag != 1
    assert (spy["forward"], spy["backward"], spy["adjoint"]) == (1, smoother, 1 + smoother)
    with eager_loops():
        eager = _gradients(est, dtype, z, dt, x0, P0)
    assert (spy["forward"], spy["backward"], spy["adjoint"]) == (1, smoother, 1 + smoother)
    tol = {"atol": 1e-10, "rtol": 1e-10} if dtype == torch.float64 else {"atol": 1e-3, "rtol": 2e-3}
    for i, (a, b) in enumerate(zip(compiled, eager, strict=True)):
        assert (a is None) == (b is None), i
        if a is not None:
            assert a.abs().sum() > 0, i  # every input reaches the loss
            assert_close(a, b, msg=f"gradient {i}", **tol)


@needs_compiler
@pytest.mark.parametrize("name", NAMES)
def test_compiled_gradients_of_sums_equal_tensor_loop_gradients(name, spy):
    """A sum's gradient reaches the compiled reverse modes as an expanded (non-contiguous)
    tensor, which they copy before reading: the gradients equal the tensor loops', over
    several calls (a copy freed too early is overwritten by then)."""
    z, dt, x0, P0 = _problem(seed=12, B=4, T=40)
    model = ts.models.ConstantVelocity(q=0.5, r=[4.0, 2.0]).double()
    est = _estimators(model)[name].double()
    psi = None
    if isinstance(getattr(est, "filter", est), ts.SVSF):
        width = 4 if getattr(est, "filter", est).artificial is not None else 2
        psi = torch.full((4, 40, width), 3.0, dtype=torch.float64, requires_grad=True)

    def grads():
        zz = z.clone().requires_grad_(True)
        kwargs = {"dt": dt} if psi is None else {"dt": dt, "psi": psi * 1.0}
        out = est(zz, x0, P0, **kwargs)
        (out.mean.sum() + out.cov.sum()).backward()
        found = [zz.grad] + ([] if psi is None else [psi.grad.clone()])
        if psi is not None:
            psi.grad = None
        return found

    compiled = [grads() for _ in range(3)]
    assert spy["adjoint"] >= 3
    with eager_loops():
        eager = grads()
    for run in compiled:
        for a, b in zip(run, eager, strict=True):
            assert a.abs().sum() > 0
            assert_close(a, b, atol=1e-10, rtol=1e-10)


@needs_compiler
@pytest.mark.parametrize(
    ("rule", "keep", "smoothing"),
    [
        ("kalman", "all", None),
        ("svsf", "all", None),
        ("svsf velocity", "all", None),
        ("kalman", "all", "gain"),
        ("svsf", "mean", "gain"),
        ("svsf velocity", "all", "projection"),
        ("kalman", "moments", "projection"),
        ("kalman", "mean", ("gain", None)),
        ("svsf", "moments", ("projection", 2)),
        ("svsf velocity", "mean", ("projection", None)),
        ("svsf velocity", "moments", ("gain", 3)),
        ("vbl-innovation", "all", None),
        ("vbl-innovation", "all", "projection"),
        ("vbl-innovation", "moments", ("projection", 2)),
    ],
)
def test_compiled_reverse_mode_passes_gradcheck(rule, keep, smoothing):
    """The compiled reverse mode against finite differences of the compiled forward (an
    oracle that shares no code with it), every differentiable input and output (the state
    after the last step, and the smoothed moments when smoothing: lag 1 in the forward loop,
    or (smoothing, lag) through the filter and the smoother's recursion together): per-step
    intervals, noise and widths, per-axis q, missing components, memory γ."""
    smoothing, lag = smoothing if isinstance(smoothing, tuple) else (smoothing, 1)
    from torchsvs.kernels.axes import _CompiledAxes

    B, T, m = 2, 6, 2
    gen = torch.Generator().manual_seed(3)

    def rand(*shape, low=0.5, high=1.5):
        return torch.rand(*shape, generator=gen, dtype=torch.float64) * (high - low) + low

    velocity = rule == "svsf velocity"
    yp = torch.randn(B, T, m, generator=gen, dtype=torch.float64) * 3
    yv = torch.randn(B, T, m, generator=gen, dtype=torch.float64) * 2
    yp[0, 2, 1] = yv[1, 3, 0] = float("nan")
    if not velocity:
        yv = torch.full_like(yv, float("nan"))
    dt = rand(B, T, 1)
    given = [
        dt,
        rand(m) * 0.3,
        rand(B, T, m) * 0.1,
        rand(B, T, m) * 0.4,
        yp,
        yv,
        rand(B, T, m) * 2 + 1,
        rand(B, T, m) * 0.2,
        rand(B, T, m) * 2 + 1,
        rand(B, T, m, low=0.5, high=6.0),
        rand(m, low=0.5, high=6.0),
    ]
    prior = [
        torch.randn(B, m, generator=gen, dtype=torch.float64),
        rand(B, m),
        rand(B, m) * 4,
        rand(B, m) * 0.3,
        rand(B, m) * 2,
    ]
    gamma = torch.tensor(0.3 if rule != "kalman" else 0.0, dtype=torch.float64)
    inputs = [x.requires_grad_(True) for x in (*given, *prior)]
    inputs[4].requires_grad_(False)  # y with NaN gaps: gradcheck perturbs the NaNs too
    inputs[5].requires_grad_(False)
    gamma.requires_grad_(rule != "kalman")
    name = "svsf" if velocity else rule

    def run(gamma, *inputs):
        shape = (B, T, m)
        out = _CompiledAxes.apply(name, velocity, shape, keep, smoothing, lag, gamma, *inputs)
        return tuple(x for i, x in enumerate(out) if x is not None and i != 9)  # 9: the mask

    assert torch.autograd.gradcheck(run, (gamma, *inputs), eps=1e-6, atol=1e-6, rtol=1e-5)

    def run_y(y):  # the measurements where observed
        full = inputs[4].detach().clone()
        full[~torch.isnan(full)] = y
        return run(gamma, *inputs[:4], full, *inputs[5:])

    observed = inputs[4].detach()[~torch.isnan(inputs[4].detach())].clone().requires_grad_(True)
    assert torch.autograd.gradcheck(run_y, (observed,), eps=1e-6, atol=1e-6, rtol=1e-5)


@needs_compiler
def test_compiled_gradients_on_threads_for_any_axis_count(spy, on_two_threads):
    """Large batches run the reverse mode on threads too; 1 and 3 axes (compile-time and
    run-time axis counts) equal the tensor loops' gradients."""
    for ndim in (1, 3):
        B, T = 1100, 100
        gen = torch.Generator().manual_seed(ndim)
        z = torch.randn(B, T, ndim, generator=gen, dtype=torch.float64) * 3
        z[torch.rand(B, T, ndim, generator=gen) < 0.1] = float("nan")
        dt = torch.rand(B, T, generator=gen, dtype=torch.float64) + 0.5
        x0 = torch.randn(B, 2 * ndim, generator=gen, dtype=torch.float64)
        P0 = torch.eye(2 * ndim, dtype=torch.float64) * 4
        model = ts.models.ConstantVelocity(ndim=ndim, q=0.5, r=[2.0] * ndim, learn_q=True)
        svss = ts.SVSS(ts.SVSF(model.double(), psi=[3.0, 2.0] * ndim, gamma=0.2), lag=2)
        compiled = _gradients(svss, torch.float64, z, dt, x0, P0)
        with eager_loops():
            eager = _gradients(svss, torch.float64, z, dt, x0, P0)
        for a, b in zip(compiled, eager, strict=True):
            assert_close(a, b, atol=1e-10, rtol=1e-10)
    assert spy["adjoint"] == 4  # the filter and the smoother, twice
    assert (
        on_two_threads == [2] * 8
    )  # every compiled call (forward and reverse, filter and smoother)


@needs_compiler
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["f64", "f32"])
def test_compiled_variable_boundary_layer_couples_each_tracks_axes(dtype, spy, on_two_threads):
    """The variable boundary layer inflates a track's axes by one λ, the largest any of them
    asks for: the compiled loops keep each vector's tracks whole (a register's lanes: 4 of
    float64 and 8 of float32 with AVX), so 1, 3 and 5 axes (tracks that would straddle
    vectors) and ties between axes (identical axes ask for the same λ: torch splits the
    gradient between them) give the tensor loops' numbers and gradients, on threads, in the
    filter, the SVSS of lag 1 in its loop and of lag 3 through the recursion. More axes than a
    vector's lanes take the tensor loops (here 9, and 5 in float64 unless AVX-512)."""
    tol = {"atol": 1e-10, "rtol": 1e-10} if dtype == torch.float64 else {"atol": 1e-3, "rtol": 2e-3}
    for ndim, twins in ((1, False), (3, False), (5, False), (2, True), (9, False)):
        B, T = (2100, 48) if ndim == 3 else (60, 30)  # ≥ 100k track-steps: on threads
        gen = torch.Generator().manual_seed(ndim)
        z = torch.randn(B, T, ndim, generator=gen, dtype=dtype) * 3
        z[torch.rand(B, T, ndim, generator=gen) < 0.1] = float("nan")
        if twins:
            z[..., 1] = z[..., 0]
        dt = torch.rand(B, T, generator=gen, dtype=dtype) + 0.5
        x0 = torch.zeros(B, 2 * ndim, dtype=dtype)
        P0 = torch.eye(2 * ndim, dtype=dtype) * 4
        r = [2.0] * ndim if twins else [2.0 + i for i in range(ndim)]
        model = ts.models.ConstantVelocity(ndim=ndim, q=0.5, r=r, learn_q=True).to(dtype)
        for est in (
            ts.VariableBoundarySVSF(model, psi=1.0, gamma=0.2),
            ts.SVSS(ts.VariableBoundarySVSF(model, psi=1.0, gamma=0.2), lag=1),
            ts.SVSS(ts.VariableBoundarySVSF(model, psi=1.0, gamma=0.2), lag=3),
        ):
            est = est.to(dtype)
            before = spy["forward"] + spy["together"]
            compiled = _gradients(est, dtype, z, dt, x0, P0)
            assert spy["forward"] + spy["together"] == before + (ndim <= build.lane_width(dtype))
            with eager_loops():
                eager = _gradients(est, dtype, z, dt, x0, P0)
            for i, (a, b) in enumerate(zip(compiled, eager, strict=True)):
                if a is None:
                    continue
                if dtype == torch.float64:
                    assert_close(a, b, msg=f"{ndim} axes, gradient {i}", **tol)
                else:  # a near-tie in float32 may pick the other axis (a kink): a few entries
                    close = torch.isclose(a, b, atol=tol["atol"], rtol=tol["rtol"])
                    assert close.double().mean() > 0.9999, (ndim, i)
            with torch.no_grad():
                inferred = est(z, x0, P0, dt=dt)
                with eager_loops():
                    reference = est(z, x0, P0, dt=dt)
            assert_close(inferred.mean, reference.mean, msg=f"{ndim} axes", **tol)
            assert_close(inferred.cov, reference.cov, msg=f"{ndim} axes", **tol)
            inflated = _filtered(reference).pred_cov.diagonal(dim1=-2, dim2=-1)
            if ndim == 3:  # the layer acted: some priors grew beyond the model's
                model_only = ts.KalmanFilter(model)(z, x0, P0, dt=dt).pred_cov
                assert (inflated > model_only.diagonal(dim1=-2, dim2=-1) * 1.01).any()
    assert 2 in on_two_threads


@needs_compiler
@pytest.mark.parametrize("lag", [1, 3, None], ids=["lag 1", "lag 3", "interval"])
@pytest.mark.parametrize("projection", [True, False], ids=["SVSS", "RTS"])
def test_compiled_smoother_reverse_mode_passes_gradcheck(lag, projection):
    """The smoother recursion's compiled reverse mode against finite differences of its
    compiled forward: every differentiable input (moments, gains, noise, intervals,
    innovations), missing components, per-step and constant inputs; the filtered covariance
    given as views of one tensor, as the filter's general layout gives it (the gradient then
    gathers in that tensor)."""
    from torchsvs.kernels.axes_smoother import _CompiledSmoother, _Views

    B, T, m = 2, 7, 2
    gen = torch.Generator().manual_seed(4)

    def rand(*shape, low=0.5, high=1.5):
        return torch.rand(*shape, generator=gen, dtype=torch.float64) * (high - low) + low

    def sym(scale):  # positive definite 2×2 blocks per step: (a, b, c)
        a, c = rand(B, T, m) * scale, rand(B, T, m) * scale
        return a, 0.3 * (a * c).sqrt() * rand(B, T, m, low=-1.0, high=1.0), c

    seen_p = (torch.rand(B, T, m, generator=gen) > 0.2).double()
    seen_v = (torch.rand(B, T, m, generator=gen) > 0.4).double() * seen_p
    gain = [rand(B, T, m, low=0.1, high=0.9) * seen_p, rand(B, T, m, low=-0.2, high=0.2)]
    gain += [rand(B, T, m, low=-0.2, high=0.2) * seen_p, rand(B, T, m, low=0.1, high=0.9)]
    inputs = [
        *sym(2.0),
        *(x + 1.0 for x in sym(2.0)),
        *gain,
        rand(m) + 1.0,  # noise constant per axis
        rand(B, T, m) * 0.2,
        rand(B, T, m) + 1.0,
        seen_p,
        seen_v,
        rand(B, T, 1),
        torch.randn(B, T, m, generator=gen, dtype=torch.float64),
        torch.randn(B, T, m, generator=gen, dtype=torch.float64),
        torch.randn(B, T, m, generator=gen, dtype=torch.float64),
        torch.randn(B, T, m, generator=gen, dtype=torch.float64),
    ]
    for i, x in enumerate(inputs):
        x.requires_grad_(i not in (13, 14))
    filtered_cov = torch.stack(inputs[:3], dim=-1).detach().requires_grad_()  # [B, T, m, 3]

    def run(cov, *xs):
        views, tensors = _Views.of([*cov.unbind(-1), *xs])
        assert len(tensors) == len(xs) + 1  # a, b, c through their base
        return _CompiledSmoother.apply((B, T, m), lag, projection, views, *tensors)

    args = (filtered_cov, *inputs[3:])
    assert torch.autograd.gradcheck(run, args, eps=1e-6, atol=1e-6, rtol=1e-5)


def test_without_a_compiler_the_tensor_loops_run(monkeypatch, spy):
    z, dt, x0, P0 = _problem(seed=8)
    model = ts.models.ConstantVelocity(q=0.5, r=[4.0, 2.0]).double()
    ks = ts.RTSSmoother(ts.KalmanFilter(model)).double()
    with torch.no_grad():
        expected = ks(z, x0, P0, dt=dt)
    monkeypatch.setattr(build, "_state", {"library": None, "failure": None})
    monkeypatch.setattr(build, "_compiler", lambda: None)
    with torch.no_grad(), pytest.warns(RuntimeWarning, match="no C.. compiler"):
        fallback = ks(z, x0, P0, dt=dt)
    assert "compiler" in (build.failure() or "")
    assert_close(fallback.mean, expected.mean, atol=1e-9)
    assert spy["forward"] == 1  # only the first run
    monkeypatch.setattr(build, "_state", {"library": None, "failure": None})
    monkeypatch.setenv("TORCHSVS_FUSED", "0")
    with torch.no_grad():
        ks(z, x0, P0, dt=dt)
    assert spy["forward"] == 1


def _dense_problem(seed: int, B: int = 3, T: int = 30):
    """A dense 3-state, 2-measurement linear-Gaussian model (H not a selection) and measurements
    with gaps; a CV model of two axes for the SVSF's H⁺ mode (H a selection)."""
    gen = torch.Generator().manual_seed(seed)
    A = torch.randn(3, 3, generator=gen, dtype=torch.float64)
    F = torch.linalg.matrix_exp(0.1 * (A - A.T)) * 0.98
    H = torch.randn(2, 3, generator=gen, dtype=torch.float64)
    Q = torch.eye(3, dtype=torch.float64) * 0.3 + 0.1
    R = torch.tensor([[2.0, 0.3], [0.3, 1.0]], dtype=torch.float64)
    dense = ts.models.LinearGaussian(F, H, Q, R)
    z = torch.randn(B, T, 2, generator=gen, dtype=torch.float64) * 2
    z[torch.rand(B, T, 2, generator=gen) < 0.2] = float("nan")
    z[:, 4] = float("nan")
    return dense, z


def _online(est, x0, P0, z, psi=None):
    """Step by step: the states and the step results."""
    state, outs, states = est.init(x0, P0), [], []
    for t in range(z.shape[-2]):
        kwargs = {} if psi is None else {"psi": psi[..., t, :]}
        state, out = est.step(state, z[..., t, :], **kwargs)
        states.append(state)
        outs.append(out)
    return states, outs


@needs_compiler
@pytest.mark.parametrize("case", ["KF dense", "EKF dense", "KF CV", "SVSF CV", "SVSF CV psi"])
@pytest.mark.parametrize("single", [False, True], ids=["batch", "one track"])
def test_compiled_online_steps_equal_the_tensor_steps(case, single, spy):
    """An online step of a linear model without gradients runs compiled (fused_dense.dense_run):
    every field of every step and state equals the tensor path's to 1e-10 in float64, with
    missing components, a step without measurements, per-step ψ and one-track states."""
    dense, z = _dense_problem(seed=11)
    cv = ts.models.ConstantVelocity(dt=1.5, q=0.5, r=[4.0, 2.0]).double()
    psi = None
    if case.startswith("SVSF"):
        model = cv
        est = ts.SVSF(cv, psi=[3.0, 2.0], gamma=0.2, artificial=None, learn=False).double()
        if case.endswith("psi"):
            psi = torch.rand(3, 30, 2, dtype=torch.float64) * 4 + 0.5
    else:
        model = dense if "dense" in case else cv
        est = (ts.ExtendedKalmanFilter if case.startswith("EKF") else ts.KalmanFilter)(model)
    n = model.state_dim
    x0 = torch.linspace(-1, 1, n, dtype=torch.float64).expand(3, n)
    P0 = torch.eye(n, dtype=torch.float64) * 5
    if single:
        x0, z = x0[0], z[0]
        psi = None if psi is None else psi[0]
    with torch.no_grad():
        states, outs = _online(est, x0, P0, z, psi)
        assert spy["dense"] == z.shape[-2]
        with eager_loops():
            ref_states, ref_outs = _online(est, x0, P0, z, psi)
        assert spy["dense"] == z.shape[-2]
    for t, (out, ref) in enumerate(zip(outs, ref_outs, strict=True)):
        for key in out._fields:
            a, b = getattr(out, key), getattr(ref, key)
            assert (a is None) == (b is None), (t, key)
            if a is not None:
                assert a.shape == b.shape, (t, key, a.shape, b.shape)
                assert_close(a.to(b.dtype), b, atol=1e-10, rtol=1e-10, msg=f"{t} {key}")
    for state, ref in zip(states, ref_states, strict=True):
        for key in ("mean", "cov", "post_innovation", "log_likelihood"):
            a, b = getattr(state, key), getattr(ref, key)
            assert (a is None) == (b is None), key
            if a is not None:
                assert_close(a, b.expand_as(a), atol=1e-10, rtol=1e-10, msg=key)
        assert (state.steps, state.single) == (ref.steps, ref.single)


@needs_compiler
def test_online_steps_step_aside_where_the_compiled_step_cannot_run(spy):
    """Gradients, an artificial measurement, a nonlinear model, a non-selection H for the
    SVSF, a per-step dt and bad input take the tensor path (and its error messages)."""
    dense, z = _dense_problem(seed=12, B=2, T=5)
    cv = ts.models.ConstantVelocity(q=0.5, r=[4.0, 2.0]).double()
    x4, P4 = torch.zeros(2, 4, dtype=torch.float64), torch.eye(4, dtype=torch.float64)
    learnable = ts.SVSF(cv, psi=[3.0, 2.0], artificial=None).double()
    state, out = learnable.step(learnable.init(x4, P4), z[:, 0])
    assert out.mean.requires_grad  # ψ learnable, grad mode on: the differentiable path
    with torch.no_grad():
        artificial = ts.SVSF(cv, psi=[3.0, 2.0, 3.0, 2.0]).double()
        artificial.step(artificial.init(x4, P4), z[:, 0])
        x3, P3 = torch.zeros(2, 3, dtype=torch.float64), torch.eye(3, dtype=torch.float64)
        skewed = ts.SVSF(dense, psi=[3.0, 2.0], artificial=None).double()
        skewed.step(skewed.init(x3, P3), z[:, 0])
        kf = ts.KalmanFilter(cv)
        kf.step(kf.init(x4, P4), z[:, 0], dt=torch.tensor(2.0, dtype=torch.float64))
        assert spy["dense"] == 0
        bad = z[:, 0].clone()
        bad[0, 0] = float("inf")
        with pytest.raises(ValueError, match="z: contains inf"):
            kf.step(kf.init(x4, P4), bad)
        with pytest.raises(ValueError, match="psi: KalmanFilter has no boundary layer"):
            kf.step(kf.init(x4, P4), z[:, 0], psi=torch.ones(2, 2, dtype=torch.float64))
        kf.step(kf.init(x4, P4), z[:, 0])
    assert spy["dense"] == 2  # the inf step tried it first, then the plain step ran it


@needs_compiler
def test_a_compiled_state_stepped_with_gradients_differentiates(spy):
    """A state made by compiled online steps (without gradients) and then stepped with grad
    mode on takes the differentiable path when a parameter or ``psi`` wants a gradient, and
    that step equals the compiled one's numbers."""
    _, z = _dense_problem(seed=14, B=2, T=6)
    cv = ts.models.ConstantVelocity(q=0.5, r=[4.0, 2.0]).double()
    x4, P4 = torch.zeros(2, 4, dtype=torch.float64), torch.eye(4, dtype=torch.float64)
    learnable = ts.SVSF(cv, psi=[3.0, 2.0], gamma=0.2, artificial=None).double()
    with torch.no_grad():
        state, _ = learnable.step(learnable.init(x4, P4), z[:, 0])
        _, compiled = learnable.step(state, z[:, 1])
    assert spy["dense"] == 2 and state.constants is not None
    _, out = learnable.step(state, z[:, 1])  # ψ learnable, grad mode on
    assert spy["dense"] == 2 and out.mean.requires_grad
    out.mean.sum().backward()
    assert torch.isfinite(learnable.boundary_layer.raw.grad).all()
    assert_close(out.mean.detach(), compiled.mean, atol=1e-10, rtol=1e-10)
    fixed = ts.SVSF(cv, psi=[3.0, 2.0], gamma=0.2, artificial=None, learn=False).double()
    with torch.no_grad():
        state, _ = fixed.step(fixed.init(x4, P4), z[:, 0])
    psi = torch.tensor([[3.0, 2.0]] * 2, dtype=torch.float64, requires_grad=True)
    _, out = fixed.step(state, z[:, 1], psi=psi)
    assert spy["dense"] == 3 and out.mean.requires_grad  # ψ given with a gradient
    kf = ts.KalmanFilter(cv)
    with torch.no_grad():
        state, _ = kf.step(kf.init(x4, P4), z[:, 0])
    wanted = z[:, 1].clone().requires_grad_()
    _, out = kf.step(state, wanted)
    assert spy["dense"] == 4 and out.mean.requires_grad  # z given with a gradient
    moved = state._replace(mean=state.mean.clone().requires_grad_())  # a caller's edit
    _, out = kf.step(moved, z[:, 1])
    assert spy["dense"] == 4 and out.mean.requires_grad
    out.mean.sum().backward()
    assert torch.isfinite(moved.mean.grad).all()


@needs_compiler
@pytest.mark.parametrize("case", ["KF", "EKF", "KS", "SVSF", "SVSF psi", "SVSS"])
def test_compiled_dense_runs_equal_the_general_path(case, spy):
    """A whole run of a dense linear model without gradients is compiled
    (:func:`fused_dense.dense_run`): every field equals the general path's to 1e-10 in float64, with
    missing components, chunks carrying the state, per-step ψ, and smoothers over it."""
    dense, z = _dense_problem(seed=13, B=3, T=40)
    selection = ts.models.LinearGaussian(
        dense.transition(),
        torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64),
        dense.process_noise(),
        torch.diag(torch.tensor([2.0, 1.0], dtype=torch.float64)),
    )
    psi = torch.rand(3, 40, 2, dtype=torch.float64) * 4 + 0.5 if case.endswith("psi") else None
    svsf = ts.SVSF(selection, psi=[3.0, 2.0], gamma=0.2, artificial=None, learn=False)
    est = {
        "KF": ts.KalmanFilter(dense),
        "EKF": ts.ExtendedKalmanFilter(dense),
        "KS": ts.RTSSmoother(ts.KalmanFilter(dense)),
        "SVSF": svsf,
        "SVSF psi": svsf,
        "SVSS": ts.SVSS(svsf, lag=3),
    }[case]
    x0 = torch.tensor([[0.5, -0.2, 1.0]], dtype=torch.float64).expand(3, 3)
    P0 = torch.eye(3, dtype=torch.float64) * 4
    kwargs = {} if psi is None else {"psi": psi}
    with torch.no_grad():
        compiled = est(z, x0, P0, **kwargs)
        assert spy["dense"] == 1
        with eager_loops():
            general = est(z, x0, P0, **kwargs)
        assert spy["dense"] == 1
    for key in compiled._fields:
        a, b = getattr(compiled, key), getattr(general, key)
        if isinstance(a, tuple):  # a smoother's filter pass
            for inner in a._fields:
                x, y = getattr(a, inner), getattr(b, inner)
                assert (x is None) == (y is None), inner
                if isinstance(x, torch.Tensor):
                    assert_close(x.to(y.dtype), y.expand_as(x), atol=1e-10, rtol=1e-10, msg=inner)
            continue
        assert (a is None) == (b is None), key
        if isinstance(a, torch.Tensor):
            assert_close(a.to(b.dtype), b.expand_as(a), atol=1e-10, rtol=1e-10, msg=key)
    if isinstance(est, ts.filters.GaussianFilter):
        with torch.no_grad():  # chunks of 7 carry the state (the SVSF's memory) compiled too
            state, parts = est.init(x0, P0), []
            for start in range(0, 40, 7):
                chunk = {} if psi is None else {"psi": psi[:, start : start + 7]}
                state, part = est.scan(state, z[:, start : start + 7], **chunk)
                parts.append(part.mean)
        assert_close(torch.cat(parts, 1), compiled.mean, atol=1e-12, rtol=0)


@needs_compiler
def test_compiled_online_steps_follow_a_changed_model():
    """The matrices a run of compiled steps keeps are rebuilt when the model changes between
    steps (an in-place update of its noise, a new interval): the same as the tensor path."""
    cv = ts.models.ConstantVelocity(dt=1.0, q=0.5, r=[4.0, 2.0]).double()
    kf = ts.KalmanFilter(cv)
    x0, P0 = torch.zeros(2, 4, dtype=torch.float64), torch.eye(4, dtype=torch.float64)
    z = torch.randn(2, 3, 2, generator=torch.Generator().manual_seed(0), dtype=torch.float64)

    def three_steps(compiled: bool) -> torch.Tensor:
        state = kf.init(x0, P0)
        state, _ = kf.step(state, z[:, 0])
        assert (state.constants is not None) == compiled
        cv.q.raw.mul_(4.0)  # in place, as an optimiser step would
        state, _ = kf.step(state, z[:, 1])
        cv.dt = 2.0
        state, out = kf.step(state, z[:, 2])
        cv.q.raw.div_(4.0)
        cv.dt = 1.0
        return out.cov

    with torch.no_grad():
        compiled = three_steps(compiled=True)
        with eager_loops():
            tensors = three_steps(compiled=False)
    assert_close(compiled, tensors, atol=1e-10, rtol=1e-10)


@pytest.mark.parametrize("kind", ["kf", "svsf"])
def test_compiled_training_pass_keeping_less_gives_the_same_gradients(kind):
    """With gradients and ``keep`` other than ``"all"`` the compiled loop writes only the
    steps' states: the means, and the gradients through them and through the state after the
    last step (a chunked run continues from it), are those of the whole record's pass."""
    model = ts.models.ConstantVelocity(ndim=2, q=0.5, r=[4.0, 9.0], learn_noise=True).double()
    if kind == "kf":
        est: torch.nn.Module = ts.KalmanFilter(model)
    else:
        est = ts.SVSF(model, psi=[5.0, 2.0, 6.0, 3.0], gamma=0.2)
    g = torch.Generator().manual_seed(2)
    z = torch.randn(3, 30, 2, generator=g, dtype=torch.float64).cumsum(1)
    z[1, 4, 0] = float("nan")
    x0, P0 = torch.zeros(3, 4, dtype=torch.float64), 4 * torch.eye(4, dtype=torch.float64)

    def grads(keep: str) -> tuple[torch.Tensor, list[torch.Tensor]]:
        state, out = est.scan(est.init(x0, P0), z, keep=keep)
        loss = out.mean.square().mean() + state.mean.sum() + state.cov.diagonal(0, -2, -1).sum()
        params = [p for p in est.parameters() if p.requires_grad]
        return out.mean, list(torch.autograd.grad(loss, params))

    mean_all, grads_all = grads("all")
    mean_kept, grads_kept = grads("mean")
    assert torch.equal(mean_all, mean_kept)
    for a, b in zip(grads_all, grads_kept, strict=True):
        assert_close(a, b, atol=1e-12, rtol=1e-10)


@pytest.mark.parametrize("gaps", [False, True], ids=["no-gaps", "gaps"])
def test_measurements_with_a_gradient_reach_the_finite_difference_velocities(gaps):
    """The SVSF's finite-difference velocities differentiate in ``z`` (a track without gaps
    takes the one-pass differences, which once wrote into a buffer autograd refuses), equal to
    the tensor loops' gradients; without a gradient the in-place differences give the same
    estimates."""
    z, _, x0, P0 = _problem(seed=14, B=3, T=25, missing=0.2 if gaps else 0.0)
    if not gaps:
        z = z.nan_to_num(1.0)  # _problem's missing step
    model = ts.models.ConstantVelocity(q=0.5, r=[4.0, 2.0]).double()
    svsf = _estimators(model)["SVSF"].double()

    def run(loops_only: bool) -> tuple[torch.Tensor, torch.Tensor]:
        zz = z.clone().requires_grad_(True)
        if loops_only:
            with eager_loops():
                out = svsf(zz, x0, P0)
        else:
            out = svsf(zz, x0, P0)
        (
            out.mean * torch.linspace(-1.0, 1.0, out.mean.numel()).reshape(out.mean.shape)
        ).sum().backward()
        return out.mean.detach(), zz.grad

    (mean, grad), (mean_loops, grad_loops) = run(False), run(True)
    assert grad.abs().sum() > 0
    assert_close(grad, grad_loops, atol=1e-10, rtol=1e-10)
    with torch.no_grad():
        assert_close(svsf(z, x0, P0).mean, mean, atol=0, rtol=0)
    assert_close(mean, mean_loops, atol=1e-10, rtol=0)


@needs_compiler
def test_a_vector_of_lanes_is_one_register_of_the_machine():
    """The compiled loops step a vector of lanes as wide as one register of the machine they
    are built for (``cpp/lanes.h``): wider, GCC splits the arithmetic but turns every ``mask ?
    a : b`` into a branch per lane through memory (on AVX2, 64 bytes against 32: twice the
    time of the SURE curves' pass, the same numbers). The width expected is read off the
    compiler's own macros for ``-march=native``, as the build sees them."""
    compiler = build._compiler()
    assert compiler is not None
    macros = subprocess.run(
        [compiler, *build.NATIVE, "-dM", "-E", "-x", "c++", "-"],
        input="",
        capture_output=True,
        text=True,
        check=False,
    )
    if macros.returncode != 0:
        pytest.skip("the compiler takes no -march=native: the plain build's width")
    defined = macros.stdout
    register = 64 if "__AVX512F__ " in defined else 32 if "__AVX__ " in defined else 16
    assert build.lane_width(torch.float64) == register // 8
    assert build.lane_width(torch.float32) == register // 4
