"""ψ from a network (experiments/network_psi.py): a reduction to the plain SVSS, gradients that
reach the network through SURE, and a truth-free training run that lowers the true error."""

from __future__ import annotations

from dataclasses import replace

import torch

from experiments.network_psi import (
    NetworkPsiSVSS,
    PsiNetwork,
    half_of,
    held_out,
    train,
)
from tests.conftest import simulate_cv
from torchsvs.datasets import RecordedTracks
from torchsvs.fitting.batches import batch_loss, recorded_batches
from torchsvs.recipes import Settings
from torchsvs.runs import run_result


def _half(q_factor: float, B: int = 12, T: int = 120, seed: int = 0):
    """CV tracks at irregular 1-3 s (q 4, σ 20 m), on settings whose q is ``q_factor`` × the
    true one: a small factor leaves the model too quiet, and the boundary layer saturates."""
    gen = torch.Generator().manual_seed(seed)
    dt = 1.0 + 2.0 * torch.rand(B, T, generator=gen, dtype=torch.float64)
    truth, z = simulate_cv(dt, 4.0, 400.0, gen, speed=30.0)
    tracks = RecordedTracks(
        z=z,
        dt=dt,
        time=torch.cumsum(dt, 1),
        lengths=torch.full((B,), T),
        ids=[str(b) for b in range(B)],
    )
    settings = Settings(
        estimator="svss", meas_var=[400.0, 400.0], q=4.0 * q_factor, psi=[3.0, 3.0], interval=2.0
    )
    return half_of("cv", tracks, truth[..., 0::2], settings, replace(settings, estimator="ks"))


def test_a_network_that_outputs_zero_is_the_svss_of_its_settings() -> None:
    half = _half(q_factor=0.05)
    plain = run_result(half.svss, half.tracks).mean
    layered = run_result(NetworkPsiSVSS(half.settings, PsiNetwork()), half.tracks).mean
    torch.testing.assert_close(layered, plain, rtol=0, atol=1e-9)
    # and a network that does not output zero changes the estimate
    network = PsiNetwork()
    torch.nn.init.constant_(network.out.bias, -1.0)
    moved = run_result(NetworkPsiSVSS(half.settings, network), half.tracks).mean
    assert (moved - plain).abs().max() > 1.0


def test_sure_reaches_the_network_and_the_q_factor() -> None:
    half = _half(q_factor=0.05)
    network = PsiNetwork()
    (batch,) = recorded_batches(half.tracks, half.meas_var, 64, 16, None)
    loss, _ = batch_loss(
        NetworkPsiSVSS(half.settings, network),
        batch,
        "sure",
        meas_cov=torch.diag(half.meas_var),
        generator=torch.Generator().manual_seed(0),
        keep="mean",
    )
    loss.backward()
    assert network.out.weight.grad is not None and network.out.weight.grad.abs().max() > 0
    assert network.log_q.grad is not None and network.log_q.grad.abs() > 0
    # the first layer's gradient is zero at the start (the last layer starts at zero)
    assert network.hidden.weight.grad is not None
    assert not network.hidden.weight.grad.any()


def test_training_without_truth_lowers_the_true_error_of_a_too_quiet_model() -> None:
    training, unseen = _half(q_factor=0.01, seed=0), _half(q_factor=0.01, seed=1)
    torch.manual_seed(0)  # the hidden layer's draw, whatever ran before in this process
    network = PsiNetwork()
    before, _ = held_out(unseen, None, seed=0)
    losses = train(network, [training], epochs=30, lr=0.05, seed=0)
    after, estimated = held_out(unseen, network, seed=0)
    assert losses[-1] < 0.9 * losses[0]
    assert after < 0.9 * before, (before, after)
    assert abs(estimated / after - 1) < 0.15  # and the truth-free estimate sees it
