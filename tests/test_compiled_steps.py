"""Compiled steps (:mod:`torchsvs.kernels.compiled`): the Gaussian filters' step through
``torch.compile`` gives the eager numbers and gradients, in whole runs and in chunks, falls back
to eager steps with one warning, turns off, and a user's ``torch.compile(est)`` finishes with the
same result.

The plumbing runs on Dynamo's ``"eager"`` and ``"aot_eager"`` backends (a trace in a second or
two); one small test compiles with inductor, the rest of those are marked slow."""

from __future__ import annotations

import pytest
import torch

import torchsvs as ts
from tests.conftest import assert_close, random_system
from torchsvs.kernels import compiled, compiled_steps, eager_loops

TOL = {"atol": 1e-10, "rtol": 1e-10}
#: Fields of a FilterResult compared (the per-step ones and the run's total).
FIELDS = ("mean", "cov", "pred_mean", "pred_cov", "innovation", "gain", "transition")
FIELDS += ("meas_matrix", "post_innovation", "innovation_cov", "log_likelihood")


@pytest.fixture(autouse=True)
def _fresh_compilations():
    compiled.clear()
    torch._dynamo.reset()
    yield
    compiled.clear()
    torch._dynamo.reset()


def _ballistic(B=3, T=12):
    sc = ts.scenarios.ballistic_scenario(B, torch.Generator().manual_seed(0), duration=T / 10)
    z = sc.z.clone()
    z[-1, 4, 0] = float("nan")  # a missing component: the mask enters the step
    return z, sc.x0, sc.P0, sc.model


def _estimators(model):
    return {
        "EKF": ts.ExtendedKalmanFilter(model),
        "UKF": ts.UnscentedKalmanFilter(model),
        "SVSF": ts.SVSF(model, psi=[400.0, 300.0], gamma=0.2),
    }


def _dense():
    """A KF on a dense linear model, the C++ dense loops off (:func:`eager_loops`)."""
    system = random_system(4, 2, T=12, B=3, seed=3)
    z, x0, P0 = system.tensors()
    return ts.KalmanFilter(system.model()), z, x0, P0


def _compare(got, expected):
    for field in FIELDS:
        a, b = getattr(got, field), getattr(expected, field)
        assert (a is None) == (b is None), field
        if a is not None:
            assert_close(a, b, **TOL, msg=field)


def _cases():
    z, x0, P0, model = _ballistic()
    cases = {name: (est, z, x0, P0) for name, est in _estimators(model).items()}
    cases["KF dense"] = _dense()
    return cases


NAMES = ["EKF", "UKF", "SVSF", "KF dense"]


@pytest.mark.parametrize("name", NAMES)
def test_compiled_steps_equal_eager_steps(name):
    est, z, x0, P0 = _cases()[name]
    with torch.no_grad(), eager_loops():
        expected = est(z, x0, P0)
        before = compiled.STATS["compiles"]
        with compiled_steps(backend="eager"):
            got = est(z, x0, P0)
            again = est(z, x0, P0)
    _compare(got, expected)
    _compare(again, expected)
    # One compilation (the first step of a fresh run is eager), reused by the second run.
    assert compiled.STATS["compiles"] == before + 1


@pytest.mark.parametrize("name", ["EKF", "UKF", "SVSF"])
def test_gradients_through_compiled_steps_equal_eager_ones(name):
    z, x0, P0, model = _ballistic(B=2, T=8)
    est = _estimators(model)[name]
    x0 = x0.clone().requires_grad_(True)
    params = [x0, *est.parameters()]

    def grads():
        out = est(z, x0, P0)
        loss = out.mean.square().mean() + out.cov.diagonal(dim1=-2, dim2=-1).log().sum()
        return torch.autograd.grad(loss, params)

    expected = grads()
    with compiled_steps(backend="aot_eager", chunk=1):
        got = grads()
        again = grads()
    assert len(got) == len(expected) >= 1
    for a, b, c in zip(got, again, expected, strict=True):
        assert_close(a, c, **TOL)
        assert_close(b, c, **TOL)


@pytest.mark.parametrize("name", ["SVSF", "KF dense"])
def test_chunked_scans_with_compiled_steps_equal_the_whole_run(name):
    est, z, x0, P0 = _cases()[name]
    with torch.no_grad(), eager_loops():
        whole = est(z, x0, P0)
        with compiled_steps(backend="eager"):
            state = est.init(x0, P0)
            parts = []
            for start in range(0, z.shape[1], 5):
                state, part = est.scan(state, z[:, start : start + 5])
                parts.append(part)
    for field in ("mean", "cov", "innovation", "gain"):
        got = torch.cat([getattr(p, field) for p in parts], dim=1)
        assert_close(got, getattr(whole, field), **TOL, msg=field)
    assert_close(state.mean, whole.mean[:, -1], **TOL)


@pytest.mark.parametrize("chunk", [1, 3])
def test_chunks_of_any_length_equal_eager_steps(chunk):
    z, x0, P0, model = _ballistic(T=11)  # 1 eager step, chunks, the rest that fills none eager
    est = ts.ExtendedKalmanFilter(model)
    with torch.no_grad():
        expected = est(z, x0, P0)
        before = compiled.STATS["compiles"]
        with compiled_steps(backend="eager", chunk=chunk):
            got = est(z, x0, P0)
    _compare(got, expected)
    assert compiled.STATS["compiles"] == before + 1


def test_online_steps_compile_once_with_one_step_chunks():
    z, x0, P0, model = _ballistic(T=8)
    z[-1, 4, 0] = z[-1, 3, 0]  # no missing component: every step has the same inputs
    est = ts.ExtendedKalmanFilter(model)
    with torch.no_grad():
        whole = est(z, x0, P0)
        before = compiled.STATS["compiles"]
        with compiled_steps(backend="eager", chunk=1):
            state = est.init(x0, P0)
            means = []
            for t in range(z.shape[1]):
                state, out = est.step(state, z[:, t])
                means.append(out.mean)
    assert_close(torch.stack(means, 1), whole.mean, **TOL)
    assert compiled.STATS["compiles"] == before + 1  # the first step eager, then one shape


def test_a_failing_compiler_falls_back_to_eager_steps_with_one_warning(monkeypatch):
    def broken(*args, **kwargs):
        raise RuntimeError("no compiler here")

    monkeypatch.setattr(torch, "compile", broken)
    z, x0, P0, model = _ballistic()
    est = ts.ExtendedKalmanFilter(model)
    with torch.no_grad():
        expected = est(z, x0, P0)
        with compiled_steps():
            with pytest.warns(RuntimeWarning, match="compiled steps unavailable.*no compiler"):
                got = est(z, x0, P0)
            again = est(z, x0, P0)  # no second warning (filterwarnings = error)
            other = ts.UnscentedKalmanFilter(model)(z, x0, P0)
    _compare(got, expected)
    _compare(again, expected)
    assert other.mean.isfinite().all()


class _SingularFactor(ts.KalmanFilter):
    """A KF whose log-likelihood also takes the Cholesky factor of a singular ``[2, 2]`` matrix
    at every step: the plain factorisation fails, the jitter of :func:`ts.linalg.cholesky`
    makes it succeed."""

    def correct(self, x_pred, P_pred, obs, carried, inputs):
        step = super().correct(x_pred, P_pred, obs, carried, inputs)
        singular = torch.ones(2, 2, dtype=x_pred.dtype) * (1.0 + x_pred[:, :1, None].square())
        L = ts.linalg.cholesky(singular)
        return step._replace(log_likelihood=step.log_likelihood + L[:, 1, 1])


def test_a_factor_that_fails_in_a_compiled_step_reruns_it_eagerly():
    """The compiled step's factor is NaN where the eager one needs its jitter: the step runs
    again eagerly, with the same numbers."""
    est, z, x0, P0 = _dense()
    est = _SingularFactor(est.model)
    with torch.no_grad(), eager_loops():
        expected = est(z, x0, P0)
        with compiled_steps(backend="eager"):
            got = est(z, x0, P0)
    assert expected.log_likelihood.isfinite().all()
    _compare(got, expected)


def test_the_off_switches(monkeypatch):
    z, x0, P0, model = _ballistic()
    est = ts.ExtendedKalmanFilter(model)
    before = compiled.STATS["compiles"]
    with torch.no_grad(), compiled_steps(backend="eager"):
        with compiled_steps(False):
            est(z, x0, P0)
        monkeypatch.setenv("TORCHSVS_COMPILE", "0")
        est(z, x0, P0)
        torch.compile(est, backend="eager")(z, x0, P0)
    assert compiled.STATS["compiles"] == before


@pytest.mark.parametrize("name", ["SVSF", "KF dense"])
def test_a_users_torch_compile_of_the_estimator(name):
    """The estimator call leaves Dynamo (no unrolled loop, no hang at the input checks' graph
    breaks) and runs its steps compiled: the same numbers as the eager call."""
    est, z, x0, P0 = _cases()[name]
    with torch.no_grad(), eager_loops():
        expected = est(z, x0, P0)
        before = compiled.STATS["compiles"]
        with compiled_steps(False, backend="eager"):
            got = torch.compile(est, backend="eager")(z, x0, P0)
            state, scanned = torch.compile(est.scan, backend="eager")(est.init(x0, P0), z)
    assert compiled.STATS["compiles"] > before
    _compare(got, expected)
    _compare(scanned, expected)


def test_a_users_torch_compile_of_an_svsf_on_compiled_per_axis_loops():
    """The issue's case: ``torch.compile(svsf)`` of a CV model (B = 64, T = 200) had not
    finished its first call after 14 minutes; its per-axis C++ loops now run outside Dynamo."""
    sc = ts.scenarios.atc_scenario(64, torch.Generator().manual_seed(0))
    z = sc.z[:, :200]
    est = ts.SVSF(sc.model, psi=[800.0, 600.0, 800.0, 600.0], gamma=0.1)
    with torch.no_grad():
        expected = est(z, sc.x0, sc.P0)
        got = torch.compile(est)(z, sc.x0, sc.P0)
    _compare(got, expected)


def _inductor_case(name):
    if name == "KF dense":
        est, z, x0, P0 = _dense()
        return est, z[:1], x0, P0
    z, x0, P0, model = _ballistic(B=1, T=6)
    return _estimators(model)[name], z, x0, P0


def _inductor_run(name, backward, chunk=None):
    est, z, x0, P0 = _inductor_case(name)
    x0 = x0.clone().requires_grad_(backward)
    with eager_loops(), torch.set_grad_enabled(backward):
        expected = est(z, x0, P0)
        with compiled_steps(chunk=chunk):
            got = est(z, x0, P0)
        if backward:
            (g_expected,) = torch.autograd.grad(expected.mean.square().sum(), x0)
            (g_got,) = torch.autograd.grad(got.mean.square().sum(), x0)
            assert_close(g_got, g_expected, **TOL)
    _compare(got, expected)


def test_inductor_compiled_kalman_step():
    """A real inductor compilation: the smallest step (a KF's), one step per call."""
    _inductor_run("KF dense", backward=False, chunk=1)


@pytest.mark.slow
@pytest.mark.parametrize("name", ["KF dense", "EKF", "UKF", "SVSF"])
def test_inductor_compiled_steps_forward_and_backward(name):
    _inductor_run(name, backward=True)
