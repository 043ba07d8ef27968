"""Each track's noise read off its own positions (torchsvs.datasets.track_noise) and the run's
choice to use it (torchsvs.sample_accuracy.with_track_noise)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
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


def _tensor_reading(z: torch.Tensor, dt: torch.Tensor, meas_var: list[float], monkeypatch):
    """The tensors' fit alone (the compiled one turned off)."""
    import torchsvs.datasets.track_noise as track_noise

    with monkeypatch.context() as patch:
        patch.setattr(track_noise, "_read_compiled", lambda *args: None)
        return track_noise._read(z, dt, meas_var)


def test_the_compiled_reading_is_the_tensor_fits(monkeypatch) -> None:
    """The compiled reading and divided differences (kernels/cpp/track_noise.h) against the
    tensors' (their formulas' home), to the bit: tracks of every length from one position,
    missing positions, irregular and repeated times, maneuvers that set residuals aside, three
    axes; and four positions a track (no stencil of order 4)."""
    import torchsvs.datasets.differences as differences
    from torchsvs.kernels import build

    if build.library() is None:
        pytest.skip("no compiler: the tensors' fit is the only one, tested above")
    g = torch.Generator().manual_seed(5)
    B, T = 300, 90
    z = torch.randn(B, T, 3, generator=g, dtype=torch.float64).cumsum(1) * 0.5
    z += (
        torch.randn(B, T, 3, generator=g, dtype=torch.float64)
        * torch.linspace(1, 20, B).view(B, 1, 1).double()
    )
    z[torch.rand(B, T, 3, generator=g) < 0.05] = math.nan
    lengths = torch.randint(1, T + 1, (B,), generator=g)
    z[torch.arange(T).view(1, T) >= lengths.view(B, 1)] = math.nan
    z[::7, 30:34] += 400.0  # (a jump: residuals beyond the maneuver cutoff)
    dt = 1.0 + 9.0 * torch.rand(B, T, generator=g, dtype=torch.float64)
    dt[::5] = 5.0
    dt[3, 10] = 0.0  # (a repeated time: its stencils are not finite)
    meas_var = [4.0, 9.0, 25.0]
    short = torch.randn(40, 4, 2, generator=g, dtype=torch.float64)
    ones = torch.ones(40, 4, dtype=torch.float64)
    for zs, dts, variances in ((z, dt, meas_var), (short, ones, [1.0, 1.0])):
        tensors = _tensor_reading(zs, dts, variances, monkeypatch)
        compiled = read_track_noise(zs, dts, variances)
        for a, b in ((tensors.log_ratio, compiled.log_ratio), (tensors.se, compiled.se)):
            assert torch.equal(a.nan_to_num(-9.0), b.nan_to_num(-9.0))
        with monkeypatch.context() as patch:
            patch.setattr(differences, "_compiled", lambda *args: None)
            expected = differences.difference_residuals(zs, dts)
        found = differences.difference_residuals(zs, dts)
        assert all(torch.equal(a, b) for a, b in zip(expected, found, strict=True))
    # other orders, up to the fixed arrays' highest; above it the tensors run
    from torchsvs.kernels import track_noise as compiled_noise

    for orders in ((1, 5, 7), (2, 8)):
        with monkeypatch.context() as patch:
            patch.setattr(differences, "_compiled", lambda *args: None)
            expected = differences.difference_residuals(z, dt, orders)
        found = differences.difference_residuals(z, dt, orders)
        assert all(torch.equal(a, b) for a, b in zip(expected, found, strict=True))
        assert set(found.order.unique().tolist()) == set(orders)
    t = dt.cumsum(1)
    assert compiled_noise.residuals(z, t, (2, 8)) is None
    assert compiled_noise.residuals(z, t, (1, 5, 7)) is not None
    read = ~read_track_noise(z, dt, meas_var).log_ratio.isnan()
    assert 0 < int(read.sum()) < B  # (some tracks too short to read)


def test_the_class_search_of_q_is_the_golden_search_of_its_summed_curves() -> None:
    """``class_sure_q`` reads each noise class's tracks and prior once and its grid in one pass
    a class: the q it finds is, bit for bit, the golden search with one pass per value of q
    and nothing kept (the search as first written)."""
    from torchsvs.fitting import defaults, noise
    from torchsvs.fitting.noise_classes import classes_of

    tracks = _tracks(torch.exp(torch.linspace(math.log(5.0), math.log(45.0), 24)).double(), 80)
    settings = Settings("ks", meas_var=[400.0, 400.0], track_noise=[0.0, 0.7])
    parts = [
        (tracks.subset(each.members), each.settings.meas_var)
        for each in classes_of(tracks, np.arange(len(tracks)), settings)
    ]
    assert len(parts) > 3  # (several classes)

    def total(log_q: float) -> float:
        risk = 0.0
        for part, own in parts:
            found = noise.q_curves(part.z, part.dt, own, math.exp(log_q), True, (1.0,))
            risk += float(found.risk.sum())
        return risk

    start = math.log(defaults._sure_q(tracks, [400.0, 400.0], "ks"))
    grid = [start + k * 0.5 * math.log(10.0) for k in range(-8, 3)]
    expected = math.exp(noise._golden_search(total, grid))
    assert defaults.class_sure_q(settings, tracks, [400.0, 400.0], "ks") == expected


def test_a_screen_that_finds_the_same_outliers_again_reads_q_once(monkeypatch) -> None:
    """The screen runs twice (the second at the q read without the first's outliers); where
    it sets aside the same positions, the tracks and so their q are the first's, and q is not
    read again."""
    from torchsvs.fitting import defaults

    tracks = _tracks(torch.full((12,), 10.0, dtype=torch.float64), 120, seed=4)
    z = tracks.z.clone()
    z[2, 40, 0] += 200.0  # (one 20σ outlier)
    tracks = replace(tracks, z=z)
    reads = []
    sure_q = defaults.file_sure_q
    monkeypatch.setattr(defaults, "file_sure_q", lambda *a: reads.append(1) or sure_q(*a))
    settings, clean, flagged = defaults.screened(Settings("ks", meas_var=[100.0, 100.0]), tracks)
    assert bool(flagged[2, 40]) and int(flagged.sum()) == 1 and len(reads) == 1
    assert settings.outlier_q == sure_q(settings, clean, [100.0, 100.0], "ks")


def test_the_compiled_sums_of_the_noise_fit_are_the_tensor_ones(monkeypatch) -> None:
    """The trimmed fit's sums (kernels/cpp/noise_fit.h) against the tensors' (their home) at
    every fit of a jackknife and at one fit of all, on residuals of irregular times, gaps and
    maneuvers (far residuals that set their neighbours aside, at some fits and not others),
    one to three axes, with white acceleration and without: to the last bits (the two sum in
    different orders), and :func:`estimate_noise` as close."""
    import torchsvs.datasets.noise_estimate as ne
    from torchsvs.kernels import build

    if build.library() is None:
        pytest.skip("no compiler: the tensors' sums are the only ones")
    g = torch.Generator().manual_seed(11)
    for m in (1, 2, 3):
        B, T = 60, 80
        z = torch.randn(B, T, m, generator=g, dtype=torch.float64).cumsum(1).cumsum(1) * 0.05
        z += torch.randn(B, T, m, generator=g, dtype=torch.float64) * 3.0
        z[torch.rand(B, T, m, generator=g) < 0.05] = math.nan
        z[::4, 40:43] += 60.0  # (maneuvers: residuals beyond the cutoffs)
        dt = 1.0 + 4.0 * torch.rand(B, T, generator=g, dtype=torch.float64)
        res = ne.difference_residuals(z, dt)
        spans = ne._spans(res)
        group = torch.randint(0, 20, (res.u.numel(),), generator=g)
        seen_far = False
        for white in (False, True):
            d = ne._design(res, m, white, ne.CUTOFF)
            for G, parts in ((1, None), (20, group)):
                r = 9.0 * (1.0 + 0.3 * torch.rand(G, m, generator=g, dtype=torch.float64))
                q = (0.01 * torch.rand(G, generator=g, dtype=torch.float64)) * white
                args = (res, d, spans, r, q, parts, ne.CUTOFF, ne.MANEUVER)
                found = ne._sums(*args, per_order=True)
                with monkeypatch.context() as patch:
                    patch.setattr(ne.compiled_noise, "trimmed_sums", lambda *a: None)
                    expected = ne._sums(*args, per_order=True)
                for a, b in zip(found, expected, strict=True):
                    torch.testing.assert_close(a, b, rtol=1e-12, atol=0.0)
                v = r[:, res.axis] + res.b * q[:, None]
                seen_far |= bool((res.u.square() > ne.MANEUVER**2 * v).any())
        assert seen_far  # (the maneuvers' stencils were set aside, neighbours too)
        with monkeypatch.context() as patch:
            patch.setattr(ne.compiled_noise, "trimmed_sums", lambda *a: None)
            expected = ne.estimate_noise(z, dt)
        found = ne.estimate_noise(z, dt)
        torch.testing.assert_close(found.meas_var, expected.meas_var, rtol=1e-9, atol=0.0)
        torch.testing.assert_close(found.meas_std_se, expected.meas_std_se, rtol=1e-7, atol=0.0)


def _switching(sigmas: tuple[float, float], B: int = 24, steps: int = 240, seed: int = 3):
    """Turning tracks at 1 s measured at ``sigmas[0]`` for their first half, ``sigmas[1]`` after
    (a sensor that changes), and their truth ``[B, T, 2]``."""
    g = torch.Generator().manual_seed(seed)
    turn = (torch.rand(B, 1, generator=g, dtype=torch.float64) - 0.5) * 0.04
    heading = turn * torch.arange(steps, dtype=torch.float64) + 6.28 * torch.rand(B, 1, generator=g)
    velocity = 15.0 * torch.stack([heading.cos(), heading.sin()], -1)
    truth = velocity.cumsum(1)
    sigma = torch.full((steps,), sigmas[0], dtype=torch.float64)
    sigma[steps // 2 :] = sigmas[1]
    noise = torch.randn(B, steps, 2, generator=g, dtype=torch.float64) * sigma.view(1, -1, 1)
    dt = torch.ones(B, steps, dtype=torch.float64)
    steps_of = torch.arange(B * steps).view(B, steps)
    lengths = torch.full((B,), steps, dtype=torch.int64)
    ids = [f"s{b}" for b in range(B)]
    tracks = RecordedTracks(truth + noise, dt, dt.cumsum(1), lengths, ids, steps=steps_of)
    return tracks, truth


def test_noise_that_changes_within_the_tracks_reads_as_a_spread_within_them() -> None:
    """Pieces of tracks whose sensor goes from 5 to 40 m read far apart (``τ`` above
    :data:`WITHIN_SPREAD`), their mean between the two; tracks at one noise, or each at its
    own, read no spread within them."""
    from torchsvs.datasets.track_noise import within_spread
    from torchsvs.fitting.noise_read import WITHIN_SPREAD

    tracks, _ = _switching((5.0, 40.0))
    found = within_spread(tracks.z, tracks.dt, [25.0, 25.0])
    assert found is not None and found.tau > 2 * WITHIN_SPREAD
    assert 0.5 < found.low < 2.0 and 5.0 < found.high < 12.0  # (σ over the 5 m given)
    assert 10.0**2 < 25.0 * found.mean_ratio < 40.0**2
    one, _ = _switching((20.0, 20.0))
    same = within_spread(one.z, one.dt, [400.0, 400.0])
    assert same is not None and same.tau < WITHIN_SPREAD / 2
    sigmas = torch.exp(torch.linspace(math.log(5.0), math.log(45.0), 24, dtype=torch.float64))
    apart = _tracks(sigmas, steps=240)
    between = within_spread(apart.z, apart.dt, [225.0, 225.0])
    assert between is not None and between.tau < WITHIN_SPREAD / 2
    short = _tracks(sigmas, steps=100)  # (no track of two pieces)
    assert within_spread(short.z, short.dt, [225.0, 225.0]) is None


def test_a_run_on_noise_that_changes_within_the_tracks_reads_their_mean_and_says_so(tmp_path):
    """``torchsvs track``'s run on tracks whose sensor goes from 5 to 40 m halfway: the noise is
    the pieces' mean, not the quiet half's (at which the Kalman smoother followed the loud half,
    its estimates 0.99 of the measurements' error and its error estimate 0.14 of the truth),
    the estimates well below the measurements, the error estimate's range holding the truth, and
    the run warns."""
    import pandas as pd

    from torchsvs.datasets import Columns
    from torchsvs.tracking import track_file

    tracks, truth = _switching((5.0, 40.0))
    B, T, _ = tracks.z.shape
    ids = np.repeat(np.array(tracks.ids), T)
    frame = pd.DataFrame(
        {
            "id": ids,
            "t": tracks.time.reshape(-1).numpy(),
            "x": tracks.z[..., 0].reshape(-1).numpy(),
            "y": tracks.z[..., 1].reshape(-1).numpy(),
        }
    )
    source, target = tmp_path / "switching.csv", tmp_path / "out.csv"
    frame.to_csv(source, index=False)
    columns = Columns(track_id="id", time="t")
    run = track_file(source, target, Settings("ks"), columns=columns, progress=False)
    within = run.settings.noise_within
    assert within is not None and within[3] < 7.0  # (the core: the quiet half's 5 m)
    assert run.settings.meas_var is not None and run.settings.meas_var[0] > 15.0**2
    assert any("changes within the tracks" in w for w in run.warnings)
    out = pd.read_csv(target)
    path = truth.reshape(-1, 2).numpy()
    error = np.sqrt(((out[["x", "y"]].to_numpy() - path) ** 2).sum(1).mean())
    raw = np.sqrt(((frame[["x", "y"]].to_numpy() - path) ** 2).sum(1).mean())
    assert error < 0.6 * raw
    found = run.accuracy
    assert found is not None
    low, high = found.interval
    assert low <= error <= high


def test_each_tracks_own_noise_is_not_taken_where_it_leaves_the_smoother_near_the_measurements(
    tmp_path,
):
    """Gliders and survey aircraft at 3-60 s reports, σ 5 m (the held-out benchmark's draw):
    their motion between reports reads as 40 m of noise track by track, and the smoother at
    each track's own was 4.6 times the measurements' error; each track's own noise now stands
    only where the smoother is clearly below the measurements at it, and the run goes to the
    low end of the file's reading instead (1.0 times)."""
    import pandas as pd

    from experiments import recorded_sets as rs
    from torchsvs.tracking import track_file

    bench = rs.build_sets(["irregular"], rows=5000, seed=3, sigmas=[5.0])[0]
    source, target = tmp_path / "irregular.csv", tmp_path / "out.csv"
    bench.measurements.to_csv(source, index=False)
    run = track_file(source, target, Settings("ks"), progress=False)
    assert run.settings.track_noise is None and run.settings.noise_lowered_from is not None
    out = pd.read_csv(target)
    truth = bench.truth.rows
    assert (out["track_id"].astype(str) == truth["track_id"].astype(str)).all()

    def rmse(frame) -> float:
        return float(np.sqrt(((frame[["x", "y"]] - truth[["x", "y"]]) ** 2).sum(axis=1).mean()))

    assert rmse(out) <= 1.02 * rmse(bench.measurements)


def test_tracks_that_repeat_one_position_tell_no_noise_and_no_error(tmp_path):
    """A parked beacon repeats its one position exactly: 40% of a file's tracks doing so made
    the noise read 1e-13 m for 5 m (the differences' Gaussian core is theirs), nothing was
    smoothed (the moving tracks at their measurements' error) and the error estimate was
    1e-11 m. They are left out of reading the noise and of the error estimate, and counted."""
    import pandas as pd

    from torchsvs.datasets import Columns, estimate_noise
    from torchsvs.tracking import track_file

    rng = np.random.default_rng(3)
    steps, rows, truth = 200, [], []
    for b in range(30):
        t = np.arange(steps, dtype=float)
        if b < 12:  # parked: one position, reported exactly
            path = np.repeat(rng.uniform(-1e4, 1e4, (1, 2)), steps, 0)
            z = path.copy()
        else:
            heading = rng.uniform(0, 2 * np.pi) + np.cumsum(rng.normal(0, 0.02, steps))
            path = np.cumsum(10.0 * np.stack([np.cos(heading), np.sin(heading)], 1), 0)
            z = path + rng.normal(0, 5.0, path.shape)
        rows.append(pd.DataFrame({"id": f"k{b}", "t": t, "x": z[:, 0], "y": z[:, 1]}))
        truth.append(path)
    frame = pd.concat(rows, ignore_index=True)
    z = torch.tensor(np.stack([f[["x", "y"]].to_numpy() for f in rows]))
    read = estimate_noise(z, torch.ones(z.shape[:2], dtype=torch.float64))
    assert all(4.5 < v**0.5 < 5.5 for v in read.meas_var.tolist())
    source, target = tmp_path / "parked.csv", tmp_path / "out.csv"
    frame.to_csv(source, index=False)
    run = track_file(
        source, target, Settings("ks"), columns=Columns(track_id="id", time="t"), progress=False
    )
    assert run.report.notes["tracks_still"] == 12
    out = pd.read_csv(target)[["x", "y"]].to_numpy().reshape(30, steps, 2)
    moving = np.sqrt(((out[12:] - np.stack(truth[12:])) ** 2).sum(-1).mean())
    raw = np.sqrt(((z[12:].numpy() - np.stack(truth[12:])) ** 2).sum(-1).mean())
    assert moving < 0.6 * raw
    found = run.accuracy
    assert found is not None
    low, high = found.interval
    assert low <= moving <= high  # (the estimate is the moving tracks')


def _drones_beside_buoys(seed: int = 85):
    """8 drones at 20 Hz and 60 buoys drifting and turning, reported every 5-30 min, all with
    σ 3 m (an outside probe's file): ``(frame, truth [N, 2], drone [N] bool)``."""
    import pandas as pd

    gen = np.random.default_rng(seed)
    parts, truth, drone = [], [], []
    for k in range(8):
        t = np.arange(3000) / 20.0
        heading = gen.uniform(0, 2 * np.pi) + np.cumsum(gen.normal(0, 0.01, len(t)))
        speed = gen.uniform(3, 15)
        path = np.cumsum(speed / 20.0 * np.c_[np.cos(heading), np.sin(heading)], 0)
        parts.append((f"drone{k}", t, path))
        drone.append(np.ones(len(t), bool))
    for k in range(60):
        t = np.cumsum(gen.uniform(300, 1800, 300))
        fine = np.arange(0.0, t[-1] + 60.0, 60.0)
        # (straight for hours, then circling: some pieces read the noise, some the turns)
        rates = gen.uniform(-0.002, 0.002, len(fine) // 840 + 1) * (
            gen.random(len(fine) // 840 + 1) < 0.6
        )
        turn = np.repeat(rates, 840)[: len(fine)]
        heading = gen.uniform(0, 2 * np.pi) + np.cumsum(turn * 60.0)
        step = gen.uniform(2, 8) * 60.0 * np.c_[np.cos(heading), np.sin(heading)]
        path = np.cumsum(step, 0)
        path = np.c_[np.interp(t, fine, path[:, 0]), np.interp(t, fine, path[:, 1])]
        parts.append((f"buoy{k}", t, path))
        drone.append(np.zeros(len(t), bool))
    frames = []
    for name, t, path in parts:
        z = path + gen.normal(0, 3.0, path.shape)
        frames.append(pd.DataFrame({"id": name, "t": t, "x": z[:, 0], "y": z[:, 1]}))
        truth.append(path)
    return pd.concat(frames, ignore_index=True), np.concatenate(truth), np.concatenate(drone)


def test_pieces_of_another_kind_do_not_set_every_tracks_noise(tmp_path):
    """Drones beside buoys whose turns between reports 5-30 min apart read as 100 times the
    noise in some pieces: the pieces' mean (338 m for 3) made the drones run 13 times the
    measurements' error. The Kalman smoother's leave-one-out error is not lower at the mean, so
    the run keeps the file's reading, says so, and the drones come out below their
    measurements."""
    import pandas as pd

    from torchsvs.datasets import Columns
    from torchsvs.tracking import track_file

    frame, truth, drone = _drones_beside_buoys()
    source, target = tmp_path / "both.csv", tmp_path / "out.csv"
    frame.to_csv(source, index=False)
    run = track_file(
        source, target, Settings("ks"), columns=Columns(track_id="id", time="t"), progress=False
    )
    within = run.settings.noise_within
    assert within is not None and within[4] > 10 * within[3]  # (the pieces' mean, far above)
    assert run.settings.meas_var is not None and run.settings.meas_var[0] < 10.0**2
    assert any("kept the file's reading" in w for w in run.warnings)
    out = pd.read_csv(target)
    error = ((out[["x", "y"]].to_numpy() - truth) ** 2).sum(1)
    raw = ((frame[["x", "y"]].to_numpy() - truth) ** 2).sum(1)
    assert error[drone].mean() < 0.7 * raw[drone].mean()
