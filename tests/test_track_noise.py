"""Each track's noise read off its own positions (torchsvs.datasets.track_noise) and the run's
choice to use it (torchsvs.sample_accuracy.with_track_noise)."""

from __future__ import annotations

import math
from dataclasses import replace

import torch

from torchsvs.datasets import RecordedTracks
from torchsvs.datasets.track_noise import read_track_noise, shrunk_ratios, spread_of
from torchsvs.recipes import Settings
from torchsvs.sample_accuracy import with_track_noise


def _tracks(sigmas: torch.Tensor, steps: int = 150, seed: int = 0) -> RecordedTracks:
    """Tracks of nearly constant velocity at 1 s, each measured with its own σ."""
    g = torch.Generator().manual_seed(seed)
    B = len(sigmas)
    accel = torch.randn(B, steps, 2, generator=g, dtype=torch.float64) * 0.3
    velocity = 10.0 + accel.cumsum(1)
    truth = velocity.cumsum(1)
    noise = torch.randn(B, steps, 2, generator=g, dtype=torch.float64) * sigmas.view(B, 1, 1)
    dt = torch.ones(B, steps, dtype=torch.float64)
    time = dt.cumsum(1)
    steps_of = torch.arange(B * steps).view(B, steps)
    lengths = torch.full((B,), steps, dtype=torch.int64)
    ids = [f"t{b}" for b in range(B)]
    return RecordedTracks(truth + noise, dt, time, lengths, ids, steps=steps_of)


def test_each_track_is_read_at_its_own_noise_and_shrunk_by_the_spread() -> None:
    sigmas = torch.exp(torch.linspace(math.log(5.0), math.log(45.0), 40, dtype=torch.float64))
    tracks = _tracks(sigmas)
    read = read_track_noise(tracks.z, tracks.dt, [225.0, 225.0])  # (the file's: 15 m)
    own = (15.0 * read.log_ratio.exp()).log()
    error = own - sigmas.log()
    assert float(error.abs().mean()) < 0.08 and float(error.abs().max()) < 0.3
    assert bool(((read.se > 0.02) & (read.se < 0.1)).all())  # (≈ 2 / √(kept residuals))
    mean, tau = spread_of(read) or (math.nan, math.nan)
    assert 0.5 < tau < 0.8  # (log-uniform over a factor 9: 0.63)
    ratios = shrunk_ratios(read, mean, tau)
    assert torch.all((ratios.log() / 2 - mean).abs() <= (read.log_ratio - mean).abs() + 1e-12)
    # one noise for all: no spread, and every track shrunk to the file's level
    same = _tracks(torch.full((40,), 15.0, dtype=torch.float64), seed=1)
    found = spread_of(read_track_noise(same.z, same.dt, [225.0, 225.0]))
    assert found is not None and found[1] < 0.1


def test_the_run_takes_each_tracks_own_noise_only_where_the_tracks_differ() -> None:
    mixed = _tracks(torch.exp(torch.linspace(math.log(5.0), math.log(45.0), 30)).double())
    read = Settings(
        "ks", meas_var=[400.0, 400.0], noise="data", meas_std_se=[5.0, 5.0], noise_spread=0.7
    )  # (the spread of a few tracks' readings lets the run look: the tracks' own decide)
    chosen = with_track_noise(read, mixed)
    assert chosen is not None
    own, line = chosen
    assert own.track_noise is not None and own.own_noise and "leave-one-out" in line
    # the file's noise is the mean over the rows of each track's own (45² + 5² ...: 22 m)
    assert 18.0 < own.meas_var[0] ** 0.5 < 28.0
    same = _tracks(torch.full((30,), 15.0, dtype=torch.float64), seed=2)
    assert with_track_noise(read, same) is None
    assert with_track_noise(replace(read, noise_spread=0.1), mixed) is None
    given = Settings("ks", meas_var=[400.0, 400.0], noise="given")
    assert with_track_noise(given, mixed) is None


def test_a_tracks_reading_is_its_own_whatever_tracks_are_read_beside_it(monkeypatch) -> None:
    """Read in chunks of tracks (to bound memory) or all at once, alone or in a batch, each
    track's reading is the same: the fit has one scale per track and nothing shared."""
    import torchsvs.datasets.track_noise as track_noise

    tracks = _tracks(torch.tensor([3.0, 30.0, 8.0, 15.0, 50.0], dtype=torch.float64), seed=3)
    whole = read_track_noise(tracks.z, tracks.dt, [100.0, 100.0])
    alone = read_track_noise(tracks.z[3:4].clone(), tracks.dt[3:4].clone(), [100.0, 100.0])
    assert torch.equal(alone.log_ratio, whole.log_ratio[3:4])
    monkeypatch.setattr(track_noise, "CHUNK_STEPS", 2 * tracks.z.shape[1])
    chunked = read_track_noise(tracks.z.clone(), tracks.dt.clone(), [100.0, 100.0])
    assert torch.equal(chunked.log_ratio, whole.log_ratio) and torch.equal(chunked.se, whole.se)
