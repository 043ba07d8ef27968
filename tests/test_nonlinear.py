"""EKF and UKF: reductions to the KF, the ballistic model's Jacobian, filterpy's UKF as oracle."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from filterpy.kalman import MerweScaledSigmaPoints
from filterpy.kalman import UnscentedKalmanFilter as FilterpyUKF

import torchsvs as ts
from tests.conftest import assert_close


@pytest.mark.parametrize("cls", [ts.ExtendedKalmanFilter, ts.UnscentedKalmanFilter])
def test_linear_model_reduces_to_kalman_filter(system, cls):
    z, x0, P0 = system.tensors()
    z = z.clone()
    z[0, 4, 0] = float("nan")
    z[1, 9] = float("nan")
    kf = ts.RTSSmoother(ts.KalmanFilter(system.model()), lag=2)(z, x0, P0)
    est = ts.RTSSmoother(cls(system.model()), lag=2)(z, x0, P0)
    tol = 1e-9 if cls is ts.ExtendedKalmanFilter else 1e-8
    for field in ("mean", "cov", "pred_mean", "pred_cov", "gain", "innovation", "log_likelihood"):
        assert_close(
            getattr(est.filtered, field), getattr(kf.filtered, field), atol=tol, rtol=tol, msg=field
        )
    assert_close(
        est.filtered.transition, kf.filtered.transition.expand_as(est.filtered.transition), atol=tol
    )
    assert_close(est.mean, kf.mean, atol=tol, rtol=tol)
    assert_close(est.cov, kf.cov, atol=tol, rtol=tol)


@pytest.mark.parametrize("offset", [0.0, 7.3e5])
def test_ukf_in_float32_across_long_gaps_is_the_kalman_filter(offset):
    """Reports 1-150 s apart (an airliner's own report times) in float32, at the origin and
    700 km out: S_h − H P Hᵀ cancelled catastrophically after a long gap (P ~ 1e6), the
    covariance turned indefinite and `torchsvs track --estimator ukf` failed in Cholesky."""
    gen = torch.Generator().manual_seed(0)
    T = 400
    gaps = [8.07, 85.69, 12.03, 71.25, 151.66, 44.3, 11.84, 1.0, 1.0, 2.0]
    dt = torch.tensor(gaps).repeat(1, T // len(gaps))
    t = dt.cumsum(1) - dt[:, :1]
    truth = torch.stack([-offset + 240.0 * t, 0.3 * offset - 40.0 * t], -1)
    z = truth + 10.9 * torch.randn(1, T, 2, generator=gen)
    model = ts.models.ConstantVelocity(q=5.0, r=119.0)
    x0 = torch.tensor([[-offset, 240.0, 0.3 * offset, -40.0]])
    P0 = torch.diag(torch.tensor([119.0, 400.0, 119.0, 400.0]))
    ukf = ts.UnscentedKalmanFilter(model)(z, x0, P0, dt=dt)
    kf = ts.KalmanFilter(model.double())(z.double(), x0.double(), P0.double(), dt=dt.double())
    assert bool((torch.linalg.eigvalsh(ukf.cov) > 0).all())
    assert float((ukf.mean.double() - kf.mean)[..., [0, 2]].abs().max()) < 1.0


def _ballistic_run(T: int = 40, B: int = 2, seed: int = 0):
    model = ts.models.BallisticReentry().double()
    gen = torch.Generator().manual_seed(seed)
    x = torch.tensor([61000.0, 3048.0, 19161.0], dtype=torch.float64).expand(B, 3)
    Q, R = model.process_noise(), model.meas_cov()
    states = []
    for _ in range(T):
        x = (
            model.f(x)
            + torch.randn(B, 3, generator=gen, dtype=torch.float64) @ torch.linalg.cholesky(Q).mT
        )
        states.append(x)
    truth = torch.stack(states, 1)
    z = (
        truth[..., :2]
        + torch.randn(B, T, 2, generator=gen, dtype=torch.float64) @ torch.linalg.cholesky(R).mT
    )
    x0 = torch.tensor([61000.0, 3048.0, 19161.0], dtype=torch.float64)
    P0 = torch.diag(torch.tensor([1e4, 1e3, 1e4], dtype=torch.float64))
    return model, truth, z, x0, P0


def test_ballistic_jacobian_equals_hand_derivation():
    model, truth, *_ = _ballistic_run(T=5)
    x = truth[:, -1]
    T = model.dt
    D = model.drag(x)
    h, v, beta = x[:, 0], x[:, 1], x[:, 2]
    # ∂D/∂h = −ηD, ∂D/∂v = 2D/v, ∂D/∂β = −D/β; v' = v − T(D − g).
    expected = torch.zeros(x.shape[0], 3, 3, dtype=x.dtype)
    expected[:, 0, 0], expected[:, 0, 1] = 1.0, -T
    expected[:, 1, 0] = T * model.decay * D
    expected[:, 1, 1] = 1.0 - 2.0 * T * D / v
    expected[:, 1, 2] = T * D / beta
    expected[:, 2, 2] = 1.0
    assert_close(model.f_jacobian(x), expected, atol=1e-10, rtol=1e-10)  # the model's own
    autograd = ts.models.StateSpaceModel.f_jacobian(model, x)  # the base class's autograd
    assert_close(autograd, expected, atol=1e-10, rtol=1e-10)
    per_track = torch.full((x.shape[0],), T, dtype=x.dtype)
    assert_close(ts.models.StateSpaceModel.f_jacobian(model, x, per_track), expected, atol=1e-10)
    assert_close(model.f_jacobian(x, per_track), expected, atol=1e-10)
    assert_close(model.h_jacobian(x), ts.models.StateSpaceModel.h_jacobian(model, x))
    assert bool((h > 0).all())


def test_ukf_equals_filterpy_on_the_ballistic_model():
    model, truth, z, x0, P0 = _ballistic_run()
    out = ts.UnscentedKalmanFilter(model, alpha=0.5, beta=2.0, kappa=0.0)(z, x0, P0)

    def fx(x, dt):
        return model.f(torch.from_numpy(x)[None]).squeeze(0).numpy()

    def hx(x):
        return x[:2].copy()

    points = MerweScaledSigmaPoints(
        3, alpha=0.5, beta=2.0, kappa=0.0, sqrt_method=lambda M: np.linalg.cholesky(M).T
    )
    for b in range(z.shape[0]):
        ukf = FilterpyUKF(dim_x=3, dim_z=2, dt=model.dt, hx=hx, fx=fx, points=points)
        ukf.x, ukf.P = x0.numpy().copy(), P0.numpy().copy()
        ukf.Q, ukf.R = model.process_noise().numpy(), model.meas_cov().numpy()
        means, covs = [], []
        for zt in z[b].numpy():
            ukf.predict()
            ukf.update(zt)
            means.append(ukf.x.copy())
            covs.append(ukf.P.copy())
        assert_close(out.mean[b], np.array(means), atol=1e-6, rtol=1e-9)
        assert_close(out.cov[b], np.array(covs), atol=1e-6, rtol=1e-7)


def test_ekf_and_ukf_track_the_ballistic_target():
    model, truth, z, x0, P0 = _ballistic_run(T=60, B=20, seed=3)
    for cls in (ts.ExtendedKalmanFilter, ts.UnscentedKalmanFilter):
        out = cls(model)(z, x0, P0)
        altitude = ts.metrics.accumulative_rmse(out.mean, truth)[0]
        assert altitude < 0.5 * 100.0  # well below the 100 m measurement noise
        dt = torch.full(z.shape[:2], model.dt, dtype=z.dtype)
        assert_close(cls(model)(z, x0, P0, dt=dt).mean, out.mean, atol=1e-8, rtol=1e-10)
        single = cls(model)(z[3], x0, P0)
        assert_close(single.mean, out.mean[3], atol=1e-8, rtol=1e-10)


def test_bad_nonlinear_settings():
    with pytest.raises(ValueError, match="^alpha: expected a number > 0"):
        ts.UnscentedKalmanFilter(ts.models.BallisticReentry(), alpha=0.0)
    with pytest.raises(ValueError, match="^kappa: expected n"):
        ts.UnscentedKalmanFilter(ts.models.BallisticReentry(), alpha=0.1, kappa=-3.0)
    with pytest.raises(TypeError, match="^model: expected a torchsvs LinearModel"):
        ts.KalmanFilter(ts.models.BallisticReentry())


class _AsNonlinear(ts.models.StateSpaceModel):
    """A linear model seen only through f, h and autograd Jacobians (the nonlinear code path)."""

    def __init__(self, linear: ts.models.LinearModel) -> None:
        super().__init__()
        self.linear = linear
        self.state_dim, self.meas_dim = linear.state_dim, linear.meas_dim

    def f(self, x, dt=None, u=None):
        return x @ self.linear.transition().to(x.dtype).mT

    def h(self, x):
        return x @ self.linear.meas_matrix().to(x.dtype).mT

    def process_noise(self, dt=None):
        return self.linear.process_noise()

    def meas_cov(self):
        return self.linear.meas_cov()


def test_nonlinear_code_paths_reduce_to_the_linear_ones(system):
    z, x0, P0 = system.tensors()
    z = z.clone()
    z[0, 5, 0] = float("nan")
    linear, wrapped = system.model(), _AsNonlinear(system.model())
    m = system.H.shape[0]
    psi = torch.linspace(0.8, 2.5, m, dtype=torch.float64)
    for make in (
        lambda mod: ts.SVSS(ts.SVSF(mod, psi=psi, gamma=0.3), lag=2),
        lambda mod: ts.RTSSmoother(ts.ExtendedKalmanFilter(mod), lag=None),
    ):
        a, b = make(linear)(z, x0, P0), make(wrapped)(z, x0, P0)
        assert_close(b.mean, a.mean)
        assert_close(b.cov, a.cov, atol=1e-8)
        assert_close(
            b.filtered.meas_matrix, a.filtered.meas_matrix.expand_as(b.filtered.meas_matrix)
        )


def test_svsf_tracks_the_ballistic_target_and_gradients_flow():
    model, truth, z, x0, P0 = _ballistic_run(T=60, B=8, seed=5)
    svsf = ts.SVSF(model, psi=[300.0, 100.0], gamma=0.1)
    out = svsf(z, x0, P0)
    assert ts.metrics.accumulative_rmse(out.mean, truth)[0] < 100.0
    out.mean[..., 0].square().mean().backward()
    assert bool(torch.isfinite(svsf.boundary_layer.raw.grad).all())
    assert out.meas_matrix.shape == (8, 60, 2, 3)


def test_ballistic_scenario_and_gravity_error():
    nominal = ts.scenarios.ballistic_scenario(4, torch.Generator().manual_seed(2))
    faulty = ts.scenarios.ballistic_scenario(
        4, torch.Generator().manual_seed(2), gravity_error_at=15.0
    )
    assert nominal.truth.shape == (4, 300, 3) and nominal.z.shape == (4, 300, 2)
    assert_close(nominal.x0, torch.tensor([67100.0, 3352.8, 21077.1], dtype=torch.float64))
    assert_close(nominal.P0, 10.0 * nominal.model.process_noise())
    # Same noise draws: identical until 15 s; then g (in gravity and in the drag of Eq. (43))
    # doubles, and the extra drag slows the object below its nominal speed.
    assert_close(faulty.truth[:, :150], nominal.truth[:, :150], atol=0, rtol=0)
    assert bool((faulty.truth[:, 200:, 1] < nominal.truth[:, 200:, 1] - 20.0).all())
    assert float(nominal.truth[:, -1, 0].mean()) > 0  # still above ground after 30 s


def test_eha_model_matches_the_transfer_function():
    model = ts.models.ElectrohydrostaticActuator().double()
    A, B_E, D_p, L, M, V0, beta = 3.37e-4, 1260.0, 6.69e-3, 5e-12, 20.0, 8.5e-5, 2.1e8
    x = torch.tensor([[0.01, 0.2, 3.0, beta]], dtype=torch.float64)
    u = torch.tensor([[0.7]], dtype=torch.float64)
    T = model.dt
    accel_rate = (model.f(x, None, u)[0, 2] - x[0, 2]) / T
    # Eq. (48): s³ + (B_E/M + Lβ/V0) s² + (2βA²/(MV0)) s  ↔  numerator 2 D_p β A / (M V0).
    expected = (
        -(B_E / M + L * beta / V0) * 3.0
        - 2 * beta * A**2 / (M * V0) * 0.2
        + 2 * D_p * beta * A / (M * V0) * 0.7
    )
    assert_close(accel_rate, torch.tensor(expected, dtype=torch.float64), rtol=1e-12)
    assert_close(model.f(x, None, u)[0, :2], x[0, :2] + T * x[0, 1:3])
    assert_close(
        ts.models.StateSpaceModel.f_jacobian(model, x, None, u)[0, 2, 3],
        torch.tensor(
            (-L / V0 * 3.0 - 2 * A**2 / (M * V0) * 0.2 + 2 * D_p * A / (M * V0) * 0.7) * T,
            dtype=torch.float64,
        ),
        rtol=1e-10,
    )


def test_eha_scenario_and_inputs_reach_the_filters():
    sc = ts.scenarios.eha_scenario(3, torch.Generator().manual_seed(0), changing=True, duration=1.2)
    assert sc.truth.shape == (3, 1200, 4) and sc.u.shape == (3, 1200, 1)
    modulus = sc.truth[0, :, 3]
    assert (
        float(modulus[498]) == 2.1e8
        and float(modulus[500]) == 1.5e8
        and float(modulus[1000]) == 2.7e8
    )
    ekf = ts.ExtendedKalmanFilter(sc.model)
    out = ekf(sc.z[:, :400], sc.x0, sc.P0, u=sc.u[:, :400])
    assert abs(float(out.mean[:, -1, 3].mean()) / 2.1e8 - 1) < 0.02  # the modulus is found
    no_input = ekf(sc.z[:, :400], sc.x0, sc.P0)
    assert (no_input.mean[:, -1, 3] - out.mean[:, -1, 3]).abs().max() > 1e6  # u matters
    with pytest.raises(ValueError, match=r"^u: expected shape \[3, 400, 1\]"):
        ekf(sc.z[:, :400], sc.x0, sc.P0, u=sc.u[:, :399])


def test_modulus_from_acceleration_lets_the_svsf_find_the_modulus():
    sc = ts.scenarios.eha_scenario(4, torch.Generator().manual_seed(1), duration=0.6)
    art = ts.filters.ModulusFromAcceleration(min_drive=0.2)
    y, H, R = art(sc.z, sc.model, None, sc.u)
    assert y.shape == (4, 600, 4) and H.shape == (4, 4) and R.shape == (4, 600, 4, 4)
    assert bool(torch.isnan(y[:, 0, 3]).all())  # no previous step
    assert 0.02 < float(torch.isnan(y[:, 1:, 3]).float().mean()) < 0.4  # weakly driven steps
    seen = ~torch.isnan(y[..., 3])
    error = (y[..., 3] - sc.truth[..., 3]).abs()[seen] / 2.1e8
    assert float(error.median()) < 0.01
    svsf = ts.SVSF(sc.model, psi=[5e-4, 5e-3, 0.5, 1e6], gamma=0.1, artificial=art)
    out = svsf(sc.z, sc.x0, sc.P0, u=sc.u)
    assert abs(float(out.mean[:, -100:, 3].mean().detach()) / 2.1e8 - 1) < 0.02
    with pytest.raises(ValueError, match="^u: ModulusFromAcceleration needs the inputs"):
        svsf(sc.z, sc.x0, sc.P0)


def test_ballistic_coefficient_from_drag_inverts_the_model():
    # Noise-free measurements of a noise-free truth: Eq. (47) gives β exactly where formed.
    model = ts.models.BallisticReentry().to(torch.float64)
    x = torch.tensor([[61000.0, 3048.0, 19161.0], [30000.0, 2500.0, 15000.0]], dtype=torch.float64)
    states = []
    for _ in range(200):
        x = model.f(x)
        states.append(x)
    truth = torch.stack(states, 1)
    exact = ts.filters.BallisticCoefficientFromDrag(min_snr=0.0)
    y, H, R = exact(model.h(truth), model, None)
    assert y.shape == (2, 200, 3) and H.shape == (3, 3) and R.shape == (2, 200, 3, 3)
    assert bool(torch.isnan(y[:, 0, 2]).all())  # no previous step
    assert_close(y[:, 1:, 2], truth[:, :-1, 2], rtol=1e-6, atol=0.0)
    assert_close(y[..., :2], model.h(truth))
    # Stated noise: variance y₃² (σ_d²/d² + …) with σ_d² = 2 R₂₂ + Q₂₂, positive where formed.
    assert bool((R[:, 1:, 2, 2] > 0).all())
    # With measurement noise the gate keeps only steps whose speed change clears 3 σ_d.
    sc = ts.scenarios.ballistic_scenario(20, torch.Generator().manual_seed(0))
    y, _, R = ts.filters.BallisticCoefficientFromDrag()(sc.z, sc.model, None)
    formed = ~torch.isnan(y[..., 2])
    assert 0.0 < float(formed.float().mean()) < 0.02  # Eq. (47) is mostly noise here
    d = 0.1 * 9.81 - (sc.z[:, 1:, 1] - sc.z[:, :-1, 1])
    sigma_d = (2 * 1e3 + 1e4 * 0.1) ** 0.5
    assert bool((d[formed[:, 1:]] >= 3 * sigma_d).all())
    assert bool((R[..., 2, 2][~formed] == 1.0).all())


def test_ballistic_coefficient_from_drag_bad_input():
    with pytest.raises(ValueError, match="^min_snr: expected a number >= 0"):
        ts.filters.BallisticCoefficientFromDrag(min_snr=-1.0)
    model = ts.models.ConstantVelocity(ndim=1, dt=1.0, q=1.0, r=1.0)
    svsf = ts.SVSF(model, psi=1.0, artificial=ts.filters.BallisticCoefficientFromDrag())
    with pytest.raises(TypeError, match="^model: BallisticCoefficientFromDrag needs a Ballistic"):
        svsf(torch.zeros(1, 5, 1), torch.zeros(2), torch.eye(2))


def test_eha_noise_scale_scales_the_truth_noise_only():
    base = ts.scenarios.eha_scenario(4, torch.Generator().manual_seed(3), duration=0.3)
    small = ts.scenarios.eha_scenario(
        4, torch.Generator().manual_seed(3), duration=0.3, noise_scale=0.1
    )
    noise = (base.z - base.model.h(base.truth)).std()
    assert_close((small.z - small.model.h(small.truth)).std(), 0.1 * noise, rtol=0.05)
    assert_close(small.P0, base.P0)
    assert_close(small.model.meas_cov(), base.model.meas_cov())
    with pytest.raises(ValueError, match="^noise_scale: expected a positive number"):
        ts.scenarios.eha_scenario(2, noise_scale=0.0)


@pytest.mark.parametrize("case", ["ballistic", "eha"])
def test_artificial_measurements_keep_gradients_finite(case):
    # The first step (no previous measurement), missing values and skipped steps are masked
    # after computing on filled values, so gradients with respect to z stay finite.
    if case == "ballistic":
        sc = ts.scenarios.ballistic_scenario(2, torch.Generator().manual_seed(0), duration=3.0)
        art, psi = ts.filters.BallisticCoefficientFromDrag(min_snr=0.0), [1e4, 8e3, 1e5]
    else:
        sc = ts.scenarios.eha_scenario(2, torch.Generator().manual_seed(0), duration=0.05)
        art, psi = ts.filters.ModulusFromAcceleration(), [5e-4, 5e-3, 0.5, 1e6]
    z = sc.z.clone()
    z[0, 7, 1] = float("nan")
    z.requires_grad_(True)
    out = ts.SVSF(sc.model, psi=psi, artificial=art)(z, sc.x0, sc.P0, u=sc.u)
    out.mean.sum().backward()
    assert z.grad is not None and bool(torch.isfinite(z.grad).all())
    assert bool((z.grad[1] != 0).any())
