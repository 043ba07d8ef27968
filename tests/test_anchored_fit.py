"""A Kalman smoother's fitted ``q`` as the run uses it: the anchor of each track's own ``q``
(:func:`~torchsvs.sample_accuracy.anchored_fit`), kept only where that is lower."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pandas as pd
import pytest

from torchsvs.datasets import Columns
from torchsvs.recipes import Settings
from torchsvs.tracking import track_file


def _rmse(out: pd.DataFrame, truth: pd.DataFrame) -> float:
    both = out.merge(truth, on=["track_id", "time"], suffixes=("", "_true"))
    return float(np.sqrt(((both.x - both.x_true) ** 2 + (both.y - both.y_true) ** 2).mean()))


@pytest.fixture(scope="module")
def walkers(tmp_path_factory):
    """Simulated people walking (1.2 m/s, waits and corners) at σ 25 m: noise far above the
    motion, where the SURE of one q for all the tracks wants half the file's q."""
    from experiments.recorded_sets import build_sets

    (bench,) = build_sets(["walker"], rows=5000, seed=2, sigmas=[25.0])
    source = tmp_path_factory.mktemp("walkers") / "in.csv"
    bench.measurements.to_csv(source, index=False)
    return source, bench.truth.rows


def test_the_fit_keeps_the_files_q_where_each_tracks_own_q_is_lower_from_it(
    walkers, tmp_path, monkeypatch
):
    source, truth = walkers
    default = track_file(source, tmp_path / "default.csv", Settings("ks"), progress=False)
    fitted = track_file(source, tmp_path / "fit.csv", Settings("ks"), fit=True, progress=False)
    assert default.settings is not None and fitted.settings is not None
    assert "kept the file's q" in fitted.fit.summary()
    assert fitted.settings.q == default.settings.q
    learned = float(fitted.fit.stages[0].split("q = ")[1].split(" ")[0])
    assert learned < 0.7 * default.settings.q  # what the fit wanted, and the run declined
    assert fitted.accuracy is not None and default.accuracy is not None
    assert fitted.accuracy.estimated_rmse == pytest.approx(default.accuracy.estimated_rmse)
    # the run as it was: each track's own q anchored on the fitted one
    import torchsvs.track_plan

    monkeypatch.setattr(torchsvs.track_plan, "anchored_fit", lambda fit, start, tracks: fit)
    before = track_file(source, tmp_path / "before.csv", Settings("ks"), fit=True, progress=False)
    assert before.settings is not None and before.settings.q == pytest.approx(learned, rel=1e-3)
    assert before.accuracy is not None
    assert before.accuracy.estimated_rmse > 1.05 * fitted.accuracy.estimated_rmse  # SURE says
    kept, declined = (_rmse(pd.read_csv(tmp_path / f), truth) for f in ("fit.csv", "before.csv"))
    assert kept < 0.97 * declined  # and the truth: 6.25 against 6.59 m


def test_the_fitted_q_stays_where_it_is_lower_and_other_fits_pass(walkers):
    import torch

    from torchsvs.datasets.tables import block_of
    from torchsvs.datasets.tracks import padded_batch
    from torchsvs.fitting.defaults import complete_settings, screened, with_q_curve
    from torchsvs.fitting.tuning import FitResult, self_tune
    from torchsvs.sample_accuracy import anchored_fit, sample_terms

    source, _ = walkers
    steps = block_of(pd.read_csv(source), Columns()).steps
    sample = padded_batch(steps, np.arange(steps.num_tracks), torch.float64)
    settings, clean, _ = screened(Settings("ks"), sample)
    start = complete_settings(settings, clean)
    fitted = self_tune(start, clean).settings
    # from a start far above anything the tracks want, the fitted anchor is the lower
    far = replace(start, q=start.q * 1e4)
    own = {
        name: sample_terms(with_q_curve(s, clean), clean).mse(start.meas_var)[0]
        for name, s in (("far", far), ("fitted", fitted))
    }
    assert own["fitted"] < own["far"]
    kept = anchored_fit(FitResult(fitted), far, clean)
    assert kept.settings == fitted and not kept.stages
    # from the file's own q, the fitted anchor is not (the test above: by the truth too)
    declined = anchored_fit(FitResult(fitted), start, clean)
    assert declined.settings == replace(fitted, q=start.q) and len(declined.stages) == 1
    # one q for all the tracks (no anchor), or a divergence that is probed: the fit stands
    for other in (replace(fitted, track_q=False), replace(fitted, estimator="svss", psi=[1.0])):
        assert anchored_fit(FitResult(other), start, clean).settings == other
