"""Every bad input raises ValueError/TypeError naming the argument and what was expected."""

from __future__ import annotations

import pytest
import torch

import torchsvs as ts
from tests.conftest import atc_batch

NAN, INF = float("nan"), float("inf")


@pytest.fixture(scope="module")
def atc():
    return atc_batch(2)


def _svss(model):
    return ts.SVSS(ts.SVSF(model, psi=[800.0, 800.0], gamma=0.1, artificial=None))


def _call_cases(sc):
    z, x0, P0 = sc.z, sc.x0, sc.P0
    B, T = z.shape[:2]
    bad_P0 = P0.clone()
    bad_P0[0, 1] = 5.0
    indefinite = torch.diag(torch.tensor([1.0, -1.0, 1.0, 1.0], dtype=z.dtype))
    z_inf = z.clone()
    z_inf[0, 3, 1] = INF
    return {
        "z not a tensor": (TypeError, "^z:", (z.tolist(), x0, P0), {}),
        "z integer": (TypeError, "^z:", (z.long(), x0, P0), {}),
        "z rank 1": (
            ValueError,
            r"^z: expected shape .*got \(980,\)",
            (z[0, :, 0].repeat(2), x0, P0),
            {},
        ),
        "z wrong m": (ValueError, "^z:.*got", (z[..., :1], x0, P0), {}),
        "z no steps": (ValueError, "^z:", (z[:, :0], x0, P0), {}),
        "z inf": (ValueError, "^z: contains inf", (z_inf, x0, P0), {}),
        "x0 wrong size": (ValueError, r"^x0: expected shape .*got \(3,\)", (z, x0[:3], P0), {}),
        "x0 wrong batch": (ValueError, "^x0:", (z, x0.expand(3, 4), P0), {}),
        "x0 nan": (ValueError, "^x0: contains NaN", (z, x0 * NAN, P0), {}),
        "x0 not numeric": (TypeError, "^x0:", (z, "origin", P0), {}),
        "P0 wrong shape": (ValueError, r"^P0: expected shape", (z, x0, P0[:3, :3]), {}),
        "P0 wrong batch": (ValueError, "^P0:", (z, x0, P0.expand(3, 4, 4)), {}),
        "P0 inf": (ValueError, "^P0: contains NaN or inf", (z, x0, P0 * INF), {}),
        "P0 asymmetric": (ValueError, "^P0: expected a symmetric", (z, x0, bad_P0), {}),
        "P0 indefinite": (ValueError, "^P0: expected a positive definite", (z, x0, indefinite), {}),
        "dt wrong shape": (
            ValueError,
            r"^dt: expected a scalar or \[2, 490\]",
            (z, x0, P0),
            {"dt": torch.ones(T)},
        ),
        "dt negative": (
            ValueError,
            "^dt: expected finite intervals > 0",
            (z, x0, P0),
            {"dt": -1.0},
        ),
        "dt zero per step": (ValueError, "^dt:", (z, x0, P0), {"dt": torch.zeros(B, T)}),
        "u given": (
            ValueError,
            "^u: ConstantVelocity takes no control input",
            (z, x0, P0),
            {"u": torch.zeros(B, T, 1)},
        ),
        "psi override rank": (
            ValueError,
            r"^psi: expected a per-step override of shape \[2, 490, m\]",
            (z, x0, P0),
            {"psi": torch.ones(B, 2)},
        ),
        "psi override m": (
            ValueError,
            r"^psi: expected a per-step override of shape \[B, T, 2\]",
            (z, x0, P0),
            {"psi": torch.ones(B, T, 3, dtype=z.dtype)},
        ),
        "psi override <= 0": (
            ValueError,
            "^psi: expected finite boundary layer widths > 0",
            (z, x0, P0),
            {"psi": torch.zeros(B, T, 2)},
        ),
        "generator type": (TypeError, "^generator:", (z, x0, P0), {"generator": 0}),
    }


@pytest.mark.parametrize("case", list(_call_cases(atc_batch(2))))
def test_bad_call_arguments(atc, case):
    error, pattern, args, kwargs = _call_cases(atc)[case]
    with pytest.raises(error, match=pattern):
        _svss(atc.model)(*args, **kwargs)


def test_single_track_needs_unbatched_prior(atc):
    with pytest.raises(ValueError, match=r"^x0: expected shape \[n\] = \[4\]"):
        ts.KalmanFilter(atc.model)(atc.z[0], atc.x0.expand(2, 4), atc.P0)


@pytest.mark.parametrize(
    "kwargs, pattern",
    [
        ({"psi": 0.0}, "^psi: expected finite values > 0"),
        ({"psi": [800.0, -1.0]}, "^psi: expected finite values > 0"),
        ({"psi": [[1.0, 2.0]]}, "^psi: expected a scalar or a vector"),
        ({"psi": "wide"}, "^psi: expected a number"),
        ({"psi": 800.0, "gamma": 1.0}, r"^gamma: expected values in \[0, 1\)"),
        ({"psi": 800.0, "gamma": -0.1}, r"^gamma: expected values in \[0, 1\)"),
        ({"psi": 800.0, "gamma": [0.1, 0.2]}, "^gamma: expected a scalar"),
        ({"psi": 800.0, "artificial": 3}, "^artificial: expected 'auto', a callable or None"),
    ],
)
def test_bad_svsf_settings(atc, kwargs, pattern):
    with pytest.raises((ValueError, TypeError), match=pattern):
        ts.SVSF(atc.model, **kwargs)


def test_an_svsf_without_memory_keeps_it_fixed(atc):
    """γ = 0 (no memory) is a valid setting (``track --gamma 0``) that logit space cannot
    learn: it stays fixed at 0 while ψ is learned."""
    svsf = ts.SVSF(atc.model, psi=800.0, gamma=0.0)
    assert float(svsf.gamma) == 0.0
    learned = {name for name, p in svsf.named_parameters() if p.requires_grad}
    assert "boundary_layer.raw" in learned and not any("memory" in n for n in learned)


def test_psi_width_count_must_match_corrector(atc):
    svsf = ts.SVSF(atc.model, psi=[1.0, 2.0, 3.0], artificial=None)
    with pytest.raises(ValueError, match="^psi: expected 2 boundary layer widths"):
        svsf(atc.z, atc.x0, atc.P0)
    artificial = ts.SVSF(atc.model, psi=[1.0, 2.0], artificial=ts.FiniteDifferenceVelocity())
    with pytest.raises(ValueError, match="^psi: expected 4 boundary layer widths"):
        artificial(atc.z, atc.x0, atc.P0)


def test_artificial_velocity_needs_a_motion_model():
    model = ts.models.LinearGaussian(torch.eye(2), torch.eye(2), torch.eye(2), torch.eye(2))
    svsf = ts.SVSF(model, psi=1.0, artificial=ts.FiniteDifferenceVelocity())
    with pytest.raises(TypeError, match="^model: FiniteDifferenceVelocity needs position_index"):
        svsf(torch.zeros(1, 3, 2), torch.zeros(2), torch.eye(2))


@pytest.mark.parametrize("lag", [0, -1, 1.5, True, "1"])
def test_bad_lag(atc, lag):
    with pytest.raises(ValueError, match="^lag: expected None"):
        ts.SVSS(ts.SVSF(atc.model, psi=1.0), lag=lag)
    with pytest.raises(ValueError, match="^lag: expected None"):
        ts.RTSSmoother(ts.KalmanFilter(atc.model), lag=lag)


def test_bad_components():
    with pytest.raises(TypeError, match="^filter: expected a torchsvs Gaussian filter"):
        ts.SVSS(torch.nn.Identity())  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="^model: expected a torchsvs LinearModel"):
        ts.KalmanFilter("cv")  # type: ignore[arg-type]


def test_dt_refused_by_fixed_matrix_model():
    model = ts.models.LinearGaussian(torch.eye(2), torch.eye(2), torch.eye(2), torch.eye(2))
    with pytest.raises(ValueError, match="^dt: LinearGaussian has fixed matrices"):
        ts.KalmanFilter(model)(torch.zeros(1, 3, 2), torch.zeros(2), torch.eye(2), dt=1.0)


@pytest.mark.parametrize(
    "args, pattern",
    [
        (
            (torch.ones(2, 3), torch.eye(2), torch.eye(2), torch.eye(2)),
            r"^F: expected a square matrix",
        ),
        (
            (torch.eye(2), torch.ones(1, 3), torch.eye(2), torch.eye(1)),
            r"^H: expected shape \[m, 2\]",
        ),
        ((torch.eye(2), torch.eye(2), torch.eye(3), torch.eye(2)), r"^Q: expected shape \[2, 2\]"),
        ((torch.eye(2), torch.eye(2), torch.eye(2), torch.eye(3)), r"^R: expected shape \[2, 2\]"),
        (
            (torch.eye(2), torch.eye(2), torch.tensor([[1.0, 2.0], [0.0, 1.0]]), torch.eye(2)),
            "^Q: expected a finite symmetric",
        ),
        (
            (torch.eye(2), torch.eye(2), -torch.eye(2), torch.eye(2)),
            "^Q: expected a positive definite",
        ),
        ((torch.eye(2), torch.eye(2), torch.eye(2), torch.ones(2)), "^R: expected a square matrix"),
    ],
)
def test_bad_linear_gaussian(args, pattern):
    with pytest.raises(ValueError, match=pattern):
        ts.models.LinearGaussian(*args)


@pytest.mark.parametrize(
    "kwargs, pattern",
    [
        ({"ndim": 0}, "^ndim: expected a positive integer"),
        ({"dt": 0.0}, "^dt: expected a positive number"),
        ({"q": -1.0}, "^q: expected finite values > 0"),
        ({"r": [1.0, 2.0, 3.0]}, "^r: expected 2 per-axis variances"),
        ({"r": -4.0}, "^r: expected a positive definite"),
    ],
)
def test_bad_constant_velocity(kwargs, pattern):
    with pytest.raises(ValueError, match=pattern):
        ts.models.ConstantVelocity(**kwargs)


def test_bad_metrics_and_segments():
    with pytest.raises(ValueError, match=r"^estimate: expected the shape of truth"):
        ts.metrics.accumulative_rmse(torch.zeros(2, 3, 4), torch.zeros(2, 3, 2))
    with pytest.raises(ValueError, match="^segments: duration 2.5 is not a positive multiple"):
        ts.scenarios.simulate_segments(torch.zeros(4), [ts.scenarios.Segment(2.5)], dt=1.0)


def test_shape_messages_say_which_axis_is_which(atc):
    """With B = n = 4 a bare "[4, 4] or [4]" would not say which is the batch."""
    z = atc.z[:1].expand(4, -1, -1)
    with pytest.raises(
        ValueError, match=r"^x0: expected shape \[B, n\] = \[4, 4\] or \[n\] = \[4\]"
    ):
        ts.KalmanFilter(atc.model)(z, torch.zeros(3, 4, dtype=z.dtype), atc.P0)
    with pytest.raises(ValueError, match=r"^P0: expected shape \[B, n, n\] = \[4, 4, 4\] or"):
        ts.KalmanFilter(atc.model)(z, torch.zeros(4, dtype=z.dtype), atc.P0.expand(3, 4, 4))


@pytest.mark.parametrize("name", ["KF", "SVSF", "SVSS", "PF", "SPVSF"])
def test_no_tracks_is_a_clear_error(atc, name):
    model = atc.model
    est = {
        "KF": ts.KalmanFilter(model),
        "SVSF": ts.SVSF(model, psi=[800.0, 800.0]),
        "SVSS": _svss(model),
        "PF": ts.ParticleFilter(model, num_particles=10),
        "SPVSF": ts.SPVSF(model, psi=[800.0, 800.0], num_particles=10),
    }[name].to(atc.z.dtype)
    with pytest.raises(
        ValueError, match=r"^z: expected at least one track, got shape \(0, 490, 2\)"
    ):
        est(atc.z[:0], atc.x0[:0], atc.P0)


@pytest.mark.parametrize("name", ["KF", "KS", "EKF", "UKF", "RSTKF", "PF", "SPVSF"])
def test_psi_is_refused_where_there_is_no_boundary_layer(atc, name):
    model = atc.model
    est = {
        "KF": ts.KalmanFilter(model),
        "KS": ts.RTSSmoother(ts.KalmanFilter(model)),
        "EKF": ts.ExtendedKalmanFilter(model),
        "UKF": ts.UnscentedKalmanFilter(model),
        "RSTKF": ts.RobustStudentTKalmanFilter(model),
        "PF": ts.ParticleFilter(model, num_particles=10),
        "SPVSF": ts.SPVSF(model, psi=[800.0, 800.0], num_particles=10),
    }[name].to(atc.z.dtype)
    psi = torch.full(atc.z.shape, 500.0, dtype=atc.z.dtype)
    with pytest.raises(ValueError, match=f"^psi: {type(est).__name__} has no boundary layer"):
        est(atc.z, atc.x0, atc.P0, psi=psi)


def test_psi_reaches_the_svsf_and_its_smoothers(atc):
    psi = torch.full(atc.z.shape, 500.0, dtype=atc.z.dtype)
    for est in (
        ts.SVSF(atc.model, psi=[800.0, 800.0], artificial=None),
        _svss(atc.model),
        ts.RTSSmoother(ts.SVSF(atc.model, psi=[800.0, 800.0], artificial=None), lag=1),
    ):
        est = est.to(atc.z.dtype)
        assert not torch.equal(
            est(atc.z, atc.x0, atc.P0, psi=psi).mean, est(atc.z, atc.x0, atc.P0).mean
        )


def test_innovation_losses_on_a_particle_filter_name_the_problem(atc):
    from torchsvs.fitting.losses import innovation_nll, prediction_error
    from torchsvs.training.data import TrackBatch
    from torchsvs.training.module import batch_loss

    pf = ts.ParticleFilter(atc.model, num_particles=10).to(atc.z.dtype)
    batch = TrackBatch(z=atc.z, x0=atc.x0, P0=atc.P0, truth=atc.truth)
    for loss in ("nll", "prediction"):
        with pytest.raises(ValueError, match=f"^loss: '{loss}' .*ParticleFilter does not form"):
            batch_loss(pf, batch, loss)
    result = pf(atc.z, atc.x0, atc.P0, generator=torch.Generator().manual_seed(0))
    for function in (innovation_nll, prediction_error):
        with pytest.raises(TypeError, match="^result: the .* loss needs .*got a ParticleResult"):
            function(result)
    value, _ = batch_loss(pf, batch, "supervised")
    assert torch.isfinite(value)


def test_spvsf_strategies_are_constructor_arguments():
    model = ts.models.ConstantVelocity()
    spvsf = ts.SPVSF(model, psi=50.0, proposal="particles", soft_resampling=0.5)
    assert spvsf.proposal == "particles" and spvsf.soft_resampling == 0.5
    with pytest.raises(ValueError, match=r"^proposal: expected one of"):
        ts.SPVSF(model, psi=50.0, proposal="estimated")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match=r"^soft_resampling: expected None or a value in \(0, 1\]"):
        ts.SPVSF(model, psi=50.0, soft_resampling=2.0)
    with pytest.raises(ValueError, match=r"^resampling: expected one of"):
        ts.SPVSF(model, psi=50.0, resampling="residual")  # type: ignore[arg-type]


def test_small_problems_run_on_one_thread_and_restore_the_setting(atc, monkeypatch):
    """A second intra-op thread slows the step loop of small problems (see
    torchsvs.estimator.SMALL_PROBLEM): the call runs on one and leaves the caller's setting."""
    from torchsvs import estimator

    seen = []
    kf = ts.KalmanFilter(atc.model).to(atc.z.dtype)
    run = kf.run
    monkeypatch.setattr(
        kf, "run", lambda inputs: seen.append(torch.get_num_threads()) or run(inputs)
    )
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        kf(atc.z, atc.x0, atc.P0)
        assert seen == [1] and torch.get_num_threads() == 2
        monkeypatch.setattr(estimator, "SMALL_PROBLEM", 1)  # now every problem is large
        kf(atc.z, atc.x0, atc.P0)
        assert seen == [1, 2] and torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)
