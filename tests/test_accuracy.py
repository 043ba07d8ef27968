"""The truth-free error estimate (torchsvs.accuracy) and ``--estimator auto``: SURE's identities,
its agreement with the true error within its own standard error, the run's JSON summary and
its warning."""

from __future__ import annotations

import json
import math

import numpy as np
import pandas as pd
import pytest
import torch

from torchsvs.accuracy import RiskTerms, RiskTotals, accuracy, risk_terms
from torchsvs.datasets import Columns
from torchsvs.recipes import Settings
from torchsvs.selection import SWITCH_ERRORS, caution_score
from torchsvs.track_run import summary_path
from torchsvs.tracking import track_file


def _measurements(B: int = 6, T: int = 100, m: int = 2, sigma: float = 3.0, seed: int = 0):
    gen = torch.Generator().manual_seed(seed)
    truth = torch.cumsum(torch.randn(B, T, m, generator=gen, dtype=torch.float64), dim=1)
    z = truth + sigma * torch.randn(B, T, m, generator=gen, dtype=torch.float64)
    z[0, 5, 1] = math.nan  # a missing component is left out of every sum
    return truth, z


def test_identity_estimate_is_scored_as_the_measurements_exactly():
    """f(z) = z: residual 0 and ∂f/∂z = 1 exactly, so SURE is r per component, whatever the
    probe: the estimated RMSE is the measurements' own, √Σ r."""
    _, z = _measurements()
    std = torch.tensor([3.0, 5.0], dtype=torch.float64)
    terms = risk_terms(lambda w: w, z, z, std, torch.Generator().manual_seed(1))
    found = accuracy(terms, [9.0, 25.0])
    assert found.estimated_rmse == pytest.approx(math.sqrt(34.0), rel=1e-12)
    # Only the chunk missing a component differs from the mean (its axes weigh differently).
    assert found.standard_error < 1e-3 * found.estimated_rmse
    assert found.points == int((~torch.isnan(z[..., 0])).sum()) + 0  # component 0 all observed


def test_constant_estimate_is_scored_by_its_residual_less_the_noise():
    """f(z) = 0: no divergence, SURE = mean z² − r per axis (the classic unbiased estimate)."""
    _, z = _measurements()
    r = [9.0, 9.0]
    terms = risk_terms(
        lambda w: torch.zeros_like(w),
        z,
        torch.zeros_like(z),
        torch.tensor([3.0, 3.0]),
        torch.Generator(),
    )
    observed = ~torch.isnan(z)
    expected = sum(float(z[..., j][observed[..., j]].square().mean()) - r[j] for j in range(2))
    mse, _ = terms.mse(r)  # each axis over its own observations, summed
    assert mse == pytest.approx(expected, rel=1e-12)


def test_running_totals_equal_the_chunks():
    """RiskTotals (sums and a Gram matrix) give RiskTerms.mse's estimate and standard error at
    any noise level, in parts."""
    gen = np.random.default_rng(0)
    C, m = 50, 3
    terms = RiskTerms(
        gen.uniform(0, 10, (C, m)),
        gen.normal(0, 3, (C, m)),
        np.full((C, m), 32.0),
        np.zeros(C, np.int64),
    )
    totals = RiskTotals(m)
    totals.add(
        RiskTerms(terms.residual[:20], terms.divergence[:20], terms.count[:20], terms.track[:20])
    )
    totals.add(
        RiskTerms(terms.residual[20:], terms.divergence[20:], terms.count[20:], terms.track[20:])
    )
    for r in ([1.0, 2.0, 3.0], [0.5, 0.5, 0.5]):
        assert totals.mse(r) == pytest.approx(terms.mse(r), rel=1e-10)


def test_totals_of_some_axes_are_those_axes_alone_and_add_up():
    """A 3-D run's horizontal and vertical estimates (RiskTotals.of_axes): each the totals of
    its axes' chunks alone (its standard error too), and their MSEs sum to the whole's (each
    axis is averaged over its own observations)."""
    gen = np.random.default_rng(1)
    C, m = 40, 3
    terms = RiskTerms(
        gen.uniform(0, 10, (C, m)),
        gen.normal(0, 3, (C, m)),
        gen.integers(20, 40, (C, m)).astype(float),
        np.zeros(C, np.int64),
    )
    totals = RiskTotals(m)
    totals.add(terms)
    r = [1.0, 2.0, 5.0]
    for axes in ((0, 1), (2,), (1,)):
        alone = RiskTerms(
            terms.residual[:, axes], terms.divergence[:, axes], terms.count[:, axes], terms.track
        )
        assert totals.of_axes(axes).mse([r[j] for j in axes]) == pytest.approx(
            alone.mse([r[j] for j in axes]), rel=1e-10
        )
    whole, _ = totals.mse(r)
    parts = totals.of_axes((0, 1)).mse(r[:2])[0] + totals.of_axes((2,)).mse(r[2:])[0]
    assert parts == pytest.approx(whole, rel=1e-10)


def test_estimate_of_a_kalman_smoother_agrees_with_the_truth():
    """On nearly-constant-velocity tracks with known noise the KS's estimated error is within
    three of its own standard errors of the true error (the noise is exactly as stated, so SURE
    is unbiased), and the true error is well below the measurements'."""
    import torchsvs as ts
    from torchsvs.datasets import with_prior
    from torchsvs.datasets.tracks import RecordedTracks

    gen = torch.Generator().manual_seed(3)
    B, T, sigma, q, dt = 40, 200, 20.0, 0.5, 2.0
    model = ts.models.ConstantVelocity(ndim=2, dt=dt, q=q, r=sigma**2)
    x = torch.zeros(B, 4, dtype=torch.float64)
    x[:, 1], x[:, 3] = 50.0, -20.0
    F, Q = model.transition().double(), model.process_noise().double()
    chol = torch.linalg.cholesky(Q)
    states = []
    for _ in range(T):
        x = x @ F.mT + torch.randn(B, 4, generator=gen, dtype=torch.float64) @ chol.mT
        states.append(x)
    truth = torch.stack(states, 1)[..., [0, 2]]
    z = truth + sigma * torch.randn(B, T, 2, generator=gen, dtype=torch.float64)
    tracks = RecordedTracks(
        z=z,
        dt=torch.full((B, T), dt, dtype=torch.float64),
        time=torch.arange(T, dtype=torch.float64).expand(B, T) * dt,
        lengths=torch.full((B,), T),
        ids=[str(b) for b in range(B)],
    )
    ks = ts.RTSSmoother(ts.KalmanFilter(model)).double()
    std = torch.tensor([sigma, sigma], dtype=torch.float64)

    def positions(w: torch.Tensor) -> torch.Tensor:
        moved = with_prior(
            RecordedTracks(w, tracks.dt, tracks.time, tracks.lengths, tracks.ids), std
        )
        return ks(moved.z, moved.x0, moved.P0, dt=moved.dt).mean[..., [0, 2]]

    estimate = positions(z)
    found = accuracy(
        risk_terms(positions, z, estimate, std, torch.Generator().manual_seed(0)), [sigma**2] * 2
    )
    true_mse = float((estimate - truth).square().sum(-1).mean())
    mse = found.estimated_rmse**2
    se_mse = 2 * found.estimated_rmse * found.standard_error
    assert abs(mse - true_mse) < 3 * se_mse, (mse, true_mse, se_mse)
    assert found.clearly_better and found.ratio < 0.8


def _turning_csv(
    path, sigma: float = 30.0, seed: int = 0, sigmas: list[float] | None = None
) -> dict[tuple[str, float], np.ndarray]:
    gen = np.random.default_rng(seed)
    paths = []
    for k in range(8):
        t = np.cumsum(np.full(150, 4.0))
        heading = np.cumsum(np.where((t > 200) & (t < 320), np.radians(4.0) * 4.0, 0.0))
        velocity = 120.0 * np.stack([np.cos(heading), np.sin(heading)], 1)
        pos = np.cumsum(velocity * 4.0, axis=0) + gen.normal(0, 1e3, 2)
        paths.append((t, pos, sigmas[k] if sigmas is not None else sigma))
    return _measured_csv(path, paths, gen)


def _measured_csv(path, paths, gen) -> dict[tuple[str, float], np.ndarray]:
    """``paths`` (times, true positions, σ per track) measured with white noise, as a CSV; the
    truth by (track id, time)."""
    rows, truth = [], {}
    for k, (t, pos, sigma) in enumerate(paths):
        for i in range(len(t)):
            x, y = pos[i] + gen.normal(0, sigma, 2)
            rows.append(f"trk{k},{t[i]:.1f},{x:.3f},{y:.3f}")
            truth[(f"trk{k}", round(float(t[i]), 1))] = pos[i]
    path.write_text("track_id,time,x,y\n" + "\n".join(rows) + "\n")
    return truth


def test_track_writes_the_summary_and_warns_where_no_better_than_the_measurements(tmp_path):
    """A KS whose q is far too small for turning tracks lags the turns: its estimated error is
    above the measurements', and the run says so and names a better choice; a sensible run
    does not warn, and its estimate is near the true error."""
    source = tmp_path / "in.csv"
    truth = _turning_csv(source)
    good, bad = tmp_path / "good.csv", tmp_path / "bad.csv"
    known = {"meas_var": [900.0, 900.0]}
    run = track_file(source, good, Settings("ks", **known), progress=False)
    lagging = track_file(source, bad, Settings("ks", q=1e-6, **known), progress=False)
    assert not run.warnings
    assert lagging.warnings and "--estimator auto" in lagging.warnings[0]
    for target, result in ((good, run), (bad, lagging)):
        summary = json.loads(summary_path(target).read_text())
        assert summary["warnings"] == result.warnings
        assert summary["measurement_rmse"] == pytest.approx(30.0 * math.sqrt(2))
        true_rmse = _true_rmse(target, truth)
        low, high = summary["estimated_position_rmse_interval"]
        assert low <= true_rmse <= high, (low, true_rmse, high)
        assert len(summary["tracks"]) == 8
        for track in summary["tracks"].values():  # each track's estimate with its range
            low, high = track["estimated_position_rmse_interval"]
            assert low <= track["estimated_position_rmse"] <= high


def test_auto_chooses_by_estimated_error_and_reports_the_candidates(tmp_path):
    source = tmp_path / "in.csv"
    _turning_csv(source)
    target = tmp_path / "out.csv"
    run = track_file(source, target, Settings("auto"), columns=Columns(), progress=False)
    summary = json.loads(summary_path(target).read_text())
    rows = {r["estimator"]: r for r in summary["candidates"] if not r.get("skipped")}
    skipped = {r["estimator"]: r["skipped"] for r in summary["candidates"] if r.get("skipped")}
    assert skipped["svstps"] == "the same estimator as svss here"  # the variable layer
    # the SVSS scored, or the Kalman smoother where its limit does not surely help
    assert "ks" in rows and ("svss" in rows) != ("svss" in skipped)
    assert "svss" in rows or skipped["svss"].startswith("ks here: its boundary layer's limit")
    chosen = summary["estimator"]
    assert chosen in rows and run.settings is not None and run.settings.chosen_from
    # the rule replayed: a later candidate replaces the one chosen so far where its score is
    # lower and its paired MSE difference below zero by more than SWITCH_ERRORS of its se
    order = [r for r in summary["candidates"] if not r.get("skipped")]
    kept = order[0]
    for row in order[1:]:
        assert {"mse_change", "mse_change_se"} <= set(row)
        lower = caution_score(row["estimated_position_rmse"], row["standard_error"]) < (
            caution_score(kept["estimated_position_rmse"], kept["standard_error"])
        )
        if lower and row["mse_change"] + SWITCH_ERRORS * row["mse_change_se"] < 0:
            kept = row
    assert kept["estimator"] == chosen
    # in the H⁺ mode svstps diverges (track refuses it there): auto skips it too
    hplus = Settings("auto", velocity=False)
    track_file(source, tmp_path / "h.csv", hplus, columns=Columns(), progress=False)
    table = json.loads(summary_path(tmp_path / "h.csv").read_text())["candidates"]
    assert {r["estimator"]: r.get("skipped") for r in table}["svstps"] == "diverges in the H⁺ mode"


def test_auto_score_prefers_the_lower_of_close_estimates_and_distrusts_a_vague_one():
    """The rule's two cases as met on recorded tracks: of two close estimates the lower wins
    whatever their standard errors (own σ100: ks 56.6 ± 4.0 against svss 58.2 ± 2.9, true 52.4
    and 54.4; a penalty of 2 se chose svss), and an estimate as uncertain as itself counts
    three times over (17 ± 17, claimed against a true 83, loses to 50 ± 2). A missing standard
    error (one chunk) counts as none."""
    assert caution_score(56.6, 4.0) < caution_score(58.2, 2.9)
    assert caution_score(17.0, 17.0) > caution_score(50.0, 2.0)
    assert caution_score(50.0, math.nan) == 50.0
    assert caution_score(0.0, 3.0) == 0.0


def test_track_reads_each_tracks_own_noise_where_one_level_does_not_fit_every_track(tmp_path):
    """Half the tracks measured with σ 15 m, half with 60 m: each track runs at its own noise
    read off its positions (:func:`~torchsvs.sample_accuracy.with_track_noise`), the file's the
    rows' mean square of theirs, and the run says so; one sensor gives neither."""
    mixed, same = tmp_path / "mixed.csv", tmp_path / "same.csv"
    _turning_csv(mixed, sigmas=[15.0] * 4 + [60.0] * 4)
    _turning_csv(same, sigma=30.0)
    runs = {}
    for source in (mixed, same):
        target = tmp_path / f"out_{source.name}"
        runs[source] = track_file(source, target, Settings("ks"), progress=False)
    spread, one = runs[mixed].settings, runs[same].settings
    assert spread.noise_spread > 0.5 and one.noise_spread < 0.1
    assert spread.track_noise is not None and one.track_noise is None
    assert 0.5 < spread.track_noise[1] < 0.9  # (log 4 / 2 = 0.69 between the two sensors)
    assert 40.0 < spread.meas_var[0] ** 0.5 < 48.0  # (√((15² + 60²) / 2) = 43.7)
    (said,) = [w for w in runs[mixed].warnings if "each track ran at its own" in w]
    assert "--noise-col" in said
    assert not any("noise level" in w for w in runs[same].warnings)


def _wandering_csv(path, sigma: float = 3.0, seed: int = 0) -> dict[tuple[str, float], np.ndarray]:
    """Tracks on 10 s scans whose motion between scans wanders 2-16 m off a straight line (by
    track) more than the CV model follows, measured with σ 3 m: the wander reads as noise."""
    gen = np.random.default_rng(seed)
    paths = []
    for k in range(12):
        t = np.cumsum(np.full(120, 10.0))
        wander = 2.0 + 14.0 * k / 11
        line = np.cumsum(np.tile([1500.0, 200.0], (120, 1)), axis=0) + gen.normal(0, 1e3, 2)
        paths.append((t, line + gen.normal(0, wander, (120, 2)), sigma))
    return _measured_csv(path, paths, gen)


def _true_rmse(target, truth) -> float:
    out = pd.read_csv(target, dtype={"track_id": str})
    errors = [
        np.sum((np.array([x, y]) - truth[(i, round(t, 1))]) ** 2)
        for i, t, x, y in zip(out.track_id, out.time, out.x, out.y, strict=True)
    ]
    return math.sqrt(np.mean(errors))


def test_a_noise_reading_that_smooths_real_motion_away_is_lowered(tmp_path, monkeypatch):
    """Motion the model does not follow reads as noise (9 m for 3): at that level the Kalman
    smoother smooths the motion away, 3x the measurements' error. Its estimate is not clearly
    below the measurements over the reading's uncertainty, so the run takes the reading's low
    end, says so, and lands at the measurements' error; given the true noise it does the same."""
    source = tmp_path / "in.csv"
    truth = _wandering_csv(source)
    raw = 3.0 * math.sqrt(2)
    target = tmp_path / "out.csv"
    run = track_file(source, target, Settings("ks"), progress=False)
    assert run.settings is not None and run.settings.meas_var is not None
    read = run.settings.noise_lowered_from
    assert read is not None and min(read) > 2 * 3.0  # the wander read as noise
    assert max(run.settings.meas_var) ** 0.5 < 0.6 * min(read)
    assert any("ran at its low end" in w for w in run.warnings)
    summary = json.loads(summary_path(target).read_text())
    assert summary["settings"]["noise_lowered_from"] == pytest.approx(read)
    assert _true_rmse(target, truth) < 1.05 * raw
    # the test is the data's (the Kalman smoother's): a fitted SVSS runs at the same noise,
    # decided before anything is fitted (the fit runs once, at the lowered noise)
    import torchsvs.track_plan

    fits: list[list[float] | None] = []
    fit_once = torchsvs.track_plan.self_tune

    def counted(settings, *args, **kwargs):
        fits.append(settings.meas_var)
        return fit_once(settings, *args, **kwargs)

    monkeypatch.setattr(torchsvs.track_plan, "self_tune", counted)
    fitted = track_file(source, tmp_path / "svss.csv", Settings("svss"), fit=True, progress=False)
    assert fitted.settings is not None and fitted.settings.noise_lowered_from == read
    assert fits and all(v == fitted.settings.meas_var for v in fits)
    assert len(fits) == 2  # the SVSS's fit and its Kalman twin's for the layer check
    assert fitted.settings.meas_var == run.settings.meas_var
    assert _true_rmse(tmp_path / "svss.csv", truth) < 1.1 * raw
    # the given noise is never lowered
    given = track_file(
        source, tmp_path / "given.csv", Settings("ks", meas_var=[9.0, 9.0]), progress=False
    )
    assert given.settings is not None and given.settings.noise_lowered_from is None
    # without the lowering, the reading smooths the motion away
    monkeypatch.setattr("torchsvs.track_plan.lowered_noise", lambda *args, **kwargs: None)
    track_file(source, target, Settings("ks"), progress=False)
    assert _true_rmse(target, truth) > 2.0 * raw


def test_a_clear_estimate_keeps_the_noise_read_off_the_data(tmp_path):
    source = tmp_path / "in.csv"
    _turning_csv(source)
    run = track_file(source, tmp_path / "out.csv", Settings("ks"), progress=False)
    assert run.settings is not None and run.settings.noise_lowered_from is None
    assert run.accuracy is not None and run.accuracy.clearly_better


def _ks_tracks(B: int = 4, T: int = 120, sigma: float = 30.0, seed: int = 3):
    """Tracks of a nearly-constant-velocity target at irregular 1-10 s intervals with priors
    (as ``track`` gives them), and the Kalman smoother ``track`` runs on them."""
    from dataclasses import replace

    from torchsvs.datasets import RecordedTracks, with_prior
    from torchsvs.filters import KalmanFilter
    from torchsvs.models import ConstantVelocity
    from torchsvs.smoothers import RTSSmoother

    gen = torch.Generator().manual_seed(seed)
    dt = 1.0 + 9.0 * torch.rand(B, T, generator=gen, dtype=torch.float64)
    velocity = torch.cumsum(torch.randn(B, T, 2, generator=gen, dtype=torch.float64), dim=1)
    truth = torch.cumsum(velocity * dt.unsqueeze(-1), dim=1)
    z = truth + sigma * torch.randn(B, T, 2, generator=gen, dtype=torch.float64)
    z[1, 40:45] = math.nan  # a gap
    z[2, 0, 1] = math.nan  # an axis observed late
    tracks = RecordedTracks(
        z=z, dt=dt, time=dt.cumsum(1), lengths=torch.full((B,), T), ids=list("abcd")[:B]
    )
    std = torch.tensor([sigma, sigma], dtype=torch.float64)
    model = ConstantVelocity(ndim=2, q=0.5, r=[sigma**2, sigma**2]).double()
    ks = RTSSmoother(KalmanFilter(model))

    def run(measured: torch.Tensor, keep: str = "all"):
        found = with_prior(replace(tracks, z=measured), std)
        with torch.no_grad():
            return ks(found.z, found.x0, found.P0, dt=found.dt, keep=keep)

    return with_prior(tracks, std), std, ks, run


def test_exact_divergence_is_the_kalman_smoothers_derivative():
    """``H P_{t|T} Hᵀ R⁻¹`` is ``∂ẑ_t/∂z_t`` of the Kalman smoother (a finite difference
    of one component at a time, the priors rebuilt), and it is unknown (NaN) exactly where the
    two-point prior reads the measurement too: an axis's first two observations."""
    from torchsvs.accuracy import exact_divergence

    tracks, std, ks, run = _ks_tracks()
    out = run(tracks.z)
    exact = exact_divergence(tracks.z, out.cov.diagonal(dim1=-2, dim2=-1)[..., 0::2], std**2)
    assert torch.isnan(exact[2, :3, 1]).all() and not torch.isnan(exact[2, 3, 1])
    assert torch.isnan(exact[1, 40:45]).all() and torch.isnan(exact[0, :2]).all()
    delta = 1e-3
    for b, t, i in [(0, 2, 0), (0, 60, 1), (1, 45, 0), (2, 3, 1), (3, 119, 0)]:
        moved = tracks.z.clone()
        moved[b, t, i] += delta
        found = (run(moved, "mean").mean[b, t, 2 * i] - out.mean[b, t, 2 * i]) / delta
        assert float(found) == pytest.approx(float(exact[b, t, i]), rel=1e-6), (b, t, i)


def test_a_kalman_smoothers_estimate_is_its_own_control_and_nearly_free_of_the_probe():
    """With the Kalman smoother as its own reference (``beta`` 1), only the first two
    observations of each axis keep the probe's divergence: the chunks without them agree
    across probe seeds to rounding, and the exact divergence is what they sum. Without it,
    one probe moves those chunks' divergence by far more."""
    from torchsvs.accuracy import Reference, exact_divergence

    tracks, std, ks, run = _ks_tracks()
    out = run(tracks.z)
    exact = exact_divergence(tracks.z, out.cov.diagonal(dim1=-2, dim2=-1)[..., 0::2], std**2)
    reference = Reference(exact, beta=1.0)

    def terms(seed: int, control: Reference | None) -> RiskTerms:
        return risk_terms(
            lambda w: run(w, "mean").mean[..., 0::2],
            tracks.z,
            out.mean[..., 0::2],
            std,
            torch.Generator().manual_seed(seed),
            reference=control,
        )

    starts = np.arange(4) * 4  # each track's first chunk (of 4) holds its first observations
    rest = np.setdiff1d(np.arange(16), starts)
    with_control = [terms(seed, reference).divergence[rest] for seed in (1, 2)]
    assert np.abs(with_control[0] - with_control[1]).max() < 1e-9
    sums = torch.nn.functional.pad(torch.nan_to_num(exact), (0, 0, 0, 8))
    expected = sums.reshape(4, 4, 32, 2).sum(2).reshape(16, 2).numpy()[rest]
    assert np.abs(with_control[0] - expected).max() < 1e-9
    without = [terms(seed, None).divergence[rest] for seed in (1, 2)]
    assert (
        np.abs(without[0] - without[1]).max()
        > 1e3 * np.abs(with_control[0] - with_control[1]).max() + 0.05
    )


def test_a_near_linear_estimators_estimate_moves_less_with_the_probe_under_the_control():
    """An SVSS (the Kalman gain inside its boundary layer) controlled by the Kalman smoother
    on its model (``error_references.LinearReference``, weight fitted): over six probe seeds its
    estimated error spreads less than half as much as without the control, around the same
    value."""
    from dataclasses import replace

    from torchsvs.accuracy import PROBE_STEP, draw_probe
    from torchsvs.datasets import with_prior
    from torchsvs.error_references import LinearReference, reference_for
    from torchsvs.recipes import make_estimator, make_model

    tracks, std, _, _ = _ks_tracks(B=4, T=120)
    settings = Settings("svss", meas_var=[900.0, 900.0], q=0.5, psi=[120.0, 60.0])
    svss = make_estimator(settings, make_model(settings)).double()

    def run(measured: torch.Tensor, keep: str = "all"):
        found = with_prior(replace(tracks, z=measured), std)
        with torch.no_grad():
            return svss(found.z, found.x0, found.P0, dt=found.dt, keep=keep)

    out = run(tracks.z)
    found = {True: [], False: []}
    for seed in range(6):
        probe = draw_probe(tracks.z, std, PROBE_STEP, torch.Generator().manual_seed(seed))
        control = reference_for(svss, out, tracks, std, probe)
        assert isinstance(control, LinearReference)
        for controlled in (True, False):
            terms = risk_terms(
                lambda w: run(w, "mean").mean[..., 0::2],
                tracks.z,
                out.mean[..., 0::2],
                std,
                None,
                reference=control.reference(out) if controlled else None,
                probe=probe,
            )
            found[controlled].append(terms.mse([900.0, 900.0])[0])
    spread = {k: float(np.std(v)) for k, v in found.items()}
    assert spread[True] < 0.5 * spread[False], spread
    assert abs(np.mean(found[True]) - np.mean(found[False])) < 2 * spread[False], found


def test_the_linear_reference_from_the_positions_loop_is_the_one_from_the_runs():
    """``LinearReference`` of a Kalman smoother and of a filter, its means and position
    variances from the compiled positions loop (``noise.kalman_positions``), equals the one
    from the estimators' whole runs (the general path it takes where R is not diagonal), for
    the smoother's pass and its filter's, on tracks with missing steps and their own
    intervals."""
    from dataclasses import replace

    from torchsvs.accuracy import PROBE_STEP, draw_probe
    from torchsvs.datasets import with_prior
    from torchsvs.error_references import LinearReference
    from torchsvs.filters import KalmanFilter
    from torchsvs.models import ConstantVelocity
    from torchsvs.smoothers import RTSSmoother

    tracks, std, _, _ = _ks_tracks(B=5, T=60)
    z = tracks.z.clone()
    z[1, 10:14] = float("nan")
    z[3, 30, 0] = float("nan")
    tracks = with_prior(replace(tracks, z=z), std)
    probe = draw_probe(tracks.z, std, PROBE_STEP, torch.Generator().manual_seed(3))
    model = ConstantVelocity(ndim=2, dt=1.0, q=0.7, r=[900.0, 400.0]).double()
    for kalman in (RTSSmoother(KalmanFilter(model)), KalmanFilter(model)):
        fast = LinearReference(kalman, tracks, std, probe)
        general = LinearReference(kalman, tracks, std, probe)
        general.positions = False
        assert fast.positions
        passes = (False, True) if isinstance(kalman, RTSSmoother) else (False,)
        for filtered in passes:
            a, b = fast.reference(None, filtered), general.reference(None, filtered)
            for name in ("exact", "shifted", "estimate"):
                x, y = getattr(a, name), getattr(b, name)
                assert torch.allclose(x, y, rtol=1e-10, atol=1e-8, equal_nan=True), name
            assert a.beta == b.beta


def test_auto_scores_every_candidate_on_the_same_tracks_and_the_imm_beyond_its_budget(
    tmp_path, monkeypatch
):
    """A sample over ``IMM_POINTS`` no longer skips the IMM: every candidate is scored on the
    same tracks spread over the sample, up to that many points (so the table compares like
    with like), while the fits see the whole sample."""
    import torchsvs.selection as selection

    source = tmp_path / "in.csv"
    _turning_csv(source)  # 8 tracks of 150 points
    monkeypatch.setattr(selection, "IMM_POINTS", 500)
    scored = []

    def counted(settings, tracks):
        scored.append((settings.estimator, len(tracks)))
        return sample_terms(settings, tracks)

    sample_terms = selection.sample_terms
    monkeypatch.setattr(selection, "sample_terms", counted)
    monkeypatch.setattr(  # (the SVSS's own layer check reads the whole sample: not a score)
        selection,
        "checked_layer",
        lambda s, *_: selection.LayerCheck(1.0, 0.1, 0.0, False, s.estimator, s),
    )
    target = tmp_path / "out.csv"
    track_file(source, target, Settings("auto"), columns=Columns(), progress=False)
    summary = json.loads(summary_path(target).read_text())
    rows = {r["estimator"]: r for r in summary["candidates"] if not r.get("skipped")}
    assert {"ks", "svss", "imm"} <= set(rows)
    assert {name for name, _ in scored} >= {"ks", "svss", "imm"}
    assert {count for _, count in scored} == {3}  # 3 tracks of 150: at most 500 points


def test_spread_tracks_keeps_the_most_tracks_within_the_points():
    from torchsvs.datasets import RecordedTracks
    from torchsvs.fitting.defaults import spread_tracks

    lengths = torch.tensor([100, 10, 50, 200, 30, 80, 120, 60])
    z = torch.full((8, 200, 2), math.nan)
    for k, n in enumerate(lengths.tolist()):
        z[k, :n] = 0.0
    dt = torch.ones(8, 200)
    tracks = RecordedTracks(
        z=z, dt=dt, time=dt.cumsum(1), lengths=lengths, ids=[f"t{k}" for k in range(8)]
    )
    for points in (100, 250, 400, 650, 10_000):
        kept = spread_tracks(tracks, points)
        total = int((~kept.z[..., 0].isnan()).sum())
        assert total <= points or len(kept) == 1
        assert kept.ids[0] == "t0" and (len(kept) == 1 or kept.ids[-1] == "t7")
    assert len(spread_tracks(tracks, 10_000)) == 8
    assert len(spread_tracks(tracks, 1)) == 1  # at least one track


def test_paired_difference_of_two_estimators_on_the_same_chunks():
    """RiskTerms.difference: the MSEs' difference (as mse() gives each), zero against itself,
    and a standard error far below either's own where the two share what varies (the
    measurements' noise, the path) and differ by little; chunks that are not the same are
    refused, naming the argument."""
    gen = np.random.default_rng(0)
    C, m = 400, 2
    count = np.full((C, m), 64.0)
    count[3, 1] = 10.0
    residual = gen.gamma(4.0, 900.0, (C, m)) * count / 64.0  # what the chunks share
    divergence = gen.uniform(5.0, 15.0, (C, m))
    a = RiskTerms(residual, divergence, count, np.arange(C) // 4)
    b = RiskTerms(residual * 1.02 + gen.normal(0.0, 5.0, (C, m)), divergence, count, a.track)
    r = [900.0, 400.0]
    change, se = b.difference(a, r)
    assert change == pytest.approx(b.mse(r)[0] - a.mse(r)[0], rel=1e-9)
    assert change > 0 and se < 0.05 * min(a.mse(r)[1], b.mse(r)[1])
    assert change > 5 * se  # b is surely worse
    assert a.difference(a, r) == (0.0, 0.0)
    other = RiskTerms(residual[1:], divergence[1:], count[1:], a.track[1:])
    with pytest.raises(ValueError, match="other: expected the terms of the same chunks"):
        a.difference(other, r)


def test_auto_keeps_the_first_candidate_on_a_near_tie_and_leaves_it_for_a_sure_gain(
    monkeypatch,
):
    """The rule's behaviour, with the fits and the scores stubbed: a later candidate whose
    estimate is lower, but by less than one standard error of the paired difference, does not
    replace the Kalman smoother; one lower by far more does, and so does one whose small gain
    is sure because the two share their chunks' variation. An SVSF-family candidate whose
    layer check (:func:`~torchsvs.selection.checked_layer`) runs its twin is skipped; one it
    keeps is compared with the smoother by that check."""
    from types import SimpleNamespace

    import torchsvs.selection as selection
    from torchsvs.datasets import RecordedTracks

    gen = np.random.default_rng(0)
    C, m = 200, 2
    count = np.full((C, m), 32.0)
    shared = gen.gamma(20.0, 1600.0, (C, m))  # what every candidate's chunks share
    divergence = np.full((C, m), 8.0)

    def terms(residual):
        return RiskTerms(residual, divergence, count, np.arange(C) // 4)

    def choose(errors, layer_kept=True):
        scored = {name: terms(residual) for name, residual in errors.items()}
        monkeypatch.setattr(selection, "sample_terms", lambda s, t: scored[s.estimator])
        monkeypatch.setattr(selection, "probed_terms", lambda s, t, k: [scored[s.estimator]] * k)
        monkeypatch.setattr(
            selection,
            "self_tune",
            lambda s, *_, **__: SimpleNamespace(settings=s, stages=[], parameters=1),
        )
        monkeypatch.setattr(  # the layer's own check, stubbed (its rule: test_svsf_defaults)
            selection,
            "checked_layer",
            lambda s, twin, *_: selection.LayerCheck(
                3.0 if layer_kept else 1.0, 2.0, 0.0, False, s.estimator, s
            ),
        )
        z = torch.randn(4, 30, m, dtype=torch.float64)
        dt = torch.ones(4, 30, dtype=torch.float64)
        sample = RecordedTracks(z, dt, dt.cumsum(1), torch.full((4,), 30), list("abcd"))
        given = Settings("auto", meas_var=[900.0, 900.0], noise="given")
        # (the blend of the chosen with the next: tests/test_blending.py)
        chosen = selection.choose_estimator(given, sample, candidates=tuple(errors), blend=False)
        assert [r["estimator"] for r in chosen.candidates] == list(errors)
        skipped = [r["skipped"] for r in chosen.candidates if "skipped" in r]
        assert skipped == (
            []
            if layer_kept
            else [
                "ks here: its boundary layer's limit does not surely help (MSE +1 ± 2 m² per point)"
            ]
        )
        return chosen.settings.estimator

    noisy = gen.normal(0.0, 400.0, (C, m))  # a difference lost in the chunks' own noise
    noisy -= noisy.mean(axis=0)  # (of mean 0: the gain is the 5 m² a chunk given)
    assert choose({"ks": shared, "imm": shared - 5.0 + noisy}) == "ks"
    assert choose({"ks": shared, "imm": shared - 2000.0 + noisy}) == "imm"
    assert choose({"ks": shared, "imm": shared - 5.0}) == "imm"  # small, but sure
    # an SVSS whose limit its own check keeps: that check is its comparison with the smoother
    # (here a sure 3 ± 2 m², whatever the near-tie of the scores)
    assert choose({"ks": shared, "svss": shared - 5.0 + noisy}) == "svss"
    # an SVSS whose boundary layer's limit does not surely help is the Kalman smoother, as
    # `--estimator svss` would run it: not scored again, however low its own estimate
    assert choose({"ks": shared, "svss": shared - 2000.0}, layer_kept=False) == "ks"
    # a candidate whose fit fails numerically (the IMM's on two ships under one id: a raw
    # traceback ended the run) is skipped, named; the first candidate's failure stands
    tune = selection.self_tune

    def failing(s, *args, **kwargs):
        if s.estimator == "imm":
            raise torch.linalg.LinAlgError("matrix is not positive definite, even with jitter")
        return tune(s, *args, **kwargs)

    monkeypatch.setattr(selection, "self_tune", failing)
    z = torch.randn(4, 30, 2, dtype=torch.float64)
    dt = torch.ones(4, 30, dtype=torch.float64)
    sample = RecordedTracks(z, dt, dt.cumsum(1), torch.full((4,), 30), list("abcd"))
    given = Settings("auto", meas_var=[900.0, 900.0], noise="given")
    chosen = selection.choose_estimator(given, sample, candidates=("ks", "imm"), blend=False)
    assert chosen.settings.estimator == "ks"
    assert chosen.candidates[1]["skipped"].startswith("its fit failed numerically (matrix is")


def test_an_uncertain_error_estimate_is_called_so_and_its_cause_named():
    """The warning where the estimate's interval reaches beyond UNCERTAIN_REACH times it: none
    for a narrow interval; the noise reading named (and --meas-std offered) where it makes the
    interval over twice the sampling error's; else the sampling error, and the probe only for
    an estimator whose divergence is probed. SURE at a noise read 4% high on 250 m: the terms'
    r(2·div − n) moves the estimate from the truth's 70 m to 27 m (recorded_wide, taxi σ250)."""
    from torchsvs.accuracy import Accuracy
    from torchsvs.estimate_warnings import UNCERTAIN_REACH, uncertain_estimate

    def found(interval, sampling, estimated=30.0, noise_estimated=True):
        return Accuracy(
            estimated, 1.0, 360.0, interval, 5000, noise_estimated, [260.0, 254.0], sampling
        )

    assert uncertain_estimate(found((20.0, 0.99 * UNCERTAIN_REACH * 30.0), (25.0, 35.0))) is None
    noise = uncertain_estimate(found((0.0, 177.0), (10.0, 45.0)))
    assert noise is not None and "30 m is uncertain" in noise and "0-177 m" in noise
    assert "noise read off the data ([260, 254] m" in noise and "--meas-std" in noise
    sampling = uncertain_estimate(found((0.0, 135.0), (0.0, 120.0)))
    assert sampling is not None and "sampling error" in sampling and "--meas-std" not in sampling
    assert "probed" not in sampling
    assert "probed at random" in (
        uncertain_estimate(found((0.0, 135.0), (0.0, 120.0)), False) or ""
    )
    given = uncertain_estimate(found((0.0, 177.0), (10.0, 45.0), noise_estimated=False))
    assert given is not None and "sampling error" in given  # a given noise is not blamed
    # the estimate's own: the sampling interval is the estimate ± 2 standard errors alone
    terms = RiskTotals(2)
    gen = np.random.default_rng(0)
    residual = gen.gamma(20.0, 1600.0, (40, 2))
    terms.add(RiskTerms(residual, np.full((40, 2), 8.0), np.full((40, 2), 32.0), np.arange(40)))
    wide = accuracy(terms, [900.0, 900.0], True, ([700.0, 700.0], [1100.0, 1100.0]))
    narrow = accuracy(terms, [900.0, 900.0])
    assert wide.sampling_interval == narrow.sampling_interval == narrow.interval
    assert wide.interval[0] < narrow.interval[0] and wide.interval[1] > narrow.interval[1]


def test_track_warns_where_its_error_estimate_rests_on_a_noise_read_off_the_data(tmp_path):
    """Slow tracks under 250 m of noise, read off the data: the smoother's error is a few tens
    of metres, far below the noise, and the estimate (the residuals less the noise's share)
    swings over the noise reading's uncertainty (0 m here: its MSE below zero, clipped); the
    run says so and offers --meas-std; with the noise given the interval is the sampling
    error's and narrower."""
    gen = np.random.default_rng(1)
    rows = []
    for k in range(20):
        t = np.arange(150.0)
        path = np.cumsum(gen.normal(0, 0.5, (150, 2)), 0) + t[:, None] * gen.normal(0, 2, 2)
        z = path + gen.normal(0, 250.0, (150, 2))
        rows += [f"k{k},{t[i]:.1f},{z[i, 0]:.3f},{z[i, 1]:.3f}" for i in range(150)]
    source = tmp_path / "slow.csv"
    source.write_text("track_id,time,x,y\n" + "\n".join(rows) + "\n")
    read = track_file(source, tmp_path / "read.csv", Settings("ks"), progress=False)
    said = [w for w in read.warnings if "is uncertain" in w]
    assert len(said) == 1 and "--meas-std" in said[0] and "noise read off the data" in said[0]
    given = Settings("ks", meas_var=[250.0**2] * 2)
    run = track_file(source, tmp_path / "given.csv", given, progress=False)
    assert run.accuracy is not None and read.accuracy is not None
    width = run.accuracy.interval[1] - run.accuracy.interval[0]
    assert width < 0.5 * (read.accuracy.interval[1] - read.accuracy.interval[0])
    assert not any("noise read off the data" in w for w in run.warnings)


def test_an_estimate_surely_below_zero_names_the_noise_at_which_it_is_zero():
    """SURE is linear in the noise: where it is surely below zero at the noise assumed, the
    noise scaled by one factor at which it is zero (``zero_at_noise``) gives an estimate of 0
    from the same totals; an estimate below zero within 2 standard errors (a small error, by
    chance) is not flagged."""
    from torchsvs.accuracy import accuracy

    gen = np.random.default_rng(3)
    chunks, m = 400, 2
    count = np.full((chunks, m), 20.0)
    divergence = np.full((chunks, m), 6.0)  # 2·div − n = −8 per chunk and axis
    residual = gen.normal(100.0, 5.0, (chunks, m))  # noise about 100 / 8 = 12.5 per axis
    terms = RiskTerms(residual, divergence, count, np.arange(chunks))
    totals = RiskTotals(m)
    totals.add(terms)
    high = accuracy(totals, [25.0, 25.0])
    assert high.below_zero and high.estimated_rmse == 0.0
    assert high.zero_at_noise is not None
    zero = [v * v for v in high.zero_at_noise]
    assert abs(totals.mse(zero)[0]) < 1e-9
    np.testing.assert_allclose(zero, [12.5, 12.5], atol=0.3)
    near = accuracy(totals, zero)
    assert not near.below_zero and near.zero_at_noise is None
    assert "unknown: below zero" in high.line() and "unknown" not in near.line()


def test_each_tracks_range_is_the_runs_range_of_its_chunks_alone():
    """A track's range (summary's per-track interval) is what the run's ratio estimator gives
    on that track's chunks alone (RiskTotals.mse), at the noise and at each other level, two
    standard errors out; unknown (NaN) for a track of one chunk."""
    gen = np.random.default_rng(4)
    C, m = 9, 2
    track = np.array([0, 0, 0, 1, 2, 2, 0, 2, 2])
    count = gen.integers(5, 33, (C, m)).astype(float)
    terms = RiskTerms(
        count * gen.uniform(10, 40, (C, m)), count * gen.uniform(0.1, 0.6, (C, m)), count, track
    )
    meas_var, levels = [25.0, 30.0], [[20.0, 24.0], [31.0, 37.0]]
    low, high = terms.per_track_ranges(meas_var, 4, levels)
    for k in (0, 2):
        ends = []
        for level in [meas_var, *levels]:
            totals = RiskTotals(m)
            totals.add(terms.select(track == k))
            mse, se = totals.mse(level)
            ends += [mse - 2 * se, mse + 2 * se]
        assert low[k] == pytest.approx(math.sqrt(max(min(ends), 0.0)), rel=1e-12)
        assert high[k] == pytest.approx(math.sqrt(max(ends)), rel=1e-12)
    assert math.isnan(low[1]) and math.isnan(high[1])  # one chunk
    assert math.isnan(low[3])  # no chunk at all


def test_a_tracks_range_wholly_below_zero_is_unknown_not_zero():
    """A track whose residuals are far below the noise assumed has every chunk's MSE below
    zero: its range read [0, 0] m, for a true 1.7 m (an outside probe); it is unknown (NaN,
    written null), as a one-chunk track's is, and the others' ranges stand."""
    count = np.full((6, 2), 32.0)
    residual = np.array([[3200.0] * 2] * 3 + [[100.0] * 2] * 3)  # (per component: 100, 3)
    residual[:3] += np.array([[40.0, 40.0], [0.0, 0.0], [-40.0, -40.0]])
    terms = RiskTerms(residual, np.full((6, 2), 8.0), count, np.repeat([0, 1], 3))
    low, high = terms.per_track_ranges([25.0, 25.0], 2)
    assert 0 < low[0] < high[0]  # (a track whose error is there to see)
    assert np.isnan(low[1]) and np.isnan(high[1])
