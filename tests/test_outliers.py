"""Isolated outliers (``torchsvs.fitting.outliers``): the studentized residual against its
leave-one-out definition, what is flagged and what is not, and ``torchsvs track``'s handling."""

from __future__ import annotations

import json
import math

import numpy as np
import pyarrow.csv as pcsv
import pytest
import torch

from torchsvs.cli import main
from torchsvs.datasets import two_point_prior
from torchsvs.filters import KalmanFilter
from torchsvs.fitting.outliers import outlier_distances, screen_outliers
from torchsvs.models import ConstantVelocity
from torchsvs.smoothers import RTSSmoother

SIGMA = 20.0


def _tracks(
    tracks: int = 8, steps: int = 300, seed: int = 0, dt: float = 1.0
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Nearly-constant-velocity tracks (q = 1) with Gaussian noise ``SIGMA``: z, dt, truth."""
    gen = torch.Generator().manual_seed(seed)
    velocity = 50.0 + torch.cumsum(torch.randn(tracks, steps, 2, generator=gen), 1) * dt**0.5
    truth = torch.cumsum(velocity * dt, 1)
    z = truth + SIGMA * torch.randn(tracks, steps, 2, generator=gen)
    return z.double(), torch.full((tracks, steps), dt, dtype=torch.float64), truth.double()


def test_distance_is_the_leave_one_out_predictive_test():
    """d² = Σ (z - ẑ₋ₜ)² / (r + H P₋ₜ Hᵀ): the row against the smoother that never saw it, for
    every row checked, from a separate smoother pass with the row missing (same prior)."""
    z, dt, _ = _tracks(tracks=2, steps=40)
    r, q = SIGMA**2, 1.0
    d2 = outlier_distances(z, dt, [r, r], q)
    prior = two_point_prior(z, dt, torch.tensor([r, r], dtype=torch.float64), inflation=1e6)
    smoother = RTSSmoother(KalmanFilter(ConstantVelocity(ndim=2, q=q, r=[r, r]).double()))
    for b, t in [(0, 5), (0, 20), (1, 33), (1, 37)]:
        left = z.clone()
        left[b, t] = math.nan
        with torch.no_grad():
            out = smoother(left, prior.x0, prior.P0, dt=dt)
        mean, var = out.mean[b, t, 0::2], out.cov[b, t].diagonal()[0::2]
        expected = float(((z[b, t] - mean).square() / (r + var)).sum())
        assert d2[b, t].item() == pytest.approx(expected, rel=1e-7)


def test_injected_outliers_are_found_and_clean_rows_kept():
    """10σ outliers at 1 s reports are all found; on 2,400 clean rows nothing is flagged (the
    chance per row is 1e-6)."""
    z, dt, _ = _tracks()
    assert not screen_outliers(z, dt, [SIGMA**2] * 2, 1.0).any()
    gen = torch.Generator().manual_seed(5)
    rows = torch.stack([torch.arange(8), torch.randint(10, 290, (8,), generator=gen)], 1)
    angle = torch.rand(8, generator=gen, dtype=torch.float64) * 2 * math.pi
    bad = z.clone()
    bad[rows[:, 0], rows[:, 1]] += 10 * SIGMA * torch.stack([angle.cos(), angle.sin()], 1)
    found = screen_outliers(bad, dt, [SIGMA**2] * 2, 1.0)
    expected = torch.zeros_like(found)
    expected[rows[:, 0], rows[:, 1]] = True
    assert torch.equal(found, expected)


def test_two_rows_off_together_are_a_maneuver_not_outliers():
    """Two neighbours displaced alike (the target went there) stay; either alone is flagged."""
    z, dt, _ = _tracks(tracks=1)
    jump = torch.tensor([10 * SIGMA, 0.0], dtype=torch.float64)
    pair = z.clone()
    pair[0, 150:152] += jump
    assert not screen_outliers(pair, dt, [SIGMA**2] * 2, 1.0).any()
    single = z.clone()
    single[0, 150] += jump
    assert screen_outliers(single, dt, [SIGMA**2] * 2, 1.0)[0].nonzero().flatten().tolist() == [150]


def test_rows_at_the_ends_are_judged_by_one_side_but_not_across_long_gaps():
    """A track's first and last rows are judged by the path the rows after (before) them make:
    one 20σ off is flagged (they were never judged: the estimate followed them, 114-210 m off
    on probe 4's cars at σ 10 m), two off together are a maneuver; a row across an interval to
    a neighbour over twice the track's median is not judged however far off."""
    z, dt, _ = _tracks(tracks=1)
    jump = torch.tensor([0.0, 20 * SIGMA], dtype=torch.float64)
    for row in (0, 1, 298, 299):
        ends = z.clone()
        ends[0, row] += jump
        found = screen_outliers(ends, dt, [SIGMA**2] * 2, 1.0)[0].nonzero().flatten().tolist()
        assert found == [row]
    for rows in ((0, 1), (298, 299)):
        pair = z.clone()
        pair[0, list(rows)] += jump
        assert not screen_outliers(pair, dt, [SIGMA**2] * 2, 1.0).any(), rows
    gap = z.clone()
    gap[0, 100:110] = math.nan  # 11 s around row 110 (median 1 s)
    gap[0, 110] += jump
    assert not screen_outliers(gap, dt, [SIGMA**2] * 2, 1.0).any()


def test_bad_probability_is_refused():
    z, dt, _ = _tracks(tracks=1, steps=10)
    with pytest.raises(ValueError, match="p_false"):
        screen_outliers(z, dt, [1.0, 1.0], 1.0, p_false=0.0)


def _write(path, z: torch.Tensor, dt: float = 1.0) -> None:
    lines = ["track_id,time,x,y"]
    for b in range(z.shape[0]):
        for t in range(z.shape[1]):
            lines.append(f"k{b},{t * dt:.1f},{z[b, t, 0]:.4f},{z[b, t, 1]:.4f}")
    path.write_text("\n".join(lines) + "\n")


def test_track_sets_outliers_aside_flags_and_counts_them(tmp_path, capsys):
    """``track`` (KS, noise read off the data) flags the injected outliers in the ``outlier``
    column, counts them in the summary, keeps the error estimate honest, and is closer to the
    truth than with ``--keep-outliers`` (which writes no such column)."""
    z, _, truth = _tracks(tracks=6, steps=200, seed=3)
    bad = z.clone()
    rows = [(b, 20 + 30 * b) for b in range(6)] + [(b, 150) for b in range(6)]
    for b, t in rows:
        bad[b, t, 0] += 12 * SIGMA
    src = tmp_path / "in.csv"
    _write(src, bad)
    errors = {}
    for mode in ("screened", "kept"):
        out = tmp_path / f"{mode}.csv"
        extra = ["--keep-outliers"] if mode == "kept" else []
        main(["track", str(src), "-o", str(out), "--estimator", "ks", *extra])
        table = pcsv.read_csv(out)
        est = np.stack([table.column("x").to_numpy(), table.column("y").to_numpy()], 1)
        true = truth.reshape(-1, 2).numpy()
        errors[mode] = float(np.sqrt(np.mean(np.sum((est - true) ** 2, 1))))
        summary = json.loads(out.with_suffix(".summary.json").read_text())
        if mode == "screened":
            flags = table.column("outlier").to_numpy(zero_copy_only=False).reshape(6, 200)
            assert sorted(map(tuple, np.argwhere(flags).tolist())) == sorted(rows)
            assert summary["rows"]["outliers"] == len(rows)
            assert summary["points"] == 6 * 200 - len(rows)
            true_rmse = errors[mode]
            assert summary["estimated_position_rmse"] == pytest.approx(true_rmse, rel=0.25)
            # 1% of the positions grossly off: the run says the estimate may miss such a
            # sensor's other errors
            gross = [w for w in summary["warnings"] if w.startswith("measurements: 12 ")]
            assert len(gross) == 1 and "counts white noise only" in gross[0]
        else:
            assert "outlier" not in table.column_names
            assert "outliers" not in summary["rows"]
    assert errors["screened"] < 0.9 * errors["kept"]
    assert "note, outliers: 12 (" in capsys.readouterr().err


def test_rows_among_others_as_far_off_are_not_isolated():
    """A stretch where every row is 6σ-noisy (a sensor in a bad patch, or motion the model
    cannot follow) is judged against its own level (``LOCAL``), not flagged row by row."""
    z, dt, _ = _tracks(tracks=4, seed=2)
    gen = torch.Generator().manual_seed(9)
    noisy = z.clone()
    noisy[:, 100:140] += 6 * SIGMA * torch.randn(4, 40, 2, generator=gen, dtype=torch.float64)
    assert not screen_outliers(noisy, dt, [SIGMA**2] * 2, 1.0).any()


def test_clipped_sure_reads_q_as_if_the_outliers_were_not_there():
    """1% of 10σ outliers drive SURE's ``q`` up (3-18× on these tracks); with each term clipped
    at 25 r (the screen's first reading, ``SCREEN_CLIP``) it stays within a factor 1.5 of the
    clean data's (measured 0.72-0.80×: an outlier still pulls its neighbours), and on clean
    data it is SURE's own. The screen reads ``q`` again without the outliers it found."""
    from torchsvs.fitting.defaults import SCREEN_CLIP
    from torchsvs.fitting.noise import smoother_q

    for seed in (4, 5):
        z, dt, _ = _tracks(tracks=8, steps=600, seed=seed)
        r = torch.tensor([SIGMA**2] * 2, dtype=torch.float64)
        clean = smoother_q(z, dt, r).q
        assert smoother_q(z, dt, r, clip=SCREEN_CLIP).q == clean
        gen = torch.Generator().manual_seed(seed)
        hit = torch.rand(z.shape[:2], generator=gen) < 0.01
        angle = torch.rand(z.shape[:2], generator=gen, dtype=torch.float64) * 2 * math.pi
        bad = z + (10 * SIGMA * hit)[..., None] * torch.stack([angle.cos(), angle.sin()], -1)
        assert smoother_q(bad, dt, r).q > 2 * clean
        assert abs(math.log(smoother_q(bad, dt, r, clip=SCREEN_CLIP).q / clean)) < math.log(1.5)


def _mixed(seed: int, tracks: int = 40, steps: int = 120) -> tuple[torch.Tensor, torch.Tensor]:
    """Tracks at irregular intervals with 10σ outliers, pairs of them, a noisy stretch, missing
    rows and axes, short tracks and long gaps: what the screen's shortcuts must not change."""
    z, _, _ = _tracks(tracks=tracks, steps=steps, seed=seed)
    gen = torch.Generator().manual_seed(seed + 100)
    dt = (0.5 + 2.0 * torch.rand(tracks, steps, generator=gen)).double()
    dt[::7, 60] = 40.0
    hit = torch.rand(tracks, steps, generator=gen) < 0.03
    z[..., 0] += 10 * SIGMA * hit
    z[::6, 30:32, 1] += 12 * SIGMA
    z[::5, 80:100] += 6 * SIGMA * torch.randn(len(range(0, tracks, 5)), 20, 2, generator=gen)
    z[torch.rand(tracks, steps, generator=gen) < 0.1] = math.nan
    z[::9, 10:50, 1] = math.nan
    z[torch.arange(steps) >= torch.randint(1, steps + 1, (tracks, 1), generator=gen)] = math.nan
    return z, dt


def test_screen_of_a_batch_is_each_tracks_own():
    """Tracks are judged apart, so later rounds run on the tracks that changed only: the flags
    of a batch are those of each track screened alone (and some are flagged)."""
    z, dt = _mixed(1)
    found = screen_outliers(z, dt, [SIGMA**2] * 2, 1.0)
    alone = torch.cat([screen_outliers(z[b : b + 1], dt[b : b + 1], [SIGMA**2] * 2, 1.0)
                       for b in range(len(z))])  # fmt: skip
    assert found.sum() > 10
    assert torch.equal(found, alone)


def test_local_median_and_largest_nearby_are_those_of_the_judged_neighbours():
    """At every judged row, the windows' median (row left out) and maximum (row in) against
    the judged rows listed track by track; the χ² tail test against the tail computed at every
    row with that median."""
    from torchsvs.fitting.outliers import CHI2_MEDIAN, _largest_nearby, _local_median, _tail_below

    z, dt = _mixed(2)
    d2 = outlier_distances(z, dt, [SIGMA**2] * 2, 10.0)
    at = (~torch.isnan(d2)).nonzero(as_tuple=True)
    median = _local_median(d2, 5, at)
    largest = _largest_nearby(d2, 2, ~torch.isnan(d2))
    scale = torch.full_like(d2, math.nan)
    for i, (b, t) in enumerate(zip(*(x.tolist() for x in at), strict=True)):
        rows = (~torch.isnan(d2[b])).nonzero().flatten().tolist()
        j = rows.index(t)
        near = sorted(d2[b, rows[max(j - 5, 0) : j] + rows[j + 1 : j + 6]].tolist())
        expected = near[(len(near) - 1) // 2] if near else math.nan
        assert median[i].item() == expected or (math.isnan(expected) and median[i].isnan())
        scale[b, t] = expected
        assert largest[b, t].item() == max(d2[b, rows[max(j - 2, 0) : j + 3]].tolist())
    tail = torch.special.gammaincc(
        torch.tensor(1.0, dtype=torch.float64), d2 / (scale / CHI2_MEDIAN[2]).clamp_min(1.0) / 2
    )
    for p in (1e-6, 1e-3, 0.2):
        assert torch.equal(_tail_below(d2, 2, p), tail < p)
    assert (tail < 1e-3).any()


def test_gross_errors_are_warned_of_above_a_thousand_times_their_chance():
    from torchsvs.datasets import RowReport
    from torchsvs.estimate_warnings import gross_errors
    from torchsvs.fitting.outliers import GROSS_ERROR_COUNT, GROSS_ERROR_SHARE

    def report(outliers: int, measured: int) -> RowReport:
        found = RowReport(total=measured, measurement=measured)
        found.notes["outliers"] = outliers
        return found

    assert gross_errors(RowReport(total=100, measurement=100)) is None  # no screen ran
    assert gross_errors(report(0, 5000)) is None
    limit = int(GROSS_ERROR_SHARE * 100_000)
    assert gross_errors(report(limit, 100_000)) is None  # at the share: not above it
    assert "101 positions (0.10%)" in (gross_errors(report(limit + 1, 100_000)) or "")
    # a few outliers in a small file are not a faulty sensor
    assert gross_errors(report(GROSS_ERROR_COUNT - 1, 100)) is None
    assert gross_errors(report(GROSS_ERROR_COUNT, 100)) is not None
    assert gross_errors(report(7, 10_000_000)) is None  # a clean 10 M-row run's count


def test_a_grossly_erring_sensor_runs_the_svsf_family_as_its_kalman_twin(tmp_path, capsys):
    """Where the screen sets aside more than 0.1% of the positions (here 1%, 12σ off), the
    SVSF family's layer is not kept and nothing is compared: ``svss`` runs as the Kalman
    smoother and says why, and ``auto`` skips it so. Two outliers (below the count) are no
    faulty sensor: the ordinary layer check runs."""
    z, _, _ = _tracks(tracks=6, steps=200, seed=3)
    for count, gross in ((12, True), (2, False)):
        bad = z.clone()
        for k in range(count):
            bad[k % 6, 20 + 13 * k, 0] += 12 * SIGMA
        src = tmp_path / f"in{count}.csv"
        _write(src, bad)
        for estimator in ("svss", "auto"):
            out = tmp_path / f"{estimator}{count}.csv"
            main(["track", str(src), "-o", str(out), "--estimator", estimator])
            said = capsys.readouterr().err
            summary = json.loads(out.with_suffix(".summary.json").read_text())
            assert ("the sensor errs grossly" in said) == gross, (estimator, count)
            if estimator == "svss" and gross:
                assert summary["estimator"] == "ks"
                assert summary["settings"]["chosen_from"] == ["svss", "ks"]
                assert "(12 of the settings' sample's 1200 positions set aside as outliers)" in said
            if estimator == "auto" and gross:
                rows = {r["estimator"]: r for r in summary["candidates"]}
                assert rows["svss"]["skipped"].startswith("ks here: the sensor errs grossly")
            if not gross:
                assert "svss: the boundary layer's limit" in said


def test_one_wild_row_in_a_small_file_is_set_aside_not_followed(tmp_path):
    """One row 5,000 km off among 300 (three straight tracks of 100 rows, 5 s, σ 20 m): its
    neighbours' clipped SURE terms drove the screen's ``q`` to follow it (3e8), where the
    screen judged no row, left the row 5,000 km off and smoothed nothing (an outside probe: 28.5
    m against 4.3 m clean). The screen then takes the ``q`` the differences read, and judges."""
    gen = np.random.default_rng(810)
    t = np.arange(100) * 5.0
    true = np.concatenate([np.stack([100 * t, 100 * t + 1000 * k], 1) for k in range(3)])
    pos = true + gen.normal(0, 20, true.shape)
    pos[10, 0] += 5e6
    src, out = tmp_path / "in.csv", tmp_path / "out.csv"
    ids = np.repeat(np.arange(3), 100)
    rows = zip(ids, np.tile(t, 3), pos, strict=True)
    lines = [f"{i},{s},{x:.6f},{y:.6f}" for i, s, (x, y) in rows]
    src.write_text("track_id,time,x,y\n" + "\n".join(lines) + "\n")
    main(["track", str(src), "-o", str(out), "--estimator", "ks", "--quiet"])
    table = pcsv.read_csv(out)
    flags = table.column("outlier").to_numpy(zero_copy_only=False)
    assert np.flatnonzero(flags).tolist() == [10]
    est = np.stack([table.column("x").to_numpy(), table.column("y").to_numpy()], 1)
    error = np.hypot(*(est - true).T)
    assert error[10] < 100.0  # (estimated from its neighbours)
    assert float(np.sqrt(np.mean(np.delete(error, 10) ** 2))) < 10.0  # (smoothed: raw 28)


def test_a_sensor_erring_at_two_percent_is_screened_not_followed(tmp_path):
    """2% of the reports 500 m off (cars at 1 Hz turning, σ 8 m): the clipped SURE ``q`` read
    8.6e4 and followed them, a screen at the differences' ``q`` set 883 aside but the SURE
    ``q`` of what it left rose again on the few it missed, and the run set none aside: 71.6 m
    against the measurements' 72.5 (an outside probe). Now the screen keeps to the lower ``q``
    and sets most aside, none of the good rows."""
    gen = np.random.default_rng(52)
    lines, truth, bad = [], [], []
    for k in range(30):
        heading = gen.uniform(0, 2 * np.pi) + np.cumsum(gen.normal(0, 0.05, 400))
        speed = gen.uniform(5, 15)
        path = np.cumsum(speed * np.c_[np.cos(heading), np.sin(heading)], 0)
        noise = gen.normal(0, 8.0, path.shape)
        off = gen.random(400) < 0.02
        angle = gen.uniform(0, 2 * np.pi, int(off.sum()))
        noise[off] += 500.0 * np.c_[np.cos(angle), np.sin(angle)]
        z = path + noise
        lines += [f"{k},{i},{x:.3f},{y:.3f}" for i, (x, y) in enumerate(z)]
        truth.append(path)
        bad.append(off)
    src, out = tmp_path / "in.csv", tmp_path / "out.csv"
    src.write_text("track_id,time,x,y\n" + "\n".join(lines) + "\n")
    main(["track", str(src), "-o", str(out), "--estimator", "ks", "--quiet"])
    table = pcsv.read_csv(out)
    flags = table.column("outlier").to_numpy(zero_copy_only=False).astype(bool)
    off = np.concatenate(bad)
    assert flags[off].mean() > 0.8 and not flags[~off].any()
    est = np.stack([table.column("x").to_numpy(), table.column("y").to_numpy()], 1)
    error = np.hypot(*(est - np.concatenate(truth)).T)
    assert float(np.sqrt(np.mean(error[~off] ** 2))) < 8.0  # (the good rows smoothed)
