"""``torchsvs track``: every input row out with its id and time, in order; streaming equals
reading whole; checkpoints; clear errors."""

from __future__ import annotations

import json
import math

import numpy as np
import pyarrow as pa
import pyarrow.csv as pcsv
import pyarrow.parquet as pq
import pytest
import torch

from tests.conftest import assert_close
from torchsvs.cli import main

TEXT = pcsv.ConvertOptions(column_types={"id": pa.string(), "t": pa.string()})


def _simulated_csv(
    path, tracks: int = 12, steps: int | list[int] = 60, sigma: float = 30.0, seed: int = 0
):
    """CV tracks with irregular times (1-3 s), 5% missing values, some duplicated rows, string
    ids, rows of each track shuffled; ``steps``: of every track, or one count per track;
    returns the truth positions by (id, time)."""
    gen = np.random.default_rng(seed)
    rows, truth = [], {}
    for k in range(tracks):
        ident = f"flight-{k:02d}"
        count = steps if isinstance(steps, int) else steps[k]
        t = np.cumsum(gen.uniform(1.0, 3.0, count))
        v = gen.normal(0, 40, 2)
        pos = gen.normal(0, 1e3, 2) + t[:, None] * v + np.cumsum(gen.normal(0, 2, (count, 2)), 0)
        for i in gen.permutation(count):
            x, y = pos[i] + gen.normal(0, sigma, 2)
            xs = "" if gen.random() < 0.05 else f"{x:.3f}"
            rows.append(f"{ident},{t[i]:.3f},{xs},{y:.3f}")
            truth[(ident, f"{t[i]:.3f}")] = pos[i]
            if gen.random() < 0.03:  # the same time again
                rows.append(f"{ident},{t[i]:.3f},{x + 1:.3f},{y - 1:.3f}")
    path.write_text("id,t,x,y\n" + "\n".join(rows) + "\n")
    return truth


def _errors(source, target, truth) -> tuple[float, float]:
    """RMS error per axis of the estimates in ``target`` and of the measurements in ``source``
    against ``truth`` (:func:`_simulated_csv`'s), over the rows with a measured position."""
    inp = pcsv.read_csv(source, convert_options=TEXT)
    out = pcsv.read_csv(target, convert_options=TEXT)
    keys = zip(inp.column("id").to_pylist(), inp.column("t").to_pylist(), strict=True)
    true = np.stack([truth[k] for k in keys])
    est = np.stack([out.column("x").to_numpy(), out.column("y").to_numpy()], 1)
    raw = np.stack([inp.column("x").to_numpy(), inp.column("y").to_numpy()], 1).astype(float)
    ok = np.isfinite(raw).all(1)
    return (
        float(np.sqrt(np.mean((est[ok] - true[ok]) ** 2))),
        float(np.sqrt(np.mean((raw[ok] - true[ok]) ** 2))),
    )


def _run(*args: str) -> None:
    main(["track", *args, "--quiet"])


def _run_simulated(source, target, *args: str) -> None:
    """``track`` on a :func:`_simulated_csv` file (its ``id`` and ``t`` columns)."""
    _run(str(source), "-o", str(target), "--id-col", "id", "--time-col", "t", *args)


def test_every_row_comes_back_with_its_id_and_time(tmp_path):
    source, target = tmp_path / "in.csv", tmp_path / "out.csv"
    truth = _simulated_csv(source)
    _run(str(source), "-o", str(target), "--id-col", "id", "--time-col", "t", "--meas-std", "30")
    inp, out = (
        pcsv.read_csv(source, convert_options=TEXT),
        pcsv.read_csv(target, convert_options=TEXT),
    )
    assert out.num_rows == inp.num_rows
    assert out.column("id").to_pylist() == inp.column("id").to_pylist()
    assert out.column("t").to_pylist() == inp.column("t").to_pylist()
    assert out.column_names == ["id", "t", "x", "vx", "y", "vy", "outlier"]
    est = np.stack([out.column("x").to_numpy(), out.column("y").to_numpy()], 1)
    assert np.isfinite(est).all()
    est_error, raw_error = _errors(source, target, truth)
    assert est_error < 0.8 * raw_error


@pytest.mark.parametrize("estimator", ["kf", "ks", "svsf", "svss", "svstps", "ukf", "rstkf"])
def test_each_estimator_runs_from_the_command_line(tmp_path, estimator):
    source, target = tmp_path / "in.csv", tmp_path / "out.parquet"
    _simulated_csv(source, tracks=3, steps=20)
    _run_simulated(source, target, "--estimator", estimator)
    out = pq.read_table(target)
    assert out.num_rows == pcsv.read_csv(source).num_rows
    assert np.isfinite(out.column("vx").to_numpy()).all()


def test_streaming_equals_reading_whole(tmp_path):
    source = tmp_path / "in.csv"
    _simulated_csv(source, tracks=8, steps=30)
    # Streaming needs each track's rows together: sort the file by id (keeping row order within).
    table = pcsv.read_csv(source, convert_options=TEXT)
    order = np.argsort(np.array(table.column("id").to_pylist()), kind="stable")
    pcsv.write_csv(table.take(pa.array(order)), source)
    whole, streamed = tmp_path / "whole.csv", tmp_path / "streamed.csv"
    # Settings left open are read off the first block, so give them all.
    common = [
        "--estimator",
        "ks",
        "--id-col",
        "id",
        "--time-col",
        "t",
        "--meas-std",
        "30",
        "--q",
        "4",
        "--double",
    ]
    common += ["--psi", "80,20,80,20"]
    _run(str(source), "-o", str(whole), "--in-memory", *common)
    _run(str(source), "-o", str(streamed), "--stream", "--block-rows", "50", *common)
    a, b = pcsv.read_csv(whole), pcsv.read_csv(streamed)
    assert a.column_names == b.column_names and a.num_rows == b.num_rows
    for name in ("x", "vx", "y", "vy"):
        assert_close(b.column(name).to_numpy(), a.column(name).to_numpy(), atol=1e-9)


def test_covariances_on_request(tmp_path):
    source, target = tmp_path / "in.csv", tmp_path / "out.csv"
    _simulated_csv(source, tracks=2, steps=15)
    _run(
        str(source),
        "-o",
        str(target),
        "--id-col",
        "id",
        "--time-col",
        "t",
        "--covariance",
        "--estimator",
        "ks",
    )
    out = pcsv.read_csv(target)
    assert "cov_x_x" in out.column_names and "cov_vy_vy" in out.column_names
    assert (out.column("cov_x_x").to_numpy() > 0).all()
    assert (out.column("cov_x_y").to_numpy() == 0).all()  # the axes are independent


def test_save_then_checkpoint_reproduces_the_output(tmp_path):
    source = tmp_path / "in.csv"
    _simulated_csv(source, tracks=4, steps=25)
    first, again, saved = tmp_path / "a.csv", tmp_path / "b.csv", tmp_path / "svss.pt"
    common = ["--id-col", "id", "--time-col", "t", "--estimator", "svss"]
    _run(
        str(source),
        "-o",
        str(first),
        "--meas-std",
        "30",
        "--psi",
        "2,3",
        "--save",
        str(saved),
        *common,
    )
    _run(str(source), "-o", str(again), "--checkpoint", str(saved), *common)
    assert_close(
        pcsv.read_csv(again).column("x").to_numpy(), pcsv.read_csv(first).column("x").to_numpy()
    )


def test_fit_tunes_on_the_file_itself(tmp_path):
    source, target = tmp_path / "in.csv", tmp_path / "out.csv"
    truth = _simulated_csv(source, tracks=10, steps=80)
    common = ["--id-col", "id", "--time-col", "t", "--meas-std", "30", "--estimator", "ks"]
    _run(str(source), "-o", str(target), "--q", "1000", *common)  # far too agile
    _run(
        str(source),
        "-o",
        str(tmp_path / "fit.csv"),
        "--q",
        "1000",
        "--fit",
        "--fit-steps",
        "8",
        *common,
    )
    inp = pcsv.read_csv(source, convert_options=TEXT)
    keys = zip(inp.column("id").to_pylist(), inp.column("t").to_pylist(), strict=True)
    true = np.stack([truth[k] for k in keys])

    def error(path) -> float:
        out = pcsv.read_csv(path)
        est = np.stack([out.column("x").to_numpy(), out.column("y").to_numpy()], 1)
        return float(np.sqrt(np.mean((est - true) ** 2)))

    assert error(tmp_path / "fit.csv") < 0.9 * error(target)


@pytest.mark.parametrize(
    "args, message",
    [
        (["--estimator", "nope"], "invalid choice"),
        (["--lag", "0"], "lag: expected an integer >= 1"),
        (["--meas-std", "1,2,3"], "meas_std: expected one value or one per axis"),
        (["--estimator", "svss", "--psi", "1,2,3"], "psi: expected 2 boundary layer widths"),
        (["--id-col", "missing"], r"columns: \['missing'\] not in the file"),
        (["--estimator", "svstps", "--no-velocity"], r"svstps with velocity=False \(--no-velocity"),
        (["--estimator", "kf", "--lag", "5"], r"lag: kf is a filter; a lag applies to ks, "),
    ],
)
def test_bad_arguments_name_what_is_wrong(tmp_path, capsys, args, message):
    source = tmp_path / "in.csv"
    _simulated_csv(source, tracks=2, steps=10)
    with pytest.raises(SystemExit) as exit_info:
        main(
            [
                "track",
                str(source),
                "-o",
                str(tmp_path / "o.csv"),
                "--time-col",
                "t",
                *(args if "--id-col" in args else ["--id-col", "id", *args]),
                "--quiet",
            ]
        )
    text = str(exit_info.value.code) + capsys.readouterr().err
    assert exit_info.value.code != 0
    import re

    assert re.search(message, text), text


def test_lightning_checkpoint_loads_into_the_command_line_estimator(tmp_path):
    from torchsvs.recipes import Settings, make_estimator, make_model
    from torchsvs.track_plan import load_parameters
    from torchsvs.training import EstimatorModule

    settings = Settings(estimator="svss", meas_var=[900.0, 900.0], q=4.0, psi=[2.0, 3.0])
    trained = make_estimator(settings, make_model(settings))
    with torch.no_grad():
        trained.filter.boundary_layer.raw.add_(0.3)
    module = EstimatorModule(trained, loss="supervised")
    path = tmp_path / "module.ckpt"
    torch.save({"state_dict": module.state_dict()}, path)
    fresh = make_estimator(settings, make_model(settings))
    load_parameters(fresh, path)
    assert_close(fresh.filter.psi, trained.filter.psi)
    wrong = make_estimator(
        Settings(estimator="ks", meas_var=[900.0, 900.0], q=4.0), make_model(settings)
    )
    with pytest.raises(ValueError, match="^checkpoint: .* does not fit the estimator"):
        load_parameters(wrong, path)


def test_geodetic_free_estimates_keep_large_coordinates_exact(tmp_path):
    """Positions far from the origin (projected coordinates in the millions) are estimated in
    float32 without losing resolution: each track is moved to start near 0 first."""
    source, target = tmp_path / "in.csv", tmp_path / "out.csv"
    t = np.arange(50.0)
    x = 5.3e6 + 100.0 * t
    rows = "\n".join(f"a,{ti},{xi:.3f},{-2.1e6:.3f}" for ti, xi in zip(t, x, strict=True))
    source.write_text("track_id,time,x,y\n" + rows + "\n")
    _run(str(source), "-o", str(target), "--meas-std", "1", "--q", "0.01", "--estimator", "ks")
    out = pcsv.read_csv(target)
    assert np.abs(out.column("x").to_numpy() - x).max() < 0.05
    assert np.abs(out.column("vx").to_numpy() - 100.0).max() < 0.05
    assert not math.isnan(out.column("y").to_numpy()[0])


def test_each_track_runs_with_its_own_q_as_if_alone(tmp_path):
    """The default picks a q per track (quiet tracks below the file's q and the maneuvering
    ones'): each track's estimates are those of a run of that track alone with its q given, the
    estimator's q is left as it was, and --shared-q runs one q for all."""
    import json

    from tests.test_noise_estimate import _two_kinds
    from torchsvs.fitting.noise import q_curves, q_factors, track_q_factors
    from torchsvs.fitting.q_kinds import track_kinds
    from torchsvs.recipes import Settings
    from torchsvs.tracking import track_file

    _, z, dt = _two_kinds(steps=150)
    t = torch.cumsum(dt, 1)
    lines = [
        f"k{b},{t[b, i]:.1f},{z[b, i, 0]:.6f},{z[b, i, 1]:.6f}"
        for b in range(len(z))
        for i in range(z.shape[1])
    ]
    source = tmp_path / "in.csv"
    source.write_text("track_id,time,x,y\n" + "\n".join(lines) + "\n")
    given = Settings(estimator="ks", meas_var=[400.0, 400.0], step_q=False)
    run = track_file(source, tmp_path / "out.csv", given, dtype=torch.float64, progress=False)
    settings = run.settings
    assert settings is not None and settings.q is not None and settings.q_curve is not None
    assert settings.q_window is None
    summary = json.loads((tmp_path / "out.summary.json").read_text())
    assert "q_per_track" in summary
    grid = q_factors(settings.q_low)  # (the quiet tracks may want the grid lower)
    curves = q_curves(z, dt, 400.0, settings.q, True, grid)._replace(kinds=track_kinds(z, dt))
    factors = track_q_factors(curves, settings.q_curve, grid, kinds=settings.q_kinds)
    assert factors[:3].max() < 1 and factors[:3].max() < factors[3:].min(), factors.tolist()
    written = [summary["tracks"][f"k{b}"]["q_factor"] for b in range(len(z))]
    assert written == pytest.approx(factors.tolist(), rel=1e-12)
    assert sum(summary["q_per_track"]["tracks_per_factor"].values()) == len(z)
    joint = pcsv.read_csv(tmp_path / "out.csv")
    for b in (0, 4):
        alone = tmp_path / f"k{b}.csv"
        alone.write_text("track_id,time,x,y\n" + "\n".join(lines[b * 150 : (b + 1) * 150]) + "\n")
        fixed = Settings(estimator="ks", meas_var=[400.0, 400.0], q=settings.q * float(factors[b]))
        track_file(alone, tmp_path / f"k{b}.out.csv", fixed, dtype=torch.float64, progress=False)
        mine = pcsv.read_csv(tmp_path / f"k{b}.out.csv")
        rows = slice(b * 150, (b + 1) * 150)
        for name in ("x", "vx", "y", "vy"):
            assert_close(
                joint.column(name).to_numpy()[rows], mine.column(name).to_numpy(), atol=1e-6
            )
    shared = Settings(estimator="ks", meas_var=[400.0, 400.0], track_q=False)
    one = track_file(source, tmp_path / "one.csv", shared, dtype=torch.float64, progress=False)
    assert one.settings is not None and one.settings.q_curve is None and not one.q_factors
    assert one.settings.q == pytest.approx(settings.q)


def test_scaled_q_scales_a_copy_and_leaves_the_estimator_alone():
    from torchsvs.estimating import scaled_q
    from torchsvs.recipes import Settings, make_estimator, make_model

    settings = Settings(estimator="svss", meas_var=[100.0, 100.0], q=0.3, psi=[2.0, 2.0])
    estimator = make_estimator(settings, make_model(settings))
    before = estimator.model.q().clone()
    with scaled_q(estimator, 10 ** (-3 / 4)) as scaled:
        assert float(scaled.model.q()) == pytest.approx(0.3 * 10 ** (-3 / 4), rel=1e-6)
        assert torch.equal(estimator.model.q(), before)  # another thread may be using it
    assert torch.equal(estimator.model.q(), before)


def test_hplus_svss_defaults_to_lag_one_and_stays_below_the_measurements(tmp_path):
    """The H⁺ mode never corrects the velocity: a backward pass longer than one step carries the
    two-point prior's velocity error into the positions (26x raw at lag 5 on recorded
    airliners); its SVSS defaults to lag 1, below the raw measurements."""
    from torchsvs.recipes import Settings

    assert Settings(estimator="svss", velocity=False).smoother_lag == 1
    assert Settings(estimator="svss").smoother_lag is None  # the fixed interval
    assert Settings(estimator="svss", velocity=False, lag=3).smoother_lag == 3
    source, target = tmp_path / "in.csv", tmp_path / "out.csv"
    truth = _simulated_csv(source, tracks=12, steps=80)
    errors = {}
    for lag in ([], ["--lag", "5"]):
        _run_simulated(source, target, "--estimator", "svss", "--no-velocity", "--force", *lag)
        errors[bool(lag)] = _errors(source, target, truth)
    assert errors[False][0] < errors[False][1], errors
    # and why the default is 1: at lag 5 the prior's velocity error reaches the positions
    assert errors[True][0] > 3 * errors[True][1], errors


def test_the_summary_json_is_read_back_as_written_a_key_to_a_line():
    """The summary's text (the C encoder, a line per key and per entry of a dict value) reads
    back to the summary itself, numpy scalars as numbers, empty dicts and nested lists kept."""
    import json

    from torchsvs.track_run import _json_text

    summary = {
        "estimator": "ks",
        "settings": {"q": 0.5, "psi": None, "q_curve": [1.0, 2.5], "nested": {"a": [1, {"b": 2}]}},
        "rows": {},
        "points": np.int64(7),
        "tracks": {
            f"t{k}": {"estimated_position_rmse": np.float64(k / 3), "points": k} for k in range(3)
        },
        "warnings": ['a "quoted" line\nand a break'],
    }
    text = _json_text(summary)
    back = json.loads(text)
    assert back == json.loads(json.dumps(summary, default=lambda v: v.item()))
    lines = text.splitlines()
    assert len(lines) == 17  # braces, 4 plain keys, 2 dicts of 4 and 3 entries between theirs
    assert '  "t1": {"estimated_position_rmse": 0.3333333333333333, "points": 1},' in lines


def test_the_summary_json_writes_an_unknown_number_as_null():
    """A number that is not finite (an unknown standard error: NaN, of a one-chunk sample) is
    written ``null``: strict JSON readers refuse ``NaN``; the finite numbers beside it stay."""
    import json

    from torchsvs.track_run import _json_text

    summary = {
        "candidates": [{"estimator": "svss", "mse_change": -3.5, "mse_change_se": math.nan}],
        "fit": {"se": np.float64(np.inf), "q": 0.25},
        "seconds": 1.5,
    }
    back = json.loads(_json_text(summary), parse_constant=lambda c: pytest.fail(f"{c} written"))
    assert back["candidates"] == [{"estimator": "svss", "mse_change": -3.5, "mse_change_se": None}]
    assert back["fit"] == {"se": None, "q": 0.25} and back["seconds"] == 1.5


def _given_noise_runs(tmp_path, levels: tuple[str, ...] = ("10", "20")) -> dict[str, dict]:
    """``track --estimator ks --meas-std`` at σ (10 m) and twice σ (or ``levels``) on 16
    simulated tracks: each run's summary, with its true 2-D RMSE (``true``) and the raw
    measurements' (``raw``)."""
    import json

    from torchsvs.track_run import summary_path

    source = tmp_path / "in.csv"
    truth = _simulated_csv(source, tracks=16, steps=120, sigma=10.0)
    found = {}
    for given in levels:
        target = tmp_path / f"out{given}.csv"
        _run_simulated(source, target, "--estimator", "ks", "--meas-std", given)
        found[given] = json.loads(summary_path(target).read_text())
        rmse, raw = _errors(source, target, truth)
        found[given]["true"], found[given]["raw"] = rmse * math.sqrt(2.0), raw * math.sqrt(2.0)
    return found


def test_a_noise_given_too_high_gives_no_error_estimate_of_zero_but_a_warning(
    tmp_path, monkeypatch
):
    """The noise given as a bound (here twice σ, a 95% one) rather than σ: SURE at it comes out
    surely below zero, and the run printed "estimated position error 0 m (range 0-0)" without a
    word. Now the summary has no number (null), and a warning names the noise given, the most
    the residuals allow (between σ and the noise given) and what to give instead. At σ itself
    the estimate is a number near the truth's, and no such warning."""
    from torchsvs.fitting import defaults

    # (the check of a given noise against the data's reading off: this is what is left where
    # that reading cannot tell, test_a_noise_given_above_what_the_data_show_is_said_so)
    monkeypatch.setattr(defaults, "GIVEN_CHECK_ERRORS", math.inf)
    found = _given_noise_runs(tmp_path)
    for run in found.values():
        assert run["true"] < 0.8 * run["raw"]  # (the estimates are written either way)
    right, high = found["10"], found["20"]
    assert not any("below zero" in w for w in right["warnings"])
    assert 0.7 < right["estimated_position_rmse"] / right["true"] < 1.3
    assert high["estimated_position_rmse"] is None
    assert high["estimated_position_rmse_interval"] == [None, None]
    (warning,) = [w for w in high["warnings"] if "below zero" in w]
    assert "noise given ([20, 20] m)" in warning and "1σ" in warning
    bound = float(warning.split("(about [")[1].split(",")[0])
    assert 10.0 < bound < 20.0


def test_a_noise_given_well_below_what_the_data_show_is_said_so(tmp_path):
    """σ 10 m given as 5: the smoother follows the measurements, and SURE at the noise given
    counted too little of what is left in them (drones with gaps at σ 20 m given as 10: 13.2 m
    [13.18, 13.23] for a true 25.2 m, without a word). Now the run warns and makes its error
    estimate at the data's reading, its range reaching the noise given; at σ, neither."""
    found = _given_noise_runs(tmp_path, ("10", "5", "7"))
    right, low, near = found["10"], found["5"], found["7"]
    # 0.7 times σ: no warning, the estimate at the noise given, its range reaching the reading's
    assert near["settings"]["noise_below_data"] is not None and near["meas_std"] == [7.0, 7.0]
    assert not any("well below what the data show" in w for w in near["warnings"])
    bottom, top = near["estimated_position_rmse_interval"]
    assert bottom <= near["true"] <= top * 1.05
    _said_and_estimated_at_reading(right, low, "noise_below_data", "well below", "5", (0.8, 1.25))


def test_a_noise_given_above_what_the_data_show_is_said_so(tmp_path):
    """σ 10 m given as 20 (a 95% bound): the noise read off the data says less, so the run warns
    and makes its error estimate at that reading, its range reaching the noise given; before,
    10 s scans printed 11.6 m for a true 15.7 m and the 1 s kinds 0 m, without a word. At σ
    itself neither the warning nor any change (no set of 63 of every kind at σ 3-250 m has
    its reading 3 standard errors below σ; at 2σ, 54 do)."""
    found = _given_noise_runs(tmp_path)
    right, high = found["10"], found["20"]
    _said_and_estimated_at_reading(right, high, "noise_above_data", "above", "20", (0.7, 1.3))


def _said_and_estimated_at_reading(
    right: dict, off: dict, field: str, words: str, given: str, ratio: tuple[float, float]
) -> None:
    """The run at σ (``right``) says nothing and keeps no reading; the run at a noise unlike the
    data's (``off``, given as ``given`` m) warns "``words`` what the data show", keeps the
    reading in ``field`` (about σ, 10 m) and makes its error estimate there, within ``ratio``
    of the truth, its range holding it."""
    phrase = f"{words} what the data show"
    assert right["settings"][field] is None
    assert not any(phrase in w for w in right["warnings"])
    (warning,) = [w for w in off["warnings"] if phrase in w]
    assert f"given as [{given}, {given}] m" in warning and "1σ" in warning
    read = off["settings"][field]
    assert all(8.0 < s < 13.0 for s in read) and off["meas_std"] == read
    assert ratio[0] < off["estimated_position_rmse"] / off["true"] < ratio[1]
    bottom, top = off["estimated_position_rmse_interval"]
    assert bottom <= off["true"] <= top * 1.05


def test_a_noise_given_below_a_reading_of_motion_stands(tmp_path):
    """Aircraft turning all the time between reports 120 s apart, σ 30 m given: the motion
    reads as noise of about 1,800 m, at which the Kalman smoother is not below the
    measurements, so the reading is motion, not noise: the run stays at the noise given (an
    error estimate made at the reading was 2,495 m for a true 42 m)."""
    import pandas as pd

    from torchsvs.datasets import Columns
    from torchsvs.recipes import Settings
    from torchsvs.tracking import track_file

    rng = np.random.default_rng(5)
    rows = []
    for b in range(30):
        point, heading, speed = (
            rng.uniform(-5e3, 5e3, 2),
            rng.uniform(0, 6.3),
            rng.uniform(150, 250),
        )
        path, rate, left = [], 0.0, 0
        for _ in range(80):
            if left == 0:  # a turn of up to 0.01 rad/s for 2-5 reports, then another
                rate, left = rng.uniform(-0.01, 0.01), int(rng.integers(2, 6))
            left -= 1
            for _ in range(60):  # (2 s substeps)
                heading += rate * 2.0
                point = point + 2.0 * speed * np.array([np.cos(heading), np.sin(heading)])
            path.append(point)
        truth = np.array(path)
        z = truth + rng.normal(0, 30.0, truth.shape)
        rows.append(
            pd.DataFrame(
                {
                    "id": f"a{b}",
                    "t": 120.0 * np.arange(80),
                    "x": z[:, 0],
                    "y": z[:, 1],
                    "tx": truth[:, 0],
                    "ty": truth[:, 1],
                }
            )
        )
    frame = pd.concat(rows, ignore_index=True)
    source, target = tmp_path / "sparse.csv", tmp_path / "out.csv"
    frame[["id", "t", "x", "y"]].to_csv(source, index=False)
    given = Settings("ks", meas_var=[900.0, 900.0])
    run = track_file(
        source, target, given, columns=Columns(track_id="id", time="t"), progress=False
    )
    assert run.settings is not None and run.settings.noise_below_data is None
    out = pd.read_csv(target)
    true = np.sqrt(((out.x - frame.tx) ** 2 + (out.y - frame.ty) ** 2).mean())
    found = run.accuracy
    assert found is not None and found.estimated_rmse < 2.0 * true


def test_a_3d_run_estimates_its_horizontal_and_vertical_errors_apart(tmp_path, capsys):
    """Aircraft at σ 20 m horizontally and 60 m in altitude: a track judged by its horizontal
    error had only the 3-D estimate, the altitude's in it. The summary and the run's line give
    each apart; each range holds its true RMSE, and their MSEs
    sum to the whole's (the noise given: read off the data, the ranges are wide)."""
    gen = np.random.default_rng(5)
    rows, truth = [], []
    for k in range(40):
        t = np.cumsum(gen.uniform(1.0, 5.0, 150))
        v = np.r_[gen.normal(0, 150, 2), gen.normal(0, 5)]
        pos = t[:, None] * v + np.cumsum(gen.normal(0, 1, (150, 3)), 0)
        z = pos + gen.normal(0, 1, (150, 3)) * np.array([20.0, 20.0, 60.0])
        rows += [
            f"a{k},{ti:.3f}," + ",".join(f"{c:.3f}" for c in p) for ti, p in zip(t, z, strict=True)
        ]
        truth.append(pos)
    source = tmp_path / "a.csv"
    source.write_text("id,time,x,y,z\n" + "\n".join(rows) + "\n")
    target = tmp_path / "o.csv"
    main(
        ["track", str(source), "-o", str(target), "--id-col", "id", "--meas-std", "20,20,60"]
        + ["--estimator", "ks"]
    )
    said = capsys.readouterr().err
    assert "  of it: horizontal " in said and "; vertical " in said, said
    out = pcsv.read_csv(target)
    est = np.stack([out.column(c).to_numpy() for c in ("x", "y", "z")], 1)
    err = est - np.concatenate(truth)
    summary = json.loads((tmp_path / "o.summary.json").read_text())
    true = {
        "horizontal": math.sqrt(float(np.mean(err[:, 0] ** 2 + err[:, 1] ** 2))),
        "vertical": math.sqrt(float(np.mean(err[:, 2] ** 2))),
    }
    for name, rmse in true.items():
        part = summary[f"{name}_position_rmse"]
        low, high = part["interval"]
        assert low <= rmse <= high, (name, rmse, part)
    # (the altitude, smoothed over many reports, has an estimate of wide sampling error)
    horizontal = summary["horizontal_position_rmse"]["estimated"]
    assert horizontal == pytest.approx(true["horizontal"], rel=0.15)
    whole = summary["estimated_position_rmse"] ** 2
    parts = sum(summary[f"{n}_position_rmse"]["estimated"] ** 2 for n in true)
    assert parts == pytest.approx(whole, rel=1e-9)
