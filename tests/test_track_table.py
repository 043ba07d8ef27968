"""One table in, the same rows with estimates out (:func:`torchsvs.track_table.track_table`),
with what a :class:`~torchsvs.track_plan.TrackPlan` settled once: the unit ``torchsvs track``
and the engines call. A table's estimates must not depend on which other tracks it holds."""

from __future__ import annotations

import pickle
from dataclasses import replace

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.csv as pcsv
import pyarrow.parquet as pq
import pytest
import torch

from tests.test_track_cli import _simulated_csv
from torchsvs.datasets import Columns
from torchsvs.datasets.tables import block_of
from torchsvs.recipes import Settings
from torchsvs.track_plan import TrackPlan, output_precision, plan_tracks
from torchsvs.track_table import output_schema, track_table
from torchsvs.tracking import track_file

COLUMNS = Columns("id", "t")
TEXT = pcsv.ConvertOptions(column_types={"id": pa.string(), "t": pa.string()})


@pytest.fixture(scope="module")
def rows(tmp_path_factory) -> tuple[pd.DataFrame, object]:
    """Irregular times, missing values, repeated times, shuffled rows (the CLI tests' file)."""
    path = tmp_path_factory.mktemp("table") / "in.csv"
    _simulated_csv(path, tracks=9, steps=[40, 7, 25, 60, 13, 33, 52, 20, 9])
    return pcsv.read_csv(path).to_pandas(), path


def _plan(frame: pd.DataFrame, estimator: str, **kwargs) -> TrackPlan:
    return plan_tracks(frame, Settings(estimator=estimator), columns=COLUMNS, **kwargs)


def _sorted(frame: pd.DataFrame) -> pd.DataFrame:
    return frame.sort_values(["id", "t"], kind="stable").reset_index(drop=True)


@pytest.mark.parametrize("estimator", ["ks", "kf", "svsf", "svss", "svstps", "rstkf"])
def test_parts_give_the_estimates_of_the_whole(rows, estimator):
    """Tracks split over three tables (as an engine's partitions split them) get the estimates
    they get in one table, to the last bit, in the same rows; the parts' runs add up to the
    whole's counts and error estimate. (Not the particle filters, whose draws are seeded per
    group of tracks, nor the IMM, whose choice between its smoother and filter per track
    weighs a control variate fitted over the group: test_imm_parts_differ_only_by_that.)"""
    frame, _ = rows
    plan = _plan(frame, estimator)
    whole = track_table(frame, plan)
    part_of = frame["id"].map(lambda i: int(i.split("-")[1]) % 3)
    parts = [track_table(frame[part_of == p], plan, check=False) for p in range(3)]
    assert all(len(p.table) == (part_of == k).sum() for k, p in enumerate(parts))
    joined = pd.concat([p.table for p in parts])
    pd.testing.assert_frame_equal(_sorted(joined), _sorted(whole.table), check_exact=True)
    run = parts[0].run
    for part in parts[1:]:
        run.merge(part.run)
    assert run.report.total == whole.run.report.total == len(frame)
    assert run.report.measurement == whole.run.report.measurement
    assert set(run.track_errors) == set(whole.run.track_errors)
    merged, alone = run.accuracy, whole.run.accuracy
    assert merged is not None and alone is not None
    if estimator in ("ks", "kf"):  # exact terms, and probes per track: the same sums
        assert merged.estimated_rmse == pytest.approx(alone.estimated_rmse, rel=1e-9)
    else:  # a control variate fitted over each group: another draw of the same estimate
        spread = 3.0 * np.hypot(merged.standard_error, alone.standard_error)
        assert abs(merged.estimated_rmse - alone.estimated_rmse) <= spread


def test_a_table_gives_what_track_writes(rows, tmp_path):
    """track_file is built on the same unit: the table's estimates are the file's, row for row
    (the file's rows in their order, ids and times as given)."""
    frame, path = rows
    target = tmp_path / "out.csv"
    run = track_file(path, target, Settings(estimator="ks"), columns=COLUMNS, progress=False)
    plan = _plan(frame, "ks")
    assert plan.settings == run.settings
    out = track_table(frame, plan).table
    written = pcsv.read_csv(target).to_pandas()
    assert list(out.columns) == list(written.columns)
    assert out["id"].tolist() == frame["id"].tolist()  # the input's row order
    for name in ("x", "vx", "y", "vy"):  # float32 written as its shortest decimal text
        expected = written[name].to_numpy().astype(out[name].dtype)
        np.testing.assert_array_equal(out[name].to_numpy(), expected)


def test_arrow_in_arrow_out_and_the_declared_schema(rows):
    """An Arrow table gives an Arrow table whose schema is the one an engine declares before
    running (output_schema), float32 estimates where the plan says so."""
    frame, _ = rows
    table = pa.Table.from_pandas(frame, preserve_index=False)
    plan = _plan(frame, "ks", precision="float32")
    out = track_table(table, plan, covariance=True).table
    assert isinstance(out, pa.Table)
    schema = output_schema(plan, table.schema.field("id").type, table.schema.field("t").type, True)
    assert out.schema == schema
    assert out.schema.field("x").type == pa.float32()


@pytest.mark.parametrize("kind", ["Int64", "string"])
def test_pandas_own_id_types_come_back_as_given_with_an_empty_id(rows, kind):
    """Nullable ``Int64`` ids (hashed, above 2^53) with one empty id came back as float64: all
    20 distinct ids one number. Each id comes back as given, in its dtype, the empty one empty
    (its row without an estimate)."""
    frame, _ = rows
    codes = {k: i for i, k in enumerate(sorted(frame["id"].unique()))}
    ids = frame["id"].map(codes).astype("int64") + 2**60
    given = frame.assign(id=ids.astype("Int64") if kind == "Int64" else ids.astype(str))
    given["id"] = given["id"].astype(kind)
    given.loc[5, "id"] = pd.NA
    out = track_table(given, _plan(frame, "ks")).table
    assert out["id"].dtype == given["id"].dtype
    pd.testing.assert_series_equal(out["id"], given["id"])
    assert np.isnan(out["x"].iloc[5]) and np.isfinite(out["x"].drop(index=5)).any()


def test_a_saved_plan_reloaded_gives_the_saved_runs_estimates(rows, tmp_path):
    """``plan_tracks(data, Settings("ks"), checkpoint=saved)`` rebuilt the settings from the
    data without the saved per-track ``q`` (its curve, kinds, window), beside the saved
    parameters: 12 m rms from the saved run's estimates at σ 20 (an outside probe). The saved
    settings are the run's; a setting given against them is refused, naming it."""
    frame, _ = rows
    saved = tmp_path / "plan.pt"
    plan = plan_tracks(frame, Settings(estimator="ks"), columns=COLUMNS, save=saved)
    assert plan.settings.q_curve is not None  # (what a rebuilt plan lacked)
    again = plan_tracks(frame, Settings(estimator="ks"), columns=COLUMNS, checkpoint=saved)
    assert again.settings == plan.settings
    pd.testing.assert_frame_equal(track_table(frame, again).table, track_table(frame, plan).table)
    with pytest.raises(
        ValueError, match=r"^settings: meas_var \(--meas-std\) = \[2500.0, 2500.0\] given, and"
    ):
        plan_tracks(frame, Settings("ks", meas_var=[2500.0] * 2), columns=COLUMNS, checkpoint=saved)


def test_a_lightning_checkpoints_noise_is_the_runs(rows, tmp_path):
    """A Lightning checkpoint holds parameters alone: its measurement noise replaced the one
    read off the data in the estimator while the error estimate stayed at the reading. The
    run's settings now carry the checkpoint's noise and ``q``; one given against it is
    refused."""
    from torchsvs.recipes import make_estimator, make_model

    frame, _ = rows
    trained = Settings(estimator="ks", meas_var=[900.0, 400.0], q=4.0)
    state = make_estimator(trained, make_model(trained)).state_dict()
    path = tmp_path / "module.ckpt"  # (as EstimatorModule's checkpoint holds it)
    torch.save({"state_dict": {f"estimator.{k}": v for k, v in state.items()}}, path)
    plan = plan_tracks(frame, Settings(estimator="ks"), columns=COLUMNS, checkpoint=path)
    assert plan.settings.meas_var == pytest.approx([900.0, 400.0])
    assert plan.settings.q == pytest.approx(4.0) and plan.settings.noise == "given"
    summary = track_table(frame, plan).run.summary_json()
    assert summary["meas_std"] == pytest.approx([30.0, 20.0])
    with pytest.raises(
        ValueError, match=r"^settings: meas_var \(--meas-std\) = \[100.0, 100.0\] given"
    ):
        plan_tracks(frame, Settings("ks", meas_var=[100.0] * 2), columns=COLUMNS, checkpoint=path)


def test_rows_in_another_time_unit_than_the_plans_are_said_so(rows):
    """A plan settles the time unit on its sample: rows whose times are in milliseconds read
    as the plan's seconds came out worse without a word (an outside probe). The run says their
    typical interval is unlike the sample's; rows like the sample's get no such warning."""
    frame, _ = rows
    plan = _plan(frame, "ks")
    assert not any(w.startswith("time:") for w in track_table(frame, plan).run.warnings)
    said = track_table(frame.assign(t=frame["t"] * 1000.0), plan).run.warnings
    assert any(w.startswith("time: these rows' typical interval is") for w in said), said
    from torchsvs.track_table import estimate_block, new_run

    run = new_run(plan)  # (a run of blocks of other intervals says it once)
    for factor in (1000.0, 3000.0):
        block = block_of(frame.assign(t=frame["t"] * factor), plan.columns)
        estimate_block(block, plan, plan.estimator(), run)
    assert sum(w.startswith("time:") for w in run.warnings) == 1, run.warnings


def test_a_noise_column_in_the_settings_is_read_without_naming_it_twice(rows):
    """``Settings(noise_column="sigma")`` failed with ``KeyError: 'sigma'`` unless the column
    was named again in ``Columns(extra=...)``; it is read beside the positions as with
    ``--noise-col``."""
    frame, _ = rows
    given = frame.assign(sigma=30.0)
    plan = plan_tracks(given, Settings("ks", noise_column="sigma"), columns=COLUMNS)
    assert "sigma" in plan.columns.extra and plan.settings.meas_var == [900.0, 900.0]
    named = replace(COLUMNS, extra=("sigma",))
    again = plan_tracks(given, Settings("ks", noise_column="sigma"), columns=named)
    pd.testing.assert_frame_equal(track_table(given, plan).table, track_table(given, again).table)


def test_a_plan_travels_by_pickle(rows):
    """An engine broadcasts the plan as a pickle: the same estimates from the copy; the fit's
    summary stays with the one who planned."""
    frame, _ = rows
    plan = _plan(frame, "svss", fit=True, fit_options={"steps": 5})
    assert plan.fit is not None
    copy = pickle.loads(pickle.dumps(plan))
    assert copy.fit is None and copy.settings == plan.settings
    assert plan == plan and copy != plan  # (compared as objects: == raised on the tensors)
    pd.testing.assert_frame_equal(
        track_table(frame, copy).table, track_table(frame, plan).table, check_exact=True
    )


@pytest.mark.parametrize(("estimator", "fit"), [("auto", False), ("svss", True)])
def test_a_plan_does_not_depend_on_the_order_of_the_tracks(rows, estimator, fit):
    """The same tracks written in another order get the same plan: the fit's windows and
    probes are drawn by position in the sample, which is taken in the order of the ids (in
    the file's order, ``auto`` moved estimates by 2 m at 5 m noise on reversed tracks)."""
    frame, _ = rows
    options = {"fit": fit, "fit_options": {"steps": 5}} if fit else {}
    plan = _plan(frame, estimator, **options)
    order = {i: k for k, i in enumerate(frame["id"].unique()[::-1])}  # tracks reversed
    reordered = frame.iloc[np.argsort(frame["id"].map(order).to_numpy(), kind="stable")]
    again = _plan(reordered, estimator, **options)
    assert again.settings == plan.settings
    assert again.parameters.keys() == plan.parameters.keys()
    for name, value in plan.parameters.items():
        assert torch.equal(again.parameters[name], value), name


def test_auto_precision_follows_the_positions_and_the_noise(rows):
    """float32 keeps metres near an origin to a hundredth of the noise; far from it (UTM
    northings) or in degrees it would not, and "auto" writes float64; a part with positions
    beyond the sample's warns."""
    frame, _ = rows
    plan = _plan(frame, "ks")
    assert plan.precision == "float32"
    far = frame.assign(y=frame["y"] + 5e6)  # a UTM northing
    assert _plan(far, "ks").precision == "float64"
    result = track_table(far, plan)  # planned near the origin, run far from it
    assert any(w.startswith("precision:") for w in result.run.warnings)
    degrees = frame.assign(lat=48.0 + frame["y"] / 111e3, lon=11.0 + frame["x"] / 74e3)
    geo = plan_tracks(degrees.drop(columns=["x", "y"]), Settings(estimator="ks"), columns=COLUMNS)
    assert geo.columns.geodetic and geo.precision == "float64"
    # the rule itself: float32's spacing at 4x the largest position (7.8 km here: 2^-9 m at
    # 31 km) against 1/100 of the noise's standard deviation
    block = block_of(frame, plan.columns)
    assert output_precision(block.steps, block.columns, [1.0, 1.0]) == "float32"  # 1 cm bar
    assert output_precision(block.steps, block.columns, [1e-6, 1e-6]) == "float64"  # 10 µm
    table = pa.Table.from_pandas(frame, preserve_index=False)
    assert track_table(table, plan).table.schema.field("x").type == pa.float32()


def test_float32_estimates_are_the_float64_ones_rounded(rows):
    """The precision is applied once, as the estimates are written."""
    frame, _ = rows
    wide = _plan(frame, "ks", precision="float64")
    narrow = TrackPlan(wide.columns, wide.settings, wide.parameters, wide.dtype, "float32")
    a, b = track_table(frame, wide).table, track_table(frame, narrow).table
    for name in ("x", "vx", "y", "vy"):
        assert b[name].dtype == np.float32
        np.testing.assert_array_equal(a[name].to_numpy().astype(np.float32), b[name].to_numpy())


def test_bad_input_names_the_argument(rows, tmp_path):
    frame, _ = rows
    plan = _plan(frame, "ks")
    with pytest.raises(TypeError, match="^data: expected a pandas DataFrame"):
        track_table(frame.to_numpy(), plan)
    with pytest.raises(ValueError, match="^precision: expected one of"):
        _plan(frame, "ks", precision="half")
    with pytest.raises(ValueError, match="^data: expected rows of tracks"):
        plan_tracks(frame.iloc[:0], columns=COLUMNS)
    with pytest.raises(ValueError, match=r"^columns: \['id'\] not in the data"):
        plan_tracks(frame.drop(columns=["id"]), columns=COLUMNS)
    with pytest.raises(ValueError, match="^settings: expected complete settings"):
        TrackPlan(plan.columns, Settings(estimator="ks"), plan.parameters)
    # (a pyarrow KeyError, a complex-number TypeError, "float has no len()" before; an outside
    # probe of the API)
    with pytest.raises(ValueError, match=r"^data: columns \['y'\] of the plan not in the data"):
        track_table(frame.drop(columns=["y"]), plan)
    codes = frame["id"].astype("category").cat.codes.astype("float64")
    with pytest.raises(ValueError, match=r"^data: the track ids 'id' are floats reaching"):
        track_table(frame.assign(id=codes + 2.0**60), plan)  # (Dask's int64 with a null)
    with pytest.raises(ValueError, match="^meas_var: expected variances > 0"):
        Settings("ks", meas_var=[-400.0, -400.0])
    with pytest.raises(ValueError, match="^meas_var: expected a list of numbers > 0"):
        Settings("ks", meas_var=400.0)
    with pytest.raises(ValueError, match="^psi: expected a list of numbers > 0"):
        Settings("svss", psi=4.0)
    path = tmp_path / "sample.parquet"
    pq.write_table(pa.Table.from_pandas(frame, preserve_index=False), path)
    from_file = plan_tracks(path, Settings(estimator="ks"), columns=COLUMNS)
    assert from_file.settings.meas_var == pytest.approx(plan.settings.meas_var)


@pytest.mark.parametrize("estimator", ["ks", "svss"])
def test_threads_may_share_one_estimator(rows, estimator):
    """Engines call track_table from several threads with one estimator (Dask's threaded
    workers): each track keeps its own q and gets the estimate it gets alone."""
    import threading

    frame, _ = rows
    plan = _plan(frame, estimator)
    assert plan.settings.q_curve is not None  # tracks with their own q
    alone = _sorted(track_table(frame, plan).table)
    shared = plan.estimator()
    part_of = frame["id"].map(lambda i: int(i.split("-")[1]) % 4)
    outs: list = [None] * 4

    def run(p: int) -> None:
        for _ in range(3):  # a few times over, so the threads overlap
            outs[p] = track_table(frame[part_of == p], plan, estimator=shared).table

    threads = [threading.Thread(target=run, args=(p,)) for p in range(4)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    pd.testing.assert_frame_equal(_sorted(pd.concat(outs)), alone, check_exact=True)


def test_one_track_tables_give_the_whole_tables_float64_estimates(rows):
    """Tables of one track each against one table of all, in float64 to the last bit: the
    compiled smoother must not pick its loop by the batch's size (the two loops round
    differently: 9% of values moved by ~1e-13 when it did)."""
    frame, _ = rows
    plan = _plan(frame, "ks", precision="float64")
    whole = _sorted(track_table(frame, plan).table)
    parts = [track_table(frame[frame["id"] == i], plan).table for i in frame["id"].unique()]
    pd.testing.assert_frame_equal(_sorted(pd.concat(parts)), whole, check_exact=True)


@pytest.mark.parametrize("estimator", ["ks", "svss", "pf", "imm"])
def test_groups_on_threads_give_the_estimates_of_one_thread(rows, estimator):
    """A table's groups run on torch's intra-op count of threads at once
    (:func:`~torchsvs.track_table.group_threads`); the estimates and the run's error estimate are
    those of one group at a time, to the last bit (particle draws too: seeded per group)."""
    import torch

    frame, _ = rows
    plan = _plan(frame, estimator)
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        alone = track_table(frame, plan, max_cells=64)
        torch.set_num_threads(3)
        threaded = track_table(frame, plan, max_cells=64)
        assert torch.get_num_threads() == 3  # restored
    finally:
        torch.set_num_threads(before)
    pd.testing.assert_frame_equal(threaded.table, alone.table, check_exact=True)
    a, b = threaded.run.summary_json(), alone.run.summary_json()
    for key in ("estimated_position_rmse", "estimated_position_rmse_interval", "tracks", "rows"):
        assert a[key] == b[key], key


def test_a_failing_group_stops_the_groups_not_started():
    """An error in one group (or an interrupt) ends the block: the groups queued behind it are
    dropped, not run to completion before the error reaches the caller (``Executor.map``
    cancels them; a pool fed with ``submit`` would not); torch's thread count is restored."""
    import threading
    import time

    import torch

    from torchsvs.track_table import group_threads

    ran = []
    lock = threading.Lock()

    def work(k: int) -> int:
        if k == 0:
            raise RuntimeError("group 0 failed")
        time.sleep(0.01)
        with lock:
            ran.append(k)
        return k

    before = torch.get_num_threads()
    try:
        torch.set_num_threads(2)
        with pytest.raises(RuntimeError, match="group 0 failed"):
            with group_threads(200) as run_groups:
                for _ in run_groups(work, range(200)):
                    pass
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)
    assert len(ran) < 50, len(ran)


def test_a_runs_worst_tracks_are_the_worst_of_all_its_blocks(monkeypatch):
    """Blocks added one at a time (the tracks at or below the worst kept so far skipped, the
    kept ones trimmed now and then) give the summary the worst ``TRACKS_KEPT`` of all the
    tracks, the first added among equal errors, as sorting them all at once does."""
    import torchsvs.track_run as track_run
    from torchsvs.accuracy import RiskTerms
    from torchsvs.track_run import TrackRun

    monkeypatch.setattr(track_run, "TRACKS_KEPT", 7)
    gen = np.random.default_rng(5)
    run = TrackRun(settings=Settings(estimator="ks", meas_var=[1.0]))
    added: list[tuple[str, float]] = []
    for block in range(15):
        tracks = int(gen.integers(1, 12))
        error = np.round(gen.uniform(0, 3, tracks), 1)  # (ties among them)
        ones = np.ones((tracks, 1))
        terms = RiskTerms(error[:, None] ** 2, 0.5 * ones, ones, np.arange(tracks))
        ids = [f"b{block}-{k}" for k in range(tracks)]
        run.add_track_errors([terms], ids)
        added += zip(ids, np.sqrt(error**2).tolist(), strict=True)
    assert len(added) > 4 * 7  # (trimmed and skipped along the way)
    expected = sorted(added, key=lambda kv: -kv[1])[:7]
    run.report.tracks = len(added)
    summary = run.summary_json()
    written = summary["tracks"]
    assert [(k, v["estimated_position_rmse"]) for k, v in written.items()] == expected
    # the summary says it lists some of the tracks (it stopped at the worst silently)
    assert summary["tracks_listed"] == f"7 of {len(added)}, the largest error first"


@pytest.mark.parametrize("placed_by_its_thread", [False, True])
def test_steps_no_group_placed_are_written_empty(placed_by_its_thread):
    """A block's estimates are placed group by group into unwritten arrays (by ``add``, or by
    ``place`` on the group's thread, then counted by ``add(placed=True)``, as ``estimate_block``
    does); a step that no group placed comes out NaN, never what the memory held, in the
    arrays once finished and in the output table whether finished or not."""
    from torchsvs.step_estimates import StepEstimates
    from torchsvs.track_run import BlockEstimates

    table = pa.table(
        {
            "id": ["a"] * 4 + ["b"] * 3,
            "t": [0.0, 1, 2, 3, 0, 1, 2],
            "x": np.arange(7.0),
            "y": np.arange(7.0),
        }
    )
    block = block_of(table, COLUMNS)
    steps = block.steps
    found = BlockEstimates.empty(steps, covariance=True)
    found.mean[:] = 7.0  # (what the memory might hold)
    assert found.cov is not None
    found.cov[:] = 7.0
    first = np.arange(steps.length[0])
    part = StepEstimates(
        0,
        np.array([0]),
        first,
        np.ones((len(first), 4)),
        np.ones((len(first), 4, 4)),
        np.zeros((1, 2), dtype=bool),
        {},
    )
    if placed_by_its_thread:
        found.place(part)
        found.add(part, placed=True)
    else:
        found.add(part)
    out = found.table(block)  # (finishes first)
    assert out.column("x").to_pylist() == [1.0] * len(first) + [None] * (7 - len(first))
    found.finish()
    assert (found.mean[first] == 1.0).all() and (found.cov[first] == 1.0).all()
    rest = np.setdiff1d(np.arange(len(found.mean)), first)
    assert len(rest) and np.isnan(found.mean[rest]).all() and np.isnan(found.cov[rest]).all()
