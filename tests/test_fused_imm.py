"""The compiled IMM(CV, CT) and Kim's smoother (``kernels/cpp/imm.h``,
:mod:`torchsvs.kernels.fused_imm`) against their home, the tensor path (TurnIMM, IMM,
IMMSmoother), and where each path is taken."""

from __future__ import annotations

import math

import pytest
import torch

from torchsvs.filters.turn_imm import TurnIMM
from torchsvs.kernels import eager_loops, fused_imm
from torchsvs.models.motion import ConstantVelocity
from torchsvs.smoothers.imm import TurnIMMSmoother

pytestmark = pytest.mark.skipif(
    fused_imm.build.library() is None, reason="no C++ compiler: the compiled loops are off"
)


def turning_tracks(B: int, T: int, D: int, irregular: bool, missing: bool, seed: int = 0):
    """Tracks that fly straight, then turn at their own rates (either way), with noise of 30 m;
    ``dt`` per step at irregular 1-10 s times, else ``None`` (the model's 5 s)."""
    g = torch.Generator().manual_seed(seed)
    f64 = torch.float64
    dt = torch.rand(B, T, generator=g, dtype=f64) * 9 + 1 if irregular else None
    t = dt.cumsum(1) if dt is not None else torch.arange(1, T + 1, dtype=f64).expand(B, T) * 5.0
    rate = (torch.rand(B, 1, generator=g, dtype=f64) - 0.5) * 0.06
    start = t[:, T // 3 : T // 3 + 1]
    angle = torch.where(t > start, rate * (t - start), torch.zeros_like(t))
    speed = 100 + 50 * torch.rand(B, 1, generator=g, dtype=f64)
    vx, vy = speed * torch.cos(angle), speed * torch.sin(angle)
    steps = torch.diff(t, dim=1, prepend=torch.zeros(B, 1, dtype=f64))
    pos = [(vx * steps).cumsum(1), (vy * steps).cumsum(1)]
    if D == 3:
        pos.append(t * 3.0)
    z = torch.stack(pos, -1) + 30 * torch.randn(B, T, D, generator=g, dtype=f64)
    if missing:
        z[torch.rand(B, T, D, generator=g) < 0.1] = float("nan")
        z[:, 3] = float("nan")  # a step without any measurement
    x0 = torch.zeros(B, 2 * D, dtype=f64)
    x0[:, 1] = 120.0
    P0 = torch.diag(torch.tensor([1e4, 1e4] * D, dtype=f64))
    return z, dt, x0, P0


def turn_imm(D: int, **kwargs) -> TurnIMM:
    cv = ConstantVelocity(ndim=D, dt=5.0, q=0.5, r=[900.0] * D).double()
    return TurnIMM(cv, turn_rate_q=1e-6, turn_rate_std=0.01, turn_q=2.0, **kwargs)


def close(a: torch.Tensor | None, b: torch.Tensor | None, what: str, tol: float = 1e-9) -> None:
    """``a`` equals ``b`` to ``tol``: relative for vectors, and for covariances relative to
    ``sqrt(P_ii P_jj)`` (cross terms near zero have no relative precision of their own)."""
    assert (a is None) == (b is None), what
    if a is None or b is None:
        return
    assert a.shape == b.shape, what
    if a.ndim >= 2 and a.shape[-1] == a.shape[-2] and a.shape[-1] > 2:
        d = b.diagonal(dim1=-2, dim2=-1).clamp_min(1e-300).sqrt()
        err = ((a - b).abs() / (d[..., :, None] * d[..., None, :])).max()
    else:
        err = ((a - b).abs() / b.abs().clamp_min(1e-6)).max()
    assert float(err) < tol, f"{what}: {float(err):.2e}"


def both(est, z, x0, P0, **kwargs):
    """The compiled pass and the tensor path's, on the same inputs."""
    with torch.no_grad():
        compiled = est(z, x0, P0, **kwargs)
        with eager_loops():
            tensors = est(z, x0, P0, **kwargs)
    return compiled, tensors


@pytest.mark.parametrize("D", [2, 3])
@pytest.mark.parametrize("irregular", [False, True])
@pytest.mark.parametrize("lag", [0, 1, 5, None, 400])
@pytest.mark.parametrize("keep", ["mean", "moments"])
def test_compiled_imm_equals_the_tensor_path(D, irregular, lag, keep):
    # 11 tracks: full blocks of lanes and a short last block (11 fills no vector width: 2, 4
    # or 8 float64), its last lane repeated;
    # missing components and a step without measurement; lag 400 beyond the track's end is
    # the fixed interval
    z, dt, x0, P0 = turning_tracks(11, 40, D, irregular, missing=True)
    turn = turn_imm(D)
    est = turn if lag == 0 else TurnIMMSmoother(turn, lag)
    compiled, tensors = both(est, z, x0, P0, dt=dt, keep=keep)
    close(compiled.mean, tensors.mean, "mean")
    close(compiled.cov, tensors.cov, "cov")
    close(compiled.mode_probs, tensors.mode_probs, "mode_probs")
    filtered = (compiled, tensors) if lag == 0 else (compiled.filtered, tensors.filtered)
    close(filtered[0].mean, filtered[1].mean, "filtered mean")
    close(filtered[0].cov, filtered[1].cov, "filtered cov")
    close(filtered[0].mode_probs, filtered[1].mode_probs, "filtered mode_probs")
    close(filtered[0].log_likelihood, filtered[1].log_likelihood, "log_likelihood")
    for j in range(2):
        close(compiled.modes[j].mean, tensors.modes[j].mean, f"mode {j} mean")
        close(compiled.modes[j].cov, tensors.modes[j].cov, f"mode {j} cov")
        if lag == 0:
            close(
                compiled.modes[j].log_likelihood,
                tensors.modes[j].log_likelihood,
                f"mode {j} log-likelihood",
            )


def test_compiled_imm_takes_every_prior_and_mode_probability_form():
    z, _, x0, P0 = turning_tracks(5, 25, 2, irregular=False, missing=False, seed=1)
    turn = turn_imm(2)
    smoother = TurnIMMSmoother(turn, 3)
    per_track = P0.expand(5, 4, 4) * torch.linspace(1, 3, 5, dtype=torch.float64)[:, None, None]
    cases = [
        {"mode_probs": None},
        {"mode_probs": [0.9, 0.1]},
        {"mode_probs": torch.tensor([[1.0, 0.0]] * 5, dtype=torch.float64)},  # CT impossible at 0
    ]
    for prior in (P0, per_track):
        for kwargs in cases:
            compiled, tensors = both(smoother, z, x0, prior, keep="moments", **kwargs)
            close(compiled.mean, tensors.mean, f"mean {kwargs}")
            close(compiled.cov, tensors.cov, f"cov {kwargs}")
            close(compiled.mode_probs, tensors.mode_probs, f"mode_probs {kwargs}")
    one, whole = both(smoother, z[0], x0[0], P0, keep="mean")  # one track without the batch axis
    close(one.mean, whole.mean, "one track")
    assert one.mean.shape == (25, 4)
    short, tensors = both(smoother, z[:, :1], x0, P0, keep="mean")  # one step: nothing to smooth
    close(short.mean, tensors.mean, "one step")


def test_compiled_imm_on_threads_gives_the_estimates_of_one_thread():
    z, dt, x0, P0 = turning_tracks(801, 130, 2, irregular=True, missing=True, seed=2)
    smoother = TurnIMMSmoother(turn_imm(2), 5)
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        with torch.no_grad():
            one = smoother(z, x0, P0, dt=dt, keep="moments")
        torch.set_num_threads(3)
        assert fused_imm.build.threads(801, 130) == 3  # (the batch is large enough to split)
        with torch.no_grad():
            three = smoother(z, x0, P0, dt=dt, keep="moments")
    finally:
        torch.set_num_threads(before)
    assert torch.equal(one.mean, three.mean) and torch.equal(one.cov, three.cov)
    assert torch.equal(one.filtered.mean, three.filtered.mean)


def test_the_tensor_path_runs_where_the_compiled_one_cannot(monkeypatch):
    z, dt, x0, P0 = turning_tracks(3, 12, 2, irregular=True, missing=False, seed=3)
    calls = []
    real = TurnIMM.compiled_pass

    def counted(self, *args, **kwargs):
        out = real(self, *args, **kwargs)
        calls.append(out is not None)
        return out

    monkeypatch.setattr(TurnIMM, "compiled_pass", counted)
    smoother = TurnIMMSmoother(turn_imm(2), 2)
    with torch.no_grad():
        smoother(z, x0, P0, dt=dt, keep="mean")
        assert calls[-1], "float64, no gradient, keep mean: compiled"
        whole = smoother(z, x0, P0, dt=dt)  # keep="all": predictions, gains, innovations
        assert not calls[-1] and whole.filtered.modes[0].gain is not None
        ukf = TurnIMMSmoother(turn_imm(2, turn_filter="ukf"), 2)
        ukf(z, x0, P0, dt=dt, keep="mean")
        assert not calls[-1], "the UKF turn mode is the tensor path's"
        single = TurnIMMSmoother(
            TurnIMM(ConstantVelocity(ndim=2, dt=5.0, q=0.5, r=900.0), 1e-6, 0.01), 2
        )
        single(z.float(), x0.float(), P0.float(), dt=dt.float(), keep="mean")
        assert not calls[-1], "float32 is the tensor path's"
    # with gradients asked of the model's noises: the tensor path, and they flow
    learnable = ConstantVelocity(ndim=2, dt=5.0, q=0.5, r=[900.0] * 2, learn_q=True).double()
    smoother = TurnIMMSmoother(TurnIMM(learnable, turn_rate_q=1e-6, turn_rate_std=0.01), 2)
    smoother(z, x0, P0, dt=dt, keep="mean").mean.square().sum().backward()
    assert not calls[-1]
    assert learnable.q.raw.grad is not None and bool(torch.isfinite(learnable.q.raw.grad).all())


def test_a_factor_that_fails_hands_the_run_to_the_tensor_path():
    # A prior the checks would refuse, given straight to the loop: its covariance NaN, so
    # the first S is not positive definite and the compiled Cholesky factor fails; the caller
    # (TurnIMM._pass, TurnIMMSmoother._pass) then runs the tensor path, whose factor adds
    # jitter where a covariance is semi-definite by rounding
    from torchsvs.estimator import Inputs

    z, _, x0, P0 = turning_tracks(4, 8, 2, irregular=False, missing=False, seed=4)
    turn = turn_imm(2)

    def inputs(prior: torch.Tensor) -> Inputs:
        return turn.common_inputs(Inputs(z, x0, prior, None, None, None, None, False, "mean"))

    assert turn.compiled_pass(inputs(P0.expand(4, 4, 4)), None, 2) is not None
    nan = P0.expand(4, 4, 4).clone()
    nan[2] = float("nan")
    assert turn.compiled_pass(inputs(nan), None, 2) is None
    assert turn.compiled_pass(inputs(nan), None, 0) is None


def test_track_imm_writes_the_same_estimates_through_either_path(tmp_path):
    """``track --estimator imm`` writes the same estimates through either path."""
    import pandas as pd

    from torchsvs.cli import main

    z, _, _, _ = turning_tracks(6, 30, 2, irregular=False, missing=False, seed=5)
    rows = [
        {"track_id": f"t{b}", "time": 5.0 * t, "x": float(z[b, t, 0]), "y": float(z[b, t, 1])}
        for b in range(6)
        for t in range(30)
    ]
    source = tmp_path / "in.csv"
    pd.DataFrame(rows).to_csv(source, index=False)
    outs = []
    for name, eager in (("compiled", False), ("tensors", True)):
        target = tmp_path / f"{name}.csv"
        args = ["track", str(source), "-o", str(target), "--estimator", "imm", "--quiet"]
        if eager:
            with eager_loops():
                main(args)
        else:
            main(args)
        outs.append(pd.read_csv(target))
    a, b = outs
    for column in ("x", "vx", "y", "vy"):
        assert math.isclose(float((a[column] - b[column]).abs().max()), 0.0, abs_tol=1e-3), column
