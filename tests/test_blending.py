"""Two estimators blended by SURE (torchsvs.blending): the identities its error terms rest
on, its weight, a blend as ``track`` runs it, and ``auto`` choosing one."""

from __future__ import annotations

import json
from dataclasses import asdict, replace

import numpy as np
import pandas as pd
import pytest
import torch

from tests.conftest import assert_close
from torchsvs.accuracy import chunk_terms
from torchsvs.blending import best_weight, blended_terms, cross_terms
from torchsvs.recipes import Settings
from torchsvs.track_plan import TrackPlan, plan_tracks, saved_settings
from torchsvs.track_run import summary_path
from torchsvs.track_table import track_table


def _estimates(seed: int = 0, B: int = 5, T: int = 70, m: int = 2):
    """Measurements (with gaps), two estimates that err differently, and their divergences."""
    gen = torch.Generator().manual_seed(seed)
    truth = torch.cumsum(torch.randn(B, T, m, generator=gen, dtype=torch.float64), 1)
    z = truth + torch.randn(B, T, m, generator=gen, dtype=torch.float64) * 3
    z[torch.rand(B, T, m, generator=gen) < 0.15] = float("nan")
    g = truth + torch.randn(B, T, m, generator=gen, dtype=torch.float64)
    f = truth + torch.randn(B, T, m, generator=gen, dtype=torch.float64) * 1.5
    dg = torch.rand(B, T, m, generator=gen, dtype=torch.float64) * 0.3
    df = torch.rand(B, T, m, generator=gen, dtype=torch.float64) * 0.2
    return z, g, f, dg, df


def _terms(z, estimate, divergence):
    observed = ~torch.isnan(z)
    residual = torch.where(observed, z - estimate, 0.0).square()
    return chunk_terms(observed, residual, torch.where(observed, divergence, 0.0))


def test_blended_terms_equal_the_terms_of_the_blended_estimate_at_any_weight():
    """The residual's identity and the divergence's linearity, chunk by chunk: the blend's SURE
    sums from the two estimators' and C equal those computed from the blend itself."""
    z, g, f, dg, df = _estimates()
    group = np.arange(z.shape[0])
    first, second = _terms(z, g, dg), _terms(z, f, df)
    cross = cross_terms(~torch.isnan(z), g, f, group)
    for w in (0.0, 0.3, 0.5, 0.9, 1.0):
        direct = _terms(z, (1 - w) * g + w * f, (1 - w) * dg + w * df)
        found = blended_terms(first, second, cross, w)
        assert_close(found.residual, direct.residual, atol=1e-9, rtol=1e-12)
        assert_close(found.divergence, direct.divergence, atol=1e-12, rtol=1e-12)
        assert np.array_equal(found.count, direct.count)
    with pytest.raises(ValueError, match="cross: expected the terms of the same chunks"):
        blended_terms(first, second, cross.select(np.arange(len(cross.count) - 1)), 0.5)


def test_best_weight_is_the_least_estimated_mse_over_every_weight():
    """w* (the closed form) against a fine grid of weights: no weight's estimated MSE is lower,
    whether the least is inside (0, 1) or at an end."""
    z, g, f, dg, df = _estimates(seed=1)
    group = np.arange(z.shape[0])
    first, second = _terms(z, g, dg), _terms(z, f, df)
    cross = cross_terms(~torch.isnan(z), g, f, group)
    meas_var = [9.0, 9.0]

    def mse(w):
        return blended_terms(first, second, cross, w).mse(meas_var)[0]

    w = best_weight(first, second, cross, meas_var)
    assert 0.05 < w < 0.95
    grid = np.linspace(0.0, 1.0, 201)
    assert mse(w) <= min(mse(v) for v in grid) + 1e-9
    # an estimate that moves away from the measurements where the other nears them: the least
    # at an end
    away = g - 2.0 * (z - g).nan_to_num(0.0)
    worse, worse_cross = _terms(z, away, df), cross_terms(~torch.isnan(z), g, away, group)
    assert best_weight(first, worse, worse_cross, meas_var) == 0.0
    back = cross_terms(~torch.isnan(z), away, g, group)
    assert best_weight(worse, first, back, meas_var) == 1.0
    # two estimates the same: no blend to find
    assert best_weight(first, first, cross_terms(~torch.isnan(z), g, g, group), meas_var) == 0.0


def _wandering(path, seed=0, sigma=40.0, n=10, T=160):
    """Tracks that alternate straight legs and turns, 4 s reports, as a CSV; the truth."""
    gen = np.random.default_rng(seed)
    rows, truth = [], []
    for k in range(n):
        t = np.arange(T) * 4.0
        rate = np.zeros(T)
        for start in gen.choice(np.arange(10, T - 30), 3, replace=False):
            rate[start : start + gen.integers(8, 25)] = np.radians(gen.uniform(-3, 3))
        heading = np.cumsum(rate * 4.0) + gen.uniform(0, 6.28)
        speed = 100 + 20 * np.sin(t / gen.uniform(80, 300))
        pos = np.cumsum(speed[:, None] * np.stack([np.cos(heading), np.sin(heading)], 1) * 4, 0)
        z = pos + gen.normal(0, sigma, pos.shape)
        rows.append(pd.DataFrame({"track_id": f"t{k}", "time": t, "x": z[:, 0], "y": z[:, 1]}))
        truth.append(pd.DataFrame({"track_id": f"t{k}", "time": t, "x": pos[:, 0], "y": pos[:, 1]}))
    data = pd.concat(rows, ignore_index=True)
    data.to_csv(path, index=False)
    return data, pd.concat(truth, ignore_index=True)


def _rmse(table, truth):
    both = table.merge(truth, on=["track_id", "time"], suffixes=("", "_t"))
    assert len(both) == len(truth)
    return float(np.sqrt(((both.x - both.x_t) ** 2 + (both.y - both.y_t) ** 2).mean()))


def test_a_blend_runs_as_its_two_estimators_blended(tmp_path):
    """A plan with a blend (the Kalman smoother's and the IMM smoother's estimates, weight
    0.4) gives the blend of the two plans' outputs, positions and velocities; its error
    estimate's residual is the blend's own against the measurements, its divergence the
    weighted sum of the two's; the covariance the blend of theirs."""
    data, _ = _wandering(tmp_path / "in.csv")
    ks = plan_tracks(data, Settings("ks"))
    ks = replace(ks, dtype=torch.float64, precision="float64")
    imm = plan_tracks(data, Settings("imm", meas_var=ks.settings.meas_var))
    imm = replace(imm, precision="float64")
    second = replace(imm.settings, outlier_q=ks.settings.outlier_q)
    w = 0.4
    settings = replace(ks.settings, blend=second, blend_weight=w)
    parameters = {f"first.{k}": v for k, v in ks.parameters.items()}
    parameters |= {f"second.{k}": v for k, v in imm.parameters.items()}
    blend = TrackPlan(ks.columns, settings, parameters, torch.float64, "float64")
    assert blend.estimator().weight == w
    runs = {
        name: track_table(data, plan, covariance=True)
        for name, plan in (("ks", ks), ("imm", replace(imm, settings=second)), ("blend", blend))
    }
    columns = ["x", "vx", "y", "vy", "cov_x_x", "cov_vx_vy"]
    ours = runs["blend"].table[columns].to_numpy()
    theirs = (1 - w) * runs["ks"].table[columns].to_numpy() + w * runs["imm"].table[columns]
    assert_close(ours, theirs.to_numpy(), atol=1e-9, rtol=1e-12)
    assert not runs["blend"].table["outlier"].any()  # (so every measurement is in the sums)
    m = 2
    totals = {name: found.run.risk.first for name, found in runs.items()}
    estimate = runs["blend"].table[["x", "y"]].to_numpy()
    residual = np.nansum((data[["x", "y"]].to_numpy() - estimate) ** 2, axis=0)
    assert_close(totals["blend"][:m], residual, atol=1e-6, rtol=1e-10)
    divergence = (1 - w) * totals["ks"][m : 2 * m] + w * totals["imm"][m : 2 * m]
    assert_close(totals["blend"][m : 2 * m], divergence, atol=1e-9, rtol=1e-10)


def test_blend_settings_are_checked_and_read_back_from_a_save_file():
    inner = Settings("imm", meas_var=[4.0, 4.0])
    blend = Settings("ks", meas_var=[4.0, 4.0], blend=inner, blend_weight=0.3)
    assert Settings(**json.loads(json.dumps(asdict(blend)))) == blend
    with pytest.raises(ValueError, match=r"blend_weight: expected a weight in \(0, 1\)"):
        Settings("ks", meas_var=[4.0, 4.0], blend=inner, blend_weight=1.0)
    with pytest.raises(ValueError, match="blend: expected the settings of one estimator"):
        Settings("svss", meas_var=[4.0, 4.0], blend=blend, blend_weight=0.5)
    with pytest.raises(ValueError, match="blend: expected the same meas_var"):
        Settings("ks", meas_var=[9.0, 4.0], blend=inner, blend_weight=0.5)


def test_auto_blends_where_surely_lower_and_says_so(tmp_path):
    """``auto`` on simulated cars in town at σ 10 m (the benchmark's kind, 2,000 rows), where
    the Kalman and IMM smoothers are about as good and each better in its own places: the
    blend of the chosen candidate with the next is surely lower on the sample, the run takes
    it (in the candidates' table and the summary, with its weight), its estimated error near
    the truth's, and the truth lower than the chosen candidate's alone. A --save file of it
    runs the same estimates again."""
    from experiments.recorded_sets import build_sets
    from torchsvs.datasets import Columns
    from torchsvs.tracking import track_file

    (bench,) = build_sets(["car"], rows=2000, seed=0, sigmas=[10.0])
    source, truth = tmp_path / "in.csv", bench.truth.rows
    bench.measurements.to_csv(source, index=False)
    target, saved = tmp_path / "auto.csv", tmp_path / "auto.pt"
    run = track_file(
        source, target, Settings("auto"), columns=Columns(), progress=False, save=saved
    )
    assert run.settings is not None and run.settings.blend is not None
    summary = json.loads(summary_path(target).read_text())
    blend_row = [r for r in summary["candidates"] if not r.get("skipped")][-1]
    first, second = run.settings.estimator, run.settings.blend.estimator
    assert blend_row["estimator"] == summary["estimator"] == f"{first}+{second}"
    assert blend_row["mse_change"] + blend_row["mse_change_se"] < 0  # surely lower
    assert f"weight {run.settings.blend_weight:.2f} on {second}" == blend_row["learned"]
    assert summary["settings"]["blend"]["estimator"] == second
    blended = _rmse(pd.read_csv(target), truth)
    alone = tmp_path / "alone.csv"
    track_file(source, alone, replace(run.settings, blend=None, blend_weight=0.0), progress=False)
    assert blended < _rmse(pd.read_csv(alone), truth)
    assert summary["estimated_position_rmse"] == pytest.approx(blended, rel=0.2)
    again = tmp_path / "again.csv"
    track_file(source, again, saved_settings(saved), checkpoint=saved, progress=False)
    assert_close(
        pd.read_csv(again)[["x", "y"]].to_numpy(), pd.read_csv(target)[["x", "y"]].to_numpy()
    )


def test_a_blend_plan_travels_by_pickle_and_splits_as_its_estimators_do(tmp_path):
    """An engine broadcasts the plan as a pickle and runs it on parts of the tracks: a blend of
    two estimators whose estimates do not depend on a table's other tracks (the Kalman
    smoother and the SVSS) gives, from the copy and over three parts, the estimates of one
    table, to the last bit (tests/test_track_table.py holds the two alone so)."""
    import pickle

    data, _ = _wandering(tmp_path / "in.csv", n=9, T=60)
    ks = plan_tracks(data, Settings("ks"))
    svss = plan_tracks(data, Settings("svss", meas_var=ks.settings.meas_var, psi=[2.0, 2.0]))
    second = replace(svss.settings, outlier_q=ks.settings.outlier_q)
    settings = replace(ks.settings, blend=second, blend_weight=0.3)
    parameters = {f"first.{k}": v for k, v in ks.parameters.items()}
    parameters |= {f"second.{k}": v for k, v in svss.parameters.items()}
    plan = TrackPlan(ks.columns, settings, parameters, ks.dtype, "float64")
    whole = track_table(data, plan).table
    copy = pickle.loads(pickle.dumps(plan))
    pd.testing.assert_frame_equal(track_table(data, copy).table, whole, check_exact=True)
    part_of = data["track_id"].map(lambda i: int(i[1:]) % 3)
    parts = [track_table(data[part_of == p], copy, check=False).table for p in range(3)]
    joined = pd.concat(parts).sort_values(["track_id", "time"], kind="stable")
    expected = whole.sort_values(["track_id", "time"], kind="stable")
    pd.testing.assert_frame_equal(
        joined.reset_index(drop=True), expected.reset_index(drop=True), check_exact=True
    )


def test_a_blend_run_is_named_by_both_and_its_divergence_not_called_exact():
    """A run's warnings name a blend by both its estimators, and an uncertain estimate of a
    blend with a probed estimator (the IMM) says its sensitivity is probed, where the Kalman
    smoother alone (exact) does not."""
    from torchsvs.accuracy import RiskTerms, RiskTotals
    from torchsvs.track_run import TrackRun

    gen = np.random.default_rng(0)
    residual = gen.gamma(1.0, 14000.0, (6, 2))  # few chunks, widely spread: uncertain
    terms = RiskTerms(residual, np.full((6, 2), 8.0), np.full((6, 2), 32.0), np.arange(6))
    inner = Settings("imm", meas_var=[900.0, 900.0], noise="given")
    warned = {}
    for blend in (None, inner):
        weight = 0.0 if blend is None else 0.4
        settings = Settings(
            "ks", meas_var=[900.0, 900.0], noise="given", blend=blend, blend_weight=weight
        )
        run = TrackRun(settings=settings, risk=RiskTotals(2))
        run.risk.add(terms)
        run.check()
        warned[settings.name] = [w for w in run.warnings if "is uncertain" in w]
    assert len(warned["ks"]) == len(warned["ks+imm"]) == 1
    assert warned["ks"][0].startswith("ks: ") and "probed" not in warned["ks"][0]
    assert warned["ks+imm"][0].startswith("ks+imm: ") and "probed at random" in warned["ks+imm"][0]


def test_the_samples_smoother_terms_are_its_runs_exact_terms(tmp_path):
    """What ``auto`` and the layer check score the Kalman smoother by on the sample
    (``sample_terms``) is its run as ``track`` runs it, its divergence exact from its pass (no
    probe: the same terms twice, and the compiled pass's own chunk sums), with one ``q`` for
    all as with the curve; a blend pairs the smoother's terms with those (before, without the
    curve, its divergence was probed and did not cancel against the blend's)."""
    from torchsvs.accuracy import terms_of_sums
    from torchsvs.datasets import read_tracks
    from torchsvs.fitting import noise
    from torchsvs.sample_accuracy import sample_terms

    _wandering(tmp_path / "in.csv", n=6, T=120)
    settings = replace(
        plan_tracks(pd.read_csv(tmp_path / "in.csv"), Settings("ks")).settings,
        q_curve=None,
        q_window=None,
        outliers=False,
    )
    tracks, _ = read_tracks(tmp_path / "in.csv", meas_std=[v**0.5 for v in settings.meas_var])
    once, twice = sample_terms(settings, tracks), sample_terms(settings, tracks)
    assert np.array_equal(once.divergence, twice.divergence)
    runs = noise.curve_runs(tracks.z, tracks.dt, settings.meas_var, settings.q, True)
    if runs.sums is None:
        pytest.skip("the compiled loops are unavailable")
    exact = terms_of_sums(runs.sums)
    assert_close(once.divergence, exact.divergence, rtol=1e-9, atol=1e-9)
    assert_close(once.residual, exact.residual, rtol=1e-9, atol=1e-6)


def test_a_sample_of_short_tracks_and_a_long_one_runs_in_groups_of_like_length(
    tmp_path, monkeypatch
):
    """Thousands of short tracks beside one long one padded the sample's batch to the long
    one's steps, every probe's copy too (17 GB and four minutes for 14,000 rows): the sample's
    runs go in groups of like length (``length_groups``), and give each track the terms one
    run gives, for one estimator (the SVSS, probed) and for a blend."""
    import torchsvs.sample_accuracy as sample_accuracy
    from torchsvs.accuracy import RiskTerms
    from torchsvs.datasets import read_tracks

    g = np.random.default_rng(4)
    rows = []
    for k in range(60):  # short tracks of 3-6 rows, and one of 300
        n = 300 if k == 30 else int(g.integers(3, 7))
        t = np.arange(n, dtype=float)
        x = 10.0 * t + g.normal(0, 5, n)
        y = 3.0 * t + 0.01 * t**2 + g.normal(0, 5, n)
        rows.append(pd.DataFrame({"track_id": f"t{k}", "time": t, "x": x, "y": y}))
    pd.concat(rows).to_csv(tmp_path / "in.csv", index=False)
    tracks, _ = read_tracks(tmp_path / "in.csv", meas_std=[5.0, 5.0])
    svss = Settings("svss", meas_var=[25.0, 25.0], q=1.0)
    ks = Settings("ks", meas_var=[25.0, 25.0], q=1.0)
    cells = len(tracks) * tracks.z.shape[1]
    groups = sample_accuracy.length_groups(tracks, cells // 8)
    assert groups is not None and len(groups) > 1
    assert sorted(torch.cat(groups).tolist()) == list(range(len(tracks)))  # each track once
    for rows_ in groups:  # within the budget, or one track alone
        assert len(rows_) == 1 or len(rows_) * int(tracks.lengths[rows_].max()) <= cells // 8
    assert sample_accuracy.length_groups(tracks, cells) is None

    def fields(terms: RiskTerms) -> list[np.ndarray]:
        return [terms.residual, terms.divergence, terms.count, terms.track]

    def both(run):
        one = run()  # (one batch: the budget is the whole)
        with monkeypatch.context() as patch:
            patch.setattr(sample_accuracy, "SAMPLE_CELLS", cells // 8)
            grouped = run()
        return one, grouped

    one, grouped = both(lambda: sample_accuracy.probed_terms(svss, tracks, 3))
    for a, b in zip(one, grouped, strict=True):
        for x, y in zip(fields(a), fields(b), strict=True):
            assert_close(x, y, rtol=1e-9, atol=1e-9)
    (w1, t1), (w2, t2) = both(lambda: sample_accuracy.sample_blend(ks, svss, tracks))
    assert w1 == pytest.approx(w2, rel=1e-9, abs=1e-12)
    for x, y in zip(fields(t1), fields(t2), strict=True):
        assert_close(x, y, rtol=1e-9, atol=1e-9)
