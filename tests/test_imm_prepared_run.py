"""The IMM's steps on each mode's run prepared once (``IMM._prepared_runs``, taken where an
interval or input is given) give the numbers of the mode-by-mode one-step ``step`` calls, to the
last bit: every field of the filter pass, its final state, and the smoother over it."""

from __future__ import annotations

import math
from typing import Any

import pytest
import torch

import torchsvs as ts
from torchsvs.filters.imm import IMM
from torchsvs.scenarios import Segment, simulate_segments

F64 = torch.float64
DEG = math.pi / 180


def _leaves(value: Any, path: str = "") -> dict[str, Any]:
    """Every tensor (and ``None``) of nested results and states, by its path."""
    if isinstance(value, torch.Tensor) or value is None:
        return {path: value}
    if isinstance(value, tuple):
        names = getattr(value, "_fields", None) or range(len(value))
        out: dict[str, Any] = {}
        for name, item in zip(names, value, strict=True):
            out.update(_leaves(item, f"{path}.{name}"))
        return out
    return {path: value}  # ints, bools: compared as they are


def _assert_identical(fast: Any, general: Any) -> None:
    a, b = _leaves(fast), _leaves(general)
    assert a.keys() == b.keys()
    for key in a:
        x, y = a[key], b[key]
        if isinstance(x, torch.Tensor):
            assert isinstance(y, torch.Tensor), key
            assert x.shape == y.shape and x.dtype == y.dtype, key
            assert torch.equal(x.nan_to_num(7.0), y.nan_to_num(7.0)), key  # (NaN where both)
            assert torch.equal(x.isnan(), y.isnan()), key
        else:
            assert x == y, key


def _turning_tracks(batch: int = 4) -> tuple[torch.Tensor, torch.Tensor]:
    """Turning tracks at irregular intervals, with a missing row, a missing component and a
    padded end (NaN), as ``track`` batches them: ``z [B, T, 2]``, ``dt [B, T]``."""
    segments = [Segment(12.0), Segment(10.0, turn_rate=3 * DEG), Segment(12.0)]
    truth = simulate_segments(torch.tensor([0.0, 100.0, 0.0, 0.0], dtype=F64), segments, 1.0)
    gen = torch.Generator().manual_seed(3)
    z = truth[..., [0, 2]].expand(batch, -1, -1) + 10.0 * torch.randn(
        batch, truth.shape[-2], 2, generator=gen, dtype=F64
    )
    dt = 0.5 + 2.0 * torch.rand(batch, truth.shape[-2], generator=gen, dtype=F64)
    z[0, 5] = float("nan")
    z[1, 9, 1] = float("nan")
    z[2, -8:] = float("nan")
    return z, dt


def _general_steps(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(IMM, "_prepared_runs", lambda self, inputs: None)


@pytest.mark.parametrize("keep", ["all", "mean"])
def test_turn_imm_and_its_smoother_on_prepared_runs_equal_the_one_step_runs(monkeypatch, keep):
    """The KF (CV) and EKF (CT) modes of ``track --estimator imm`` at irregular intervals."""
    z, dt = _turning_tracks()
    model = ts.models.ConstantVelocity(ndim=2, dt=1.0, q=2.0, r=100.0).double()
    turn = ts.TurnIMM(model, turn_rate_q=1e-5, turn_rate_std=0.02)
    smoother = ts.TurnIMMSmoother(turn, lag=3)
    x0 = torch.tensor([0.0, 90.0, 0.0, 5.0], dtype=F64).expand(4, -1)
    P0 = torch.diag(torch.tensor([100.0, 100.0, 100.0, 100.0], dtype=F64))
    inputs = ts.estimator.prepare_inputs(turn.model, z, x0, P0, dt=dt, keep=keep)
    common = turn.common_inputs(inputs)
    assert turn.imm._prepared_runs(common) is not None  # (the path under test runs)
    with torch.no_grad():
        fast = (turn(z, x0, P0, dt=dt, keep=keep), smoother(z, x0, P0, dt=dt, keep=keep))
        start = turn.imm.init(common.x0, common.P0[0])
        fast_scan = turn.imm.scan(start, common.z, dt=dt)
        _general_steps(monkeypatch)
        general = (turn(z, x0, P0, dt=dt, keep=keep), smoother(z, x0, P0, dt=dt, keep=keep))
        general_scan = turn.imm.scan(start, common.z, dt=dt)
    _assert_identical(fast, general)
    _assert_identical(fast_scan, general_scan)  # the state after the run too


def test_kalman_modes_whose_fast_path_runs_on_prepared_runs_equal_the_one_step_runs(monkeypatch):
    """CV and CA Kalman modes that never couple the axes (each mode's per-axis fast path can
    take its steps) at a given scalar interval."""
    z, _ = _turning_tracks()
    models = [
        ts.models.ConstantVelocity(q=0.05, r=100.0).double(),
        ts.models.ConstantAcceleration(q=0.5, r=100.0).double(),
    ]
    imm = ts.IMM(
        [ts.KalmanFilter(m) for m in models],
        transition=[[0.9, 0.1], [0.2, 0.8]],
        embedding=[[0, 1, 3, 4], [0, 1, 2, 3, 4, 5]],
    )
    x0 = torch.tensor([0.0, 90.0, 0.0, 0.0, 5.0, 0.0], dtype=F64)
    P0 = torch.diag(torch.tensor([100.0, 100.0, 1.0, 100.0, 100.0, 1.0], dtype=F64))
    dt = torch.tensor(1.0, dtype=F64)
    with torch.no_grad():
        fast = ts.IMMSmoother(imm, lag=4)(z, x0, P0, dt=dt)
        _general_steps(monkeypatch)
        general = ts.IMMSmoother(imm, lag=4)(z, x0, P0, dt=dt)
    _assert_identical(fast, general)


def test_prepared_runs_keep_the_modes_input_checks():
    """A mode whose model takes no interval refuses one, as its own step does."""
    cv = ts.models.ConstantVelocity(q=0.05, r=100.0).double()
    fixed = ts.models.LinearGaussian(
        cv.transition(), cv.meas_matrix(), cv.process_noise(), cv.R()
    ).double()
    imm = ts.IMM([ts.KalmanFilter(cv), ts.KalmanFilter(fixed)], [[0.9, 0.1], [0.1, 0.9]])
    z, _ = _turning_tracks()
    x0 = torch.zeros(4, dtype=F64)
    P0 = 100.0 * torch.eye(4, dtype=F64)
    with pytest.raises(ValueError, match="^dt: LinearGaussian has fixed matrices"):
        imm(z, x0, P0, dt=torch.ones(z.shape[:2], dtype=F64))


def test_gradients_through_prepared_runs_match_the_one_step_runs(monkeypatch):
    """With a learnable ``q``: the same log-likelihood; its gradient is summed over the steps
    in another order (the run's process noise formed once), so it agrees to rounding."""
    z, dt = _turning_tracks()
    model = ts.models.ConstantVelocity(ndim=2, dt=1.0, q=2.0, r=100.0, learn_q=True).double()
    turn = ts.TurnIMM(model, turn_rate_q=1e-5, turn_rate_std=0.02)
    x0 = torch.tensor([0.0, 90.0, 0.0, 5.0], dtype=F64).expand(4, -1)
    P0 = torch.diag(torch.tensor([100.0, 100.0, 100.0, 100.0], dtype=F64))

    def loglik_and_grads() -> tuple[torch.Tensor, list[torch.Tensor]]:
        turn.zero_grad()
        total = turn(z, x0, P0, dt=dt).log_likelihood.sum()
        total.backward()
        return total.detach(), [p.grad.clone() for p in turn.parameters() if p.grad is not None]

    fast, fast_grads = loglik_and_grads()
    _general_steps(monkeypatch)
    general, general_grads = loglik_and_grads()
    assert torch.equal(fast, general)
    assert len(fast_grads) == len(general_grads) > 0
    for a, b in zip(fast_grads, general_grads, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=0.0)
