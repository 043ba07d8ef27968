"""IMM(CV, CT) for recorded tracks: ``TurnIMM``, ``CoordinatedTurn3D`` and ``torchsvs track
--estimator imm``."""

from __future__ import annotations

import math
import re
from typing import Any, NamedTuple

import numpy as np
import pyarrow.csv as pcsv
import pytest
import torch

import torchsvs as ts
from tests.conftest import assert_close
from torchsvs.cli import main
from torchsvs.models import ConstantVelocity, CoordinatedTurn, CoordinatedTurn3D
from torchsvs.recipes import Settings

RATE = 3.0


def _turning_tracks(
    tracks: int, steps: int, ndim: int, sigma: float, seed: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """Truth and measurements ``[K, T, ndim]`` of targets at 150 m/s, 1 s apart: straight for 40
    s, a ±3°/s coordinated turn for 60 s, straight again; in 3-D climbing at 2 m/s."""
    gen = np.random.default_rng(seed)
    truth = np.zeros((tracks, steps, ndim))
    for k in range(tracks):
        p, v = np.zeros(2), np.array([150.0, 0.0]) @ _rotation(gen.uniform(0, 2 * math.pi))
        sign = 1.0 if k % 2 else -1.0
        for t in range(steps):
            w = sign * math.radians(RATE) if 40 <= t < 100 else 0.0
            if w == 0.0:
                p = p + v
            else:
                s, c = math.sin(w), math.cos(w)
                p = p + np.array([s * v[0] - (1 - c) * v[1], (1 - c) * v[0] + s * v[1]]) / w
                v = np.array([c * v[0] - s * v[1], s * v[0] + c * v[1]])
            truth[k, t, :2] = p
            if ndim == 3:
                truth[k, t, 2] = 2.0 * (t + 1)
    return truth, truth + gen.normal(0.0, sigma, truth.shape)


def _rotation(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, s], [-s, c]])


def _write(path, z: np.ndarray) -> None:
    ndim = z.shape[-1]
    names = ["x", "y", "z"][:ndim]
    rows = [
        ",".join([f"t{k}", f"{t:.1f}", *(f"{v:.3f}" for v in z[k, t])])
        for k in range(z.shape[0])
        for t in range(z.shape[1])
    ]
    path.write_text("track_id,time," + ",".join(names) + "\n" + "\n".join(rows) + "\n")


def _track(*args: str) -> None:
    main(["track", *args, "--quiet"])


def _positions(path, ndim: int) -> np.ndarray:
    out = pcsv.read_csv(path)
    return np.stack([out.column(c).to_numpy() for c in ["x", "y", "z"][:ndim]], -1)


@pytest.mark.parametrize("ndim", [2, 3])
def test_track_imm_writes_a_row_per_input_row_and_beats_the_kf_on_turns(tmp_path, ndim):
    truth, z = _turning_tracks(4, 150, ndim, sigma=30.0)
    source = tmp_path / "in.csv"
    _write(source, z)
    errors = {}
    for name in ("kf", "imm"):
        target = tmp_path / f"{name}.csv"
        _track(str(source), "-o", str(target), "--estimator", name, "--meas-std", "30")
        out = pcsv.read_csv(target)
        assert out.num_rows == pcsv.read_csv(source).num_rows == 4 * 150
        assert out.column_names[-2 * ndim - 1 :] == [
            *(c for axis in ["x", "y", "z"][:ndim] for c in (axis, f"v{axis}")),
            "outlier",
        ]
        est = _positions(target, ndim)
        assert np.isfinite(est).all()
        errors[name] = np.sqrt(np.mean((est - truth.reshape(-1, ndim))[:, :2] ** 2))
    # Each estimator with its settings read off the file (the IMM's from the same data q, which
    # is noisy here: 30 m noise at 1 s hides most of a 3°/s turn between two steps), so the KF
    # is tuned to the turns too: the IMM still gains (29% in 2-D, 7% in 3-D at this seed).
    assert errors["imm"] < 0.95 * errors["kf"], errors


def test_track_imm_fit_runs_and_reports_the_turn_noises(tmp_path, capsys):
    _, z = _turning_tracks(3, 60, 2, sigma=30.0, seed=1)
    source, target = tmp_path / "in.csv", tmp_path / "out.csv"
    _write(source, z)
    main(
        ["track", str(source), "-o", str(target), "--estimator", "imm", "--meas-std", "30"]
        + ["--fit", "--fit-steps", "2"]
    )
    assert "imm by SURE" in capsys.readouterr().err
    assert np.isfinite(_positions(target, 2)).all()


@pytest.mark.parametrize(
    "args, message",
    [
        (["--switch-prob", "1.5"], r"switch_prob: expected a value in \[0, 1\)"),
        (["--turn-rate-q", "-1"], "turn_rate_q: expected a number > 0"),
        (["--turn-rate-std", "0"], "turn_rate_std: expected a number > 0"),
        (["--turn-q", "-2"], "turn_q: expected a number > 0"),
        (["--pos-cols", "x"], "estimator: imm turns in the horizontal plane of 2 or 3 position"),
    ],
)
def test_bad_imm_options_name_the_argument(tmp_path, capsys, args, message):
    _, z = _turning_tracks(2, 20, 2, sigma=30.0)
    source = tmp_path / "in.csv"
    _write(source, z)
    with pytest.raises(SystemExit) as exit_info:
        _track(str(source), "-o", str(tmp_path / "o.csv"), "--estimator", "imm", *args)
    text = str(exit_info.value.code) + capsys.readouterr().err
    assert exit_info.value.code != 0
    assert re.search(message, text), text


def _prior(ndim: int, B: int) -> tuple[torch.Tensor, torch.Tensor]:
    gen = torch.Generator().manual_seed(3)
    x0 = torch.randn(B, 2 * ndim, generator=gen, dtype=torch.float64) * 10
    P0 = torch.diag(torch.tensor([900.0, 100.0] * ndim, dtype=torch.float64))
    return x0, P0


def test_turn_imm_held_in_its_cv_mode_is_the_kalman_filter():
    """No switching and all probability on the CV mode: the combined estimate is the KF's."""
    truth, z = _turning_tracks(3, 30, 2, sigma=30.0)
    z_t = torch.from_numpy(z)
    model = ConstantVelocity(ndim=2, dt=1.0, q=2.0, r=900.0)
    imm = ts.TurnIMM(model, turn_rate_q=1e-5, turn_rate_std=0.02, transition=[[1, 0], [0, 1]])
    x0, P0 = _prior(2, 3)
    out = imm(z_t, x0, P0, mode_probs=torch.tensor([1.0, 0.0]))
    kf = ts.KalmanFilter(model)(z_t, x0, P0)
    assert out.mean.shape == (3, 30, 4) and out.cov.shape == (3, 30, 4, 4)
    assert_close(out.mean, kf.mean)
    assert_close(out.cov, kf.cov)
    assert out.modes[1].mean.shape == (3, 30, 5)  # the turn mode keeps its turn rate


def test_turn_imm_3d_estimates_height_as_the_kf_does():
    """Both modes share the vertical axis (dynamics, noise, R): height and climb rate equal the
    3-axis KF's, whatever the mode probabilities do in the horizontal plane."""
    _, z = _turning_tracks(3, 120, 3, sigma=30.0)
    z_t = torch.from_numpy(z)
    model = ConstantVelocity(ndim=3, dt=1.0, q=0.5, r=900.0)
    imm = ts.TurnIMM(model, turn_rate_q=1e-5, turn_rate_std=0.02)
    x0, P0 = _prior(3, 3)
    out = imm(z_t, x0, P0)
    kf = ts.KalmanFilter(model)(z_t, x0, P0)
    assert out.mode_probs[..., 1].max() > 0.9 and out.mode_probs[..., 1].min() < 0.1
    assert_close(out.mean[..., 4:], kf.mean[..., 4:])
    assert_close(out.cov[..., 4:, 4:], kf.cov[..., 4:, 4:])
    assert not torch.allclose(out.mean[..., :4], kf.mean[..., :4])


def test_turn_imm_single_track_and_learnable_noises():
    _, z = _turning_tracks(1, 20, 2, sigma=30.0)
    model = ConstantVelocity(ndim=2, dt=1.0, q=2.0, r=900.0, learn_q=True)
    imm = ts.TurnIMM(model, turn_rate_q=1e-5, turn_rate_std=0.02)
    x0, P0 = _prior(2, 1)
    out = imm(torch.from_numpy(z[0]), x0[0], P0)
    assert out.mean.shape == (20, 4) and out.mode_probs.shape == (20, 2)
    out.mean.square().sum().backward()
    learned = {name for name, p in imm.named_parameters() if p.grad is not None}
    assert learned == {
        "imm.filters.0.model.q.raw",
        "imm.filters.1.model.q.raw",
        "imm.filters.1.model.q_turn.raw",
    }


def test_turn_imm_bad_arguments_name_themselves():
    model = ConstantVelocity(ndim=2, dt=1.0, q=2.0, r=900.0)
    with pytest.raises(ValueError, match="^turn_rate_q: expected a number > 0"):
        ts.TurnIMM(model, turn_rate_q=0.0, turn_rate_std=0.02)
    with pytest.raises(ValueError, match="^turn_filter: expected 'ekf' or 'ukf'"):
        ts.TurnIMM(model, turn_rate_q=1e-5, turn_rate_std=0.02, turn_filter="pf")
    with pytest.raises(ValueError, match="^model: expected 2 or 3 axes"):
        ts.TurnIMM(ConstantVelocity(ndim=1), turn_rate_q=1e-5, turn_rate_std=0.02)
    with pytest.raises(ValueError, match=r"^x0: expected shape \[B, n\] = \[2, 4\]"):
        ts.TurnIMM(model, turn_rate_q=1e-5, turn_rate_std=0.02)(
            torch.zeros(2, 5, 2, dtype=torch.float64), torch.zeros(2, 5), torch.eye(4)
        )


def test_coordinated_turn_3d_is_the_planar_turn_and_a_cv_height():
    gen = torch.Generator().manual_seed(0)
    x = torch.randn(6, 7, generator=gen, dtype=torch.float64) * torch.tensor(
        [100.0, 50.0, 100.0, 50.0, 100.0, 5.0, 0.1], dtype=torch.float64
    )
    dt = torch.rand(6, generator=gen, dtype=torch.float64) * 5 + 0.5
    model = CoordinatedTurn3D(dt=2.0, q=3.0, q_turn=1e-4, q_vertical=0.7, r=[4.0, 4.0, 9.0])
    plane = CoordinatedTurn(dt=2.0, q=3.0, q_turn=1e-4)
    height = ConstantVelocity(ndim=1, dt=2.0, q=0.7)
    horizontal, vertical = [0, 1, 2, 3, 6], [4, 5]
    for d in (None, dt):
        fx = model.f(x, d)
        assert_close(fx[:, horizontal], plane.f(x[:, horizontal], d))
        F_v = height.transition(d).to(torch.float64)
        assert_close(fx[:, vertical], (F_v @ x[:, vertical].unsqueeze(-1)).squeeze(-1))
        # The analytic Jacobian against autograd's (the base class's default).
        auto = ts.models.StateSpaceModel.f_jacobian(model, x, d)
        assert_close(model.f_jacobian(x, d), auto)
        # linearize evaluates the turn's terms once: f and F to the last bit, 3-D and planar.
        for turn, state in ((model, x), (plane, x[:, horizontal])):
            f, F = turn.linearize(state, d)
            assert torch.equal(f, turn.f(state, d)) and torch.equal(F, turn.f_jacobian(state, d))
    Q = model.process_noise(dt)
    assert Q.shape == (6, 7, 7)
    assert_close(Q[:, horizontal][:, :, horizontal], plane.process_noise(dt))
    assert_close(Q[:, vertical][:, :, vertical], height.process_noise(dt))
    assert not Q[:, horizontal][:, :, vertical].any()
    assert_close(model.h(x), x[:, [0, 2, 4]])
    assert_close(model.meas_cov(), torch.diag(torch.tensor([4.0, 4.0, 9.0], dtype=torch.float64)))


def test_real_flights_merges_the_imm_rows_without_touching_the_rest():
    """``experiments/real_flights.py --only-imm`` merges its rows into the recorded report:
    every other line stays as it was, and merging again changes nothing."""
    from pathlib import Path

    from experiments.real_flights import IMM_LABEL, merge_imm

    path = Path(__file__).resolve().parents[1] / "experiments" / "results" / "real_flights.md"
    text = path.read_text()
    rows = [
        [IMM_LABEL, "rules of thumb", "84.0", "10.5", "17.1", "290.00", "CV q 6.3"],
        [IMM_LABEL, "learned, SURE (σ known)", "83.3", "10.3", "16.9", "280.00", "CV q 0.9"],
    ]
    section = [f"## {IMM_LABEL}: test", "", "IMM_RANKING", ""]
    once = merge_imm(text, rows, section)
    assert merge_imm(once, rows, section) == once
    kept = [line for line in text.rstrip("\n").split("\n") if not line.startswith("| IMM")]
    heading = [i for i, line in enumerate(kept) if line.startswith(f"## {IMM_LABEL}")]
    kept = kept[: heading[0]] if heading else kept  # a recorded IMM section is replaced
    rest = [line for line in once.split("\n") if not line.startswith("| IMM")]
    assert rest[: len(kept)] == kept
    table = once[once.index("## Held-out flights") :]
    assert table.index("| IMM(CV, CT) | learned") < table.index("| traffic KalmanSmoother6D")
    assert re.search(r"the learned IMM ranks \d+ of \d+ rows \(83\.3 m\)", once)


def test_turn_imm_smoother_is_kims_smoother_over_the_turn_imm_pass():
    """``TurnIMMSmoother`` is ``IMMSmoother`` over the ``TurnIMM``'s IMM with the turn rate
    appended to the prior (an independent construction here), cut to the CV state; its filter
    pass is the ``TurnIMM``'s own, and at the last step (nothing later to use) the smoothed
    estimate is the filtered one."""
    truth, z = _turning_tracks(3, 120, 2, sigma=30.0)
    z64 = torch.tensor(z)
    model = ConstantVelocity(ndim=2, q=1.0, r=900.0).double()
    turn = ts.TurnIMM(model, turn_rate_q=1e-5, turn_rate_std=0.05)
    prior = ts.datasets.two_point_prior(z64, torch.ones(3, 120, dtype=torch.float64), 900.0)
    with torch.no_grad():
        smoothed = ts.TurnIMMSmoother(turn, lag=8)(z64, prior.x0, prior.P0)
        filtered = turn(z64, prior.x0, prior.P0)
        x0 = torch.cat([prior.x0, torch.zeros(3, 1, dtype=torch.float64)], -1)
        P0 = torch.zeros(3, 5, 5, dtype=torch.float64)
        P0[:, :4, :4] = prior.P0
        P0[:, 4, 4] = 0.05**2
        kim = ts.IMMSmoother(turn.imm, lag=8)(z64, x0, P0)
    assert_close(smoothed.mean, kim.mean[..., :4], atol=1e-9)
    assert_close(smoothed.cov, kim.cov[..., :4, :4], atol=1e-9)
    assert_close(smoothed.filtered.mean[..., :4], filtered.mean, atol=1e-9)
    assert_close(smoothed.mean[:, -1], filtered.mean[:, -1], atol=1e-9)
    error = {
        name: float(np.sqrt(np.mean((out.mean[..., 0::2].numpy() - truth) ** 2)))
        for name, out in (("smoothed", smoothed), ("filtered", filtered))
    }
    assert error["smoothed"] < 0.8 * error["filtered"], error


def test_track_imm_smooths_by_default(tmp_path):
    """``--estimator imm`` runs Kim's fixed-lag smoother (lag 5; ``--lag 8`` another lag):
    closer to the truth than the IMM filter (``--lag 0``) on the same file and settings."""
    truth, z = _turning_tracks(4, 150, 2, sigma=30.0, seed=2)
    source = tmp_path / "in.csv"
    _write(source, z)
    errors = {}
    for name, extra in (("filter", ["--lag", "0"]), ("default", []), ("lag 8", ["--lag", "8"])):
        target = tmp_path / f"{name}.csv"
        _track(str(source), "-o", str(target), "--estimator", "imm", "--meas-std", "30", *extra)
        est = _positions(target, 2)
        errors[name] = float(np.sqrt(np.mean((est - truth.reshape(-1, 2)) ** 2)))
    assert errors["default"] < 0.85 * errors["filter"], errors
    assert errors["lag 8"] < 0.85 * errors["filter"], errors
    assert errors["default"] != errors["lag 8"], errors


@pytest.mark.parametrize("name", ["kf", "ekf", "ukf", "rstkf", "pf", "svsf", "spvsf"])
def test_a_lag_for_a_filter_is_refused(name):
    with pytest.raises(ValueError, match=f"lag: {name} is a filter"):
        Settings(estimator=name, lag=3)


def test_imm_fit_searches_the_noises_and_moves_a_bad_start():
    """``self_tune`` of the IMM scores scaled noises by SURE (no descent): from noises 30×
    too small for these turns it raises the turn mode's (the straight legs need no more ``q``),
    and its fresh-probe risk falls."""
    from dataclasses import replace

    from torchsvs.datasets import RecordedTracks
    from torchsvs.fitting.defaults import complete_settings
    from torchsvs.fitting.tuning import self_tune

    _, z = _turning_tracks(6, 150, 2, sigma=30.0, seed=4)
    z64 = torch.tensor(z)
    dt = torch.ones(6, 150, dtype=torch.float64)
    tracks = RecordedTracks(
        z=z64, dt=dt, time=dt.cumsum(1), lengths=torch.full((6,), 150), ids=list("abcdef")
    )
    good = complete_settings(Settings("imm", meas_var=[900.0, 900.0]), tracks)
    bad = replace(good, q=good.q / 30, turn_q=good.turn_q / 30, turn_rate_q=good.turn_rate_q / 30)
    fit = self_tune(bad, tracks)
    assert fit.settings.turn_rate_q > 3 * bad.turn_rate_q
    began, ended = map(
        float, re.search(r"fresh probes ([\d.]+) → ([\d.]+)", fit.stages[-1]).groups()
    )
    assert ended < began


class _Passes(NamedTuple):
    """A smoother's result as :func:`~torchsvs.smoother_guard.smoothed_or_filtered` reads it."""

    mean: torch.Tensor
    cov: torch.Tensor | None
    filtered: Any


def _linear_passes(smooth: torch.Tensor, filt: torch.Tensor):
    """A "smoother" ``smooth[b] · z`` and a "filter" ``filt[b] · z`` per track ``b`` (states
    ``[B, T, 4]`` of two axes, position and velocity, the velocities 0)."""

    def state(positions: torch.Tensor) -> torch.Tensor:
        out = positions.new_zeros(*positions.shape[:-1], 4)
        out[..., 0::2] = positions
        return out

    def run(z: torch.Tensor) -> _Passes:
        inner = _Passes(state(filt[:, None, None] * z), None, None)
        return _Passes(state(smooth[:, None, None] * z), None, inner)

    return run


def _probe(z: torch.Tensor, std: torch.Tensor):
    from torchsvs.accuracy import PROBE_STEP, draw_probe

    return draw_probe(z, std, PROBE_STEP, torch.Generator().manual_seed(3))


def test_the_imm_smoother_falls_back_to_its_filter_per_track_by_sure():
    """Each track keeps the pass of lower SURE: on pure noise (track 0) estimating 0 (the
    "filter" 0·z: SURE ≈ 0) beats following the data (the "smoother" z: SURE = r); on a large
    signal (track 1) the other way round. The risk terms are the chosen pass's."""
    from torchsvs.estimating import smoothed_or_filtered

    g = torch.Generator().manual_seed(0)
    z = torch.randn(2, 400, 2, generator=g, dtype=torch.float64)
    z[1] += 1000.0 * torch.randn(400, 2, generator=g, dtype=torch.float64)
    run = _linear_passes(torch.tensor([1.0, 1.0]), torch.tensor([0.0, 0.0]))
    std = torch.ones(2, dtype=torch.float64)
    chosen, terms, back = smoothed_or_filtered(run(z), run, z, std, _probe(z, std))
    assert back.tolist() == [True, False]
    assert_close(chosen.mean[0, :, 0::2], torch.zeros_like(z[0]), atol=0)
    assert_close(chosen.mean[1, :, 0::2], z[1], atol=0)
    # the estimates of the passes kept: ≈ 0 for 0·z on noise, exactly √(r + r) for z itself
    rmse, _ = terms.per_track([1.0, 1.0], 2)
    assert rmse[0] < 0.45 and abs(rmse[1] - math.sqrt(2.0)) < 1e-9, rmse


def test_the_imm_smoother_is_kept_only_where_it_wins_over_the_noise_interval():
    """SURE is linear in the noise variance: with a "smoother" 0.2·z and a "filter" 0.8·z on
    pure noise of variance 1.5 read as r = 1, the smoother wins at r (SURE difference
    0.6·1.5 − 1.2·r < 0) and loses at 0.5 r; given that interval the track falls back."""
    from torchsvs.estimating import smoothed_or_filtered

    z = math.sqrt(1.5) * torch.randn(1, 2000, 2, generator=torch.Generator().manual_seed(1))
    z = z.double()
    run = _linear_passes(torch.tensor([0.2]), torch.tensor([0.8]))
    std = torch.ones(2, dtype=torch.float64)
    _, _, alone = smoothed_or_filtered(run(z), run, z, std, _probe(z, std))
    _, _, ranged = smoothed_or_filtered(
        run(z), run, z, std, _probe(z, std), ([0.5, 0.5], [2.0, 2.0])
    )
    assert alone.tolist() == [False] and ranged.tolist() == [True]


def test_imm_lag_zero_is_its_filter_and_refused_elsewhere():
    assert Settings(estimator="imm", lag=0).smoother_lag == 0
    assert Settings(estimator="imm").smoother_lag == 5
    with pytest.raises(ValueError, match=r"^lag: expected an integer >= 1, got 0"):
        Settings(estimator="ks", lag=0)
    with pytest.raises(ValueError, match=r"^lag: expected an integer >= 0 \(0 for imm"):
        Settings(estimator="imm", lag=-1)


def test_paired_probes_change_nothing_but_the_time(tmp_path, monkeypatch):
    """The IMM's plain and probed runs in one batch (``paired_probes``: the fit's SURE and the
    error estimate) choose the same noises and write the same estimates and error estimate
    as two runs, and they did run paired (the split counted)."""
    import json

    import torchsvs.estimating as estimating
    import torchsvs.fitting.batches as batches
    from torchsvs.estimator import split_batch
    from torchsvs.smoothers.imm import IMMSmoother
    from torchsvs.track_run import summary_path

    _, z = _turning_tracks(4, 120, 2, sigma=30.0, seed=2)
    source = tmp_path / "in.csv"
    _write(source, z)
    splits = []

    def counted(result: Any, first: int) -> Any:
        splits.append(first)
        return split_batch(result, first)

    monkeypatch.setattr(estimating, "split_batch", counted)
    monkeypatch.setattr(batches, "split_batch", counted)
    found = {}
    for paired in (True, False):
        monkeypatch.setattr(IMMSmoother, "paired_probes", paired)
        out = tmp_path / f"{paired}.csv"
        _track(str(source), "-o", str(out), "--estimator", "imm", "--fit", "--meas-std", "30")
        summary = json.loads(summary_path(out).read_text())
        fit = re.sub(r"\(\d+\.\d s\)", "", summary["fit"])
        found[paired] = (_positions(out, 2), fit, summary["estimated_position_rmse"])
        if paired:
            assert len(splits) >= 12, splits  # 11 fit candidates' risks and the estimate
            splits.clear()
    assert not splits
    assert_close(torch.tensor(found[True][0]), torch.tensor(found[False][0]), atol=1e-9)
    assert found[True][1] == found[False][1]
    assert found[True][2] == pytest.approx(found[False][2], rel=1e-9)


def test_split_batch_cuts_every_batched_tensor():
    from torchsvs.estimator import split_batch

    class Inner(NamedTuple):
        mean: torch.Tensor
        total: torch.Tensor

    class Outer(NamedTuple):
        mean: torch.Tensor
        cov: torch.Tensor | None
        modes: tuple[Inner, ...]

    x = torch.arange(5.0)
    inner = Inner(x, torch.tensor(7.0))
    first, second = split_batch(Outer(x[:, None], None, (inner, inner)), 2)
    assert first.mean.flatten().tolist() == [0.0, 1.0] and second.mean.shape == (3, 1)
    assert first.cov is None and second.cov is None
    assert second.modes[1].mean.tolist() == [2.0, 3.0, 4.0]
    assert float(first.modes[0].total) == 7.0  # no batch axis: both halves keep it
