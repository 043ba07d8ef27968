"""Road targets (Zhang & Zhou 2022): mileage models, the SM augmented model, its building blocks
(unscented initialisation, least-squares reset, online fitting) and the road scenarios."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.interpolate import CubicSpline
from torch.func import jacrev, vmap

import torchsvs as ts
from tests.conftest import assert_close
from tests.reference import road_numpy
from torchsvs.filters.separate.initialisation import (
    _three_point,
    three_point_state,
    unscented_initialisation,
)
from torchsvs.filters.separate.online_fitting import online_fit, sliding_windows
from torchsvs.filters.separate.reset import reset_trajectory_parameters
from torchsvs.scenarios import road as road_module

F64 = torch.float64


def _gen(seed: int = 0) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def _scenario(name: str, num_runs: int = 4, seed: int = 0) -> ts.scenarios.RoadScenario:
    g = _gen(seed)
    if name == "straight":
        return ts.scenarios.straight_road_scenario(num_runs, g)
    if name == "circle":
        return ts.scenarios.circular_road_scenario(num_runs, g)
    return ts.scenarios.curve_road_scenario(int(name[-1]), num_runs, g)


SCENARIOS = ["straight", "circle", "curve1", "curve2"]

# (initial speed, [(step, speed at that step)], [(first, last, a)], steps, dt) from the text.
PROFILES = {
    "straight": (1.0, [(40, 1.0), (70, 46.0), (120, 46.0), (150, 91.0), (200, 91.0)],
                 [(41, 70, 5.0), (121, 150, 5.0)], 200, 0.3),
    "circle": (5.0, [(40, 5.0), (70, 14.0), (110, 14.0), (150, 22.0), (200, 22.0)],
               [(41, 70, 3.0), (111, 150, 2.0)], 200, 0.1),
    "curve1": (2.3, [(40, 2.3), (70, 24.5), (110, 24.5), (150, 42.1), (200, 42.1)],
               [(41, 70, 3.7), (111, 150, 2.2)], 200, 0.2),
    "curve2": (16.5, [(40, 16.5), (80, 31.7), (110, 31.7), (150, 44.5), (180, 44.5),
                      (210, 45.1), (250, 45.1)],
               [(41, 80, 1.9), (111, 150, 1.6), (181, 210, 0.1)], 250, 0.2),
}  # fmt: skip


# --- scenarios ---------------------------------------------------------------------------------


@pytest.mark.parametrize("name", SCENARIOS)
def test_speed_profile_follows_the_paper(name):
    sc = _scenario(name, num_runs=2)
    v0, checkpoints, phases, steps, dt = PROFILES[name]
    assert sc.z.shape == (2, steps, 2) and sc.dt == dt
    assert_close(sc.speed[:, 0], torch.full((2,), v0, dtype=F64))
    for step, speed in checkpoints:
        assert_close(sc.speed[:, step - 1], torch.full((2,), speed, dtype=F64), atol=1e-9)
    expected = torch.zeros(steps, dtype=F64)
    for first, last, a in phases:
        expected[first - 1 : last] = a
    assert_close(sc.acceleration[0], expected)
    assert_close(sc.speed[0].diff(), dt * expected[1:], atol=1e-12)


@pytest.mark.parametrize("name", SCENARIOS)
def test_arc_length_increments_equal_speed_times_interval(name):
    sc = _scenario(name, num_runs=1)
    v, s = sc.speed[0], sc.arc_length[0]
    assert float(s[0]) == 0.0
    # Constant acceleration within an interval: the mean of its end speeds times T.
    assert_close(s.diff(), sc.dt * (v[1:] + v[:-1]) / 2, atol=1e-10)
    steady = sc.acceleration[0, 1:] == 0
    assert_close(s.diff()[steady], sc.dt * v[1:][steady], atol=1e-10)


@pytest.mark.parametrize("name", SCENARIOS)
def test_positions_move_along_the_road_by_arc_length(name):
    """Between consecutive samples the road's length (dense chords) equals the arc-length
    increment, and the velocity is the speed along the road's tangent."""
    sc = _scenario(name, num_runs=1)
    s = sc.arc_length[0]
    fine = s[:-1, None] + (s.diff()[:, None]) * torch.linspace(0, 1, 51, dtype=F64)
    dense = sc.road.position(fine)
    along = dense.diff(dim=1).norm(dim=-1).sum(-1)
    assert_close(along, s.diff(), atol=1e-5, rtol=1e-6)
    assert_close(sc.position[0], sc.road.position(s), atol=1e-9)
    assert_close(sc.velocity[0].norm(dim=-1), sc.speed[0], atol=1e-9)
    ahead = sc.road.position(s + 1e-4)
    tangent = (ahead - sc.position[0]) / 1e-4
    assert_close(sc.velocity[0], sc.speed[0, :, None] * tangent, atol=1e-4 * 91)


def test_straight_road_is_the_65_degree_line_from_the_start():
    sc = _scenario("straight", num_runs=2)
    offset = sc.position[0] - torch.tensor([200.0, 300.0], dtype=F64)
    angle = torch.rad2deg(torch.atan2(offset[1:, 1], offset[1:, 0]))
    assert_close(angle, torch.full_like(angle, 65.0), atol=1e-9)
    assert_close(offset.norm(dim=-1), sc.arc_length[0], atol=1e-9)
    heading = torch.rad2deg(torch.atan2(sc.velocity[0, :, 1], sc.velocity[0, :, 0]))
    assert_close(heading, torch.full_like(heading, 65.0), atol=1e-9)
    assert_close(sc.arc_length[0, -1], torch.tensor(2894.7, dtype=F64), atol=1e-9)


def test_circular_road_keeps_the_radius_and_turns_counter_clockwise():
    sc = _scenario("circle", num_runs=2)
    centre = torch.tensor([60.0, 60.0], dtype=F64)
    assert_close(sc.position[0, 0], torch.tensor([100.0, 30.0], dtype=F64), atol=1e-12)
    rel = sc.position[0] - centre
    assert_close(rel.norm(dim=-1), torch.full((200,), 50.0, dtype=F64), atol=1e-9)
    angle = torch.atan2(rel[:, 1], rel[:, 0])
    turned = torch.remainder(angle.diff() + math.pi, 2 * math.pi) - math.pi
    assert_close(turned, sc.arc_length[0].diff() / 50.0, atol=1e-9)  # ccw, Δφ = Δs/R
    assert float(sc.arc_length[0, -1]) < 2 * math.pi * 50.0  # one arc, no lap
    cw = ts.scenarios.circular_road_scenario(1, _gen(), clockwise=True)
    rel = cw.position[0] - centre
    assert_close(rel.norm(dim=-1), torch.full((200,), 50.0, dtype=F64), atol=1e-9)
    assert float(rel[1, 1]) < float(rel[0, 1])  # from (100, 30) clockwise: downwards


def test_circular_road_rejects_a_start_off_the_circle():
    with pytest.raises(ValueError, match="start"):
        ts.scenarios.CircularRoad((100.0, 31.0), (60.0, 60.0), 50.0)


@pytest.mark.parametrize("variant", [1, 2])
def test_curve_roads_start_at_the_paper_points(variant):
    sc = _scenario(f"curve{variant}", num_runs=1)
    start = (-400.0, 0.0) if variant == 1 else (-700.0, 260.0)
    assert_close(sc.position[0, 0], torch.tensor(start, dtype=F64), atol=1e-9)
    points = (ts.scenarios.CURVE_ROAD_I_POINTS, ts.scenarios.CURVE_ROAD_II_POINTS)[variant - 1]
    assert points[0] == start
    assert sc.arc_length[0, -1] < sc.road.length


@pytest.mark.parametrize(
    "points", [ts.scenarios.CURVE_ROAD_I_POINTS, ts.scenarios.CURVE_ROAD_II_POINTS]
)
def test_spline_road_passes_through_its_supporting_points(points):
    road = ts.scenarios.ArcLengthSpline(points)
    P = torch.tensor(points, dtype=F64)
    assert_close(road.spline(road.chord_knots), P, atol=1e-9)
    assert_close(road.position(road.arc_knots), P, atol=1e-8)
    # Natural cubic spline in chord length: scipy's as the oracle.
    oracle = CubicSpline(road.chord_knots.numpy(), P.numpy(), bc_type="natural")
    u = torch.linspace(0, float(road.chord_knots[-1]), 997, dtype=F64)
    for order in range(3):
        assert_close(road.spline(u, derivative=order), oracle(u.numpy(), order), atol=1e-8)
    # Arc length: unit speed in s, and the chord knots never exceed the arc knots.
    s = torch.linspace(0, road.length, 5001, dtype=F64)
    # The dense chords fall short of the arc by about sum(h³κ²/24) < 1e-6 relative.
    chords = road.position(s).diff(dim=0).norm(dim=-1).sum()
    assert_close(chords, torch.tensor(road.length, dtype=F64), rtol=1e-6)
    assert bool((road.arc_knots >= road.chord_knots - 1e-9).all())
    assert_close(road.direction(s).norm(dim=-1), torch.ones(5001), atol=1e-12)


@pytest.mark.parametrize(
    ("points", "length", "radius"),
    [
        (ts.scenarios.CURVE_ROAD_I_POINTS, 1107.7, 123.0),
        (ts.scenarios.CURVE_ROAD_II_POINTS, 1822.1, 110.0),
    ],
)
def test_designed_roads_have_the_documented_geometry(points, length, radius):
    """The lengths and smallest radii of curvature quoted in torchsvs.scenarios.road."""
    road = ts.scenarios.ArcLengthSpline(points)
    assert abs(road.length - length) < 0.05
    curvature = road.curvature(torch.linspace(0, road.length, 20001, dtype=F64))
    assert abs(1.0 / float(curvature.abs().max()) - radius) < 0.5


def test_speed_profile_and_scenarios_reject_bad_input():
    with pytest.raises(ValueError, match="accelerations"):
        ts.scenarios.speed_profile(1.0, [(1, 5, 1.0)], 10, 0.1)
    with pytest.raises(ValueError, match="steps"):
        ts.scenarios.speed_profile(1.0, [], 0, 0.1)
    with pytest.raises(ValueError, match="variant"):
        ts.scenarios.curve_road_scenario(3)
    with pytest.raises(ValueError, match="profile"):  # 286 m on a 100 m road
        ts.scenarios.curve_road_scenario(1, points=[(0.0, 0.0), (50.0, 10.0), (100.0, 0.0)])
    with pytest.raises(ValueError, match="profile"):  # dt 0.3 laps the circle
        ts.scenarios.circular_road_scenario(1, dt=0.3)


@pytest.mark.parametrize("name", SCENARIOS)
def test_measurement_noise_has_the_stated_std(name):
    sc = _scenario(name, num_runs=50, seed=3)
    noise = (sc.z - sc.position).reshape(-1, 2)
    n = noise.shape[0]
    std = noise.std(dim=0)
    # Sample std of n Gaussian draws: relative standard error 1/sqrt(2n); 5 of them allowed.
    assert_close(std, torch.full((2,), sc.meas_std, dtype=F64), rtol=5 / math.sqrt(2 * n), atol=0)
    assert_close(noise.mean(0), torch.zeros(2), atol=5 * sc.meas_std / math.sqrt(n))
    corr = torch.corrcoef(noise.T)[0, 1]
    assert abs(float(corr)) < 5 / math.sqrt(n)


def test_scenarios_are_reproducible_from_the_seed():
    a, b = _scenario("curve2", seed=7), _scenario("curve2", seed=7)
    c = _scenario("curve2", seed=8)
    assert torch.equal(a.z, b.z) and torch.equal(a.position, b.position)
    assert not torch.equal(a.z, c.z)
    assert torch.equal(a.position, c.position)  # the truth is the same in every run
    assert not torch.equal(a.z[0], a.z[1])
    f32 = ts.scenarios.curve_road_scenario(2, 4, _gen(7), dtype=torch.float32)
    assert f32.z.dtype == torch.float32 and f32.truth.shape == (4, 250, 4)


def test_scenario_carries_the_paper_settings():
    assert (_scenario("straight").q, _scenario("straight").eta_std) == (0.008, 1e-5)
    assert _scenario("straight").window == 16
    assert (_scenario("circle").eta_std, _scenario("circle").window) == (1e-3, 12)
    assert (_scenario("curve1").q, _scenario("curve2").eta_std) == (0.01, 0.002)
    sc = _scenario("curve1")
    assert_close(sc.mileage[..., 0], sc.arc_length)
    assert_close(sc.truth[..., [0, 2]], sc.position)


def test_spline_machinery_lives_in_one_module():
    assert road_module.ArcLengthSpline is ts.scenarios.ArcLengthSpline
    assert ts.scenarios.ArcLengthSpline.__module__ == "torchsvs.scenarios.spline"


# --- models ------------------------------------------------------------------------------------


def test_mileage_models_are_the_discrete_noise_models():
    T, q = 0.3, 0.008
    ncv = ts.models.MileageConstantVelocity(dt=T, q=q)
    assert_close(ncv.transition(), torch.tensor([[1.0, T], [0.0, 1.0]], dtype=F64))
    G = torch.tensor([T**2 / 2, T], dtype=F64)
    assert_close(ncv.process_noise(), q**2 * torch.outer(G, G), atol=1e-15)
    nca = ts.models.MileageConstantAcceleration(dt=T, q=q)
    F = torch.tensor([[1.0, T, T**2 / 2], [0.0, 1.0, T], [0.0, 0.0, 1.0]], dtype=F64)
    assert_close(nca.transition(), F)
    G = torch.tensor([T**2 / 2, T, 1.0], dtype=F64)
    assert_close(nca.process_noise(), q**2 * torch.outer(G, G), atol=1e-15)
    dt = torch.full((3, 5), 0.2, dtype=F64)
    assert nca.transition(dt).shape == (3, 5, 3, 3)
    assert_close(nca.process_noise(dt)[1, 2], nca.process_noise(torch.tensor(0.2)))
    with pytest.raises(ValueError, match="q"):
        ts.models.MileageConstantVelocity(q=0.0)
    with pytest.raises(ValueError, match="dt"):
        ts.models.MileageConstantAcceleration(dt=-1.0)


def _models():
    ncv = ts.models.MileageConstantVelocity(dt=0.2, q=0.01)
    nca = ts.models.MileageConstantAcceleration(dt=0.2, q=0.01)
    return {
        "ncv": ts.models.SeparateModel(ncv, eta_std=0.002, r=0.64).double(),
        "ncv-embedded": ts.models.SeparateModel(
            ncv, eta_std=0.002, r=0.64, embed_acceleration=True
        ).double(),
        "nca": ts.models.SeparateModel(nca, eta_std=0.002, r=0.64).double(),
    }


@pytest.mark.parametrize("kind", ["ncv", "ncv-embedded", "nca"])
def test_augmented_jacobians_equal_autograd(kind):
    model = _models()[kind]
    x = torch.randn(6, model.state_dim, generator=_gen(1), dtype=F64) * 10
    auto_h = vmap(jacrev(lambda s: model.h(s.unsqueeze(0)).squeeze(0)))(x)
    assert_close(model.h_jacobian(x), auto_h, atol=1e-12)
    dt = torch.rand(6, generator=_gen(2), dtype=F64) + 0.1
    auto_f = vmap(jacrev(lambda s, d: model.f(s.unsqueeze(0), d).squeeze(0)))(x, dt)
    assert_close(model.f_jacobian(x, dt), auto_f, atol=1e-12)
    assert model.h_jacobian(x).shape == (6, 2, model.state_dim)


def test_augmented_model_layout_and_noise():
    models = _models()
    assert [m.state_dim for m in models.values()] == [7, 8, 8]
    emb, nca = models["ncv-embedded"], models["nca"]
    assert emb.eta_index == nca.eta_index == [3, 4, 5, 6, 7]
    F, Q = emb.transition(), emb.process_noise()
    assert float(F[2].abs().sum()) == 0.0 and float(F[:, 2].abs().sum()) == 0.0
    assert float(Q[2].abs().sum()) == 0.0
    assert_close(Q[3:, 3:], 0.002**2 * torch.eye(5))
    assert_close(F[3:, 3:], torch.eye(5))
    assert_close(nca.transition()[:3, :3], nca.base.transition())
    # h is Eq. (13): the line through (x_l, y_l) at s_l along (r_x, r_y).
    x = torch.tensor([[30.0, 5.0, 0.5, 1.0, 0.6, 2.0, 0.8, 10.0]], dtype=F64)
    assert_close(nca.h(x), torch.tensor([[1.0 + 0.6 * 20.0, 2.0 + 0.8 * 20.0]], dtype=F64))
    assert_close(nca.cartesian(x), torch.tensor([[13.0, 3.0, 18.0, 4.0]], dtype=F64))
    with pytest.raises(ValueError, match="eta_std"):
        ts.models.SeparateModel(nca.base, eta_std=0.0)
    with pytest.raises(ValueError, match="r"):
        ts.models.SeparateModel(nca.base, r=[1.0, 2.0, 3.0])
    with pytest.raises(TypeError, match="base"):
        ts.models.SeparateModel(ts.models.ConstantVelocity())  # type: ignore[arg-type]


def _straight_road_tracks(B: int, T: int, speed: float, dt: float, sigma: float, seed: int):
    heading = math.radians(65.0)
    unit = torch.tensor([math.cos(heading), math.sin(heading)], dtype=F64)
    s = speed * dt * torch.arange(T, dtype=F64)
    truth = torch.tensor([200.0, 300.0], dtype=F64) + s[:, None] * unit
    z = truth + sigma * torch.randn(B, T, 2, generator=_gen(seed), dtype=F64)
    return truth, z


def test_ekf_on_the_ncv_augmented_model_recovers_the_road_direction():
    """An EKF on the NCV augmented model, initialised by the unscented transform, finds the
    straight road's direction and tracks the position far below the measurement noise."""
    dt, sigma = 0.3, 2.0
    truth, z = _straight_road_tracks(B=16, T=150, speed=10.0, dt=dt, sigma=sigma, seed=0)
    base = ts.models.MileageConstantVelocity(dt=dt, q=0.008)
    model = ts.models.SeparateModel(base, eta_std=1e-5, r=sigma**2).double()
    prior = unscented_initialisation(model, z, floor=1e-6)
    out = ts.ExtendedKalmanFilter(model)(z[:, 3:], prior.mean, prior.cov)
    r_x, r_y = model.eta_index[1], model.eta_index[3]
    direction = out.mean[:, -1][:, [r_x, r_y]]
    angle = torch.rad2deg(torch.atan2(direction[:, 1], direction[:, 0]))
    assert float((angle - 65.0).abs().max()) < 1.0
    error = (model.h(out.mean) - truth[3:]).norm(dim=-1)
    assert float(error[:, -50:].pow(2).mean().sqrt()) < 0.5 * sigma
    # The NCV embedded in the NCA layout is the same filter on the shared components.
    emb = ts.models.SeparateModel(base, eta_std=1e-5, r=sigma**2, embed_acceleration=True)
    prior_e = unscented_initialisation(emb.double(), z, floor=1e-6)
    out_e = ts.ExtendedKalmanFilter(emb)(z[:, 3:], prior_e.mean, prior_e.cov)
    keep = [0, 1, 3, 4, 5, 6, 7]
    assert_close(out_e.mean[..., keep], out.mean, atol=1e-8, rtol=1e-8)
    assert_close(out_e.mean[..., 2], torch.zeros_like(out_e.mean[..., 2]))


# --- unscented initialisation ------------------------------------------------------------------


@pytest.mark.parametrize("kind", ["ncv", "ncv-embedded", "nca"])
@pytest.mark.parametrize("kappa", [0.0, -3.0, 2.0])
def test_unscented_initialisation_equals_the_numpy_reference(kind, kappa):
    model = _models()[kind]
    B = 3
    z = torch.randn(B, 5, 2, generator=_gen(4), dtype=F64) * 3.0
    z[:, :, 0] += torch.arange(5, dtype=F64) * 4.0
    dt = torch.rand(B, 5, generator=_gen(5), dtype=F64) * 0.2 + 0.1
    R = torch.tensor([[0.7, 0.2], [0.2, 0.5]], dtype=F64)
    R_b = R.expand(B, 2, 2) * torch.tensor([1.0, 2.0, 0.5], dtype=F64)[:, None, None]
    accel = {"ncv": "none", "ncv-embedded": "zero", "nca": "difference"}[kind]
    for R_arg in (R, R_b):
        prior = unscented_initialisation(model, z, dt=dt, R=R_arg, kappa=kappa)
        for b in range(B):
            R_np = (R_arg if R_arg.ndim == 2 else R_arg[b]).numpy()
            T2, T3 = float(dt[b, 1]), float(dt[b, 2])
            mean, cov = road_numpy.unscented_prior(z[b].numpy(), R_np, T2, T3, accel, kappa)
            assert_close(prior.mean[b], mean, atol=1e-10)
            assert_close(prior.cov[b], cov, atol=1e-10)
            state = road_numpy.three_point(z[b, :3].reshape(6).numpy(), T2, T3, accel)
            assert_close(three_point_state(model, z, dt)[b], state, atol=1e-12)


@pytest.mark.parametrize("kind", ["ncv-embedded", "nca"])
def test_unscented_initialisation_agrees_with_monte_carlo(kind):
    """Where the steps are long against the noise (curve road II: 3.3 m a step, 0.8 m noise),
    the unscented moments match a Monte Carlo estimate of the same map."""
    model = _models()[kind]
    heading = torch.tensor([math.cos(0.5), math.sin(0.5)], dtype=F64)
    z = torch.tensor([0.0, 3.3, 6.8], dtype=F64)[:, None] * heading
    prior = unscented_initialisation(model, z)
    n = 200_000
    Z = z.reshape(1, 6) + 0.8 * torch.randn(n, 6, generator=_gen(6), dtype=F64)
    image = _three_point(Z, torch.full((n, 2), 0.2, dtype=F64), model)
    mc_mean, mc_cov = image.mean(0), torch.cov(image.T)
    active = mc_cov.diagonal() > 0  # s_l = 0 exactly, and so is the embedded acceleration
    assert bool((prior.cov.diagonal()[~active] == 0).all())
    sd = mc_cov.diagonal()[active].sqrt()
    assert_close((prior.mean - mc_mean)[active] / sd, torch.zeros_like(sd), atol=0.05)
    scaled = (prior.cov - mc_cov)[active][:, active] / torch.outer(sd, sd)
    assert_close(scaled, torch.zeros_like(scaled), atol=0.15)


def test_unscented_initialisation_shapes_and_floor():
    model = _models()["ncv-embedded"]
    z = torch.randn(7, 2, generator=_gen(8), dtype=F64) + torch.arange(7, dtype=F64)[:, None]
    prior = unscented_initialisation(model, z)
    assert prior.mean.shape == (8,) and prior.cov.shape == (8, 8)
    assert float(prior.mean[2]) == 0.0 and float(prior.cov[2].abs().sum()) == 0.0
    assert float(prior.mean[-1]) == 0.0 and float(prior.cov[-1].abs().sum()) < 1e-20
    assert int(torch.linalg.cholesky_ex(prior.cov).info) != 0  # singular without a floor
    floored = unscented_initialisation(model, z, floor=1e-6)
    assert int(torch.linalg.cholesky_ex(floored.cov).info) == 0
    assert_close(floored.cov - prior.cov, 1e-6 * torch.eye(8, dtype=F64), atol=1e-15)
    with pytest.raises(ValueError, match="z"):
        unscented_initialisation(model, z[:2])
    bad = z.clone()
    bad[1, 0] = float("nan")
    with pytest.raises(ValueError, match="z"):
        unscented_initialisation(model, bad)
    with pytest.raises(ValueError, match="kappa"):
        unscented_initialisation(model, z, kappa=-6.0)
    with pytest.raises(ValueError, match="dt"):
        unscented_initialisation(model, z.expand(2, 7, 2), dt=torch.ones(3))
    with pytest.raises(ValueError, match="R"):
        unscented_initialisation(model, z, R=torch.eye(3, dtype=F64))


# --- least-squares reset -----------------------------------------------------------------------


def test_reset_recovers_the_exact_line_from_noise_free_points():
    sc = _scenario("straight", num_runs=1)
    unit = torch.tensor([math.cos(math.radians(65)), math.sin(math.radians(65))], dtype=F64)
    for start in (0, 40, 120, 184):
        window = slice(start, start + 15)  # the latest 16 except the newest
        pos, s = sc.position[:, window], sc.arc_length[:, window]
        for normalize in (True, False):
            eta = reset_trajectory_parameters(pos, s, normalize=normalize)[0]
            assert_close(eta[[0, 2]], pos[0, 0], atol=1e-8)
            assert_close(eta[[1, 3]], unit, atol=1e-10)
            assert_close(eta[4], s[0, 0])
        # Arc lengths counted backwards: the opposite unit direction.
        eta = reset_trajectory_parameters(pos, -s)[0]
        assert_close(eta[[1, 3]], -unit, atol=1e-10)


def test_reset_equals_numpy_lstsq_on_noisy_data():
    B, W = 6, 11
    g = _gen(9)
    s = torch.cumsum(torch.rand(B, W, generator=g, dtype=F64) * 5 + 0.5, dim=1) + 100.0
    pos = torch.stack([3.0 + 0.6 * s, -2.0 + 0.8 * s], dim=-1)
    pos = pos + torch.randn(B, W, 2, generator=g, dtype=F64) * 2.0
    s_hat = s + torch.randn(B, W, generator=g, dtype=F64)
    mask = torch.ones(B, W, dtype=torch.bool)
    mask[1, :4] = False  # a window still filling at the start of a track
    mask[2, : W - 2] = False  # two samples only
    pos[3, 5] = float("nan")  # a missing measurement
    raw = reset_trajectory_parameters(pos, s_hat, mask=mask, normalize=False)
    unit = reset_trajectory_parameters(pos, s_hat, mask=mask)
    for b in range(B):
        ok = (mask[b] & torch.isfinite(pos[b]).all(-1)).numpy()
        sj = s_hat[b].numpy()[ok]
        V = np.stack([np.ones_like(sj), sj - sj[0]], axis=1)
        coef, *_ = np.linalg.lstsq(V, pos[b].numpy()[ok], rcond=None)
        expected = np.array([coef[0, 0], coef[1, 0], coef[0, 1], coef[1, 1], sj[0]])
        assert_close(raw[b], expected, atol=1e-9)
        direction = coef[1] / np.linalg.norm(coef[1])
        assert_close(unit[b, [1, 3]], direction, atol=1e-12)
        assert_close(unit[b, [0, 2, 4]], expected[[0, 2, 4]], atol=1e-9)
    one = reset_trajectory_parameters(pos[0], s_hat[0])
    assert_close(one, unit[0], atol=1e-12)


def test_reset_gives_nan_for_unsolvable_windows_and_finite_gradients():
    W = 6
    pos = torch.randn(3, W, 2, generator=_gen(10), dtype=F64).requires_grad_()
    s = torch.arange(W, dtype=F64).expand(3, W).clone()
    s[1] = 4.0  # a standing target: no spread of arc lengths
    mask = torch.ones(3, W, dtype=torch.bool)
    mask[2, 1:] = False  # one sample
    eta = reset_trajectory_parameters(pos, s, mask=mask)
    assert bool(torch.isfinite(eta[0]).all()) and bool(torch.isnan(eta[1:]).all())
    eta[0].sum().backward()
    assert pos.grad is not None and bool(torch.isfinite(pos.grad).all())
    with pytest.raises(ValueError, match="arc_length"):
        reset_trajectory_parameters(pos, s[:, :3])
    with pytest.raises(ValueError, match="mask"):
        reset_trajectory_parameters(pos, s, mask=mask.float())


def test_building_blocks_are_differentiable():
    g = _gen(11)
    pos = (
        torch.randn(2, 5, 2, generator=g, dtype=F64) + torch.arange(5.0)[:, None]
    ).requires_grad_()
    s = torch.arange(5, dtype=F64) * 1.3 + torch.rand(2, 5, generator=g, dtype=F64) * 0.1
    s = s.requires_grad_()
    assert torch.autograd.gradcheck(lambda p, a: reset_trajectory_parameters(p, a), (pos, s))
    z = torch.randn(2, 6, 2, generator=g, dtype=F64).requires_grad_()
    assert torch.autograd.gradcheck(lambda x: online_fit(x, 3, 0.5)[:, 1:], (z,))
    model = _models()["nca"]
    z3 = torch.randn(2, 3, 2, generator=g, dtype=F64) + torch.arange(3.0)[:, None] * 4
    assert torch.autograd.gradcheck(
        lambda x: tuple(unscented_initialisation(model, x)), (z3.requires_grad_(),)
    )


# --- online fitting ----------------------------------------------------------------------------


def test_sliding_windows_hold_the_latest_samples():
    x = torch.arange(12, dtype=F64).reshape(2, 6, 1)
    windows, valid = sliding_windows(x, 3)
    assert windows.shape == (2, 6, 3, 1) and valid.shape == (2, 6, 3)
    assert windows[1, 4, :, 0].tolist() == [8.0, 9.0, 10.0]
    assert valid[0, 1].tolist() == [False, True, True]
    assert windows[0, 0, :, 0].tolist() == [0.0, 0.0, 0.0]


@pytest.mark.parametrize("per_step_dt", [False, True])
def test_online_fit_equals_polyfit_over_each_window(per_step_dt):
    B, T, window = 3, 30, 8
    g = _gen(12)
    t = torch.arange(T, dtype=F64) * 0.2
    z = torch.stack([5.0 * t + t**2, -3.0 * t], dim=-1) + torch.randn(B, T, 2, generator=g)
    z[1, 10, 0] = float("nan")  # one missing component
    if per_step_dt:
        dt = torch.rand(B, T, generator=g, dtype=F64) * 0.3 + 0.05
        times = torch.cat([torch.zeros(B, 1, dtype=F64), dt[:, 1:].cumsum(1)], dim=1)
    else:
        dt, times = 0.2, t.expand(B, T)
    out = online_fit(z, window, dt)
    assert out.shape == (B, T, 4)
    assert bool(torch.isnan(out[:, 0]).all())  # one sample: nothing to fit
    for b in range(B):
        for k in range(1, T):
            lo = max(0, k - window + 1)
            for axis in range(2):
                tj, yj = times[b, lo : k + 1].numpy(), z[b, lo : k + 1, axis].numpy()
                ok = np.isfinite(yj)
                slope, intercept = np.polyfit(tj[ok], yj[ok], 1)
                at_k = slope * float(times[b, k]) + intercept
                assert_close(out[b, k, 2 * axis], np.array(at_k), atol=1e-8)
                assert_close(out[b, k, 2 * axis + 1], np.array(slope), atol=1e-8)
    single = online_fit(z[0], window, dt if not per_step_dt else dt[0])
    assert_close(single[1:], out[0, 1:], atol=1e-12)


def test_online_fit_rejects_bad_input():
    z = torch.zeros(2, 5, 2, dtype=F64)
    with pytest.raises(ValueError, match="window"):
        online_fit(z, 1)
    with pytest.raises(ValueError, match="dt"):
        online_fit(z, 3, torch.ones(2, 4, dtype=F64))
    with pytest.raises(ValueError, match="dt"):
        online_fit(z, 3, -1.0)
    with pytest.raises(TypeError, match="z"):
        online_fit(z.long(), 3)
