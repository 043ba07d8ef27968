"""``keep``: a result keeps every field, the moments or the means of each step; what it keeps is
what the whole result holds, on every path (the compiled loops skip writing the rest), whole
runs and chunks alike, and the state carried between chunks is whole."""

from __future__ import annotations

import pytest
import torch

import torchsvs as ts
from tests.conftest import assert_close, random_system
from tests.test_kernels import _estimators, _filtered, _problem, needs_compiler, spy  # noqa: F401
from torchsvs.kernels import eager_loops, general_path

KEEPS = ["moments", "mean"]


def _kept(result):
    """The names of a result's fields that are not None."""
    return {name for name, value in zip(result._fields, result, strict=True) if value is not None}


def _check(trimmed, whole, keep, tol):
    assert_close(trimmed.mean, whole.mean, **tol)
    if keep == "moments":
        assert_close(trimmed.cov, whole.cov, **tol)
    else:
        assert trimmed.cov is None
    if isinstance(whole, ts.SmootherResult):
        _check(trimmed.filtered, whole.filtered, keep, tol)
        return
    run_totals = {"log_likelihood", "particles", "log_weights"} & _kept(whole)
    moments = {"mean", "cov"} if keep == "moments" else {"mean"}
    assert _kept(trimmed) == moments | run_totals
    for name in run_totals:
        assert_close(getattr(trimmed, name), getattr(whole, name), **tol)


@needs_compiler
@pytest.mark.parametrize("keep", KEEPS)
@pytest.mark.parametrize("name", list(_estimators(ts.models.ConstantVelocity())))
def test_compiled_loops_write_what_is_kept(name, keep, spy):  # noqa: F811
    """The compiled forward loop, told to write the moments or the means only, gives exactly
    those of the whole result (a misplaced record would show in the means); a smoother of a
    lag other than 1 then runs its recursion in the filter's pass (fused_axes.filter_smoother),
    whose filtered moments are exactly those of the whole result and its smoothed ones equal
    (the fixed-interval RTS by the general recursion, not Eq. (17)'s form: to 1e-9)."""
    z, dt, x0, P0 = _problem(seed=3, B=70, T=33)  # more tracks than a block of lanes
    model = ts.models.ConstantVelocity(dt=1.5, q=0.5, r=[4.0, 2.0]).double()
    est = _estimators(model)[name].double()
    with torch.no_grad():
        whole = est(z, x0, P0, dt=dt)
        trimmed = est(z, x0, P0, dt=dt, keep=keep)
    together = isinstance(est, ts.RTSSmoother) and est.lag != 1
    assert (spy["forward"], spy["together"]) == (2 - together, together)
    exact = {"atol": 0.0, "rtol": 0.0}
    if together:
        _check(trimmed.filtered, whole.filtered, keep, exact)
        assert_close(trimmed.mean, whole.mean, atol=1e-9, rtol=0.0)
        if keep == "moments":
            assert_close(trimmed.cov, whole.cov, atol=1e-9, rtol=0.0)
        else:
            assert trimmed.cov is None
    else:
        _check(trimmed, whole, keep, exact)


def _others():
    """Estimators off the per-axis kernel, each with its inputs ``(z, x0, P0)``."""
    dense = random_system(3, 2, T=25, B=3)
    sc = ts.scenarios.ballistic_scenario(3, torch.Generator().manual_seed(0))
    ballistic = (sc.z[:, :40].double(), sc.x0.double(), sc.P0.double())
    return {
        "KF dense": (ts.KalmanFilter(dense.model()), dense.tensors()),
        "SVSS over a dense model": (ts.SVSS(ts.SVSF(dense.model(), psi=3.0)), dense.tensors()),
        "EKF": (ts.ExtendedKalmanFilter(sc.model), ballistic),
        "UKF": (ts.UnscentedKalmanFilter(sc.model), ballistic),
        "PF": (ts.ParticleFilter(sc.model, num_particles=40), ballistic),
    }


@pytest.mark.parametrize("keep", KEEPS)
@pytest.mark.parametrize("name", list(_others()))
def test_every_path_keeps_what_is_asked(name, keep):
    """Paths that compute every field (dense steps, tensor loops, particle filters) drop what
    is not kept; the kept fields equal the whole result's."""
    est, (z, x0, P0) = _others()[name]
    est = est.double()
    with torch.no_grad():
        whole = est(z, x0, P0, generator=torch.Generator().manual_seed(1))
        trimmed = est(z, x0, P0, generator=torch.Generator().manual_seed(1), keep=keep)
    _check(trimmed, whole, keep, {"atol": 0.0, "rtol": 0.0})


@pytest.mark.parametrize("keep", KEEPS)
@pytest.mark.parametrize("name", ["KF", "SVSF", "SVSF H+"])
def test_chunks_that_keep_less_carry_the_whole_state(name, keep):
    """A run in chunks keeping only the means or moments gives the whole run's numbers: the
    state after each chunk (mean, covariance, SVSF memory) is whole whatever is kept."""
    z, dt, x0, P0 = _problem(seed=6, B=5, T=40)
    model = ts.models.ConstantVelocity(dt=1.5, q=0.5, r=[4.0, 2.0]).double()
    est = _estimators(model)[name].double()
    with torch.no_grad():
        whole = est(z, x0, P0, dt=dt)
        state = est.init(x0, P0)
        parts = []
        for cut in (slice(0, 1), slice(1, 17), slice(17, 40)):
            state, part = est.scan(state, z[:, cut], dt=dt[:, cut], keep=keep)
            parts.append(part)
    tol = {"atol": 1e-10, "rtol": 1e-10}
    assert_close(torch.cat([p.mean for p in parts], 1), whole.mean, **tol)
    if keep == "moments":
        assert_close(torch.cat([p.cov for p in parts], 1), whole.cov, **tol)
    assert_close(state.mean, whole.mean[:, -1], **tol)
    assert_close(state.cov, whole.cov[:, -1], **tol)
    if whole.post_innovation is not None:
        assert_close(state.post_innovation, whole.post_innovation[:, -1], **tol)
    if whole.log_likelihood is not None:
        assert_close(state.log_likelihood, whole.log_likelihood, **tol)


@needs_compiler
def test_compiled_state_after_a_trimmed_pass_is_the_last_step():
    """The compiled loop's own record of the last state (written when the history is not)
    equals the last step of the whole history, per track, for many tracks on threads."""
    z, dt, x0, P0 = _problem(seed=8, B=150, T=12)
    model = ts.models.ConstantVelocity(dt=1.5, q=0.5, r=[4.0, 2.0]).double()
    svsf = ts.SVSF(model, psi=[3.0, 2.0, 4.0, 1.5], gamma=0.2).double()
    with torch.no_grad():
        whole = svsf(z, x0, P0, dt=dt)
        state, _ = svsf.scan(svsf.init(x0, P0), z, dt=dt, keep="mean")
    assert_close(state.mean, whole.mean[:, -1], atol=0, rtol=0)
    assert_close(state.cov, whole.cov[:, -1], atol=0, rtol=0)
    assert_close(state.post_innovation, whole.post_innovation[:, -1], atol=0, rtol=0)


def test_one_track_keeps_what_is_asked():
    z, dt, x0, P0 = _problem(seed=2, B=1, T=20)
    kf = ts.KalmanFilter(ts.models.ConstantVelocity(q=0.5, r=4.0)).double()
    out = kf(z[0], x0[0], P0[0], keep="mean")
    assert out.mean.shape == (20, 4) and out.cov is None and out.log_likelihood.ndim == 0


def test_gradients_flow_through_a_trimmed_result():
    """Training may keep less too: the gradients equal those through the whole result."""
    z, dt, x0, P0 = _problem(seed=9, B=3, T=25)
    model = ts.models.ConstantVelocity(dt=1.5, q=0.5, r=[4.0, 2.0]).double()
    svss = ts.SVSS(ts.SVSF(model, psi=[3.0, 2.0, 4.0, 1.5], gamma=0.2)).double()
    grads = []
    for keep in ("all", "mean"):
        svss.zero_grad()
        svss(z, x0, P0, dt=dt, keep=keep).mean.square().sum().backward()
        grads.append([p.grad.clone() for p in svss.parameters()])
    for a, b in zip(*grads, strict=True):
        assert_close(a, b, atol=0, rtol=0)


@pytest.mark.parametrize("keep", ["everything", "", None, 1])
def test_bad_keep_names_the_argument(keep):
    z, dt, x0, P0 = _problem(seed=1, B=2, T=9)
    kf = ts.KalmanFilter(ts.models.ConstantVelocity()).double()
    with pytest.raises(ValueError, match="keep: expected one of 'all', 'moments', 'mean'"):
        kf(z, x0, P0, keep=keep)
    with pytest.raises(ValueError, match="keep"):
        kf.scan(kf.init(x0, P0), z, keep=keep)
    with pytest.raises(ValueError, match="keep: expected one of"):
        kf.step(kf.init(x0, P0), z[:, 0], keep=keep)  # the compiled step says so too


def test_reference_paths_agree_when_keeping_less():
    """General path and tensor loops keep the same as the compiled loops."""
    z, dt, x0, P0 = _problem(seed=7, B=3, T=20)
    model = ts.models.ConstantVelocity(dt=1.5, q=0.5, r=[4.0, 2.0]).double()
    svss = ts.SVSS(ts.SVSF(model, psi=[3.0, 2.0, 4.0, 1.5], gamma=0.2), lag=2).double()
    with torch.no_grad():
        compiled = svss(z, x0, P0, dt=dt, keep="moments")
        with eager_loops():
            eager = svss(z, x0, P0, dt=dt, keep="moments")
        with general_path():
            general = svss(z, x0, P0, dt=dt, keep="moments")
    for other in (eager, general):
        _check(other, compiled, "moments", {"atol": 1e-9, "rtol": 1e-9})


@needs_compiler
@pytest.mark.parametrize("keep", KEEPS)
@pytest.mark.parametrize("case", ["KF dense", "SVSF CV"])
@pytest.mark.parametrize("single", [False, True], ids=["batch", "one track"])
def test_online_steps_keep_what_is_asked(case, keep, single, spy):  # noqa: F811
    """An online step keeping less writes less (the compiled dense step) and gives the whole
    step's moments; the states, which carry the filter on, are whole."""
    dense = random_system(3, 2, T=25, B=3)
    z, x0, P0 = dense.tensors()
    z = z.clone()
    z[:, 4] = float("nan")  # a pure prediction
    z[1, 7:9, 0] = float("nan")  # a component missing
    x0 = x0.expand(3, -1)
    est = ts.KalmanFilter(dense.model())
    if case == "SVSF CV":
        cv = ts.models.ConstantVelocity(dt=1.5, q=0.5, r=[4.0, 2.0])
        est = ts.SVSF(cv, psi=[3.0, 2.0], gamma=0.2, artificial=None)
        x0, P0 = x0.new_zeros(3, 4), torch.eye(4, dtype=x0.dtype) * 5
    est = est.double()
    if single:
        z, x0 = z[0], x0[0]
        P0 = P0[0] if P0.ndim == 3 else P0
    with torch.no_grad():
        whole_state, trimmed_state = est.init(x0, P0), est.init(x0, P0)
        for t in range(z.shape[-2]):
            whole_state, whole = est.step(whole_state, z[..., t, :])
            trimmed_state, trimmed = est.step(trimmed_state, z[..., t, :], keep=keep)
            _check(trimmed, whole, keep, {"atol": 0.0, "rtol": 0.0})
            for name in ("mean", "cov", "post_innovation", "log_likelihood"):
                a, b = getattr(trimmed_state, name), getattr(whole_state, name)
                assert (a is None) == (b is None), name
                if a is not None:
                    assert_close(a, b, atol=0.0, rtol=0.0, msg=name)
    assert spy["dense"] == 2 * z.shape[-2]
