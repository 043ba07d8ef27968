"""The step protocol of the Gaussian filters: ``init``, ``step`` and ``scan`` (chunks with the
state carried between them) give the whole-sequence result, with gaps, per-step ``dt`` and ψ."""

from __future__ import annotations

import pytest
import torch

import torchsvs as ts
from tests.conftest import assert_close
from torchsvs.types import FilterState

#: Fields of a FilterResult that hold one entry per step.
PER_STEP = ("mean", "cov", "pred_mean", "pred_cov", "innovation", "mask", "gain")
PER_STEP += ("post_innovation", "innovation_cov")
TOL = {"atol": 1e-12, "rtol": 1e-12}


def _problem(seed=0, B=3, T=40):
    gen = torch.Generator().manual_seed(seed)
    z = torch.randn(B, T, 2, generator=gen, dtype=torch.float64) * 3
    z = z + torch.arange(T, dtype=torch.float64)[None, :, None] * torch.tensor([2.0, -1.0])
    z[torch.rand(B, T, 2, generator=gen) < 0.2] = float("nan")
    z[:, 7] = float("nan")  # a step without any measurement
    z[0, 20:26, 1] = float("nan")  # a gap on one axis
    dt = torch.rand(B, T, generator=gen, dtype=torch.float64) + 0.5
    x0 = torch.randn(B, 4, generator=gen, dtype=torch.float64)
    P0 = torch.diag(torch.tensor([9.0, 2.0, 9.0, 2.0], dtype=torch.float64)).repeat(B, 1, 1)
    psi = torch.rand(B, T, 4, generator=gen, dtype=torch.float64) * 4 + 0.5
    return z, dt, x0, P0, psi


def _estimators():
    model = ts.models.ConstantVelocity(dt=1.5, q=0.5, r=[4.0, 2.0])
    fd = [3.0, 2.0, 4.0, 1.5]
    return {
        "KF": ts.KalmanFilter(model),
        "EKF": ts.ExtendedKalmanFilter(model),
        "UKF": ts.UnscentedKalmanFilter(model),
        "RSTKF": ts.RobustStudentTKalmanFilter(model),
        "SVSF H+": ts.SVSF(model, psi=[3.0, 4.0], gamma=0.2, artificial=None),
        "SVSF": ts.SVSF(model, psi=fd, gamma=0.2),
        "SVSF adjacent": ts.SVSF(
            model, psi=fd, gamma=0.2, artificial=ts.FiniteDifferenceVelocity(bridge_gaps=False)
        ),
    }


NAMES = list(_estimators())


def _chunked(est, state, z, dt, psi, size):
    """Runs ``z`` in chunks of ``size`` steps; the results concatenated over time."""
    parts = []
    for start in range(0, z.shape[1], size):
        window = slice(start, start + size)
        kwargs = {"psi": psi[:, window]} if psi is not None else {}
        state, result = est.scan(state, z[:, window], dt=dt[:, window], **kwargs)
        parts.append(result)
    return state, parts


@pytest.mark.parametrize("name", NAMES)
@pytest.mark.parametrize("size", [1, 7, 333])
def test_chunked_runs_equal_the_whole_run(name, size):
    z, dt, x0, P0, psi = _problem()
    est = _estimators()[name].double()
    psi = psi if est.takes_psi() and name != "SVSF H+" else None
    kwargs = {"psi": psi} if psi is not None else {}
    with torch.no_grad():
        whole = est(z, x0, P0, dt=dt, **kwargs)
        state, parts = _chunked(est, est.init(x0, P0), z, dt, psi, size)
    for key in PER_STEP:
        expected = getattr(whole, key)
        if expected is None:
            assert all(getattr(p, key) is None for p in parts), key
            continue
        got = torch.cat(
            [getattr(p, key).expand(z.shape[0], *getattr(p, key).shape[1:]) for p in parts], 1
        )
        assert_close(got.double(), expected.double(), msg=key, **TOL)
    assert state.steps == z.shape[1]
    assert_close(state.mean, whole.mean[:, -1], **TOL)
    assert_close(state.cov.expand_as(whole.cov[:, -1]), whole.cov[:, -1], **TOL)
    if whole.log_likelihood is not None:
        assert_close(state.log_likelihood, whole.log_likelihood, **TOL)
        assert_close(sum(p.log_likelihood for p in parts), whole.log_likelihood, **TOL)


@pytest.mark.parametrize("name", NAMES)
def test_step_by_step_equals_the_whole_run(name):
    z, dt, x0, P0, psi = _problem(seed=1, T=25)
    est = _estimators()[name].double()
    use_psi = est.takes_psi() and name != "SVSF H+"
    with torch.no_grad():
        whole = est(z, x0, P0, dt=dt, **({"psi": psi} if use_psi else {}))
        state = est.init(x0, P0)
        means, covs = [], []
        for t in range(z.shape[1]):
            kwargs = {"psi": psi[:, t]} if use_psi else {}
            state, out = est.step(state, z[:, t], dt=dt[:, t], **kwargs)
            assert out.mean.shape == (3, 4) and out.cov.shape[-2:] == (4, 4)
            assert_close(state.mean, out.mean, atol=0, rtol=0)
            means.append(out.mean)
            covs.append(out.cov.expand(3, 4, 4))
    assert_close(torch.stack(means, 1), whole.mean, **TOL)
    assert_close(torch.stack(covs, 1), whole.cov, **TOL)


def test_one_track_online_and_a_constant_interval():
    """A live feed of one track: ``init`` on ``[n]``, ``step`` on ``[m]``, the model's ``dt``."""
    z, _, x0, P0, _ = _problem(seed=2, B=1, T=30)
    svsf = _estimators()["SVSF"].double()
    with torch.no_grad():
        whole = svsf(z[0], x0[0], P0[0])
        state = svsf.init(x0[0], P0[0])
        assert state.single and state.mean.shape == (1, 4)
        outs = []
        for t in range(30):
            state, out = svsf.step(state, z[0, t])
            outs.append(out.mean)
    assert outs[0].shape == (4,)
    assert_close(torch.stack(outs), whole.mean, **TOL)


def test_artificial_measurements_with_inputs_carry_their_rows():
    """The EHA's bulk-modulus measurement reads the previous row and the input ``u``."""
    sc = ts.scenarios.eha_scenario(4, torch.Generator().manual_seed(0))
    svsf = ts.SVSF(
        sc.model, psi=[1e-3, 1e-3, 1e-2, 1e8], artificial=ts.filters.ModulusFromAcceleration()
    ).double()
    with torch.no_grad():
        whole = svsf(sc.z, sc.x0, sc.P0, u=sc.u)
        state, parts = svsf.init(sc.x0, sc.P0), []
        for start in range(0, sc.z.shape[1], 50):
            window = slice(start, start + 50)
            state, result = svsf.scan(state, sc.z[:, window], u=sc.u[:, window])
            parts.append(result.mean)
        assert state.history is not None and state.history.z.shape[1] <= 2
    assert_close(torch.cat(parts, 1), whole.mean, **TOL)


def test_steps_are_pure_and_the_history_stays_short():
    z, dt, x0, P0, psi = _problem(seed=3)
    svsf = _estimators()["SVSF"].double()
    state = svsf.init(x0, P0)
    for t in range(12):
        state, _ = svsf.step(state, z[:, t], dt=dt[:, t], psi=psi[:, t])
    before = [x.clone() for x in (state.mean, state.cov, state.post_innovation)]
    z_t = z[:, 12].clone()
    with torch.no_grad():
        after, _ = svsf.step(state, z[:, 12], dt=dt[:, 12], psi=psi[:, 12])
        again, _ = svsf.step(state, z[:, 12], dt=dt[:, 12], psi=psi[:, 12])
    for x, y in zip(before, (state.mean, state.cov, state.post_innovation), strict=True):
        assert torch.equal(x, y)
    assert torch.allclose(z_t, z[:, 12], rtol=0, atol=0, equal_nan=True)
    assert torch.equal(after.mean, again.mean)
    # Finite differences look back to the last observation of each axis, not further.
    assert after.history.z.shape[1] <= 3


def test_gradients_flow_through_steps():
    z, dt, x0, P0, psi = _problem(seed=4, T=10)
    svsf = _estimators()["SVSF"].double()
    state = svsf.init(x0, P0)
    loss = torch.zeros((), dtype=torch.float64)
    for t in range(10):
        state, out = svsf.step(state, z[:, t], dt=dt[:, t])
        loss = loss + out.mean.square().sum()
    loss.backward()
    assert svsf.boundary_layer.raw.grad is not None
    assert bool(torch.isfinite(svsf.boundary_layer.raw.grad).all())


def test_bad_steps_name_the_argument():
    z, dt, x0, P0, psi = _problem(seed=5, T=10)
    kf = _estimators()["KF"].double()
    state = kf.init(x0, P0)
    with pytest.raises(TypeError, match="^state: expected a FilterState"):
        kf.step((x0, P0), z[:, 0])
    with pytest.raises(ValueError, match=r"^z: expected shape \[B, T, 2\]"):
        kf.scan(state, z[0, :, 0])
    with pytest.raises(ValueError, match="^psi: KalmanFilter has no boundary layer"):
        kf.step(state, z[:, 0], psi=psi[:, 0])
    with pytest.raises(ValueError, match=r"^x0: expected shape \[B, n\] or \[n\] = \[4\]"):
        kf.init(x0[:, :3], P0)
    svsf = _estimators()["SVSF"].double()
    state, _ = svsf.step(svsf.init(x0, P0), z[:, 0], dt=dt[:, 0])
    with pytest.raises(ValueError, match="^dt: pass it at every step or at none"):
        svsf.step(state, z[:, 1])
    assert isinstance(state, FilterState)


def _smoothers():
    model = ts.models.ConstantVelocity(dt=1.5, q=0.5, r=[4.0, 2.0])
    fd = [3.0, 2.0, 4.0, 1.5]
    return {
        "KS lag 3": ts.RTSSmoother(ts.KalmanFilter(model), lag=3),
        "SVSS lag 1": ts.SVSS(ts.SVSF(model, psi=[3.0, 4.0], gamma=0.2, artificial=None), lag=1),
        "SVSS lag 4": ts.SVSS(ts.SVSF(model, psi=fd, gamma=0.2), lag=4),
        "SVSTPS lag 2": ts.RTSSmoother(ts.SVSF(model, psi=fd, gamma=0.2), lag=2),
    }


@pytest.mark.parametrize("name", list(_smoothers()))
def test_online_fixed_lag_smoothing_equals_the_offline_one(name):
    z, dt, x0, P0, psi = _problem(seed=6, T=30)
    est = _smoothers()[name].double()
    use_psi = "lag 1" not in name and est.takes_psi()
    lag = est.lag
    with torch.no_grad():
        offline = est(z, x0, P0, dt=dt, **({"psi": psi} if use_psi else {}))
        state = est.init(x0, P0)
        means, covs = [], []
        for t in range(z.shape[1]):
            kwargs = {"psi": psi[:, t]} if use_psi else {}
            state, out = est.step(state, z[:, t], dt=dt[:, t], **kwargs)
            if t < lag:
                assert out is None
            else:
                means.append(out.mean)  # x̂_{t-L|t}
                covs.append(out.cov.expand(3, 4, 4))
        rest = est.flush(state)
    assert rest.mean.shape[1] == lag
    mean = torch.cat([torch.stack(means, 1), rest.mean], 1)
    cov = torch.cat([torch.stack(covs, 1), rest.cov.expand(3, lag, 4, 4)], 1)
    assert_close(mean, offline.mean, atol=1e-10, rtol=1e-10)
    assert_close(cov, offline.cov, atol=1e-10, rtol=1e-10)


def test_online_smoothing_of_one_track_and_its_limits():
    z, _, x0, P0, _ = _problem(seed=7, B=1, T=12)
    ks = _smoothers()["KS lag 3"].double()
    with torch.no_grad():
        offline = ks(z[0], x0[0], P0[0])
        state, emitted = ks.init(x0[0], P0[0]), []
        for t in range(12):
            state, out = ks.step(state, z[0, t])
            if out is not None:
                assert out.mean.shape == (4,)
                emitted.append(out.mean)
        rest = ks.flush(state)
    assert_close(torch.cat([torch.stack(emitted), rest.mean]), offline.mean, atol=1e-10)
    interval = ts.RTSSmoother(ts.KalmanFilter(ts.models.ConstantVelocity()))
    with pytest.raises(ValueError, match="^lag: online smoothing needs a fixed lag"):
        interval.init(x0[0].float(), P0[0].float())
    with pytest.raises(TypeError, match="^state: expected a LagState"):
        ks.step(ks.filter.init(x0[0], P0[0]), z[0, 0])


def _particle_filters():
    model = ts.models.ConstantVelocity(dt=1.5, q=0.5, r=[4.0, 2.0])
    fd = [3.0, 2.0, 4.0, 1.5]
    return {
        "PF": ts.ParticleFilter(model, num_particles=64, resample_threshold=0.8),
        "SPVSF adapted": ts.SPVSF(model, psi=fd, num_particles=32),
        "SPVSF estimate": ts.SPVSF(
            model, psi=[3.0, 4.0], artificial=None, num_particles=32, proposal="estimate"
        ),
        "SPVSF particles": ts.SPVSF(
            model, psi=fd, num_particles=32, proposal="particles", soft_resampling=0.5
        ),
    }


@pytest.mark.parametrize("name", list(_particle_filters()))
def test_particle_filters_in_chunks_equal_the_whole_run(name):
    """With one generator passed through ``init`` and every chunk, the draws are the whole
    run's: the results agree (exactly, up to the finite-difference velocities' clock over a
    window, ~1e-13)."""
    z, dt, x0, P0, _ = _problem(seed=8, T=30)
    est = _particle_filters()[name].double()
    with torch.no_grad():
        whole = est(z, x0, P0, dt=dt, generator=torch.Generator().manual_seed(3))
        for size in (1, 7):
            gen = torch.Generator().manual_seed(3)
            state = est.init(x0, P0, generator=gen)
            parts = []
            for start in range(0, 30, size):
                window = slice(start, start + size)
                if size == 1:
                    state, out = est.step(state, z[:, start], dt=dt[:, start], generator=gen)
                    parts.append(out.mean.unsqueeze(1))
                else:
                    state, result = est.scan(state, z[:, window], dt=dt[:, window], generator=gen)
                    parts.append(result.mean)
            assert_close(torch.cat(parts, 1), whole.mean, **TOL)
            assert_close(state.particles, whole.particles, **TOL)
            assert_close(state.log_likelihood, whole.log_likelihood, **TOL)
