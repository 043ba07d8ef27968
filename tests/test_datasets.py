"""Recorded tracks: reading, row accounting, padding, priors, noise estimates, streaming."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import torchsvs as ts
from tests.conftest import assert_close, simulate_cv
from torchsvs.datasets import (
    Columns,
    estimate_noise,
    geodesy,
    read_tracks,
    track_blocks,
    two_point_prior,
    write_estimates,
)

DIRTY = """track_id,time,x,y
a,0,0,0
a,2,20.5,9.8
a,1,10,5
a,1,12,5
a,3,abc,15
a,4,,
a,5,50,inf
b7,2020-01-01T00:00:00Z,100,100
b7,2020-01-01T00:00:05Z,105,98
b7,,110,96
,6,1,1
c,1,5,5
d,1,,
d,2,nan,
"""


@pytest.fixture
def dirty(tmp_path):
    path = tmp_path / "dirty.csv"
    path.write_text(DIRTY)
    return path


def test_every_row_has_one_fate(dirty):
    tracks, report = read_tracks(dirty, meas_std=1.0)
    assert report.total == 14
    assert (report.measurement, report.prediction) == (9, 1)
    assert dict(report.set_aside) == {"no_time": 1, "no_track_id": 1, "track_without_position": 2}
    assert report.notes["duplicate_time"] == 1
    assert report.notes["out_of_order"] == 1
    assert report.notes["non_numeric_value"] == 2  # "abc" and "inf"
    assert report.notes["partial_position"] == 2
    assert report.notes["tracks_single_point_axis"] == 1  # c: one position, velocity 0 (wide)
    assert tracks.ids == ["a", "b7", "c"]
    assert tracks.lengths.tolist() == [6, 2, 1]


def test_steps_sort_merge_and_time_parsing(dirty):
    tracks, _ = read_tracks(dirty, meas_std=1.0)
    nan = math.nan
    expected_a = [[0, 0], [11, 5], [20.5, 9.8], [nan, 15], [nan, nan], [50, nan]]
    assert_close(tracks.z[0], torch.tensor(expected_a, dtype=torch.float64))
    assert_close(tracks.dt[0], torch.ones(6, dtype=torch.float64))  # median interval first
    assert_close(tracks.dt[1, :2], torch.tensor([5.0, 5.0], dtype=torch.float64))
    assert tracks.time[1, 0].item() == 1577836800.0  # 2020-01-01T00:00:00Z
    assert bool(torch.isnan(tracks.z[1, 2:]).all()) and bool(torch.isnan(tracks.time[1, 2:]).all())


def test_output_has_every_row_with_its_id_and_time(dirty, tmp_path):
    import pyarrow.csv as pcsv

    tracks, _ = read_tracks(dirty, meas_std=1.0)
    model = ts.models.ConstantVelocity(q=1.0, r=1.0).double()
    out = ts.RTSSmoother(ts.KalmanFilter(model))(tracks.z, tracks.x0, tracks.P0, dt=tracks.dt)
    target = tmp_path / "out.csv"
    write_estimates(tracks, out.mean, target, cov=out.cov)
    table = pcsv.read_csv(
        target,
        convert_options=pcsv.ConvertOptions(column_types={"track_id": "string", "time": "string"}),
    )
    source = pcsv.read_csv(
        dirty,
        convert_options=pcsv.ConvertOptions(column_types={"track_id": "string", "time": "string"}),
    )
    assert table.column("track_id").to_pylist() == source.column("track_id").to_pylist()
    assert table.column("time").to_pylist() == source.column("time").to_pylist()
    assert table.column_names[:6] == ["track_id", "time", "x", "vx", "y", "vy"]
    assert "cov_x_vx" in table.column_names and "cov_vy_vy" in table.column_names
    x = np.array(table.column("x").to_pylist(), dtype=float)
    placed = [0, 1, 2, 3, 4, 5, 6, 7, 8, 11]  # rows 9 (no time), 10 (no id), 12-13 (no position)
    assert np.isfinite(x[placed]).all() and np.isnan(np.delete(x, placed)).all()
    # The two rows at a = 1 share one step and so one estimate.
    assert x[2] == x[3]
    # A row set aside keeps its id and time, with empty estimates.
    no_id = target.read_text().splitlines()[11].split(",")
    assert no_id[:2] == ["", '"6"'] and set(no_id[2:]) == {""}


def test_bad_files_get_clear_errors(tmp_path):
    with pytest.raises(ValueError, match="^path: expected a .csv or .parquet"):
        read_tracks(tmp_path / "tracks.xlsx")
    path = tmp_path / "t.csv"
    path.write_text("id,t,x,y\n1,0,1,1\n")
    with pytest.raises(ValueError, match=r"^columns: \['track_id', 'time'\] not in the file"):
        read_tracks(path)
    tracks, _ = read_tracks(path, Columns(track_id="id", time="t"), meas_std=1.0)
    assert tracks.ids == ["1"]
    with pytest.raises(ValueError, match="^meas_std: expected one standard deviation > 0"):
        read_tracks(path, Columns(track_id="id", time="t"), meas_std=-1.0)


def _interleaved_file(tmp_path, tracks: int = 30, steps: int = 17):
    gen = np.random.default_rng(0)
    rows = ["track_id,time,x,y"]
    for k in range(tracks):
        for t in gen.permutation(steps):
            rows.append(f"id{k},{t * 2.5},{k + t * 3.0 + gen.normal()},{-t + gen.normal()}")
    path = tmp_path / "many.csv"
    path.write_text("\n".join(rows) + "\n")
    return path


def test_streaming_blocks_equal_the_whole_file(tmp_path):
    path = _interleaved_file(tmp_path)
    whole = next(track_blocks(path, whole=True)).steps
    blocks = list(track_blocks(path, block_rows=40))
    assert len(blocks) > 5
    assert [i for b in blocks for i in b.steps.ids] == whole.ids
    assert_close(np.concatenate([b.steps.position for b in blocks]), whole.position)
    assert sum(b.steps.report.total for b in blocks) == whole.report.total


def test_streaming_refuses_split_tracks(tmp_path):
    path = tmp_path / "split.csv"
    path.write_text("track_id,time,x,y\na,0,0,0\nb,0,1,1\na,1,1,1\n")
    with pytest.raises(ValueError, match="^track 'a': its rows are not contiguous"):
        list(track_blocks(path))
    assert next(track_blocks(path, whole=True)).steps.ids == ["a", "b"]


def test_padding_does_not_change_any_estimate(tmp_path):
    """A padded batch gives each track the estimates it gets alone, for filters and smoothers."""
    tracks, _ = read_tracks(_interleaved_file(tmp_path, tracks=4, steps=9), meas_std=1.0)
    short = torch.tensor([9, 5, 7, 3])
    z = tracks.z.clone()
    for b, L in enumerate(short.tolist()):
        z[b, L:] = float("nan")  # as if padded after L steps
    model = ts.models.ConstantVelocity(q=0.5, r=1.0).double()
    estimators = {
        "KS": ts.RTSSmoother(ts.KalmanFilter(model)),
        "SVSS": ts.SVSS(ts.SVSF(model, psi=3.0, gamma=0.1), lag=2),
    }
    for name, est in estimators.items():
        batch = est(z, tracks.x0, tracks.P0, dt=tracks.dt)
        for b, L in enumerate(short.tolist()):
            alone = est(z[b, :L], tracks.x0[b], tracks.P0[b], dt=tracks.dt[b, :L])
            assert_close(batch.mean[b, :L], alone.mean, msg=name)
            assert_close(batch.cov[b, :L], alone.cov, msg=name)


def test_two_point_prior_is_the_two_point_estimate_and_its_covariance():
    """Monte Carlo over the noise: the prior's mean is unbiased and its covariance is
    ``inflation`` times the empirical one."""
    gen = torch.Generator().manual_seed(0)
    runs, T = 200_000, 5
    dt = torch.tensor([[2.0, 1.5, 0.5, 3.0, 1.0]], dtype=torch.float64).expand(runs, T)
    t = torch.cumsum(dt, 1)
    truth = torch.stack([10.0 + 3.0 * t, -5.0 - 2.0 * t], dim=-1)  # constant velocity
    r = torch.tensor([4.0, 9.0], dtype=torch.float64)
    z = truth + torch.randn(runs, T, 2, generator=gen, dtype=torch.float64) * r.sqrt()
    z[:, 0, 1] = float("nan")  # the second axis starts at its second step
    prior = two_point_prior(z, dt, r, inflation=4.0)
    true_x0 = torch.tensor([10.0, 3.0, -5.0, -2.0], dtype=torch.float64)
    error = prior.x0 - true_x0
    assert_close(error.mean(0), torch.zeros(4), atol=0.03)
    empirical = error.T @ error / runs
    P = prior.P0[0] / 4.0
    standard_error = ((P.diagonal()[:, None] * P.diagonal()[None, :] + P.square()) / runs).sqrt()
    assert bool(((P - empirical).abs() < 4 * standard_error).all())
    assert_close(prior.P0, prior.P0[:1].expand(runs, 4, 4))
    assert not bool(prior.single_point.any()) and not bool(prior.never_observed.any())


def test_two_point_prior_fix_ups():
    z = torch.tensor([[[1.0, math.nan], [math.nan, math.nan], [math.nan, 7.0]]])
    dt = torch.ones(1, 3)
    prior = two_point_prior(z, dt, 1.0, speed_std=5.0)
    assert prior.single_point.tolist() == [[True, True]]
    assert_close(prior.x0, torch.tensor([[1.0, 0.0, 7.0, 0.0]]))
    assert prior.P0[0, 1, 1].item() == pytest.approx(4.0 * 25.0)
    z = torch.tensor([[[1.0, math.nan], [2.0, math.nan]]])
    prior = two_point_prior(z, torch.ones(1, 2), 1.0)
    assert prior.never_observed.tolist() == [[False, True]]
    assert bool(torch.isfinite(prior.P0).all())


def test_noise_estimate_recovers_r_and_q_of_simulated_tracks():
    gen = torch.Generator().manual_seed(1)
    B, T, q, r = 40, 400, 2.0, 25.0
    dt = 1.0 + 4.0 * torch.rand(B, T, generator=gen, dtype=torch.float64)  # irregular, 1-5 s
    _, z = simulate_cv(dt, q, r, gen)
    z[torch.rand(B, T, 2, generator=gen) < 0.1] = float("nan")
    est = estimate_noise(z, dt)
    assert_close(est.meas_var, torch.full((2,), r), rtol=0.08)
    assert est.q == pytest.approx(q, rel=0.2)


def test_geodesy_round_trip_and_known_points():
    a, b = geodesy.A, geodesy.B
    assert_close(geodesy.geodetic_to_ecef(np.array(0.0), np.array(0.0), np.array(0.0)), [a, 0, 0])
    assert_close(
        geodesy.geodetic_to_ecef(np.array(90.0), np.array(0.0), np.array(0.0)), [0, 0, b], atol=1e-6
    )
    gen = np.random.default_rng(0)
    lat, lon, h = gen.uniform(-80, 80, 50), gen.uniform(-180, 180, 50), gen.uniform(-100, 12000, 50)
    enu = geodesy.geodetic_to_enu(lat, lon, h, lat + 0.7, lon - 1.1, 200.0)
    back = geodesy.enu_to_geodetic(enu, lat + 0.7, lon - 1.1, 200.0)
    assert_close(np.stack(back), np.stack([lat, lon, h]), atol=1e-6)
    # One arc minute of latitude at 45°: 1852.2 m north (meridian radius of curvature).
    north = geodesy.geodetic_to_enu(
        np.array(45.0 + 1 / 60), np.array(7.0), np.array(0.0), 45.0, 7.0, 0.0
    )
    assert north[1] == pytest.approx(1852.2, abs=0.5) and abs(north[0]) < 1e-6


def test_velocities_rotate_into_the_frame():
    """A velocity due north at a point east of the frame's origin points slightly west of the
    frame's north in the northern hemisphere (meridians converge)."""
    v = geodesy.rotate_enu(np.array([0.0, 100.0, 0.0]), 45.0, 10.0, 45.0, 7.0)
    assert np.linalg.norm(v) == pytest.approx(100.0)
    assert v[0] < -1.0 and v[1] > 99.0
    same = geodesy.rotate_enu(np.array([3.0, 4.0, 0.0]), 45.0, 7.0, 45.0, 7.0)
    assert_close(same, [3.0, 4.0, 0.0], atol=1e-12)


def test_parquet_with_typed_columns_reads_like_csv(tmp_path):
    """Parquet keeps its types: integer ids, timestamp times, float positions."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    start = np.datetime64("2024-05-01T12:00:00", "ns")
    table = pa.table(
        {
            "id": pa.array([7, 7, 7, 9, 9], type=pa.int64()),
            "when": pa.array([start + np.timedelta64(s, "s") for s in (0, 4, 2, 0, 5)]),
            "x": [0.0, 40.0, 20.0, 5.0, None],
            "y": [0.0, 8.0, 4.0, 5.0, 10.0],
        }
    )
    path = tmp_path / "t.parquet"
    pq.write_table(table, path)
    tracks, report = read_tracks(path, Columns(track_id="id", time="when"), meas_std=1.0)
    assert tracks.ids == ["7", "9"] and report.notes["out_of_order"] == 1
    assert_close(
        tracks.z[0], torch.tensor([[0.0, 0.0], [20.0, 4.0], [40.0, 8.0]], dtype=torch.float64)
    )
    assert_close(tracks.dt[1, 1:2], torch.tensor([5.0], dtype=torch.float64))
    write_estimates(tracks, tracks.z.new_zeros(2, 3, 4), tmp_path / "o.parquet")
    out = pq.read_table(tmp_path / "o.parquet")
    assert out.column("id").to_pylist() == [7, 7, 7, 9, 9]  # as stored, not as text
    assert out.column("when").type == table.column("when").type


def test_shortcuts_of_a_group_equal_their_general_paths():
    """The fast paths of padding, centring and the two-point prior (tracks of one length, first
    steps observed) give what the general paths give, bit for bit."""
    from dataclasses import replace

    from torchsvs.datasets import priors
    from torchsvs.datasets.steps import RowReport, TrackSteps, as_rows, median_interval
    from torchsvs.datasets.tracks import padded_batch
    from torchsvs.step_estimates import centred

    rng = np.random.default_rng(3)
    K, T = 30, 12
    time = np.cumsum(rng.uniform(0.5, 3.0, K * T))
    position = rng.normal(1e5, 1e3, (K * T, 2))
    position[rng.random((K * T, 2)) < 0.1] = np.nan  # some missing, first steps too
    steps = TrackSteps(
        ids=[str(k) for k in range(K)],
        start=np.arange(K) * T,
        length=np.full(K, T),
        time=time,
        position=position,
        extra={"alt": rng.normal(0, 1, K * T)},
        row_step=np.arange(K * T),
        report=RowReport(total=K * T),
    )
    group = np.arange(K)
    fast = padded_batch(steps, group)
    # the general path: one track a step longer forces padding; the others are as before
    longer = TrackSteps(
        ids=[*steps.ids, "x"],
        start=np.r_[steps.start, K * T],
        length=np.r_[steps.length, T + 1],
        time=np.r_[time, time[-1] + np.arange(1, T + 2)],
        position=np.r_[position, np.zeros((T + 1, 2))],
        extra={"alt": np.r_[steps.extra["alt"], np.zeros(T + 1)]},
        row_step=np.arange(K * T + T + 1),
        report=RowReport(total=K * T + T + 1),
    )
    general = padded_batch(longer, np.arange(K + 1))
    for name in ("z", "dt", "time", "steps"):
        a, b = getattr(fast, name), getattr(general, name)[:K, :T]
        assert torch.equal(a.isnan(), b.isnan()), name
        assert torch.equal(a.nan_to_num(7.0), b.nan_to_num(7.0)), name
    assert torch.equal(fast.extra["alt"], general.extra["alt"][:K, :T])
    # the padded cells (the step past each shorter track's end): missing, at no flat step
    assert bool(general.z[:K, T].isnan().all()) and bool(general.time[:K, T].isnan().all())
    assert bool(general.extra["alt"][:K, T].isnan().all())
    assert bool((general.steps[:K, T] == -1).all()) and not bool(general.z[K].isnan().any())
    assert torch.equal(general.dt[:K, T], general.dt[:K, 1:T].median(1).values)  # (11: odd)

    with pytest.raises(ValueError, match="C-contiguous"):  # (a copy would lose the writes)
        as_rows(np.zeros((4, 6))[:, :2])
    rows = np.zeros((5, 2, 2))
    as_rows(rows)[[1, 3]] = as_rows(np.arange(8.0).reshape(2, 2, 2))
    assert np.array_equal(rows[[1, 3]], np.arange(8.0).reshape(2, 2, 2)) and rows[0].sum() == 0

    dt = np.diff(time.reshape(K, T), axis=1)
    assert np.array_equal(median_interval(dt), np.nanmedian(dt, axis=1))
    dt[0, 3] = np.nan  # the sorting path
    assert np.array_equal(median_interval(dt), np.nanmedian(dt, axis=1))

    def first_observed(z: torch.Tensor) -> torch.Tensor:  # the general path's offsets
        first = (~torch.isnan(z)).to(torch.int64).argmax(dim=1, keepdim=True)
        return z.nan_to_num(0.0).gather(1, first).squeeze(1)

    z = fast.z
    full = replace(fast, z=torch.nan_to_num(z, 5.0))  # every first step observed: the shortcut
    assert bool(torch.isnan(z[:, 0]).any())  # (and the general path on the other)
    for tracks in (fast, full):
        moved, offset = centred(tracks)
        assert torch.equal(offset, first_observed(tracks.z))
        assert torch.equal(moved.z.nan_to_num(7.0), (tracks.z - offset[:, None]).nan_to_num(7.0))

    for zs in (z, full.z, z[:, :1]):
        dts = fast.dt[:, : zs.shape[1]]
        got = priors._two_points(zs, dts)
        want = priors._scanned_two_points(zs, dts.to(torch.float64))
        for a, b in zip(got, want, strict=True):
            assert torch.equal(a, b)


@pytest.mark.parametrize("shuffled", [False, True])
def test_estimate_table_gives_each_row_its_steps_estimates(tmp_path, shuffled):
    """Each output row carries its step's estimates (rows of one step share them; a row set
    aside has none), whether the rows are their steps in order (nothing taken) or not (the
    rows taken as items): against a row-by-row reference, covariances and outliers too."""
    import pyarrow as pa

    from torchsvs.datasets import track_blocks
    from torchsvs.datasets.writing import estimate_table

    rng = np.random.default_rng(5)
    rows = [(f"t{k}", float(t), *rng.normal(0, 100, 2)) for k in range(6) for t in range(9)]
    if shuffled:
        rows += [rows[3], ("t2", math.nan, 1.0, 2.0)]  # a duplicate time, a row without time
        rows = [rows[i] for i in rng.permutation(len(rows))]
    path = tmp_path / "rows.csv"
    path.write_text("id,time,x,y\n" + "\n".join(",".join(map(str, r)) for r in rows) + "\n")
    (block,) = track_blocks(path, Columns(track_id="id"), whole=True)
    S = block.steps.position.shape[0]
    mean = rng.normal(size=(S, 4))
    cov = rng.normal(size=(S, 4, 4))
    outlier = rng.random(S) < 0.3
    out = estimate_table(block, mean, cov, outlier=outlier, precision="float32")
    step = block.steps.row_step
    assert (step >= 0).all() != shuffled  # (the shuffled file has a row set aside)
    for name, j in (("x", 0), ("vx", 1), ("y", 2), ("vy", 3)):
        expected = [None if s < 0 else float(np.float32(mean[s, j])) for s in step]
        assert out.column(name).to_pylist() == expected, name
    expected = [None if s < 0 else float(np.float32(cov[s, 1, 2])) for s in step]
    assert out.column("cov_vx_y").to_pylist() == expected
    assert out.column("outlier").to_pylist() == [bool(s >= 0 and outlier[s]) for s in step]
    assert out.column("x").type == pa.float32() and len(out) == len(rows)
