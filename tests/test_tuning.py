"""Truth-free learning on recorded tracks: windows, the self-tuning fit, the Lightning path."""

from __future__ import annotations

from dataclasses import replace

import pytest
import torch

import torchsvs as ts
from tests.conftest import assert_close, simulate_cv
from torchsvs.datasets import RecordedTracks, with_prior
from torchsvs.datasets.tracks import windows
from torchsvs.fitting.defaults import complete_settings
from torchsvs.fitting.tuning import self_tune
from torchsvs.recipes import Settings, make_estimator, make_model
from torchsvs.step_estimates import centred
from torchsvs.training import EstimatorModule, RecordedTracksDataModule
from torchsvs.training.quiet import tool_trainer

pytestmark = pytest.mark.filterwarnings(
    "ignore:.*does not have many workers.*", "ignore:.*LeafSpec.*", "ignore:.*litlogger.*"
)


def _cv_tracks(B=24, T=160, q=4.0, r=400.0, seed=0, missing=0.05) -> RecordedTracks:
    """Tracks of the CV model itself (so the best q is the true one) at irregular 1-3 s."""
    gen = torch.Generator().manual_seed(seed)
    dt = 1.0 + 2.0 * torch.rand(B, T, generator=gen, dtype=torch.float64)
    truth, z = simulate_cv(dt, q, r, gen, speed=30.0)
    z[torch.rand(B, T, 2, generator=gen) < missing] = float("nan")
    return RecordedTracks(
        z=z,
        dt=dt,
        time=torch.cumsum(dt, 1),
        lengths=torch.full((B,), T),
        ids=[str(b) for b in range(B)],
        truth=truth,
    )


def _position_rmse(settings: Settings, tracks: RecordedTracks) -> float:
    est = make_estimator(settings, make_model(settings)).double()
    moved, offset = centred(tracks)
    moved = with_prior(moved, torch.tensor(settings.meas_var).sqrt())
    with torch.no_grad():
        mean = est(moved.z, moved.x0, moved.P0, dt=moved.dt).mean.clone()
    mean[..., 0::2] += offset.unsqueeze(1)
    assert tracks.truth is not None
    return float((mean[..., [0, 2]] - tracks.truth[..., [0, 2]]).square().mean().sqrt())


def test_windows_score_every_real_step_once():
    tracks = _cv_tracks(B=3, T=50)
    tracks.lengths = torch.tensor([50, 31, 7])
    tracks.z[1, 31:] = float("nan")
    tracks.z[2, 7:] = float("nan")
    cut, scored = windows(tracks, length=16, burn_in=4)
    counts = torch.zeros(3, 50, dtype=torch.int64)
    for w, ident in enumerate(cut.ids):
        b, start = (int(v) for v in ident.split("@"))
        steps = torch.arange(start, start + 16)[scored[w]]
        counts[b, steps] += 1
        inside = torch.arange(start, start + 16) < tracks.lengths[b]
        assert_close(
            cut.z[w][inside], tracks.z[b, start : start + 16][inside[: min(16, 50 - start)]]
        )
    assert bool((counts[tracks.mask] == 1).all()) and int(counts[~tracks.mask].sum()) == 0


def test_fit_finds_the_true_q_without_truth():
    tracks = _cv_tracks(q=4.0, r=400.0)
    start = complete_settings(Settings(estimator="ks", meas_var=[400.0, 400.0], q=100.0), tracks)
    fit = self_tune(start, tracks, known_noise=True)
    assert 2.0 < fit.settings.q < 8.0
    assert fit.curve[-1] < fit.curve[0]
    assert fit.parameters == 1  # q


@pytest.mark.parametrize("lag", [None, 5])
def test_fit_learns_the_noise_when_it_is_not_given(lag):
    """The noise is learned by a Kalman filter's innovation likelihood, whatever the smoother's
    lag (a lag given to the smoother is not the filter's: it was refused as one)."""
    tracks = _cv_tracks(q=4.0, r=400.0, B=32)
    start = Settings(estimator="ks", meas_var=[50.0, 50.0], q=1.0, lag=lag)
    start = complete_settings(start, tracks)
    fit = self_tune(start, tracks, known_noise=False)
    assert fit.settings.meas_var == pytest.approx([400.0, 400.0], rel=0.15)
    assert "innovation NLL" in fit.summary()


def test_fit_of_an_svss_lowers_its_true_error():
    tracks = _cv_tracks(q=20.0, r=900.0, B=16, T=120, seed=3)
    # A limit of the variable boundary layer far too narrow: the filter follows the measurements.
    start = complete_settings(
        Settings(estimator="svss", meas_var=[900.0, 900.0], psi=[0.2, 0.2], lag=2), tracks
    )
    fit = self_tune(start, tracks, known_noise=True, steps=10)
    assert _position_rmse(fit.settings, tracks) < 0.9 * _position_rmse(start, tracks)
    assert len(fit.settings.psi) == 2 and fit.settings.psi[0] == fit.settings.psi[1]  # tied axes
    assert fit.parameters == 3  # q, one ψ for both axes, γ (what the layer check counts)
    fixed = self_tune(replace(start, gamma=0.0), tracks, known_noise=True, steps=2)
    assert fixed.parameters == 2 and fixed.settings.gamma == 0.0


def test_rstkf_fit_searches_q_and_keeps_the_least_risk(monkeypatch):
    """The RSTKF's ``q`` is searched (its step loop made L-BFGS take 71 s on 5,000 rows): from a
    start 1000× too large the fit keeps the candidate of least SURE among those it scored, and
    the start's risk scored again is higher."""
    from torchsvs.fitting import tuning

    tracks = _cv_tracks(q=4.0, r=400.0, B=8, T=80)
    start = complete_settings(
        Settings(estimator="rstkf", meas_var=[400.0, 400.0], q=4000.0), tracks
    )
    scored: list[tuple[float, float]] = []
    risk = tuning._risk

    steps: list[int] = []

    def recorded(est, batches, *args):
        value = risk(est, batches, *args)
        scored.append((float(est.model.q()), value))
        steps.append(batches[0].z.shape[1])
        return value

    monkeypatch.setattr(tuning, "_risk", recorded)
    fit = self_tune(start, tracks)
    assert fit.parameters == 1 and fit.curve == []
    searched = scored[:-2]  # (the last two: the start and the choice on fresh probes)
    assert len(searched) == len(tuning.Q_DECADES) + 4
    # scored on windows, checked on the whole tracks (what runs: on windows a q 0.002 times the
    # reading's looked best where whole tracks came out at 1.46 of the measurements' error)
    assert set(steps[:-2]) == {tuning.SEARCH_WINDOWS[0]} and steps[-2:] == [80, 80]
    least = min(searched, key=lambda pair: pair[1])
    assert fit.settings.q == pytest.approx(least[0], rel=1e-12)
    assert fit.settings.q < 0.1 * start.q
    start_risk = next(value for q, value in searched if q == pytest.approx(start.q, rel=1e-12))
    assert least[1] < start_risk


def test_rstkf_paired_probes_give_the_risk_of_two_runs():
    """The RSTKF runs SURE's plain and probed measurements in one batch (paired_probes): the
    same risk as two runs."""
    from torchsvs.fitting.batches import batch_loss, recorded_batches

    tracks = _cv_tracks(q=4.0, r=400.0, B=4, T=40)
    settings = complete_settings(
        Settings(estimator="rstkf", meas_var=[400.0, 400.0], q=4.0), tracks
    )
    est = make_estimator(settings, make_model(settings)).double()
    assert est.paired_probes
    batch = recorded_batches(tracks, torch.tensor([400.0, 400.0]), 32, 8, None)[0]
    meas_cov = torch.diag(torch.tensor([400.0, 400.0], dtype=torch.float64))
    with torch.no_grad():
        paired = batch_loss(
            est, batch, "sure", meas_cov=meas_cov, generator=torch.Generator().manual_seed(1)
        )[0]
        est.paired_probes = False
        apart = batch_loss(
            est, batch, "sure", meas_cov=meas_cov, generator=torch.Generator().manual_seed(1)
        )[0]
    assert_close(paired, apart, atol=1e-10, rtol=1e-10)


@pytest.mark.parametrize("estimator", ["pf", "spvsf"])
def test_particle_filters_take_the_kalman_filters_q(estimator):
    tracks = _cv_tracks(q=4.0, r=400.0, B=4, T=60)
    start = complete_settings(
        Settings(estimator=estimator, meas_var=[400.0, 400.0], q=0.01, particles=64), tracks
    )
    fit = self_tune(start, tracks, steps=8)
    twin = self_tune(replace(start, estimator="kf"), tracks, steps=8)
    assert fit.settings.estimator == estimator and fit.settings.particles == 64
    assert fit.settings.q == twin.settings.q != start.q
    assert "from the kf's fit" in fit.stages[-1]
    with pytest.raises(ValueError, match="^estimator: --fit tunes .*; got 'auto'"):
        self_tune(replace(start, estimator="auto"), tracks)


def test_lightning_fits_recorded_tracks_without_truth(tmp_path):
    tracks = _cv_tracks(q=4.0, r=400.0, B=16, T=96)
    truthless = RecordedTracks(
        z=tracks.z, dt=tracks.dt, time=tracks.time, lengths=tracks.lengths, ids=tracks.ids
    )
    data = RecordedTracksDataModule(
        truthless, meas_std=20.0, window=48, burn_in=8, batch_size=32, double=True
    )
    data.setup("fit")
    assert all(b.truth is None for b in data.batches["train"])
    model = ts.models.ConstantVelocity(q=200.0, r=400.0, learn_q=True).double()
    module = EstimatorModule(
        ts.RTSSmoother(ts.KalmanFilter(model), lag=2), loss="sure", lr=0.3, meas_cov=data.meas_cov
    )
    trainer = tool_trainer(max_epochs=12, default_root_dir=tmp_path)
    trainer.fit(module, data)
    assert float(model.q().detach()) < 100.0  # from 200 toward the true 4
    assert "val_rmse" not in trainer.callback_metrics  # no truth, no RMSE


def test_sure_refuses_a_learnable_measurement_noise():
    model = ts.models.ConstantVelocity(q=1.0, r=4.0, learn_noise=True)
    with pytest.raises(ValueError, match="^meas_cov: loss 'sure' needs the sensor's known"):
        EstimatorModule(ts.KalmanFilter(model), loss="sure")
    EstimatorModule(ts.KalmanFilter(model), loss="sure", meas_cov=torch.eye(2) * 4.0)  # given: fine
    q_only = ts.models.ConstantVelocity(q=1.0, r=4.0, learn_q=True)
    assert [n for n, p in q_only.named_parameters()] == ["q.raw"]


def test_supervised_loss_on_recorded_tracks_needs_truth():
    tracks = _cv_tracks(B=4, T=40)
    truthless = RecordedTracks(
        z=tracks.z, dt=tracks.dt, time=tracks.time, lengths=tracks.lengths, ids=tracks.ids
    )
    data = RecordedTracksDataModule(
        truthless, meas_std=20.0, window=20, burn_in=4, val_fraction=0.25
    )
    data.setup("fit")
    module = EstimatorModule(
        ts.KalmanFilter(ts.models.ConstantVelocity(q=1.0, r=400.0, learn_q=True)), loss="supervised"
    )
    with pytest.raises(ValueError, match="^loss: 'supervised' needs truth"):
        module.training_step(data.batches["train"][0], 0)


def test_eager_optimizers_fit_without_importing_dynamo_and_restore_the_markers():
    """An L-BFGS fit inside ``eager_optimizers`` never imports ``torch._dynamo`` (1.1-1.4 s of
    a fresh process), reaches the optimum it reaches outside, and leaves torch.optim's methods
    as it found them (a fresh interpreter: other tests may have imported Dynamo already)."""
    import subprocess
    import sys

    script = """
import sys, torch
from torchsvs.fitting.tuning import eager_optimizers

def fit():
    p = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    opt = torch.optim.LBFGS([p], max_iter=20, line_search_fn="strong_wolfe")
    def closure():
        opt.zero_grad()
        loss = ((p - torch.tensor([1.0, -2.0, 0.5], dtype=torch.float64)) ** 4).sum()
        loss.backward()
        return loss
    opt.step(closure)
    return p.detach().tolist()

with eager_optimizers():
    inside = fit()
print("dynamo after the block:", "torch._dynamo" in sys.modules)
zero_grad = torch.optim.Optimizer.zero_grad.__wrapped__
print("marker left:", hasattr(zero_grad, "__dynamo_disable"))
outside = fit()
print("dynamo outside:", "torch._dynamo" in sys.modules)
print("same:", inside == outside)
"""
    done = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, check=True, timeout=300
    )
    assert done.stdout.split("\n")[:4] == [
        "dynamo after the block: False",
        "marker left: False",
        "dynamo outside: True",  # (torch's own path, as before)
        "same: True",
    ], done.stdout + done.stderr


def test_a_searched_fit_keeps_its_start_where_the_whole_tracks_say_so(monkeypatch):
    """The search's choice, scored on windows, stands only where its SURE on the whole tracks
    (fresh probes) is not above the start's: else the start is kept and the fit says so."""
    from torchsvs.fitting import tuning

    tracks = _cv_tracks(q=4.0, r=400.0, B=8, T=80)
    start = complete_settings(
        Settings(estimator="rstkf", meas_var=[400.0, 400.0], q=4000.0), tracks
    )
    risk = tuning._risk

    def windows_only(est, batches, *args):
        if batches[0].z.shape[1] == tuning.SEARCH_WINDOWS[0]:
            return risk(est, batches, *args)
        return 1.0 / float(est.model.q())  # (whole tracks: the least q the worst)

    monkeypatch.setattr(tuning, "_risk", windows_only)
    fit = self_tune(start, tracks)
    assert fit.settings.q == start.q
    assert any("kept the starting point" in line for line in fit.stages)
