"""Example 4 of Bermúdez Ordoñez et al. 2020 (DME-DME navigation): the slant-range model, the
scenario, and the experiment's report (``experiments/ksvd_paper.py``)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import torchsvs as ts
from tests.conftest import assert_close
from torchsvs.models.base import StateSpaceModel
from torchsvs.scenarios import dme

F64 = torch.float64


def _states(B=16, seed=0):
    g = torch.Generator().manual_seed(seed)
    x = torch.randn(B, 4, generator=g, dtype=F64) * torch.tensor([3e4, 100.0, 3e4, 100.0])
    return x


@pytest.mark.parametrize("height", [0.0, 9000.0])
def test_ranges_and_jacobian_equal_the_formula_and_autograd(height):
    stations = [[-20e3, 0.0], [20e3, 0.0], [5e3, -7e3]]
    model = ts.models.SlantRanges(stations, r=[1.0, 4.0, 9.0], height=height).double()
    x = _states()
    s = np.array(stations)
    xn = x.numpy()
    expected = np.sqrt(
        (xn[:, 0:1] - s[:, 0]) ** 2 + (xn[:, 2:3] - s[:, 1]) ** 2 + height**2
    )  # Eqs. (47)-(48)
    assert_close(model.h(x), expected, atol=1e-8, rtol=1e-12)
    autograd = StateSpaceModel.h_jacobian(model, x)  # the base class's jacrev of h
    assert_close(model.h_jacobian(x), autograd, atol=1e-15, rtol=1e-12)
    # Direction cosines: a unit row of sin θ, cos θ where the aircraft is in the stations' plane.
    if height == 0.0:
        J = model.h_jacobian(x)
        assert_close(J[..., 0].square() + J[..., 2].square(), torch.ones(16, 3), atol=1e-12)
    assert_close(model.meas_cov(), torch.diag(torch.tensor([1.0, 4.0, 9.0])), atol=1e-12)


def test_motion_is_the_constant_velocity_model():
    model = ts.models.SlantRanges([[0.0, 0.0]], dt=2.0, q=0.3).double()
    cv = ts.models.ConstantVelocity(ndim=2, dt=2.0, q=0.3).double()
    x = _states()
    assert_close(model.f(x), cv.f(x), atol=0, rtol=0)
    assert_close(model.f_jacobian(x), cv.f_jacobian(x), atol=0, rtol=0)
    assert_close(model.process_noise(), cv.process_noise(), atol=0, rtol=0)
    dt = torch.full((16,), 0.5, dtype=F64)
    assert_close(model.f(x, dt), cv.f(x, dt), atol=0, rtol=0)


def test_the_svsf_takes_no_finite_difference_velocity_of_ranges():
    model = ts.models.SlantRanges([[-1.0, 0.0], [1.0, 0.0]])
    assert ts.SVSF(model, psi=10.0).artificial is None


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"stations": [1.0, 2.0]}, "stations"),
        ({"stations": [[1.0, 2.0, 3.0]]}, "stations"),
        ({"stations": [[math.nan, 0.0]]}, "stations"),
        ({"stations": [[0.0, 0.0]], "height": -1.0}, "height"),
        ({"stations": [[0.0, 0.0]], "r": [1.0, 2.0]}, "r"),
    ],
)
def test_bad_model_arguments_name_themselves(kwargs, name):
    with pytest.raises(ValueError, match=f"^{name}:"):
        ts.models.SlantRanges(**kwargs)


# --- the scenario --------------------------------------------------------------------------------


def _scenario(seed=0, runs=3, **kwargs):
    return ts.scenarios.dme_scenario(runs, torch.Generator().manual_seed(seed), **kwargs)


def test_scenario_is_reproducible_from_the_seed():
    a, b, c = _scenario(), _scenario(), _scenario(seed=1)
    assert torch.equal(a.truth, b.truth) and torch.equal(a.z, b.z)
    assert not torch.equal(a.truth, c.truth) and not torch.equal(a.z, c.z)
    assert a.truth.shape == (3, 1500, 4) and a.z.shape == (3, 1500, 2)
    assert a.dt == 2.0 and a.range_std.shape == (1500, 2)


def test_the_flight_goes_straight_across_the_baseline_then_turns_270_degrees():
    sc = _scenario(runs=4)
    v = sc.truth[..., [1, 3]]
    speed = v.norm(dim=-1)
    assert_close(speed, torch.full_like(speed, 583 / 3.6), atol=0.5, rtol=0)
    heading = torch.atan2(v[..., 1], v[..., 0])
    turn = round(sc.turn_start / sc.dt)  # the first step of the turn
    assert sc.turn_start == 2418.0
    straight = heading[:, : turn - 1]
    assert float((straight - straight[:, :1]).abs().max()) < 5e-3  # σ_a = 0.001 m/s²
    turned = torch.diff(heading[:, turn - 1 :], dim=1)
    turned = (turned + math.pi) % (2 * math.pi) - math.pi  # unwrap
    assert_close(turned.sum(1), torch.full((4,), 1.5 * math.pi), atol=1e-3, rtol=0)
    # Radius of the turn: speed / turn rate.
    rate = turned.mean(1) / sc.dt
    assert_close(speed[:, -1] / rate, torch.full((4,), 20e3), atol=30.0, rtol=0)
    # The path crosses y = 0 between the stations, about |start| / v after the start.
    y = sc.truth[..., 2]
    crossing = (y[:, :-1] > 0) & (y[:, 1:] <= 0)
    assert bool((crossing.sum(1) == 1).all())
    step = crossing.float().argmax(1)
    x_at = sc.truth[torch.arange(4), step, 0]
    assert bool((x_at.abs() < 20e3).all())
    t_at = (step + 1).double() * sc.dt
    assert_close(t_at, torch.full((4,), 218.4e3 / (583 / 3.6)), atol=80.0, rtol=0)


def test_range_noise_has_the_stated_std_per_step_and_station():
    std = torch.full((1500, 2), 100.0, dtype=F64)
    std[700:, 1] = 400.0
    sc = _scenario(runs=40, range_std=std)
    noise = sc.z - sc.model.h(sc.truth)
    assert noise[:, :700].std().item() == pytest.approx(100.0, rel=0.02)
    assert noise[:, 700:, 1].std().item() == pytest.approx(400.0, rel=0.02)
    assert noise[:, 700:, 0].std().item() == pytest.approx(100.0, rel=0.02)
    assert_close(sc.model.meas_cov(), torch.eye(2) * 1e4, atol=1e-8)  # the first step's


def test_scenario_rejects_bad_arguments():
    with pytest.raises(ValueError, match="^range_std:"):
        _scenario(range_std=[1.0, 2.0, 3.0])
    with pytest.raises(ValueError, match="^range_std:"):
        _scenario(range_std=-1.0)
    with pytest.raises(ValueError, match="^num_runs:"):
        ts.scenarios.dme_scenario(0)
    with pytest.raises(ValueError, match="^turn_direction:"):
        _scenario(turn_direction=0)


def test_an_ekf_navigates_the_flight():
    sc = _scenario(runs=4)
    with torch.no_grad():
        out = ts.ExtendedKalmanFilter(sc.model)(sc.z, sc.x0, sc.P0)
    error = (out.mean[..., [0, 2]] - sc.truth[..., [0, 2]]).norm(dim=-1)
    # 100 m ranges: about 130 m on the straight leg once converged (the stations far and close
    # together as seen from the aircraft), more in the turn, where the CV model lags.
    assert float(error[:, 50:1209].square().mean().sqrt()) < 200.0
    assert float(error[:, 1209:].square().mean().sqrt()) < 1500.0
    assert math.isclose(dme.SPEED, 161.94, rel_tol=1e-4)


# --- the experiment ------------------------------------------------------------------------------


def test_the_experiment_finds_the_forms_the_filter_accepts():
    from experiments.ksvd_paper import FORMS, form_builder

    model = ts.models.SlantRanges([[0.0, 0.0]])
    forms, build = form_builder(ts.ExtendedKalmanFilter, model)
    assert "joseph" in forms and set(forms) <= set(FORMS)
    assert isinstance(build(forms[0]), ts.ExtendedKalmanFilter)


def test_quick_run_writes_its_report(tmp_path):
    # About 10 s with the Joseph form alone (more with every covariance form the filter gains).
    from experiments import ksvd_paper

    ksvd_paper.main(["--quick", "--out", str(tmp_path)])
    text = (tmp_path / "ksvd_paper.md").read_text()
    assert "## Example 1" in text and "## Example 4" in text and "Yuma" in text
    assert "| joseph |" in text and "| degraded | float64 | adaptive R | joseph |" in text
    for name in (
        "ksvd_example1_digits.png",
        "ksvd_dme_trajectory.png",
        "ksvd_dme_errors.png",
        "ksvd_adaptive_step.png",
    ):
        assert (tmp_path / name).stat().st_size > 1000
