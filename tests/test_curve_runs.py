"""A Kalman smoother's (filter's) estimates and error terms in ``torchsvs track`` read off the
SURE curves' passes (:func:`torchsvs.fitting.noise.q_curve_runs`) are those of its own run per
q factor (the path that runs the estimator again), on a batch with what real files have."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from torchsvs import estimating
from torchsvs.datasets import RecordedTracks
from torchsvs.estimating import estimate_group
from torchsvs.fitting import noise
from torchsvs.fitting.noise import q_curves, smoother_q
from torchsvs.recipes import Settings, make_estimator, make_model
from torchsvs.step_estimates import GroupBatch, StepEstimates, centred

SIGMA = 20.0


def _batch() -> RecordedTracks:
    """Quiet and maneuvering tracks at irregular intervals, with 10σ outliers, missing rows, an
    axis missing for a stretch, an axis seen once, tracks of 1, 2 and 3 rows, and padding (the
    quiet tracks shorter than the others)."""
    gen = torch.Generator().manual_seed(3)
    B, T = 24, 90
    dt = (0.5 + 2.0 * torch.rand(B, T, generator=gen)).double()
    agility = torch.where(torch.arange(B) % 2 == 0, 0.1, 30.0).reshape(B, 1, 1)
    accel = torch.randn(B, T, 2, generator=gen, dtype=torch.float64) * agility.sqrt()
    velocity = 30.0 + torch.cumsum(accel * dt.unsqueeze(-1), 1)
    z = torch.cumsum(velocity * dt.unsqueeze(-1), 1) + 5e4
    z = z + SIGMA * torch.randn(B, T, 2, generator=gen, dtype=torch.float64)
    z[::5, 40, 0] += 10 * SIGMA
    z[torch.rand(B, T, generator=gen) < 0.1] = math.nan
    z[3, 20:60, 1] = math.nan
    z[7, :, 1] = math.nan
    z[7, 10, 1] = 5e4
    lengths = torch.full((B,), T, dtype=torch.int64)
    lengths[::2] = 70  # the quiet tracks shorter: their factors' parts are trimmed
    lengths[[1, 2, 4, 6]] = torch.tensor([1, 2, 3, 50])
    padded = torch.arange(T) >= lengths.unsqueeze(1)
    z[padded] = math.nan
    z[[1, 2, 4], 0] = 5e4  # the short tracks' rows observed
    z[[2, 4], 1] = 5e4 + 30.0
    z[4, 2] = 5e4 + 60.0
    steps = torch.arange(B * T).reshape(B, T)
    steps = torch.where(padded, -1, steps)
    time = torch.where(padded, math.nan, torch.cumsum(dt, 1))
    ids = [f"t{b}" for b in range(B)]
    return RecordedTracks(z=z, dt=dt, time=time, lengths=lengths, ids=ids, steps=steps)


def _settings(tracks: RecordedTracks, name: str) -> Settings:
    r = [SIGMA**2] * 2
    smoothed = name == "ks"
    q = smoother_q(tracks.z, tracks.dt, SIGMA**2, smoothed=smoothed).q
    curve = q_curves(tracks.z, tracks.dt, r, q, smoothed).pooled()
    return Settings(name, meas_var=r, q=q, q_curve=curve, outliers=True, outlier_q=q)


def _flat(found: StepEstimates) -> tuple[np.ndarray, np.ndarray]:
    order = np.argsort(found.steps)
    return found.steps[order], found.mean[order]


@pytest.mark.parametrize(("name", "cells"), [("ks", None), ("kf", None), ("ks", 500)])
def test_estimates_and_error_terms_from_the_curves_are_the_runs_own(name, cells, monkeypatch):
    """float64, so the two paths agree to rounding: the estimates, each track's factor, the
    outliers set aside and SURE's sums per chunk (the divergence exact from the run's own
    covariances, and at the first two observations the same probe's: the compiled pass's
    exact values there are held to autograd in test_curves_kernel.py) are the same; also with
    the curves' passes run five tracks at a time (``cells``)."""
    if cells is not None:
        monkeypatch.setattr(noise, "CHUNK_CELLS", cells)
    with_probe = estimating.run_risk_terms
    monkeypatch.setattr(estimating, "run_risk_terms", lambda *args: with_probe(*args[:7]))
    tracks = _batch()
    settings = _settings(tracks, name)
    estimator = make_estimator(settings, make_model(settings)).double()
    assert estimating.is_curves_estimator(estimator, settings)
    moved, offset = centred(tracks)
    batch = GroupBatch(0, np.arange(len(tracks)), moved, offset)
    meas_std = torch.full((2,), SIGMA, dtype=torch.float64)
    reused = estimate_group(estimator, batch, meas_std, settings=settings)
    monkeypatch.setattr(estimating, "is_curves_estimator", lambda *_: False)
    rerun = estimate_group(estimator, batch, meas_std, settings=settings)
    assert reused.q_factor is not None and rerun.q_factor is not None
    assert len(np.unique(reused.q_factor)) > 1  # tracks of several factors
    factor = dict(zip(reused.group.tolist(), reused.q_factor.tolist(), strict=True))
    assert factor == dict(zip(rerun.group.tolist(), rerun.q_factor.tolist(), strict=True))
    assert reused.outliers is not None and len(reused.outliers) > 0
    assert np.array_equal(np.sort(reused.outliers), np.sort(rerun.outliers))
    assert reused.notes == rerun.notes
    steps, mean = _flat(reused)
    steps_again, mean_again = _flat(rerun)
    assert np.array_equal(steps, steps_again)
    np.testing.assert_allclose(mean, mean_again, rtol=0, atol=1e-6)  # (positions ~5e4 m)
    terms, again = reused.risk, rerun.risk
    assert terms is not None and again is not None
    key = np.lexsort((terms.count[:, 0], terms.residual[:, 0], terms.track))
    key_again = np.lexsort((again.count[:, 0], again.residual[:, 0], again.track))
    assert np.array_equal(terms.track[key], again.track[key_again])
    assert np.array_equal(terms.count[key], again.count[key_again])
    np.testing.assert_allclose(
        terms.residual[key], again.residual[key_again], rtol=1e-9, atol=1e-12
    )
    np.testing.assert_allclose(terms.divergence[key], again.divergence[key_again], atol=1e-8)
    assert terms.mse(settings.meas_var) == pytest.approx(again.mse(settings.meas_var), rel=1e-9)


def test_a_smoother_the_curves_do_not_run_is_run_again():
    """A fixed-lag smoother, another q than the settings', a filter where the curves are a
    smoother's: not the curves' estimator."""
    tracks = _batch()
    settings = _settings(tracks, "ks")
    assert not estimating.is_curves_estimator(
        make_estimator(Settings("ks", meas_var=settings.meas_var, q=settings.q, lag=5),
                       make_model(settings)), settings)  # fmt: skip
    other = Settings("ks", meas_var=settings.meas_var, q=2 * settings.q)
    assert not estimating.is_curves_estimator(make_estimator(other, make_model(other)), settings)
    kf = Settings("kf", meas_var=settings.meas_var, q=settings.q)
    assert not estimating.is_curves_estimator(make_estimator(kf, make_model(kf)), settings)


def test_the_probes_run_in_float32_is_the_float64_divergence_to_its_precision():
    """The probe's response runs in the estimator's dtype: in float32 each chunk's divergence
    (a sum of at most 64 components of size ~1, all but each axis's first two exact from the
    float64 curves) is the float64 one to 1e-4."""
    tracks = _batch()
    settings = _settings(tracks, "ks")
    estimator = make_estimator(settings, make_model(settings))
    moved, offset = centred(tracks)
    found = {}
    for dtype in (torch.float32, torch.float64):
        batch = GroupBatch(0, np.arange(len(tracks)), moved.to(dtype), offset)
        meas_std = torch.full((2,), SIGMA, dtype=dtype)
        found[dtype] = estimate_group(estimator.to(dtype), batch, meas_std, settings=settings)
    single, double = found[torch.float32].risk, found[torch.float64].risk
    assert single is not None and double is not None
    assert np.array_equal(single.track, double.track)
    assert np.abs(single.divergence - double.divergence).max() < 1e-4
    assert np.abs(double.divergence).max() > 1.0


def test_curves_run_by_chunks_are_the_whole_batchs():
    """The curves, the factors and the passes kept are the same whatever the chunk (to the
    rounding of another split of the batch: sums, and the compiled loop's lanes of several
    tracks, ~1e-11 relative)."""
    tracks = _batch()
    settings = _settings(tracks, "ks")
    assert settings.q_curve is not None and settings.q is not None
    pooled = settings.q_curve

    def found(cells: int) -> tuple:
        noise.CHUNK_CELLS, kept = cells, noise.CHUNK_CELLS
        try:
            return noise.q_curve_runs(
                tracks.z, tracks.dt, settings.meas_var, settings.q,
                choose=lambda c: noise.track_q_factors(c, pooled), keep=True,
            )  # fmt: skip
        finally:
            noise.CHUNK_CELLS = kept

    whole, parts = found(1 << 20), found(7 * 90)
    torch.testing.assert_close(whole[0].risk, parts[0].risk, rtol=1e-9, atol=1e-6)
    assert torch.equal(whole[1], parts[1])
    assert whole[2] is not None and parts[2] is not None and bool(whole[2].ran.all())
    assert torch.equal(whole[2].ran, parts[2].ran)
    for a, b in zip(whole[2][:2], parts[2][:2], strict=True):
        torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-6, equal_nan=True)
