"""The adaptive measurement covariance (Eqs. (29)-(30), Bermúdez Ordoñez et al. 2020): against a
NumPy reference written from the paper, on the filters that take it, online and in chunks."""

from __future__ import annotations

import math

import pytest
import torch

import torchsvs as ts
from tests.conftest import assert_close, random_system
from tests.reference import adaptive_numpy
from torchsvs.filters.adaptive import AdaptiveNoise, differenced_variance
from torchsvs.filters.kalman import KalmanFilter

F64 = torch.float64
TOL = {"atol": 1e-12, "rtol": 1e-12}


def _gen(seed: int = 0) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def _noisy_ramp(B=3, T=60, m=2, seed=0, missing=0.15):
    """A slowly varying signal plus unit noise, NaN sprinkled, an all-NaN step and a gap."""
    g = _gen(seed)
    t = torch.arange(T, dtype=F64)[None, :, None]
    z = 3.0 * t * torch.linspace(-1.0, 1.0, m, dtype=F64) + torch.sin(t / 9.0) * 20.0
    z = z + torch.randn(B, T, m, generator=g, dtype=F64) * torch.linspace(1.0, 2.5, m, dtype=F64)
    z[torch.rand(B, T, m, generator=g) < missing] = math.nan
    z[:, 11] = math.nan
    z[0, 30:41, 0] = math.nan
    return z


def _cv(m=2, r=(4.0, 2.0)):
    R = torch.tensor([[r[0], 0.5], [0.5, r[1]]], dtype=F64)  # correlated: tests the fallback
    return ts.models.ConstantVelocity(ndim=m, dt=1.0, q=0.5, r=R).double()


# --- the formula ---------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("window", "floor", "least", "current"),
    [(8, 0.0, None, True), (5, 1.2, 2, True), (12, 0.3, 6, False), (3, 0.0, 2, False)],
)
def test_r_sequence_equals_the_numpy_reference(window, floor, least, current):
    z = _noisy_ramp()
    model = _cv()
    adaptive = AdaptiveNoise(window, floor=floor, min_differences=least, include_current=current)
    kf = ts.KalmanFilter(model, adaptive_noise=adaptive)
    P0 = torch.eye(4, dtype=F64) * 10
    out = kf(z, torch.zeros(4, dtype=F64), P0)
    R = model.meas_cov().detach().numpy()
    for b in range(z.shape[0]):
        expected = adaptive_numpy.adaptive_R(
            z[b].numpy(), R, window, floor, window - 1 if least is None else least, 1 - current
        )
        assert_close(out.meas_cov[b], expected, atol=1e-12, rtol=1e-12, msg=f"track {b}")
    # The same numbers straight from the formula.
    direct = adaptive.covariance(model.meas_cov().detach(), z)
    assert_close(direct, out.meas_cov, atol=0, rtol=0)


def test_the_filter_uses_r_k_at_step_k():
    """A KF with the adaptive R equals the textbook KF given the reference's R sequence."""
    system = random_system(4, 2, T=40, B=2, seed=3)
    z, x0, P0 = system.tensors()
    adaptive = AdaptiveNoise(6, floor=0.05)
    out = ts.KalmanFilter(system.model(), adaptive_noise=adaptive)(z, x0, P0)
    for b in range(2):
        R_seq = adaptive_numpy.adaptive_R(system.z[b], system.R, 6, 0.05, 5)
        mean, cov = adaptive_numpy.kalman_filter(
            system.z[b], system.F, system.H, system.Q, R_seq, system.x0, system.P0
        )
        assert_close(out.mean[b], mean, atol=1e-9, rtol=1e-9)
        assert_close(out.cov[b], cov, atol=1e-9, rtol=1e-9)


def test_white_noise_variance_is_unbiased_up_to_n_over_n_minus_1():
    """E[σ̂²] = σ² N/(N − 1) for white noise (MATLAB's std of N − 1 correlated differences)."""
    N, sigma = 6, 2.0
    z = torch.randn(20000, N, 1, generator=_gen(1), dtype=F64) * sigma
    variance, count = differenced_variance(z, N)
    assert int(count[:, -1].min()) == N - 1
    assert variance[:, -1].mean().item() == pytest.approx(sigma**2 * N / (N - 1), rel=0.03)


def test_recovers_a_step_change_of_the_noise_from_1_to_5():
    """Noise std 1 for 300 steps, then 5, on a slow signal: the mean over tracks of the
    estimated std is within 15% of the truth once the window has filled."""
    B, T, change, window = 64, 600, 300, 30
    g = _gen(2)
    t = torch.arange(T, dtype=F64)
    signal = 100.0 * torch.sin(2 * math.pi * t / 600.0) + 2.0 * t  # slow against the window
    std = torch.where(t < change, 1.0, 5.0)
    z = (signal + std * torch.randn(B, T, generator=g, dtype=F64)).unsqueeze(-1)
    model = ts.models.LinearGaussian(
        torch.eye(2, dtype=F64) + torch.tensor([[0.0, 1.0], [0.0, 0.0]], dtype=F64),
        torch.tensor([[1.0, 0.0]], dtype=F64),
        torch.eye(2, dtype=F64),
        torch.eye(1, dtype=F64) * 9.0,
    )
    kf = ts.KalmanFilter(model, adaptive_noise=AdaptiveNoise(window))
    out = kf(z, torch.zeros(2, dtype=F64), torch.eye(2, dtype=F64) * 100)
    estimated = out.meas_cov[..., 0, 0].sqrt().mean(0)  # [T]
    before, after = estimated[window:change], estimated[change + window :]
    assert float((before / 1.0 - 1).abs().max()) < 0.15
    assert float((after / 5.0 - 1).abs().max()) < 0.15
    R = model.meas_cov()[0, 0]
    assert bool((out.meas_cov[:, : window - 1, 0, 0] == R).all())  # the model's R until full


# --- the online protocol -------------------------------------------------------------------------


def _estimators():
    adaptive = AdaptiveNoise(7, floor=0.1, min_differences=3)
    cv = _cv()
    dme = ts.models.SlantRanges([[-50.0, 0.0], [60.0, 5.0]], dt=1.0, q=0.5, r=4.0).double()
    return {
        "KF": (ts.KalmanFilter(cv, adaptive_noise=adaptive), cv),
        "EKF": (ts.ExtendedKalmanFilter(dme, adaptive_noise=adaptive), dme),
        "SVSF H+": (ts.SVSF(cv, psi=[3.0, 4.0], artificial=None, adaptive_noise=adaptive), cv),
        "SVSF": (ts.SVSF(cv, psi=[3.0, 2.0, 4.0, 1.5], adaptive_noise=adaptive), cv),
        "SVSF lagged": (
            ts.SVSF(
                cv,
                psi=[3.0, 2.0, 4.0, 1.5],
                adaptive_noise=AdaptiveNoise(5, include_current=False),
            ),
            cv,
        ),
    }


def _inputs(name: str, B=3, T=45):
    z = _noisy_ramp(B=B, T=T, seed=4)
    x0 = torch.tensor([0.0, 1.0, 0.0, -1.0], dtype=F64)
    if name == "EKF":  # ranges of a target moving near the origin
        z = (z.nan_to_num(0.0) + 100.0).abs().where(~torch.isnan(z), z)
        x0 = torch.tensor([10.0, 1.0, 80.0, -1.0], dtype=F64)
    return z, x0, torch.eye(4, dtype=F64) * 25


FIELDS = ("mean", "cov", "pred_cov", "innovation", "innovation_cov", "meas_cov", "gain")


@pytest.mark.parametrize("name", list(_estimators()))
@pytest.mark.parametrize("size", [1, 4, 10])
def test_chunked_runs_equal_the_whole_run(name, size):
    est, _ = _estimators()[name]
    z, x0, P0 = _inputs(name)
    whole = est(z, x0, P0)
    state = est.init(x0, P0)
    parts = []
    for start in range(0, z.shape[1], size):
        state, part = est.scan(state, z[:, start : start + size])
        parts.append(part)
    for key in FIELDS:
        got = torch.cat([getattr(p, key).expand_as(getattr(whole, key)[:, : p.mean.shape[1]])
                         for p in parts], 1)  # fmt: skip
        assert_close(got, getattr(whole, key), msg=key, **TOL)
    assert_close(state.mean, whole.mean[:, -1], **TOL)


@pytest.mark.parametrize("name", ["KF", "SVSF H+"])
def test_step_by_step_equals_the_whole_run(name):
    est, _ = _estimators()[name]
    z, x0, P0 = _inputs(name, T=25)
    whole = est(z, x0, P0)
    state = est.init(x0, P0)
    for t in range(z.shape[1]):
        state, out = est.step(state, z[:, t])
        assert_close(out.meas_cov, whole.meas_cov[:, t], **TOL)
        assert_close(out.mean, whole.mean[:, t], **TOL)


def test_a_batch_equals_its_rows():
    est, _ = _estimators()["KF"]
    z, x0, P0 = _inputs("KF")
    whole = est(z, x0, P0)
    for b in range(z.shape[0]):
        one = est(z[b], x0, P0)
        assert_close(one.mean, whole.mean[b], **TOL)
        assert_close(one.meas_cov, whole.meas_cov[b], **TOL)


# --- NaN, gradients, the SVSF's gain -------------------------------------------------------------


def test_missing_values_are_skipped_and_an_unseen_component_keeps_the_model_r():
    z = _noisy_ramp(B=2, T=30, missing=0.0)
    z[:, :, 1] = math.nan  # never observed
    z[1, 10:20, 0] = math.nan
    model = _cv()
    out = ts.KalmanFilter(model, adaptive_noise=AdaptiveNoise(5))(
        z, torch.zeros(4, dtype=F64), torch.eye(4, dtype=F64)
    )
    R = model.meas_cov().detach()
    assert bool(torch.isfinite(out.mean).all())
    assert_close(out.meas_cov[..., 1, 1], R[1, 1].expand(2, 30), atol=0, rtol=0)
    # Four differences of five samples, both observed: every row is observed but step 11
    # (all NaN) in track 0; track 1 misses component 0 at steps 10-19 too.
    full = torch.zeros(2, 30, dtype=torch.bool)
    full[0, 4:11] = full[0, 16:] = True
    full[1, 4:10] = full[1, 24:] = True
    estimated = out.meas_cov[..., 0, 0] != R[0, 0]
    assert bool((estimated == full).all())
    cross = torch.where(full, 0.0, R[0, 1]).to(F64)  # Eq. (29) is diagonal
    assert_close(out.meas_cov[..., 0, 1], cross, atol=0, rtol=0)


@pytest.mark.parametrize("name", ["KF", "EKF", "SVSF"])
def test_gradients_are_finite(name):
    est, _ = _estimators()[name]
    z, x0, P0 = _inputs(name, T=20)
    z = z.clone().requires_grad_(True)
    out = est(z, x0, P0)
    (out.mean.square().sum() + out.cov.diagonal(dim1=-2, dim2=-1).sum()).backward()
    assert z.grad is not None and bool(torch.isfinite(z.grad).all())
    assert float(z.grad.abs().sum()) > 0


def test_the_covariance_passes_gradcheck():
    z = _noisy_ramp(B=1, T=14, missing=0.1).clone()
    z.requires_grad_(True)
    adaptive = AdaptiveNoise(4, floor=0.01, min_differences=2)
    R = torch.tensor([[2.0, 0.3], [0.3, 1.0]], dtype=F64)
    assert torch.autograd.gradcheck(lambda x: adaptive.covariance(R, x), (z,))


@pytest.mark.parametrize("artificial", [None, "auto"])
def test_the_svsf_gain_does_not_read_r(artificial):
    """The SVSF's estimate is the same with the adaptive R; only its covariance changes."""
    z, x0, P0 = _inputs("KF")
    model = _cv()
    psi = [3.0, 4.0] if artificial is None else [3.0, 2.0, 4.0, 1.5]
    plain = ts.SVSF(model, psi=psi, artificial=artificial)(z, x0, P0)
    adaptive = ts.SVSF(model, psi=psi, artificial=artificial, adaptive_noise=AdaptiveNoise(6))
    out = adaptive(z, x0, P0)
    assert_close(out.mean, plain.mean, **TOL)
    assert not torch.allclose(out.cov, plain.cov)


# --- fast paths and the default ------------------------------------------------------------------


def _cv_problem():
    model = ts.models.ConstantVelocity(ndim=2, dt=1.0, q=0.5, r=[4.0, 2.0]).double()
    z = _noisy_ramp(B=4, T=30, missing=0.0)
    return model, z, torch.zeros(4, dtype=F64), torch.eye(4, dtype=F64) * 10


def test_without_adaptive_noise_the_fast_paths_run_and_with_it_they_decline():
    model, z, x0, P0 = _cv_problem()
    plain, adaptive = KalmanFilter(model), KalmanFilter(model, adaptive_noise=AdaptiveNoise(40))
    assert KalmanFilter(model, adaptive_noise=None).adaptive_noise is None
    with torch.no_grad():
        fast = plain(z, x0, P0)
        slow = adaptive(z, x0, P0)
        assert fast.axes is not None  # the per-axis kernel
        assert slow.axes is None
        state = plain.init(x0, P0)
        if plain.step_shortcut(state, z[:, 0], None, "all") is not None:  # compiled, if built
            assert adaptive.step_shortcut(adaptive.init(x0, P0), z[:, 0], None, "all") is None
        assert adaptive.dense_scan(adaptive.init(x0, P0), _as_inputs(model, z, x0, P0)) is None
        assert plain.dense_ready(None) and not adaptive.dense_ready(None)
    # The window never fills (T < window): the model's R at every step, the same numbers.
    for key in ("mean", "cov", "innovation_cov"):
        assert_close(getattr(slow, key), getattr(fast, key), atol=1e-9, rtol=1e-9)
    assert_close(slow.meas_cov, model.meas_cov().expand(4, 30, 2, 2), atol=0, rtol=0)


def _as_inputs(model, z, x0, P0):
    from torchsvs.estimator import prepare_inputs

    return prepare_inputs(model, z, x0, P0)


def test_smoothers_run_over_an_adaptive_filter():
    model, z, x0, P0 = _cv_problem()
    kf = KalmanFilter(model, adaptive_noise=AdaptiveNoise(6))
    with torch.no_grad():
        smoothed = ts.RTSSmoother(kf)(z, x0, P0)
        filtered = kf(z, x0, P0)
    assert_close(smoothed.filtered.mean, filtered.mean, **TOL)
    assert bool(torch.isfinite(smoothed.mean).all())


# --- arguments -----------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("kwargs", "error", "name"),
    [
        ({"window": 2}, ValueError, "window"),
        ({"window": 4.0}, ValueError, "window"),
        ({"window": True}, ValueError, "window"),
        ({"window": 5, "floor": -1.0}, ValueError, "floor"),
        ({"window": 5, "floor": math.nan}, ValueError, "floor"),
        ({"window": 5, "floor": "1"}, TypeError, "floor"),
        ({"window": 5, "min_differences": 1}, ValueError, "min_differences"),
        ({"window": 5, "min_differences": 5}, ValueError, "min_differences"),
        ({"window": 5, "include_current": 1}, TypeError, "include_current"),
    ],
)
def test_bad_arguments_name_themselves(kwargs, error, name):
    with pytest.raises(error, match=f"^{name}:"):
        AdaptiveNoise(**kwargs)


def test_filters_reject_what_is_not_an_adaptive_noise():
    model = _cv()
    with pytest.raises(TypeError, match="^adaptive_noise:"):
        ts.KalmanFilter(model, adaptive_noise=20)
    with pytest.raises(TypeError, match="^adaptive_noise:"):
        ts.SVSF(model, psi=1.0, adaptive_noise={"window": 20})
    ballistic = ts.models.BallisticReentry()
    with pytest.raises(ValueError, match="^adaptive_noise: the artificial measurement"):
        ts.SVSF(
            ballistic,
            psi=1.0,
            artificial=ts.filters.BallisticCoefficientFromDrag(),
            adaptive_noise=AdaptiveNoise(5),
        )


def test_the_formula_lives_in_one_module():
    import inspect

    from torchsvs.filters import kalman, svsf

    for module in (kalman, svsf):
        assert "unfold" not in inspect.getsource(module)
    assert AdaptiveNoise(4).rows_needed == 3
    assert AdaptiveNoise(4, include_current=False).rows_needed == 4
