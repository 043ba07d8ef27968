"""The recorded-tracks benchmark (experiments/recorded_tracks.py) end to end on a tiny set, and
its parts against numbers that follow from their definitions."""

from __future__ import annotations

import json
import math
from dataclasses import asdict
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from experiments import recorded_sets as rs
from experiments import recorded_tracks as rt


def tiny_turning(rows: int = 400, sigma: float = 50.0, seed: int = 0) -> rs.BenchSet:
    kind = rs.KINDS["turning"]
    truth = kind.build(rows, seed)
    return rs.BenchSet(kind, sigma, truth, rs.measure(truth.rows, sigma, seed))


def test_input_holds_measurements_only_with_the_noise_asked_for(tmp_path: Path) -> None:
    bench = tiny_turning(rows=1000, sigma=50.0)
    source, truth_file = bench.write(tmp_path)
    measured, truth = pd.read_csv(source), pd.read_csv(truth_file)
    assert list(measured.columns) == ["track_id", "time", "x", "y"]
    assert len(measured) == len(truth) == 1000
    assert (measured["track_id"] == truth["track_id"]).all()
    noise = (measured[["x", "y"]] - truth[["x", "y"]]).to_numpy().ravel()
    # 2000 N(0, σ²) draws: the variance ratio has standard deviation √(2/2000) ≈ 0.032.
    assert abs(noise.var() / 50.0**2 - 1) < 5 * math.sqrt(2 / len(noise))
    assert abs(noise.mean()) < 5 * 50.0 / math.sqrt(len(noise))
    # 2-D raw RMSE ≈ σ√2
    assert rs.describe(bench).raw_rmse == pytest.approx(
        math.sqrt(2) * 50.0, rel=5 * math.sqrt(1 / 1000)
    )
    # the same seed gives the same set; another noise level other noise
    again = tiny_turning(rows=1000, sigma=50.0)
    assert np.array_equal(again.measurements[["x", "y"]], bench.measurements[["x", "y"]])
    with pytest.raises(ValueError, match="^sigma"):
        rs.measure(truth, 0.0, 0)


def test_score_counts_rows_without_an_estimate_and_matches_rows_by_key() -> None:
    truth = pd.DataFrame(
        {"track_id": ["a"] * 4 + ["b"] * 3, "time": [0, 1, 2, 3, 0, 5, 9], "x": 1.0, "y": 2.0}
    )
    truth["x"] = np.arange(7, dtype=float)
    output = truth.assign(x=truth["x"] + 3.0, y=truth["y"] + 4.0)  # every error 5 m
    assert rt.score(output, truth) == (pytest.approx(5.0), 0)
    holes = output.copy()
    holes.loc[[1, 5], "x"] = np.nan
    assert rt.score(holes, truth) == (pytest.approx(5.0), 2)
    shuffled = holes.sample(frac=1.0, random_state=1).iloc[1:]  # another order, one row gone
    rmse, missing = rt.score(shuffled, truth)
    gone = holes.sample(frac=1.0, random_state=1).iloc[0]
    assert rmse == pytest.approx(5.0)
    assert missing == 2 + int(np.isfinite(gone["x"]))


def test_dejitter_moves_positions_along_the_track_only_and_cuts_white_timing_error() -> None:
    t = np.arange(0.0, 2000.0)
    speed = 150.0
    line = np.stack([speed * t, np.zeros_like(t)], 1)
    s = 25.0
    rng = np.random.default_rng(0)
    recorded = line + np.stack([rng.normal(0, s, len(t)), np.zeros_like(t)], 1)
    moved, done = rs.dejitter(t, recorded)
    interior = (t >= rs.DEJITTER_WINDOW) & (t <= t[-1] - rs.DEJITTER_WINDOW)
    assert done[interior].all()
    # the track is a line along x: nothing moves across it
    assert np.abs(moved[:, 1]).max() < 1e-6
    # along it, the error left is the local fit's: Σ ℓ_j² of its equivalent kernel (probed with
    # unit impulses) times s²
    centre = 1000
    weights = []
    for j in range(centre - 12, centre + 13):
        impulse = np.zeros((len(t), 1))
        impulse[j] = 1.0
        fitted, _, _ = rs.local_quadratic(t, impulse, rs.DEJITTER_WINDOW, 2)
        weights.append(fitted[centre, 0])
    expected = s * math.sqrt(sum(w * w for w in weights))
    left = np.sqrt(np.mean((moved[interior, 0] - line[interior, 0]) ** 2))
    # about 1950 interior errors correlated over ±10 steps: ~100 independent ones, so the RMS
    # is within ~7% (1/√(2·100)); 25% is over three of those
    assert left == pytest.approx(expected, rel=0.25)
    assert expected < 0.6 * s

    # a constant-speed turn sampled evenly: the fit's bias is radial, so nothing moves inside
    omega = math.radians(6.0)
    circle = 2500.0 * np.stack([np.cos(omega * t[:300]), np.sin(omega * t[:300])], 1)
    moved, done = rs.dejitter(t[:300], circle)
    inner = slice(11, 289)
    assert done[inner].all()
    assert np.abs(moved[inner] - circle[inner]).max() < 1e-6


def test_timing_glitches_find_a_report_stamped_seconds_off_on_straight_flight_only() -> None:
    rng = np.random.default_rng(3)
    t = np.cumsum(rng.uniform(10.0, 30.0, 60))  # sparse, irregular reports
    line = np.stack([240.0 * t, 0.5 * t], 1)
    stamped = t.copy()
    stamped[20] += 9.0  # the report at step 20 carries a time stamp 9 s late
    found = rs.timing_glitches(stamped, line)
    assert found.tolist() == [k == 20 for k in range(60)]
    # 4 s off is within the rule
    stamped = t.copy()
    stamped[20] += 0.8 * rs.GLITCH_SECONDS
    assert not rs.timing_glitches(stamped, line).any()
    # motion, not glitches: a 3 deg/s turn, and a speed change, sampled the same way
    omega = math.radians(3.0)
    turn = 4000.0 * np.stack([np.cos(omega * t), np.sin(omega * t)], 1)
    assert not rs.timing_glitches(t, turn).any()
    speeding = np.stack([150.0 * t + 0.05 * t**2, np.zeros_like(t)], 1)
    assert not rs.timing_glitches(t, speeding).any()


def test_isolated_jumps_split_two_tracks_joined_but_not_a_take_off_roll() -> None:
    t = np.arange(0.0, 400.0, 8.0)
    path = np.stack([30.0 * t, 5.0 * t], 1)
    path[25:] += [2700.0, 0.0]  # the record jumps 2.7 km in 8 s and goes on from there
    piece = rs.Piece("g", t, path, np.full(len(t), np.nan))
    assert rs.isolated_jumps(piece).tolist() == [k == 25 for k in range(len(t))]
    assert [len(p) for p in rs.split_at(piece, rs.isolated_jumps(piece))] == [25, len(t) - 25]
    # a take-off roll: 5 to 80 m/s at 3 m/s² over many steps, at the end of a taxi piece
    speed = np.concatenate([np.full(40, 5.0), 5.0 + 3.0 * np.arange(1, 26)])
    roll = np.stack([np.cumsum(speed), np.zeros_like(speed)], 1)
    taxi = rs.Piece("r", np.arange(len(speed), dtype=float), roll, np.full(len(speed), np.nan))
    assert not rs.isolated_jumps(taxi).any()


def test_add_faults_keeps_rows_aligned_and_gives_each_fault_its_share() -> None:
    t = np.arange(0.0, 4000.0, 2.0)
    truth = pd.concat(
        [
            pd.DataFrame({"track_id": k, "time": t, "x": 100.0 * t, "y": 0.0 * t})
            for k in ("a", "b", "c", "d", "e")
        ],
        ignore_index=True,
    )
    sigma = 10.0
    measured = rs.measure(truth, sigma, seed=1)
    faulty_truth, faulty = rs.add_faults(truth, measured, sigma, seed=2)
    # row for row, same keys, times still increasing within each track
    assert faulty_truth[["track_id", "time"]].equals(faulty[["track_id", "time"]])
    assert faulty.groupby("track_id")["time"].apply(lambda s: s.is_monotonic_increasing).all()
    lost = 1 - len(faulty) / len(truth)
    assert 0.5 * rs.DROPOUT_SHARE < lost < 2 * rs.DROPOUT_SHARE
    # the truth keeps its positions; the stamps moved by the jitter only
    shift = faulty_truth["time"] - faulty_truth["x"] / 100.0
    assert 0.5 * rs.JITTER_STD < shift.std() < 1.5 * rs.JITTER_STD
    error = np.hypot(faulty["x"] - faulty_truth["x"], faulty["y"] - faulty_truth["y"]) / sigma
    # outliers: 10σ off (noise alone passes 7σ with probability e^-24.5)
    far = error > 7
    assert 0.5 * rs.OUTLIER_SHARE < far.mean() < 2 * rs.OUTLIER_SHARE
    # elsewhere the squared error is the noise's (2σ², two axes) plus the bias's on its share
    expected = 2.0 + rs.BIAS_SHARE * rs.BIAS_SIGMAS**2
    assert (error[~far] ** 2).mean() == pytest.approx(expected, rel=0.1)


def test_roughness_reads_white_error_off_one_second_reports() -> None:
    t = np.arange(0.0, 5000.0)
    rng = np.random.default_rng(1)
    along, across = 20.0, 3.0
    path = np.stack([100.0 * t + rng.normal(0, along, len(t)), rng.normal(0, across, len(t))], 1)
    piece = rs.Piece("a", t, path, np.full(len(t), np.nan))
    found = rs.roughness([piece])
    # 4998 offsets each; relative standard error of an RMS about 1/√(2n) = 1%
    assert found["along"] == pytest.approx(along, rel=0.06)
    assert found["across"] == pytest.approx(across, rel=0.06)
    sparse = rs.Piece("b", 10.0 * t[:50], path[:50], np.full(50, np.nan))
    assert math.isnan(rs.roughness([sparse])["along"])


def test_estimator_choices_follow_the_command_including_auto() -> None:
    from torchsvs.estimator_names import ESTIMATORS
    from torchsvs.track_options import track_parser

    names, default = rt.estimator_choices()
    assert set(names) >= set(ESTIMATORS) and default in names
    parser = track_parser()
    action = next(a for a in parser._actions if "--estimator" in a.option_strings)
    action.choices = sorted({*ESTIMATORS, "auto", "new"})
    action.default = "auto"
    names, default = rt.estimator_choices(parser)
    extra = sorted({"auto", "new"} - set(ESTIMATORS))
    assert names == [*ESTIMATORS, *extra]  # the table's order first, the others after
    assert default == "auto"


def test_summary_beside_the_output_is_read_and_flagged(tmp_path: Path) -> None:
    target = tmp_path / "out.csv"
    assert rt.summary_path(target) == tmp_path / "out.summary.json"
    assert rt.read_summary(target) == {}
    rt.summary_path(target).write_text(
        json.dumps({"estimated_position_rmse": 30.0, "measurement_rmse": 70.0})
    )
    summary = rt.read_summary(target)
    assert rt.summary_number(summary, "estimated_position_rmse") == 30.0
    assert rt.summary_number({"overall": summary}, "measurement_rmse") == 70.0
    assert math.isnan(rt.summary_number(summary, "nothing"))
    bench = tiny_turning(rows=200)
    close = rt.Run(bench.name, "ks", "default", [], rmse=27.0, raw=70.0, estimated=30.0)
    far = rt.Run(bench.name, "kf", "default", [], rmse=25.0, raw=70.0, estimated=30.0)
    text = rt.detail_section([close, far], bench)
    assert "| 1.11 |" in text  # 30 / 27: within 15%
    assert "**1.20** ⚠" in text  # 30 / 25: flagged
    text = rt.estimate_section([close, far])
    assert text.startswith("2 runs wrote a truth-free estimate; 1 are more than 15% off")


def test_harness_end_to_end_on_a_tiny_set(tmp_path: Path) -> None:
    bench = tiny_turning(rows=400)
    runs = rt.run_all([bench], ["ks"], ["default", "--meas-std σ"], tmp_path, progress=False)
    assert [(r.estimator, r.mode) for r in runs] == [("ks", "default"), ("ks", "--meas-std σ")]
    raw = rs.describe(bench).raw_rmse
    for run in runs:
        assert run.ok and run.missing == 0 and run.rows == 400
        assert run.raw == raw and math.isfinite(run.rmse) and run.seconds > 0
    assert runs[1].argv[-2:] == ["--meas-std", "50"]
    # the work folder's journal resumes an interrupted benchmark: nothing runs again
    again = rt.run_all([bench], ["ks"], ["default", "--meas-std σ"], tmp_path, progress=False)
    assert [json.dumps(asdict(r)) for r in again] == [json.dumps(asdict(r)) for r in runs]
    # a run that cannot run is kept with the command's message, every row counted as missing
    broken = rt.run_job(
        rt.Job(bench.name, 50.0, raw, str(tmp_path / "nothing.csv"), str(tmp_path / "sets" /
               f"{bench.slug}.truth.csv"), "ks", "default", str(tmp_path / "x.csv"), "inprocess")
    )  # fmt: skip
    assert not broken.ok and broken.error and broken.missing == 400
    figure = tmp_path / "map.png"
    rt.heat_map([*runs, broken], [bench.name], ["ks"], ["default", "--meas-std σ"], figure)
    assert figure.stat().st_size > 0
    check = {"before": 25.0, "after": 3.0}
    text = rt.report(
        [bench], [*runs, broken], ["ks"], ["default"], "ks", {}, "1 s", figure.name, check
    )
    assert bench.name in text and "The command's default estimator is `" in text
    assert "from 25.0 m as recorded to 3.0 m after it" in text
    assert "Messages of the runs that gave nothing:\n\n- 1 × " in text and "$" not in text
    # the mode without options says so; no `auto` among the estimators: the best table says so
    assert "the mode's options: `default` (no option: the noise is read off the data). " in text
    assert ". The command has no `auto` yet: its column appears when it does." in text
    assert "1 runs (1 sets × 1 estimators × 1 modes)" not in text  # three runs were given
    assert "3 runs (1 sets × 1 estimators × 1 modes)" in text
    assert rt.estimate_section([broken]).startswith("No run wrote a summary")
    near = [rt.Run(bench.name, "ks", "default", [], rmse=27.0, raw=70.0, estimated=30.0)]
    assert rt.estimate_section(near).startswith(
        "1 runs wrote a truth-free estimate; 0 are more than 15% off the true RMSE."
    )


def test_the_command_line_gives_what_the_in_process_run_gives(tmp_path: Path) -> None:
    bench = tiny_turning(rows=200)
    source, truth = bench.write(tmp_path / "sets")
    raw = rs.describe(bench).raw_rmse

    def job(via: str) -> rt.Job:
        target = str(tmp_path / f"{via}.csv")
        return rt.Job(
            bench.name, 50.0, raw, str(source), str(truth), "ks", "--meas-std σ", target, via
        )

    inprocess, cli = rt.run_job(job("inprocess")), rt.run_job(job("cli"))
    assert inprocess.ok and cli.ok
    assert cli.rmse == pytest.approx(inprocess.rmse, rel=1e-12)
    assert cli.sigma_used == pytest.approx(inprocess.sigma_used)


def test_the_family_section_sets_the_best_of_the_svsf_family_against_the_smoother() -> None:
    """Issue 29's measure in the report: the best of svsf, svss and svstps over ks per set and
    mode, bold above 1 as printed (a Kalman twin's float noise reads 1.0000, not above), with
    the count above 1, the worst and the mean; nothing where the smoother or the family is
    missing."""

    def run(s: str, estimator: str, mode: str, rmse: float) -> rt.Run:
        return rt.Run(s, estimator, mode, [], rmse=rmse, raw=100.0)

    runs = [
        run("a", "ks", "default", 50.0),
        run("a", "svss", "default", 50.0 * (1 + 1e-9)),  # a twin: 1.0000
        run("a", "svsf", "default", 70.0),
        run("a", "ks", "--fit", 50.0),
        run("a", "svstps", "--fit", 51.0),  # 1.0200, bold
        run("b", "ks", "default", 40.0),
        run("b", "svss", "default", 38.0),  # 0.9500
        run("b", "ks", "--fit", 40.0),  # (no family run: —)
    ]
    text = rt.family_section(runs, ["a", "b"], ["default", "--fit"])
    assert "| a | 1.0000 (svss) | **1.0200 (svstps)** |" in text
    assert "| b | 0.9500 (svss) | — |" in text
    assert "Above 1 on 1 of 3; the worst 1.0200 (a, --fit); the mean 0.9900." in text
    assert rt.family_section([run("a", "ks", "default", 5.0)], ["a"], ["default"]) == ""


def test_a_merge_keeps_the_saved_runs_of_other_noise_levels(tmp_path: Path, monkeypatch) -> None:
    """``--merge`` of one kind at one σ into a report of several: every saved run stays, each
    set rebuilt at its own σ (one merge at σ 50 dropped a report's σ 10 and 100 sets, 240 of
    its 528 runs, and wrote the file without them)."""
    kept = [rt.Run(f"walker σ{s:g}", "ks", "default", [], rmse=1.0, raw=2.0) for s in (3.0, 10.0)]
    to_run = rs.build_sets(["walker"], rows=200, seed=0, sigmas=[25.0])
    sets = rt.merged_sets(to_run, kept, rows=200, seed=0, faults=False)
    assert [b.name for b in sets] == ["walker σ3", "walker σ10", "walker σ25"]
    again = rs.build_sets(["walker"], rows=200, seed=0, sigmas=[3.0])[0]
    pd.testing.assert_frame_equal(sets[0].measurements, again.measurements)  # as first built
    # a saved run the report has no set for stops the command before anything is written
    out = tmp_path / "out"
    out.mkdir()
    saved = out / "r.json"
    rt.save_runs(saved, {}, [*kept, rt.Run("walker σ3", "nosuch", "default", [])])
    before = saved.read_text()
    monkeypatch.setattr(rt, "run_all", lambda *args, **kw: [])
    with pytest.raises(SystemExit, match="merge: 1 saved runs"):
        rt.main(["--merge", "--kinds", "walker", "--sigmas", "25", "--estimators", "ks",
                 "--rows", "200", "--out", str(out), "--name", "r", "--quiet"])  # fmt: skip
    assert saved.read_text() == before
    # runs of another draw are not merged into a report of saved ones (its sets are rebuilt
    # as the saved runs drew them: --report-only of a seed-3 report shows seed 3's sets)
    rt.save_runs(saved, {"seed": 5, "rows": "~200 per set"}, kept)
    with pytest.raises(SystemExit, match="saved runs are of --seed 5 --rows 200"):
        rt.main(["--merge", "--kinds", "walker", "--sigmas", "25", "--estimators", "ks",
                 "--rows", "200", "--out", str(out), "--name", "r", "--quiet"])  # fmt: skip


def test_each_noise_kind_has_its_standard_deviation_and_its_shape():
    """``measure``'s kinds (the benchmark's --noise): white is the Gaussian draw as before (the
    saved reports' sets are drawn again as they were) and has no column beside it; white, heavy
    and correlated have about σ overall; mixed gives each track its own σ within σ/3-3σ, σ
    their geometric mean, and states it in the rows' ``sigma`` column; heavy has the tails of t
    with 3 degrees of freedom (far more beyond 4σ than the Gaussian); correlated has the
    correlation exp(-Δt/τ) between a track's successive reports and none between tracks."""
    gen = np.random.default_rng(0)
    tracks, steps, sigma = 200, 100, 10.0
    truth = pd.DataFrame(
        {
            "track_id": np.repeat([f"t{k:03d}" for k in range(tracks)], steps),
            "time": np.tile(np.arange(steps, dtype=float) * 2.0, tracks),
            "x": gen.normal(0.0, 1e3, tracks * steps),
            "y": gen.normal(0.0, 1e3, tracks * steps),
        }
    )

    def error(noise: str) -> np.ndarray:
        measured = rs.measure(truth, sigma, 7, noise)
        return (measured[["x", "y"]].to_numpy() - truth[["x", "y"]].to_numpy()).reshape(
            tracks, steps, 2
        )

    before = np.random.default_rng(7).normal(0.0, sigma, size=(tracks * steps, 2))
    white = rs.measure(truth, sigma, 7, "white")[["x", "y"]].to_numpy()
    np.testing.assert_array_equal(white, truth[["x", "y"]].to_numpy() + before)
    for noise in ("white", "heavy", "correlated"):
        assert 0.85 * sigma < error(noise).std() < 1.15 * sigma, noise
    per_track = error("mixed").std(axis=(1, 2))
    stated = rs.measure(truth, sigma, 7, "mixed")["sigma"].to_numpy().reshape(tracks, steps)
    assert (stated == stated[:, :1]).all()
    np.testing.assert_allclose(stated[:, 0], per_track, rtol=0.25)
    assert "sigma" not in rs.measure(truth, sigma, 7, "white").columns
    assert 0.75 * sigma < np.exp(np.log(per_track).mean()) < 1.25 * sigma  # (σ in the middle)
    assert per_track.min() > sigma / 3.5 and per_track.max() < 3.5 * sigma
    assert per_track.max() / per_track.min() > 4.0  # (white: within ±15%)
    far = [np.mean(np.abs(error(n)) > 4 * sigma) for n in ("white", "heavy")]
    assert far[0] < 2e-4 and far[1] > 20 * max(far[0], 1e-4)
    wander = error("correlated")
    lag1 = np.mean(wander[:, 1:] * wander[:, :-1]) / np.mean(wander**2)
    assert abs(lag1 - math.exp(-2.0 / rs.CORRELATION_TIME)) < 0.03
    assert abs(np.mean(wander[1:, 0] * wander[:-1, 0]) / sigma**2) < 0.1
    with pytest.raises(ValueError, match="noise: expected one of"):
        rs.measure(truth, sigma, 7, "pink")
