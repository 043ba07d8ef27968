"""The Kalman smoother's ``q`` chosen per step by SURE over a window (torchsvs.fitting.q_windows):
its pass and error terms against the compiled pass's own, the window's choice, and ``track``
running it."""

from __future__ import annotations

import math
from dataclasses import asdict, replace

import numpy as np
import pandas as pd
import pytest
import torch

from tests.conftest import assert_close
from torchsvs.datasets import RecordedTracks
from torchsvs.fitting import noise, q_windows
from torchsvs.fitting.defaults import with_q_curve
from torchsvs.recipes import Settings
from torchsvs.track_plan import plan_tracks
from torchsvs.track_table import track_table

SIGMA = 30.0


def _maneuvering(B: int = 6, T: int = 400, seed: int = 0, gaps: float = 0.05):
    """``z, truth [B, T, 2]``, ``dt [B, T]``: level flight at 200 m/s, a 3 deg/s turn of 60
    steps at a random time, level again; 2 s steps, noise ``SIGMA``, some reports missing."""
    gen = np.random.default_rng(seed)
    truth = np.zeros((B, T, 2))
    for b in range(B):
        heading = gen.uniform(0, 2 * math.pi)
        turn_at = gen.integers(T // 5, T - 90)
        p = np.zeros(2)
        for t in range(T):
            if turn_at <= t < turn_at + 60:
                heading += math.radians(3.0) * 2.0
            p = p + 400.0 * np.array([math.cos(heading), math.sin(heading)])
            truth[b, t] = p
    z = truth + gen.normal(0, SIGMA, truth.shape)
    z[gen.random((B, T)) < gaps] = np.nan
    dt = np.full((B, T), 2.0)
    return torch.from_numpy(z), torch.from_numpy(truth), torch.from_numpy(dt)


def _rmse(estimate: torch.Tensor, truth: torch.Tensor) -> float:
    return float((estimate[..., 0::2] - truth).square().sum(-1).mean().sqrt())


def test_one_factor_is_the_compiled_pass_and_its_sums():
    """With one factor the weights have nothing to choose: the composite is the compiled pass at
    ``q`` and its SURE sums, built step by step from the pass's variances and the first two
    observations' tangents, equal the sums the compiled pass writes itself."""
    z, _, dt = _maneuvering(B=4, T=150)
    r = [SIGMA**2, SIGMA**2]
    z64, dt64, rr, prior = noise.curve_inputs(z, dt, r)
    one = noise.kalman_positions(z64, dt64, prior.x0, prior.P0, rr, 40.0, True, 32)
    if one.sums is None:
        pytest.skip("the compiled loops are unavailable")
    found = q_windows.windowed_runs(z, dt, r, 40.0, 21, factors=(1.0,))
    assert found is not None
    assert torch.equal(found.runs.mean, one.mean)
    assert torch.equal(found.runs.position_var, one.var)
    assert_close(found.runs.sums, one.sums, rtol=1e-10, atol=1e-8)
    assert torch.equal(found.factor, torch.ones(4, dtype=torch.float64))


def test_an_axis_observed_once_keeps_its_divergence():
    """A track observed once (at its first step, or later) or an axis observed once: the
    composite's sums are the compiled pass's, the one point's divergence its tangent through
    the prior (1: the estimate is the measurement), so its error is the noise's. (Its missing
    second observation's index, 0, is the first's step: one scatter of both wrote 0 there and
    the per-track error read 0.)"""
    z, _, dt = _maneuvering(B=4, T=150, seed=2, gaps=0.0)
    z[0, 1:] = math.nan  # observed at its first step alone
    z[1, :3] = math.nan
    z[1, 4:] = math.nan  # observed at step 3 alone
    z[2, 1:, 1] = math.nan  # its y observed once
    r = [SIGMA**2, SIGMA**2]
    z64, dt64, rr, prior = noise.curve_inputs(z, dt, r)
    one = noise.kalman_positions(z64, dt64, prior.x0, prior.P0, rr, 40.0, True, 32)
    if one.sums is None:
        pytest.skip("the compiled loops are unavailable")
    residual, divergence, count = q_windows.step_terms(z64, one, rr)
    assert_close(divergence[0, 0], torch.ones(2, dtype=torch.float64), rtol=1e-9, atol=1e-12)
    assert_close(divergence[1, 3], torch.ones(2, dtype=torch.float64), rtol=1e-9, atol=1e-12)
    assert_close(divergence[2, 0, 1], torch.tensor(1.0, dtype=torch.float64), rtol=1e-9)
    found = q_windows.windowed_runs(z, dt, r, 40.0, 21, factors=(1.0,))
    assert found is not None
    assert_close(found.runs.sums, one.sums, rtol=1e-10, atol=1e-8)


def test_box_sums_and_the_weights_leave_each_step_out():
    risk = torch.tensor([[[1.0, 1.0, -100.0, 1.0, 1.0]], [[0.0, 0.0, 0.0, 0.0, 0.0]]])
    naive = torch.stack(
        [risk[..., max(0, t - 1) : t + 2].sum(-1) for t in range(5)], -1
    )  # window 3
    assert torch.equal(q_windows.box_sums(risk, 3), naive)
    assert torch.equal(q_windows.box_sums(risk, 99), risk.sum(-1, keepdim=True).expand(2, 1, 5))
    # nearly hard weights: step 2's own term (-100) does not weigh for its pass, its
    # neighbours' do (and at the ends the one neighbour's 1 against 0)
    hard = q_windows.window_weights(risk, 3, 1e-3)
    assert hard.argmax(0).tolist() == [[1, 0, 1, 0, 1]]
    assert_close(hard.sum(0), torch.ones(1, 5))
    assert q_windows.window_weights(risk, 5, 1e-3).argmax(0).tolist() == [[0, 0, 1, 0, 0]]
    # soft: a pass one scale worse over the window weighs 1/e of the best
    soft = q_windows.window_weights(torch.tensor([[[0.0, 2.0, 0.0]], [[0.0, 0.0, 0.0]]]), 3, 2.0)
    assert_close(soft[0, 0, 1], torch.tensor(0.5))  # (step 1's own 2 left out)
    assert_close(soft[0, 0, 0] / soft[1, 0, 0], torch.tensor(math.exp(-1.0)))


def test_the_window_follows_a_turn_that_one_q_per_track_cannot():
    """On level flights with one hard turn, the steps of the turn take larger factors than the
    level steps, and the composite's error by the truth is below the best single ``q`` per
    track (chosen by the truth)."""
    z, truth, dt = _maneuvering(B=6, T=400, seed=1)
    r = [SIGMA**2, SIGMA**2]
    z64, dt64, rr, prior = noise.curve_inputs(z, dt, r)
    q = 5.0
    found = q_windows.windowed_runs(z, dt, r, q, 41)
    if found is None:
        pytest.skip("the compiled loops are unavailable")
    best = math.inf
    per_track = torch.zeros(6)
    for b in range(6):
        errors = []
        for f in noise.Q_FACTORS:
            one = noise.kalman_positions(
                z64[b : b + 1], dt64[b : b + 1], prior.x0[b : b + 1], prior.P0[b : b + 1],
                rr, q * f,
            )  # fmt: skip
            errors.append(float((one.mean[..., 0::2] - truth[b : b + 1]).square().sum()))
        per_track[b] = min(errors)
    best = math.sqrt(float(per_track.sum()) / (6 * 400))
    assert _rmse(found.runs.mean, truth) < 0.97 * best
    grid = torch.tensor(noise.Q_FACTORS, dtype=torch.float64)
    step_factor = torch.einsum("k,kbt->bt", grid.log(), found.weights).exp()
    speed_change = (truth[:, 2:] - 2 * truth[:, 1:-1] + truth[:, :-2]).norm(dim=-1)
    turning = torch.nn.functional.pad(speed_change > 1.0, (1, 1))
    assert float(step_factor[turning].log().mean()) > float(step_factor[~turning].log().mean()) + 1


def test_a_track_is_windowed_alike_alone_and_in_a_batch():
    """Each track's weights and estimates depend on its own measurements alone (an engine's
    partition of the tracks changes nothing), whatever the batch's padding."""
    z, _, dt = _maneuvering(B=5, T=200, seed=2)
    z[1, 150:] = math.nan  # a shorter track: padded in the batch
    r = [SIGMA**2, SIGMA**2]
    whole = q_windows.windowed_runs(z, dt, r, 5.0, 31)
    if whole is None:
        pytest.skip("the compiled loops are unavailable")
    for b in range(5):
        steps = 150 if b == 1 else 200
        alone = q_windows.windowed_runs(z[b : b + 1, :steps], dt[b : b + 1, :steps], r, 5.0, 31)
        assert alone is not None
        assert_close(alone.weights[:, 0], whole.weights[:, b, :steps], rtol=1e-12, atol=1e-12)
        assert_close(alone.runs.mean[0], whole.runs.mean[b, :steps], rtol=1e-12, atol=1e-9)
        assert_close(alone.factor[0], whole.factor[b], rtol=1e-12, atol=0.0)


@pytest.mark.parametrize("window", [2, 1, 0, 3.0, True, "9"])
def test_q_window_must_be_an_odd_count_of_steps(window):
    with pytest.raises(ValueError, match="q_window: expected an odd number of steps >= 3"):
        Settings("ks", q_window=window)


def _table(z: torch.Tensor, dt: torch.Tensor) -> pd.DataFrame:
    B, T, _ = z.shape
    time = dt.cumsum(1)
    rows = {
        "track_id": np.repeat([f"t{b}" for b in range(B)], T),
        "time": time.reshape(-1).numpy(),
        "x": z[..., 0].reshape(-1).numpy(),
        "y": z[..., 1].reshape(-1).numpy(),
    }
    frame = pd.DataFrame(rows)
    return frame[~frame["x"].isna()].reset_index(drop=True)


def test_track_runs_the_window_the_sample_chose():
    """``track``'s settings for the Kalman smoother carry the window where SURE chose one (not
    for the SVSS nor the filter); its estimates are the composite's, its summary names the
    window, its estimated error is the composite's SURE, and with covariances the means are
    unchanged and each step's covariance is the weighted mixture of the factors' passes'."""
    z, truth, dt = _maneuvering(B=6, T=300, seed=3, gaps=0.0)
    data = _table(z, dt)
    plan = plan_tracks(data, Settings("ks"), dtype=torch.float64, precision="float64")
    settings = plan.settings
    assert settings.q_window is not None, "the turns: SURE prefers a window here"
    assert settings.q is not None and settings.meas_var is not None
    svss = replace(settings, estimator="svss", psi=[3.0, 3.0], q_window=None, q_curve=None)
    found = track_table(data, plan)
    table = found.table
    grid = noise.q_factors(settings.q_low)  # (the level flight's steps may want it lower)
    composite = q_windows.windowed_runs(
        z, dt, settings.meas_var, settings.q, settings.q_window, grid
    )
    assert composite is not None
    x = torch.tensor(table["x"].to_numpy()).reshape(6, 300)
    assert_close(x, composite.runs.mean[..., 0], rtol=0, atol=1e-6)
    summary = found.run.summary_json()
    assert summary["settings"]["q_window"] == settings.q_window
    sums = composite.runs.sums
    r = torch.tensor(settings.meas_var, dtype=torch.float64)
    mse = float((sums[..., 0] + 2 * r * sums[..., 1] - r * sums[..., 2]).sum() / sums[..., 2].sum())
    assert summary["estimated_position_rmse"] == pytest.approx(math.sqrt(2 * mse), rel=1e-4)
    with_cov = track_table(data, plan, covariance=True).table
    assert_close(
        torch.tensor(with_cov["x"].to_numpy()), torch.tensor(table["x"].to_numpy()),
        rtol=0, atol=1e-6,
    )  # fmt: skip
    cov_xx = torch.tensor(with_cov["cov_x_x"].to_numpy()).reshape(6, 300)
    z64, dt64, r64, prior = noise.curve_inputs(z, dt, settings.meas_var)
    mixture = torch.zeros(6, 300, dtype=torch.float64)
    for k, f in enumerate(grid):
        one = noise.kalman_positions(z64, dt64, prior.x0, prior.P0, r64, settings.q * f)
        spread = (one.mean[..., 0] - composite.runs.mean[..., 0]).square()
        mixture += composite.weights[k] * (one.var[..., 0] + spread)
    assert_close(cov_xx, mixture, rtol=1e-6, atol=1e-6)
    # the window is the Kalman smoother's alone
    tracks = RecordedTracks(z, dt, dt.cumsum(1), torch.full((6,), 300), [f"t{b}" for b in range(6)])
    assert with_q_curve(replace(settings, q_curve=None), tracks).q_window == settings.q_window
    assert with_q_curve(svss, tracks).q_window is None
    kf = replace(settings, estimator="kf", q_window=None, q_curve=None)
    assert with_q_curve(kf, tracks).q_window is None
    assert asdict(Settings(**asdict(settings))) == asdict(settings)


def test_the_command_line_names_the_window_and_turns_it_off(tmp_path, capsys):
    """``torchsvs track``: the default prints the window it chose and saves it in the summary;
    ``--no-step-q`` runs each track with its own ``q`` (as the summary's settings say)."""
    import json

    from torchsvs.cli import main

    z, _, dt = _maneuvering(B=6, T=300, seed=3, gaps=0.0)
    source = tmp_path / "in.csv"
    _table(z, dt).to_csv(source, index=False)
    main(["track", str(source), "-o", str(tmp_path / "w.csv"), "--estimator", "ks"])
    printed = capsys.readouterr()
    summary = json.loads((tmp_path / "w.summary.json").read_text())
    window = summary["settings"]["q_window"]
    assert window is not None
    assert (
        f"q per step: the factors' passes weighted by their SURE over {window} steps"
        in printed.out + printed.err
    )
    main(["track", str(source), "-o", str(tmp_path / "t.csv"), "--estimator", "ks", "--no-step-q"])
    printed = capsys.readouterr()
    summary = json.loads((tmp_path / "t.summary.json").read_text())
    assert summary["settings"]["q_window"] is None and summary["settings"]["step_q"] is False
    assert "q per track:" in printed.out + printed.err


def test_a_window_is_kept_only_where_it_wins_across_the_noise_reading():
    """SURE weighs the divergence by the noise: a window the reading prefers is refused where a
    noise level within the reading's interval prefers each track's own ``q``. Judged on the
    composite's own sums, against a rival whose residuals are larger and divergence smaller
    (it wins at high noise only)."""
    z, _, dt = _maneuvering(B=6, T=300, seed=3, gaps=0.0)
    r = [SIGMA**2, SIGMA**2]
    q = 5.0

    def choose(found: noise.QCurves) -> torch.Tensor:
        return noise.track_q_factors(found, found.pooled())

    _, _, own = noise.q_curve_runs(z, dt, r, q, choose=choose, keep=True)
    assert own is not None
    window = q_windows.choose_window(z, dt, r, q, own)
    if window is None:
        pytest.skip("the compiled loops are unavailable")
    sums = q_windows.window_sums(z, dt, r, q, [window])
    assert sums is not None
    composite = q_windows.windowed_runs(z, dt, r, q, window)
    assert composite is not None
    assert_close(sums[0], composite.runs.sums.sum((0, 1)), rtol=1e-12, atol=1e-6)
    assert q_windows.choose_window(z, dt, r, q, own, noise_range=(r, r)) == window
    rival = sums[0].clone()
    rival[:, 0] *= 1.05  # residuals 5% above the window's
    rival[:, 1] *= 0.9  # a tenth less divergence
    assert float(q_windows.sure_of(sums[0], r)) < float(q_windows.sure_of(rival, r))
    rival_run = own._replace(sums=rival.reshape(1, 1, 2, 3))
    assert q_windows.choose_window(z, dt, r, q, rival_run) == window
    high = [100 * v for v in r]
    assert q_windows.choose_window(z, dt, r, q, rival_run, noise_range=(r, high)) is None


def test_the_per_step_risk_is_the_step_terms_sure():
    """The compiled pass's per-step SURE the weights are read from (the first two
    observations' divergence from the tangents) equals the one summed from :func:`step_terms`,
    with gaps, an axis seen once and one never seen."""
    z, _, dt = _maneuvering(B=4, T=120, seed=4, gaps=0.2)
    z[1, :, 1] = math.nan
    z[1, 40, 1] = 500.0  # one observation on that axis
    z[2, :, 0] = math.nan  # an axis never seen
    r = [SIGMA**2, SIGMA**2]
    z64, dt64, rr, prior = noise.curve_inputs(z, dt, r)
    risk = torch.full(z64.shape[:2], math.nan, dtype=z64.dtype)
    found = noise.kalman_positions(z64, dt64, prior.x0, prior.P0, rr, 20.0, True, 32, risk)
    if found.step_risk is None:
        pytest.skip("the compiled loops are unavailable")
    residual, divergence, count = q_windows.step_terms(z64, found, rr)
    expected = (residual + 2 * rr * divergence - rr * count).sum(-1)
    assert_close(risk, expected, rtol=1e-12, atol=1e-8)
    assert bool((risk[torch.isnan(z64).all(-1)] == 0).all())


def test_the_blends_divergence_is_its_derivative_with_the_weights_held():
    """The composite's divergence (its ``var`` over ``r``, and at an axis's first observation
    its blended tangent) is the blended estimate's derivative by the step's own measurement with
    the weights held, by finite differences: at a step inside a track and at the first
    observation, which the two-point prior reads."""
    z, _, dt = _maneuvering(B=2, T=150, seed=5, gaps=0.05)
    r = [SIGMA**2, SIGMA**2]

    def blend(zz, weight=None):
        z64, dt64, rr, prior = noise.curve_inputs(zz, dt, r)
        found = q_windows._factor_passes(z64, dt64, prior, rr, 5.0, noise.Q_FACTORS)
        if found is None:
            pytest.skip("the compiled loops are unavailable")
        if weight is None:
            weight = q_windows.window_weights(found.risk, 21, SIGMA**2)
        return q_windows._composite(found, weight), weight

    base, weight = blend(z)
    assert weight.std(0).max() > 0.1, "the weights blend more than one pass"
    first = int((~torch.isnan(z[1, :, 0])).nonzero()[0])
    for t, expected in ((70, base.var[1, 70, 0] / SIGMA**2), (first, base.first_two[1, 0, 0])):
        moved = z.clone()
        moved[1, t, 0] += 1e-3
        shifted, _ = blend(moved, weight)
        derivative = (shifted.mean[1, t, 0] - base.mean[1, t, 0]) / 1e-3
        assert_close(derivative, expected, rtol=1e-5, atol=1e-7)


def test_a_windowed_plan_travels_by_pickle_and_splits_as_one_table():
    """An engine (Spark, Dask, ``--processes``) broadcasts the plan as a pickle and runs it on
    parts of the tracks: with a window of ``q``, the copy over three parts gives the estimates
    and error terms of one table."""
    import pickle

    z, _, dt = _maneuvering(B=9, T=200, seed=6, gaps=0.02)
    data = _table(z, dt)
    plan = plan_tracks(data, Settings("ks"), dtype=torch.float64, precision="float64")
    assert plan.settings.q_window is not None
    whole = track_table(data, plan)
    copy = pickle.loads(pickle.dumps(plan))
    part_of = data["track_id"].map(lambda i: int(i[1:]) % 3)
    parts = [track_table(data[part_of == p], copy, check=False) for p in range(3)]
    joined = pd.concat([p.table for p in parts]).sort_values(["track_id", "time"], kind="stable")
    expected = whole.table.sort_values(["track_id", "time"], kind="stable")
    pd.testing.assert_frame_equal(
        joined.reset_index(drop=True), expected.reset_index(drop=True), check_exact=True
    )
    squares = sum(
        p.run.summary_json()["estimated_position_rmse"] ** 2 * p.run.summary_json()["points"]
        for p in parts
    )
    one = whole.run.summary_json()
    assert math.sqrt(squares / one["points"]) == pytest.approx(
        one["estimated_position_rmse"], rel=1e-9
    )


def _parked_and_moving(parked: int = 6, moving: int = 6, T: int = 240, seed: int = 0):
    """A table of cars at 1 s reports, σ 5 m: ``parked`` standing still, ``moving`` driving
    (white acceleration, 1 m²/s³), ids ``P..``/``C..``; and the truth's positions."""
    gen = np.random.default_rng(seed)
    frames, truth = [], []
    for k in range(parked + moving):
        if k < parked:
            path = np.repeat(gen.normal(0, 500, (1, 2)), T, axis=0)
        else:
            v = np.cumsum(gen.normal(0, 1.0, (T, 2)), axis=0) + gen.normal(0, 10, 2)
            path = np.cumsum(v, axis=0)
        z = path + gen.normal(0, 5.0, path.shape)
        name = f"{'P' if k < parked else 'C'}{k:02d}"
        frames.append(
            pd.DataFrame({"id": name, "t": np.arange(T, dtype=float), "x": z[:, 0], "y": z[:, 1]})
        )
        truth.append(path)
    return pd.concat(frames, ignore_index=True), np.concatenate(truth)


def test_still_targets_among_moving_ones_reach_below_the_grid(monkeypatch):
    """Parked cars among moving ones: their own SURE is least at the grid's lowest factor
    (1/30 of the file's q, the moving cars'), so the file's grid reaches lower (q_low) and
    they are estimated closer to the truth; the moving cars as before; a file of moving cars
    alone keeps the grid."""
    from torchsvs.datasets import Columns
    from torchsvs.fitting import defaults

    frame, truth = _parked_and_moving()
    columns = Columns("id", "t")

    def errors(plan):
        out = track_table(frame, plan).table
        err = np.hypot(out["x"].to_numpy() - truth[:, 0], out["y"].to_numpy() - truth[:, 1])
        still = frame["id"].str.startswith("P").to_numpy()
        return np.sqrt(np.mean(err[still] ** 2)), np.sqrt(np.mean(err[~still] ** 2))

    low = plan_tracks(frame, Settings(estimator="ks"), columns=columns)
    assert low.settings.q_low and len(low.settings.q_curve) == len(noise.q_factors(True))
    monkeypatch.setattr(defaults, "LOW_EDGE_SHARE", 2.0)  # (never: the grid as it was)
    grid = plan_tracks(frame, Settings(estimator="ks"), columns=columns)
    assert not grid.settings.q_low
    (still_low, moving_low), (still_grid, moving_grid) = errors(low), errors(grid)
    assert still_low < 0.8 * still_grid
    assert moving_low == pytest.approx(moving_grid, rel=0.02)
    monkeypatch.undo()
    cars = frame[frame["id"].str.startswith("C")]
    assert not plan_tracks(cars, Settings(estimator="ks"), columns=columns).settings.q_low


def test_wants_lower_q_counts_positions_at_the_lowest_factor():
    """Tracks whose own curve is least at the lowest factor and below the next, weighed by
    their scored positions, against LOW_EDGE_SHARE."""
    from torchsvs.fitting.defaults import LOW_EDGE_SHARE, wants_lower_q

    F = len(noise.Q_FACTORS)
    falling = torch.linspace(1.0, 2.0, F)  # least at the lowest factor
    rising = falling.flip(0)
    flat = torch.ones(F)  # least at the lowest too, but not below the next
    risk = torch.stack([falling, rising, flat], 1)
    share = LOW_EDGE_SHARE
    counts = torch.tensor([share * 100, 50 - share * 100, 50.0], dtype=torch.float64)
    assert wants_lower_q(noise.QCurves(risk.double() * counts, counts))  # exactly the share
    counts[0] = share * 90
    assert not wants_lower_q(noise.QCurves(risk.double() * counts, counts))


def _stop_and_go(tracks: int = 4, seed: int = 0):
    """Cars at 1 s reports, σ 5 m, each parked 200 s, driving 200 s (10 m/s, turning gently),
    parked 200 s; the table, the truth and which rows are parked."""
    gen = np.random.default_rng(seed)
    frames, truth, still = [], [], []
    t = np.arange(600.0)
    for k in range(tracks):
        heading = gen.uniform(0, 2 * math.pi) + 0.002 * np.clip(t - 200, 0, 200) ** 1.5 / 10
        speed = np.where((t >= 200) & (t < 400), 10.0, 0.0)
        step = np.stack([speed * np.cos(heading), speed * np.sin(heading)], 1)
        path = gen.normal(0, 500, 2) + np.cumsum(step, axis=0)
        z = path + gen.normal(0, 5.0, path.shape)
        frames.append(pd.DataFrame({"id": f"G{k}", "t": t, "x": z[:, 0], "y": z[:, 1]}))
        truth.append(path)
        still.append(speed == 0)
    return pd.concat(frames, ignore_index=True), np.concatenate(truth), np.concatenate(still)


def test_tracks_that_stop_reach_below_the_grid_at_their_still_steps(monkeypatch):
    """Cars that park between drives: no track's own curve wants less than the grid offers,
    but with q per step the still steps weigh the lowest factor most; where they are 5% of the
    steps the grid reaches lower, and the parked steps are estimated closer to the truth."""
    from torchsvs.datasets import Columns
    from torchsvs.fitting import defaults

    frame, truth, still = _stop_and_go()
    columns = Columns("id", "t")

    def still_error(plan):
        out = track_table(frame, plan).table
        err = np.hypot(out["x"].to_numpy() - truth[:, 0], out["y"].to_numpy() - truth[:, 1])
        return float(np.sqrt(np.mean(err[still] ** 2)))

    low = plan_tracks(frame, Settings(estimator="ks"), columns=columns)
    assert low.settings.q_low and low.settings.q_window is not None
    monkeypatch.setattr(defaults, "LOW_EDGE_SHARE", 2.0)  # (never: the grid as it was)
    grid = plan_tracks(frame, Settings(estimator="ks"), columns=columns)
    assert not grid.settings.q_low
    assert still_error(low) < 0.97 * still_error(grid)  # (measured: 1.61 against 1.71 m)


def _three_axes(vertical_noise: float, seed: int = 0, tracks: int = 8, T: int = 300):
    """Tracks at 1 s reports turning in the horizontal (σ 5 m) at a level altitude of noise
    ``vertical_noise``."""
    gen = np.random.default_rng(seed)
    frames = []
    t = np.arange(float(T))
    for k in range(tracks):
        heading = gen.uniform(0, 2 * math.pi) + 0.03 * np.sin(t / 30.0) * 30.0
        path = np.cumsum(np.stack([60 * np.cos(heading), 60 * np.sin(heading)], 1), axis=0)
        alt = np.full(T, 3000.0)
        z = np.column_stack([path, alt]) + gen.normal(0, 1, (T, 3)) * [5, 5, vertical_noise]
        frames.append(
            pd.DataFrame({"id": f"A{k}", "t": t, "x": z[:, 0], "y": z[:, 1], "z": z[:, 2]})
        )
    return pd.concat(frames, ignore_index=True)


def test_axes_that_want_q_a_decade_apart_are_named():
    """3-D tracks turning in the horizontal at a level, noisy altitude: the axes alone want
    q's a decade apart, the settings say so (axis_q) and the run warns; a file whose three
    axes move alike gets no warning."""
    from torchsvs.datasets import Columns

    columns = Columns("id", "t", position=("x", "y", "z"))
    plan = plan_tracks(_three_axes(50.0), Settings(estimator="ks"), columns=columns)
    apart = plan.settings.axis_q
    assert apart is not None and max(apart) >= 10 * min(apart)
    assert apart[2] == min(apart)  # the level altitude wants the least
    out = track_table(_three_axes(50.0), plan)
    assert any("axes alone want process noises far apart" in w for w in out.run.warnings)
    alike = _three_axes(5.0).rename(columns={"z": "w"})
    alike["z"] = alike["x"] * 0.5 + alike["y"] * 0.5  # a third axis moving as the others
    alike = alike.drop(columns=["w"])
    assert plan_tracks(alike, Settings(estimator="ks"), columns=columns).settings.axis_q is None


def test_a_lower_grid_is_kept_only_where_the_samples_sure_is_lower(monkeypatch):
    """checked_low returns, of the widened grid and the grid as it was, the one whose SURE on
    the sample (as the run runs) is lower: the widened for parked cars among moving ones;
    forced on moving cars alone, whichever SURE says."""
    from torchsvs.datasets import Columns
    from torchsvs.datasets.tables import block_of
    from torchsvs.datasets.tracks import padded_batch
    from torchsvs.fitting import defaults
    from torchsvs.fitting.defaults import complete_settings
    from torchsvs.sample_accuracy import checked_low, sample_terms

    frame, _ = _parked_and_moving()
    for rows, force in ((frame, False), (frame[frame["id"].str.startswith("C")], True)):
        block = block_of(rows, Columns("id", "t"))
        tracks = padded_batch(block.steps, np.arange(block.steps.num_tracks))
        settings = complete_settings(Settings(estimator="ks"), tracks)
        if force:
            monkeypatch.setattr(defaults, "wants_lower_q", lambda curves: True)
        wide = with_q_curve(settings, tracks)
        monkeypatch.undo()
        assert wide.q_low
        narrow = with_q_curve(replace(settings, q_low=False), tracks, widen=False)
        kept = checked_low(wide, tracks)
        mse = {s.q_low: sample_terms(s, tracks).mse(settings.meas_var)[0] for s in (wide, narrow)}
        assert kept.q_low == (mse[True] < mse[False])
        if not force:
            assert kept.q_low  # parked cars: the lower grid surely helps
