"""One evaluation path: the RMSE definitions against a NumPy reference, and ``evaluate`` on every
kind of data (scenarios, training batches with per-track priors and dt, controls, particle
filters' generators, recorded tracks with padding)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import torchsvs as ts
from tests.conftest import assert_close
from torchsvs import metrics
from torchsvs.evaluation import evaluate
from torchsvs.training.data import TrackBatch


def _data(seed: int = 0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    gen = torch.Generator().manual_seed(seed)
    est = torch.randn(4, 6, 3, generator=gen, dtype=torch.float64)
    truth = torch.randn(4, 6, 3, generator=gen, dtype=torch.float64)
    steps = torch.rand(4, 6, generator=gen) < 0.7
    steps[:, 0] = True
    return est, truth, steps


def test_rmse_definitions_match_a_numpy_reference():
    est, truth, steps = _data()
    e, t, m = est.numpy(), truth.numpy(), steps.numpy()
    sq = (e - t) ** 2
    assert_close(metrics.accumulative_rmse(est, truth), torch.from_numpy(np.sqrt(sq.mean((0, 1)))))
    assert_close(metrics.rmse_over_time(est, truth), torch.from_numpy(np.sqrt(sq.mean(0))))
    assert_close(metrics.pooled_rmse(est, truth), torch.tensor(np.sqrt(sq.mean())))
    # Counted steps only, with NaN in the truth of the others (padding).
    holed = truth.masked_fill(~steps.unsqueeze(-1), float("nan"))
    w = m[..., None].astype(float)
    acc = np.sqrt((sq * w).sum((0, 1)) / w.sum((0, 1)))
    assert_close(metrics.accumulative_rmse(est, holed, steps), torch.from_numpy(acc))
    pooled = np.sqrt((sq * w).sum() / (w.sum() * 3))
    assert_close(metrics.pooled_rmse(est, holed, steps), torch.tensor(pooled))
    # Entry masks (a missing component).
    entries = steps.unsqueeze(-1).expand(-1, -1, 3).clone()
    entries[..., 2] = False
    assert_close(
        metrics.accumulative_rmse(est, truth, entries)[:2],
        metrics.accumulative_rmse(est, holed, steps)[:2],
    )
    # The SPVSF paper's: per run including the prior's error, averaged over runs.
    x0_hat, x0 = torch.tensor([1.0, 2.0, 3.0]), torch.tensor([0.0, 0.0, 1.0])
    first = ((x0_hat - x0).numpy() ** 2)[None, None, :]
    per_run = np.sqrt(np.concatenate([np.repeat(first, 4, 0), sq], 1).mean(1))
    run = metrics.run_rmse(est, truth, initial=(x0_hat.double(), x0.double()))
    assert_close(run, torch.from_numpy(per_run))
    assert_close(
        metrics.paper_rmse(est, truth, initial=(x0_hat.double(), x0.double())), run.mean(0)
    )


def test_supervised_loss_is_the_mean_squared_error_with_gradients():
    est, truth, steps = _data(1)
    est.requires_grad_(True)
    loss = metrics.mean_squared_error(
        est, truth.masked_fill(~steps.unsqueeze(-1), float("nan")), steps
    )
    loss.backward()
    assert est.grad is not None and bool(torch.isfinite(est.grad).all())
    assert bool((est.grad[~steps] == 0).all())  # uncounted (NaN) entries give no gradient


@pytest.mark.parametrize(
    "mask, pattern",
    [
        (torch.ones(4, 5, dtype=torch.bool), r"mask: expected a bool tensor of shape \(4, 6\)"),
        (torch.ones(4, 6), r"mask: expected a bool tensor .* got torch.float32"),
    ],
)
def test_bad_masks_are_named(mask, pattern):
    est, truth, _ = _data()
    with pytest.raises(ValueError, match=pattern):
        metrics.accumulative_rmse(est, truth, mask)


def test_evaluate_on_a_scenario_and_on_a_training_batch_with_per_track_priors():
    sc = ts.scenarios.atc_scenario(6, torch.Generator().manual_seed(0))
    kf = ts.KalmanFilter(sc.model)
    rows = evaluate({"KF": kf}, sc, progress=False)
    expected = ts.metrics.accumulative_rmse(kf(sc.z, sc.x0, sc.P0).mean, sc.truth)
    assert_close(rows[0].rmse, expected, atol=0, rtol=0)
    assert rows[0].us_per_track_step > 0
    # A batch with a prior per track, per-step intervals and a mask of the scored steps.
    B, T = sc.z.shape[:2]
    dt = torch.full((B, T), sc.dt, dtype=torch.float64)
    x0 = sc.truth[:, 0] + 10.0
    P0 = sc.P0.expand(B, 4, 4)
    scored = torch.ones(B, T, dtype=torch.bool)
    scored[:, :20] = False
    batch = TrackBatch(sc.z, sc.truth, x0, P0, dt=dt, scored=scored)
    svsf = ts.SVSF(sc.model, psi=[800.0, 800.0], artificial=None)
    rows = evaluate({"KF": kf, "SVSF": svsf}, batch, progress=False)
    for row, est in zip(rows, (kf, svsf), strict=True):
        out = est(sc.z, x0, P0, dt=dt)
        assert_close(row.mean, out.mean, atol=0, rtol=0)
        assert_close(row.rmse, ts.metrics.accumulative_rmse(out.mean, sc.truth, scored))


def test_evaluate_passes_controls_and_a_seeded_generator():
    sc = ts.scenarios.eha_scenario(3, torch.Generator().manual_seed(1), duration=0.05)
    spvsf = ts.SPVSF(sc.model, psi=[1.0, 1.0, 1.0], num_particles=40, artificial=None)
    first = evaluate({"SPVSF": spvsf}, sc, seed=3, progress=False)[0]
    again = evaluate({"SPVSF": spvsf}, sc, seed=3, progress=False)[0]
    other = evaluate({"SPVSF": spvsf}, sc, seed=4, progress=False)[0]
    direct = spvsf(sc.z, sc.x0, sc.P0, u=sc.u, generator=torch.Generator().manual_seed(3))
    assert_close(first.mean, direct.mean, atol=0, rtol=0)  # u and the generator reached it
    assert_close(first.mean, again.mean, atol=0, rtol=0)
    assert bool((first.mean != other.mean).any())


def test_evaluate_on_truth_of_some_components_and_padded_tracks():
    sc = ts.scenarios.atc_scenario(4, torch.Generator().manual_seed(2))
    kf = ts.KalmanFilter(sc.model)
    positions = sc.truth[..., [0, 2]]
    row = evaluate({"KF": kf}, sc, truth=positions, components=[0, 2], progress=False)[0]
    assert_close(row.rmse, ts.metrics.accumulative_rmse(row.mean, sc.truth)[[0, 2]])
    holed = positions.clone()
    holed[0, :10, 1] = float("nan")  # truth missing there: not scored
    row = evaluate({"KF": kf}, sc, truth=holed, components=[0, 2], progress=False)[0]
    expected = ts.metrics.accumulative_rmse(row.mean[..., [0, 2]], holed, torch.isfinite(holed))
    assert bool(torch.isfinite(row.rmse).all())
    assert_close(row.rmse, expected, atol=0, rtol=0)
    with pytest.raises(ValueError, match=r"truth: expected the estimates' shape .*components="):
        evaluate({"KF": kf}, sc, truth=positions, progress=False)
    with pytest.raises(ValueError, match=r"data: expected a prior"):
        evaluate({"KF": kf}, sc._replace(x0=None), progress=False)
