"""Each track at its own measurement noise, given per row (torchsvs.fitting.noise_classes)."""

from __future__ import annotations

import json
import math
from dataclasses import replace

import numpy as np
import pandas as pd
import pytest
import torch

from torchsvs.accuracy import RiskTerms, RiskTotals
from torchsvs.cli import main
from torchsvs.constraints import SPDMatrix
from torchsvs.fitting import noise_classes as nc
from torchsvs.recipes import Settings, make_estimator, make_model
from torchsvs.track_run import summary_path


def _walkers(sigmas: list[float], steps: int = 200, seed: int = 0) -> tuple[pd.DataFrame, ...]:
    """Walkers (1.3 m/s, a new heading now and then) at 1 s, track k measured with
    ``sigmas[k]`` and that σ in a ``sigma`` column: the truth and the measurements."""
    gen = np.random.default_rng(seed)
    rows, truth = [], []
    for k, sigma in enumerate(sigmas):
        heading = np.cumsum(np.where(gen.random(steps) < 0.05, gen.normal(0, 1.2, steps), 0.0))
        velocity = 1.3 * np.stack([np.cos(heading), np.sin(heading)], 1)
        path = np.cumsum(velocity, 0) + gen.normal(0, 500, 2)
        t = np.arange(steps, dtype=float)
        ids = [f"w{k:02d}"] * steps
        truth.append(pd.DataFrame({"track_id": ids, "time": t, "x": path[:, 0], "y": path[:, 1]}))
        noisy = path + gen.normal(0, sigma, (steps, 2))
        rows.append(
            pd.DataFrame(
                {"track_id": ids, "time": t, "x": noisy[:, 0], "y": noisy[:, 1], "sigma": sigma}
            )
        )
    return pd.concat(truth, ignore_index=True), pd.concat(rows, ignore_index=True)


def test_a_tracks_factor_is_its_rows_median_variance_on_the_grid():
    """A track's factor is the median of its rows' squared σ over the file's, on the grid of
    FACTOR_STEP (within half a step); a track without any keeps the file's; the file's noise is
    the rows' mean square, and a σ of 0 or none at all is refused, naming the column."""
    values = torch.tensor([[3.0, 3.0, 30.0, 3.0], [10.0, 10.0, 10.0, math.nan], [math.nan] * 4])
    observed = torch.tensor([[True] * 4, [True, True, False, True], [True] * 4])
    factors = nc.on_grid(nc.column_ratios(values, observed, [100.0, 100.0]))
    half = 0.5 * math.log(nc.FACTOR_STEP)
    assert abs(math.log(float(factors[0]) / 0.09)) <= half + 1e-12
    assert float(factors[1]) == 1.0 and float(factors[2]) == 1.0
    assert nc.column_noise(values, observed, "sigma") == pytest.approx((3 * 9 + 900 + 200) / 6)
    with pytest.raises(ValueError, match="noise column 'acc': expected standard deviations > 0"):
        nc.column_noise(values.clamp_max(0.0), observed, "acc")
    with pytest.raises(ValueError, match="noise column 'acc': expected a standard deviation"):
        nc.column_noise(torch.full((2, 3), math.nan), torch.ones(2, 3, dtype=torch.bool), "acc")


def test_a_class_runs_the_estimator_at_its_noise_and_its_sure_reads_at_the_files():
    """``noise_scaled`` scales every model's R once (the IMM's modes share their model's) and
    leaves the estimator as it was; ``at_file_noise`` writes a class's SURE terms so that SURE
    at the file's noise, in the run's totals too, is theirs at the class's."""
    for name in ("ks", "svss", "imm"):
        settings = Settings(
            estimator=name, meas_var=[4.0, 9.0], q=0.5, turn_rate_q=1e-4, turn_rate_std=0.05
        )
        estimator = make_estimator(settings, make_model(settings))
        before = {k: v.clone() for k, v in estimator.state_dict().items()}
        with nc.noise_scaled(estimator, 3.0) as scaled:
            Rs = [m.R() for m in scaled.modules() if isinstance(getattr(m, "R", None), SPDMatrix)]
            assert Rs, name
            for R in Rs:
                assert torch.allclose(R.diagonal(), torch.tensor([12.0, 27.0], dtype=R.dtype))
        for k, v in estimator.state_dict().items():
            assert torch.equal(v, before[k]), (name, k)
    gen = np.random.default_rng(1)
    terms = RiskTerms(
        gen.uniform(50, 90, (30, 2)), gen.uniform(2, 6, (30, 2)), np.full((30, 2), 16.0),
        np.arange(30),
    )  # fmt: skip
    folded = nc.at_file_noise(terms, 3.0)
    assert math.isclose(folded.mse([4.0, 9.0])[0], terms.mse([12.0, 27.0])[0], rel_tol=1e-12)
    totals = RiskTotals(2)
    totals.add(folded)
    assert math.isclose(totals.mse([4.0, 9.0])[0], terms.mse([12.0, 27.0])[0], rel_tol=1e-12)


def test_a_file_of_sensors_of_different_quality_runs_each_track_at_its_own_noise(tmp_path):
    """Walkers measured with σ from 1 to 9 m in one file, each row's σ in a column: one noise,
    given as the rows' root mean square, fits none of them; with --noise-col each track runs at
    its own, well below it, and the error estimate and the measurements' error it prints are
    within 25% of the truth's; without the column, each track's read off its positions comes
    within 25% of that (:func:`~torchsvs.sample_accuracy.with_track_noise`). The column's
    tracks all at one σ run as --meas-std σ runs (to 2%), and --noise-col with --meas-std is
    refused."""
    sigmas = [1.0, 9.0, 2.0, 6.0, 1.5, 4.0, 9.0, 1.0, 3.0, 7.0, 2.0, 5.0] * 2
    truth, measured = _walkers(sigmas)
    source = tmp_path / "in.csv"
    measured.to_csv(source, index=False)

    def run(name: str, *args: str) -> tuple[float, dict]:
        target = tmp_path / f"{name}.csv"
        main(["track", str(source), "-o", str(target), "--quiet", *args])
        out = pd.read_csv(target)
        error = np.sqrt(np.mean((out.x - truth.x) ** 2 + (out.y - truth.y) ** 2))
        return float(error), json.loads(summary_path(target).read_text())

    raw = float(np.sqrt(np.mean((measured.x - truth.x) ** 2 + (measured.y - truth.y) ** 2)))
    own, summary = run("own", "--noise-col", "sigma")
    read, by_track = run("read")
    rms = math.sqrt(float(np.mean(np.square(sigmas))))
    one, _ = run("one", "--meas-std", f"{rms:.4f}")
    assert summary["settings"]["noise_column"] == "sigma"
    assert own < 0.35 * raw and own < 0.75 * one
    assert by_track["settings"]["track_noise"] is not None and read < min(1.25 * own, 0.75 * one)
    assert 0.75 < summary["estimated_position_rmse"] / own < 1.25
    assert 0.75 < summary["measurement_rmse"] / raw < 1.25

    truth, measured = _walkers([3.0] * 12, seed=2)
    measured.to_csv(source, index=False)
    column, _ = run("column", "--noise-col", "sigma", "--estimator", "ks")
    given, _ = run("given", "--meas-std", "3", "--estimator", "ks")
    assert column == pytest.approx(given, rel=0.02)
    with pytest.raises(SystemExit):
        run("both", "--noise-col", "sigma", "--meas-std", "3")
    with pytest.raises(SystemExit, match=r"\['accuracy'\] not in .* name yours with --noise-col"):
        run("missing", "--noise-col", "accuracy")


def test_autos_blend_weight_is_read_with_each_track_at_its_own_noise():
    """``sample_blend`` with a noise column runs each class at its own noise and writes the two
    estimators' terms at the file's: with every track at one σ it is the blend at that noise
    given, to rounding; with σ from 1 to 9 m it differs from the weight at the file's noise."""
    from torchsvs.datasets import RecordedTracks
    from torchsvs.sample_accuracy import sample_blend

    def sample(sigmas: list[float]) -> RecordedTracks:
        _, measured = _walkers(sigmas, steps=120, seed=4)
        B = len(sigmas)
        z = torch.tensor(measured[["x", "y"]].to_numpy()).reshape(B, -1, 2)
        sigma = torch.tensor(measured["sigma"].to_numpy()).reshape(B, -1)
        dt = torch.ones(z.shape[:2], dtype=torch.float64)
        time = dt.cumsum(1)
        lengths = torch.full((B,), z.shape[1], dtype=torch.int64)
        ids = [str(b) for b in range(B)]
        steps = torch.arange(z.shape[0] * z.shape[1]).reshape(z.shape[:2])
        return RecordedTracks(z, dt, time, lengths, ids, extra={"sigma": sigma}, steps=steps)

    base = Settings("ks", q=0.003, track_q=False, turn_rate_q=1e-4, turn_rate_std=0.05)
    imm = replace(base, estimator="imm", turn_q=0.5)

    def weight(tracks: RecordedTracks, meas_var: float, column: str | None) -> float:
        first = replace(base, meas_var=[meas_var] * 2, noise_column=column)
        second = replace(imm, meas_var=[meas_var] * 2)
        return sample_blend(first, second, tracks)[0]

    same = sample([3.0] * 8)
    one = weight(same, 9.0, "sigma")
    assert 0.1 < one < 0.9 and one == pytest.approx(weight(same, 9.0, None), abs=1e-9)
    mixed = sample([1.0, 9.0, 2.0, 6.0, 1.5, 4.0, 9.0, 1.0])
    rms = float(np.mean(np.square([1.0, 9.0, 2.0, 6.0, 1.5, 4.0, 9.0, 1.0])))
    assert abs(weight(mixed, rms, "sigma") - weight(mixed, rms, None)) > 1e-3


def test_a_zero_noise_in_a_block_past_the_plans_is_refused_by_name(tmp_path):
    """The plan reads the column off its sample; a later block's σ of 0 (a sensor's "unknown")
    is refused there too, naming the column, and no output is left behind."""
    _, measured = _walkers([2.0, 3.0, 4.0, 5.0, 6.0, 3.0], steps=100)
    last = measured["track_id"] == "w05"
    measured.loc[last & (measured["time"] > 50), "sigma"] = 0.0
    source, target = tmp_path / "in.csv", tmp_path / "out.csv"
    measured.to_csv(source, index=False)
    args = ["track", str(source), "-o", str(target), "--noise-col", "sigma", "--quiet"]
    with pytest.raises(SystemExit, match="noise column 'sigma': expected standard deviations > 0"):
        main([*args, "--stream", "--block-rows", "250"])
    assert not target.exists()
