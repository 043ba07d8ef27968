"""`make bench`: the benchmark matrix. Every torchsvs estimator × B ∈ {1, 100, 10,000} tracks ×
T steps × float32/float64 × forward and forward+backward, beside filterpy, pykalman,
simdkalman and torch-kf on the same data in the same run.

* Data: the constant-velocity model of the papers (:class:`benchmarks.common.CVProblem`),
  seeded tracks, per-track priors ``P0 [B, 4, 4]``; float32 and float64 runs see the same
  numbers (float32 data, upcast).
* Timing: per (B, dtype), the implementations take turns round by round in this process
  (:func:`benchmarks.timing.alternating_best`), best of ``--repeats`` rounds after an untimed
  first call that also checks the estimates; reported as ns per track-step and as a ratio to
  torchsvs's KF in the same configuration and pass.
* Peak memory: every case once more in a fresh process (forked from a server that has only
  imported the libraries; ``--case NAME --tracks B --dtype D --pass P`` runs one from the
  command line and prints its JSON), after a warm-up on one short track: the peak resident
  memory of the call above the resident memory before it (``VmHWM`` reset through
  ``/proc/self/clear_refs``).
* Slow implementations run on the first tracks only (filterpy, pykalman, the SPVSF at large
  B), timed per track-step.

    python -m benchmarks.matrix [--tracks 1 100 10000] [--steps 1000] [--repeats 4]

Writes ``benchmarks/results.md`` and ``benchmarks/results.png``.
"""

from __future__ import annotations

import argparse
import gc
import json
import multiprocessing
import os
import resource
import sys
import time
from collections.abc import Callable, Sequence
from concurrent.futures import Future, ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

import torchsvs as ts
from benchmarks.common import CVProblem, filterpy_run, simdkalman_run
from benchmarks.timing import alternating_best
from torchsvs.evaluation import markdown_table

HERE = Path(__file__).parent
PSI = [800.0, 60.0, 800.0, 60.0]  # m, m/s: finite-difference velocity (ts.SVSF's default mode)
GAMMA = 0.1
FORWARD, BACKWARD = "forward", "forward+backward"
KF = "torchsvs KF"


@dataclass(frozen=True)
class Settings:
    """Sizes of the run: subsample caps of the slow implementations and the particles."""

    steps: int = 1000
    particles: int = 100
    spvsf_tracks: int = 20
    spvsf_steps: int = 200
    filterpy_tracks: int = 20
    pykalman_tracks: int = 5
    torch_kf_tracks: int = 100
    threads: int = 0  # torch's intra-op threads; 0: torch's default


@dataclass
class Runner:
    """One timed call on the first ``tracks`` tracks (and ``steps`` steps, if not all); it
    returns the means ``[tracks, T, n]`` (or the loss, for forward+backward); ``check``: the
    float64 torchsvs pass its means are compared with (``"filter"``: the KF, ``"smooth"``: the
    RTS), if any."""

    call: Callable[[], Any]
    tracks: int
    check: str | None = None
    steps: int | None = None


@dataclass(frozen=True)
class Case:
    """An implementation: its builder ``(problem, dtype, pass, settings) -> Runner``, the dtypes
    it runs in, and whether it has a forward+backward pass."""

    name: str
    build: Callable[[CVProblem, torch.dtype, str, Settings], Runner]
    dtypes: tuple[str, ...] = ("float32", "float64")
    backward: bool = False


Make = Callable[[ts.models.ConstantVelocity, Settings], torch.nn.Module]


def _torchsvs(make: Make, check: str | None = None):  # noqa: ANN202
    """A torchsvs case: forward (no gradients, means and covariances kept: what the peers
    return) or forward+backward (a scalar loss of the means, ``keep="mean"``; the learnable
    parameters: ψ and γ, or for the KF and RTS the model's q and R)."""

    def build(problem: CVProblem, dtype: torch.dtype, mode: str, settings: Settings) -> Runner:
        # The Kalman pair learns its noise in the forward+backward pass.
        model = problem.make_model(learn_noise=mode == BACKWARD and check is not None)
        est = make(model, settings).to(dtype)
        tracks, steps = problem.tracks, problem.steps
        if isinstance(est, ts.ParticleFilter):
            tracks, steps = min(tracks, settings.spvsf_tracks), min(steps, settings.spvsf_steps)
        z = problem.z_as(dtype)[:tracks, :steps]
        x0, P0 = problem.x0.to(dtype), problem.per_track_P0(dtype)[:tracks]
        stochastic = isinstance(est, ts.ParticleFilter)

        def options() -> dict[str, Any]:
            return {"generator": torch.Generator().manual_seed(1)} if stochastic else {}

        if mode == FORWARD:

            def forward() -> Any:
                with torch.no_grad():
                    return est(z, x0, P0, keep="moments", **options()).mean

            return Runner(forward, tracks, check, steps)

        def forward_backward() -> Any:
            est.zero_grad(set_to_none=True)
            loss = est(z, x0, P0, keep="mean", **options()).mean.mean()
            loss.backward()
            return loss

        return Runner(forward_backward, tracks, steps=steps)

    return build


def _simdkalman(smoothed: bool):  # noqa: ANN202
    def build(problem: CVProblem, dtype: torch.dtype, mode: str, settings: Settings) -> Runner:
        return Runner(
            lambda: simdkalman_run(problem, smoothed=smoothed),
            problem.tracks,
            "smooth" if smoothed else "filter",
        )

    return build


def _filterpy(smooth: bool):  # noqa: ANN202
    def build(problem: CVProblem, dtype: torch.dtype, mode: str, settings: Settings) -> Runner:
        tracks = min(problem.tracks, settings.filterpy_tracks)
        return Runner(
            lambda: filterpy_run(problem, tracks, smooth), tracks, "smooth" if smooth else "filter"
        )

    return build


def _pykalman(smooth: bool):  # noqa: ANN202
    def build(problem: CVProblem, dtype: torch.dtype, mode: str, settings: Settings) -> Runner:
        from pykalman import KalmanFilter

        F, H, Q, R = problem.matrices
        m0, P_init = problem.first_prior
        tracks = min(problem.tracks, settings.pykalman_tracks)
        data = problem.z_numpy[:tracks]

        def call() -> np.ndarray:
            means = []
            for track in data:  # one track at a time: pykalman has no batch axis
                kf = KalmanFilter(
                    F, H, Q, R, initial_state_mean=m0, initial_state_covariance=P_init
                )
                means.append((kf.smooth if smooth else kf.filter)(track)[0])
            return np.stack(means)

        return Runner(call, tracks, "smooth" if smooth else "filter")

    return build


def _torch_kf(smooth: bool):  # noqa: ANN202
    """torch-kf's batched ``filter`` (and ``rts_smooth``) with its defaults (explicit inverse
    of S, no Joseph form: its fastest); measurements ``[T, B, m, 1]`` prepared outside the
    timed call."""

    def build(problem: CVProblem, dtype: torch.dtype, mode: str, settings: Settings) -> Runner:
        import torch_kf

        F, H, Q, R = (torch.from_numpy(a).to(dtype) for a in problem.matrices)
        m0, P_init = (torch.from_numpy(a).to(dtype) for a in problem.first_prior)
        B = min(problem.tracks, settings.torch_kf_tracks)
        kf = torch_kf.KalmanFilter(F, H, Q, R)
        measures = problem.z_as(dtype)[:B].transpose(0, 1).unsqueeze(-1).contiguous()
        prior = torch_kf.GaussianState(
            m0.expand(B, 4).unsqueeze(-1).contiguous(), P_init.expand(B, 4, 4).contiguous()
        )

        def call() -> torch.Tensor:
            with torch.no_grad():
                states = kf.filter(prior, measures, update_first=True, return_all=True)
                if smooth:
                    states = kf.rts_smooth(states, inplace=True)
            return states.mean[..., 0].transpose(0, 1)

        return Runner(call, B, "smooth" if smooth else "filter")

    return build


def _svsf(model: ts.models.ConstantVelocity, settings: Settings | None = None) -> ts.SVSF:
    return ts.SVSF(model, psi=PSI, gamma=GAMMA)


CASES: dict[str, Case] = {
    case.name: case
    for case in [
        Case(KF, _torchsvs(lambda m, s: ts.KalmanFilter(m), "filter"), backward=True),
        Case(
            "torchsvs RTS",
            _torchsvs(lambda m, s: ts.RTSSmoother(ts.KalmanFilter(m)), "smooth"),
            backward=True,
        ),
        Case("torchsvs SVSF", _torchsvs(_svsf), backward=True),
        *(
            Case(
                f"torchsvs SVSS lag {lag}",
                _torchsvs(lambda m, s, lag=lag: ts.SVSS(_svsf(m), lag=lag)),
                backward=True,
            )
            for lag in (1, 2, 3)
        ),
        Case(
            "torchsvs SPVSF",
            _torchsvs(lambda m, s: ts.SPVSF(m, psi=PSI, gamma=GAMMA, num_particles=s.particles)),
            backward=True,
        ),
        Case("torch-kf KF", _torch_kf(False)),
        Case("torch-kf KF + RTS", _torch_kf(True)),
        Case("simdkalman KF", _simdkalman(False), dtypes=("float64",)),
        Case("simdkalman KF + RTS", _simdkalman(True), dtypes=("float64",)),
        Case("filterpy KF", _filterpy(False), ("float64",)),
        Case("filterpy KF + RTS", _filterpy(True), ("float64",)),
        Case("pykalman filter", _pykalman(False), ("float64",)),
        Case("pykalman smooth", _pykalman(True), ("float64",)),
    ]
}


def _passes(case: Case) -> tuple[str, ...]:
    return (FORWARD, BACKWARD) if case.backward else (FORWARD,)


def _build(name: str, problem: CVProblem, dtype: str, mode: str, settings: Settings) -> Runner:
    return CASES[name].build(problem, getattr(torch, dtype), mode, settings)


# ------------------------------------------------------------------ one case, fresh process
def _status(key: str) -> float:
    """A ``/proc/self/status`` field in MB."""
    with open("/proc/self/status") as status:
        for line in status:
            if line.startswith(key + ":"):
                return int(line.split()[1]) / 1024
    raise KeyError(key)


def _reset_peak() -> bool:
    """Resets the peak resident memory (VmHWM) to the current one (Linux ≥ 4.0)."""
    try:
        with open("/proc/self/clear_refs", "w") as refs:
            refs.write("5")
        return True
    except OSError:
        return False


def memory_case(name: str, tracks: int, dtype: str, mode: str, settings: Settings) -> dict:
    """Runs one case once in this (fresh) process after a warm-up on one short track (library
    loads, compiled kernels): its peak resident memory above the resident memory before it."""
    if settings.threads:
        torch.set_num_threads(settings.threads)
    warm = _build(name, CVProblem(1, 10), dtype, mode, settings)
    warm.call()
    runner = _build(name, CVProblem(tracks, settings.steps), dtype, mode, settings)
    gc.collect()
    reset = _reset_peak()
    baseline = (
        _status("VmRSS") if reset else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    )
    start = time.perf_counter()
    runner.call()
    seconds = time.perf_counter() - start
    peak = _status("VmHWM")
    return {"baseline_mb": baseline, "peak_mb": peak - baseline, "seconds": seconds, "reset": reset}


class FreshProcesses:
    """Runs :func:`memory_case` calls each in a new process: forked from a server that has
    imported the libraries and run nothing (``forkserver``), so every case starts clean without
    paying the imports again."""

    # Not this module: each child runs it afresh as its __main__ (runpy warns when preloaded).
    PRELOAD = ["benchmarks.common", "filterpy.kalman", "pykalman", "simdkalman", "torch_kf"]

    def __enter__(self) -> FreshProcesses:
        context = multiprocessing.get_context("forkserver")
        context.set_forkserver_preload(self.PRELOAD)
        self.pool = ProcessPoolExecutor(1, mp_context=context, max_tasks_per_child=1)
        return self

    def __exit__(self, *exc: object) -> None:
        self.pool.shutdown()

    def memory(self, name: str, tracks: int, dtype: str, mode: str, settings: Settings) -> Future:
        """The case's :func:`memory_case` result, to come (the cases queue: one at a time)."""
        return self.pool.submit(memory_case, name, tracks, dtype, mode, settings)


# ------------------------------------------------------------------------------ the matrix
@dataclass
class Measurement:
    implementation: str
    mode: str
    dtype: str
    B: int
    tracks: int
    steps: int
    seconds: float
    ns: float = 0.0  # per track-step
    ratio: float = float("nan")  # time ÷ torchsvs KF's, same B, dtype and pass
    peak_mb: float = float("nan")
    max_abs_diff: float | None = None
    extra: dict = field(default_factory=dict)
    memory: Future | None = field(default=None, repr=False)


def _as_numpy(means: Any) -> np.ndarray:
    if isinstance(means, torch.Tensor):
        return means.detach().double().numpy()
    return np.asarray(means, dtype=np.float64)


def run_configuration(
    problem: CVProblem,
    dtype: str,
    settings: Settings,
    repeats: int,
    names: Sequence[str],
    reference: dict[str, np.ndarray],
    processes: FreshProcesses | None = None,
) -> list[Measurement]:
    """Every case of ``names`` that runs in ``dtype`` on ``problem``: a warm-up call on one
    short track, alternating timing rounds (the first round's means are checked against
    ``reference``), and each case's peak memory queued for a fresh process (its
    :attr:`Measurement.memory`, collected later)."""
    B, T = problem.tracks, problem.steps
    tiny = CVProblem(1, 10)
    runners: dict[tuple[str, str], Runner] = {}
    for name in names:
        case = CASES[name]
        if dtype not in case.dtypes:
            continue
        for mode in _passes(case):
            _build(name, tiny, dtype, mode, settings).call()  # library loads, compiled kernels
            runners[(name, mode)] = _build(name, problem, dtype, mode, settings)
    diffs: dict[tuple[str, str], float] = {}

    def check(key: tuple[str, str], means: Any) -> None:
        runner = runners[key]
        if runner.check is not None and key not in diffs:
            ref = reference[runner.check][: runner.tracks]
            diffs[key] = float(np.abs(_as_numpy(means) - ref).max())

    timed = alternating_best(
        {key: runner.call for key, runner in runners.items()},
        repeats,
        progress=f"B={B:,} {dtype}, {len(runners)} calls a round",
        warm_up=False,
        inspect=check,
    )
    results = []
    for (name, mode), seconds in timed.items():
        tracks, steps = runners[(name, mode)].tracks, runners[(name, mode)].steps or T
        results.append(
            Measurement(
                name, mode, dtype, B, tracks, steps, seconds, 1e9 * seconds / (tracks * steps),
                max_abs_diff=diffs.get((name, mode)),
            )
        )  # fmt: skip
        print(
            f"  B={B:,} {dtype} {name}, {mode}: {results[-1].ns:,.0f} ns / track-step"
            + (f", max |Δ| {diffs[(name, mode)]:.2e}" if (name, mode) in diffs else ""),
            flush=True,
        )
    runners.clear()
    gc.collect()
    for m in results:
        base = next((r for r in results if r.implementation == KF and r.mode == m.mode), None)
        if base is not None:
            m.ratio = m.ns / base.ns
        if processes is not None:
            m.memory = processes.memory(m.implementation, B, dtype, m.mode, settings)
    return results


def collect_memory(results: list[Measurement], wait: bool = True) -> None:
    """Records the peaks of the queued memory processes (those done, unless ``wait``)."""
    for m in results:
        if m.memory is not None and np.isnan(m.peak_mb) and (wait or m.memory.done()):
            probe = m.memory.result()
            m.peak_mb, m.extra = probe["peak_mb"], probe
            print(
                f"  memory B={m.B:,} {m.dtype} {m.implementation}, {m.mode}: "
                f"{probe['peak_mb']:.1f} MB above {probe['baseline_mb']:.0f} MB",
                flush=True,
            )


def reference_means(problem: CVProblem) -> dict[str, np.ndarray]:
    """torchsvs's float64 KF and RTS means on ``problem``: what every estimate is compared with."""
    z, x0, P0 = problem.z.double(), problem.x0.double(), problem.per_track_P0(torch.float64)
    model = problem.make_model().double()
    with torch.no_grad():
        return {
            "filter": ts.KalmanFilter(model)(z, x0, P0, keep="mean").mean.numpy(),
            "smooth": ts.RTSSmoother(ts.KalmanFilter(model))(z, x0, P0, keep="mean").mean.numpy(),
        }


# ---------------------------------------------------------------------------------- report
def _cell(
    results: list[Measurement], name: str, mode: str, dtype: str, B: int
) -> Measurement | None:
    return next(
        (r for r in results if (r.implementation, r.mode, r.dtype, r.B) == (name, mode, dtype, B)),
        None,
    )


def _fmt_ns(ns: float) -> str:
    return f"{ns:,.0f}" if ns >= 100 else f"{ns:.1f}"


def _fmt_mb(mb: float) -> str:
    if np.isnan(mb):
        return "–"
    return f"{mb:,.0f}" if abs(mb) >= 10 else f"{mb:.1f}"


def _subsample(cells: Sequence[Measurement | None], steps: int) -> str:
    """What a row ran where it did not run the whole problem."""
    runs = [c for c in cells if c is not None]
    tracks = {c.tracks for c in runs if c.tracks < c.B}
    short = {c.steps for c in runs if c.steps < steps}
    parts = (
        [f"first {', '.join(map(str, sorted(tracks)))} tracks when B is larger"] if tracks else []
    )
    parts += [f"first {', '.join(map(str, sorted(short)))} steps"] if short else []
    return "; ".join(parts) or "none"


def tables(results: list[Measurement], sizes: Sequence[int], settings: Settings) -> str:
    """One markdown table per dtype: ns per track-step (÷ torchsvs KF) and peak MB per B."""
    out = []
    for dtype in ("float32", "float64"):
        header = ["implementation", "pass"]
        header += [f"B = {B:,}: ns / track-step (÷ KF)" for B in sizes]
        header += [f"B = {B:,}: peak MB" for B in sizes]
        header.append("subsample (timed per track-step)")
        rows = []
        for name, case in CASES.items():
            for mode in _passes(case):
                cells = [_cell(results, name, mode, dtype, B) for B in sizes]
                if all(c is None for c in cells):
                    continue
                row: list[object] = [name, mode]
                row += ["–" if c is None else f"{_fmt_ns(c.ns)} ({c.ratio:.2f}×)" for c in cells]
                row += ["–" if c is None else _fmt_mb(c.peak_mb) for c in cells]
                row.append(_subsample(cells, settings.steps))
                rows.append(row)
        out.append(f"### {dtype}\n\n" + markdown_table(header, rows))
    return "\n\n".join(out)


def differences(results: list[Measurement], sizes: Sequence[int]) -> str:
    """The max-abs-difference lines: every checked estimate against torchsvs's float64 KF
    (filtered means) or RTS (smoothed means), on the tracks it ran."""
    lines = []
    for B in sizes:
        parts = []
        for r in results:
            if r.B == B and r.max_abs_diff is not None and r.mode == FORWARD:
                if r.implementation in (KF, "torchsvs RTS") and r.dtype == "float64":
                    continue  # the reference itself
                parts.append(f"{r.implementation} ({r.dtype}) {r.max_abs_diff:.1e}")
        if parts:
            lines.append(f"- B = {B:,}: " + "; ".join(parts) + ".")
    return "\n".join(lines)


def reading(results: list[Measurement], sizes: Sequence[int], settings: Settings) -> str:
    """A few generated sentences reading the numbers."""
    big = max(sizes)
    sentences = []

    def get(name: str, mode: str = FORWARD, dtype: str = "float32", B: int = big):  # noqa: ANN202
        return _cell(results, name, mode, dtype, B)

    kf32, kf64 = get(KF), get(KF, dtype="float64")
    simd, tkf32, tkf64 = (
        get("simdkalman KF", dtype="float64"),
        get("torch-kf KF"),
        get("torch-kf KF", dtype="float64"),
    )
    if kf32 and kf64 and simd:
        sentences.append(
            f"At B = {big:,}, torchsvs's KF forward pass costs {_fmt_ns(kf32.ns)} ns per "
            f"track-step in float32 and {_fmt_ns(kf64.ns)} in float64: simdkalman (float64) "
            f"takes {simd.ns / kf64.ns:.1f}× the float64 time"
            + (
                f", torch-kf {tkf32.ns / kf32.ns:.1f}× (float32) and {tkf64.ns / kf64.ns:.1f}× "
                "(float64)"
                if tkf32 and tkf64
                else ""
            )
            + "."
        )
    rts, srts = get("torchsvs RTS", dtype="float64"), get("simdkalman KF + RTS", dtype="float64")
    if rts and srts:
        sentences.append(
            f"The RTS smoother (filter and backward pass) costs {_fmt_ns(rts.ns)} ns per "
            f"track-step in float64 against simdkalman's {_fmt_ns(srts.ns)}."
        )
    svsf = get("torchsvs SVSF")
    lags = [get(f"torchsvs SVSS lag {lag}") for lag in (1, 2, 3)]
    if svsf and all(lags):
        sentences.append(
            f"In float32 at B = {big:,} the SVSF costs {svsf.ratio:.2f}× the KF, and the SVSS "
            "with lags 1, 2, 3 "
            + ", ".join(f"{lag.ns / svsf.ns:.2f}×" for lag in lags if lag)
            + " the SVSF."
        )
    backward = [
        (name, get(name, BACKWARD), get(name))
        for name, case in CASES.items()
        if case.backward and name != "torchsvs SPVSF"
    ]
    ratios = [(name, b.ns / f.ns) for name, b, f in backward if b and f]
    if ratios:
        sentences.append(
            f"Forward+backward ÷ forward (float32, B = {big:,}) ranges from "
            f"{min(r for _, r in ratios):.1f} ({min(ratios, key=lambda x: x[1])[0]}) to "
            f"{max(r for _, r in ratios):.1f} ({max(ratios, key=lambda x: x[1])[0]})."
        )
    small = min(sizes)
    kf1, kf_big = get(KF, B=small), kf32
    if kf1 and kf_big and small < big:
        sentences.append(
            f"At B = {small:,} the per-step overhead dominates: the KF costs "
            f"{kf1.ns / kf_big.ns:,.0f}× more per track-step than at B = {big:,}."
        )
    fp = get("filterpy KF", dtype="float64")
    if fp and kf64:
        sentences.append(
            f"filterpy, one track at a time, takes {fp.ns / kf64.ns:,.0f}× torchsvs's float64 "
            f"KF per track-step at B = {big:,}."
        )
    peaks = [r for r in results if r.B == big and not np.isnan(r.peak_mb)]
    if peaks:
        top = max(peaks, key=lambda r: r.peak_mb)
        sentences.append(
            f"The largest peak at B = {big:,} is {top.implementation}'s {top.mode} in "
            f"{top.dtype}: {_fmt_mb(top.peak_mb)} MB above the process's resident memory "
            "before the call"
            + (f" (on its first {top.tracks:,} tracks)" if top.tracks < top.B else "")
            + (f" (on its first {top.steps:,} steps)" if top.steps < settings.steps else "")
            + "."
        )
    diffs = [r.max_abs_diff for r in results if r.max_abs_diff is not None and r.dtype == "float64"]
    diffs = [d for d in diffs if d > 0]
    if diffs:
        sentences.append(
            f"Every float64 peer's means agree with torchsvs's to {max(diffs):.1e} m or better "
            "(positions of order 10⁵ m)."
        )
    return " ".join(sentences)


def plot(results: list[Measurement], sizes: Sequence[int], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(13, 5.5), sharey=True)
    colors = plt.get_cmap("tab20").colors
    for ax, dtype in zip(axes, ("float32", "float64"), strict=True):
        for index, (name, case) in enumerate(CASES.items()):
            for mode in _passes(case):
                points = [_cell(results, name, mode, dtype, B) for B in sizes]
                xs = [B for B, p in zip(sizes, points, strict=True) if p]
                ys = [p.ns for p in points if p]
                if not xs:
                    continue
                ax.plot(
                    xs,
                    ys,
                    marker="o" if mode == FORWARD else "s",
                    linestyle="-" if mode == FORWARD else "--",
                    color=colors[index % len(colors)],
                    label=name + (" (fwd+bwd)" if mode == BACKWARD else ""),
                )
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("B (tracks)")
        ax.set_title(dtype)
        ax.grid(True, which="both", alpha=0.3)
    axes[0].set_ylabel("ns per track-step (best of the rounds)")
    handles, labels = {}, {}
    for ax in axes:
        for h, label in zip(*ax.get_legend_handles_labels(), strict=True):
            handles.setdefault(label, h)
    labels = list(handles)
    fig.legend([handles[k] for k in labels], labels, loc="center right", fontsize=8)
    fig.tight_layout(rect=(0, 0, 0.78, 1))
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tracks", type=int, nargs="+", default=[1, 100, 10_000])
    parser.add_argument("--steps", type=int, default=Settings.steps)
    # Best of 4: on a shared machine a round that touches cold memory (pages the host took
    # back) costs up to 10x; with 2 rounds a forward pass came out 8x its usual time.
    parser.add_argument("--repeats", type=int, default=4)
    parser.add_argument("--particles", type=int, default=Settings.particles)
    parser.add_argument("--spvsf-tracks", type=int, default=Settings.spvsf_tracks)
    parser.add_argument("--spvsf-steps", type=int, default=Settings.spvsf_steps)
    parser.add_argument("--filterpy-tracks", type=int, default=Settings.filterpy_tracks)
    parser.add_argument("--pykalman-tracks", type=int, default=Settings.pykalman_tracks)
    parser.add_argument("--torch-kf-tracks", type=int, default=Settings.torch_kf_tracks)
    parser.add_argument("--threads", type=int, default=0, help="torch threads (0: torch's)")
    parser.add_argument("--cases", nargs="+", default=list(CASES), metavar="NAME")
    parser.add_argument("--no-memory", action="store_true", help="skip the memory processes")
    parser.add_argument("--out", type=Path, default=HERE, help="directory of results.md/.png")
    parser.add_argument("--case", help=argparse.SUPPRESS)  # one case's memory, fresh process
    parser.add_argument("--dtype", default="float64", help=argparse.SUPPRESS)
    parser.add_argument("--pass", dest="mode", default=FORWARD, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    settings = Settings(
        args.steps,
        args.particles,
        args.spvsf_tracks,
        args.spvsf_steps,
        args.filterpy_tracks,
        args.pykalman_tracks,
        args.torch_kf_tracks,
        args.threads,
    )
    if args.threads:
        torch.set_num_threads(args.threads)
    if args.case:
        print(json.dumps(memory_case(args.case, args.tracks[0], args.dtype, args.mode, settings)))
        return
    unknown = set(args.cases) - set(CASES)
    if unknown:
        parser.error(f"--cases: unknown {sorted(unknown)}; known: {list(CASES)}")

    start = time.perf_counter()
    load = os.getloadavg()[0]
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads; {settings}", flush=True)
    command = " ".join(["python -m benchmarks.matrix", *(sys.argv[1:] if argv is None else argv)])
    results: list[Measurement] = []

    def report(final: bool) -> str:
        collect_memory(results, wait=final)
        minutes = (time.perf_counter() - start) / 60
        text = write_report(results, args, settings, command, minutes, (load, os.getloadavg()[0]))
        if not final:
            text = "**Partial: the run is still going.**\n\n" + text
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "results.md").write_text(text)
        plot(results, list(args.tracks), args.out / "results.png")
        return text

    with FreshProcesses() as processes:
        for B in args.tracks:
            problem = CVProblem(B, args.steps)
            reference = reference_means(problem)
            for dtype in ("float32", "float64"):
                results += run_configuration(
                    problem,
                    dtype,
                    settings,
                    args.repeats,
                    args.cases,
                    reference,
                    None if args.no_memory else processes,
                )
                report(final=False)
            del problem, reference
            gc.collect()
        text = report(final=True)
    print(text)
    print(f"total run time {(time.perf_counter() - start) / 60:.1f} min")


def write_report(
    results: list[Measurement],
    args: argparse.Namespace,
    settings: Settings,
    command: str,
    minutes: float,
    load: tuple[float, float],
) -> str:
    """results.md's text."""
    sizes = list(args.tracks)
    return (
        f"# Benchmark matrix: B ∈ {{{', '.join(f'{B:,}' for B in sizes)}}} × T = "
        f"{args.steps:,}\n\n"
        f"Generated by `{command}` in {minutes:.1f} min: torch {torch.__version__}, "
        f"{torch.get_num_threads()} threads, numpy {np.__version__}; the machine is shared "
        f"(1-minute load average {load[0]:.1f} at the start, {load[1]:.1f} at the end, on "
        f"{os.cpu_count()} cores). Model: the papers' 2-D constant-velocity "
        "model (dt 1 s, q 0.16, 200 m position noise), seeded tracks from one prior, "
        "per-track priors `P0 [B, 4, 4]`; float32 and float64 runs get the same numbers. "
        "Timing: best of "
        f"{args.repeats} round(s) in one process, per (B, dtype) the implementations taking "
        "turns, after a warm-up call of each on one 10-step track (the first round's means "
        "are the ones checked); ns per track-step, and in brackets the time ÷ "
        "torchsvs KF's in the same B, dtype and pass. torchsvs forward: no gradients, "
        "keeping means and covariances (`keep='moments'`, what the peers return); "
        "forward+backward: the mean of the means as loss, `.backward()` (`keep='mean'`) with "
        "ψ and γ learnable (SVSF, SVSS, SPVSF) or the model's q and R (KF, RTS). SVSF: "
        f"finite-difference velocity (ts.SVSF's default), ψ = {PSI}, γ = {GAMMA}. SPVSF: "
        f"{settings.particles} particles, on the first {settings.spvsf_tracks} tracks when B "
        f"is larger and the first {settings.spvsf_steps} steps (its forward+backward pass is "
        "slow whatever B: a per-step cost). Subsamples, timed per track-step: filterpy on "
        f"the first {settings.filterpy_tracks} tracks, pykalman on the first "
        f"{settings.pykalman_tracks} (both one track at a time), torch-kf on the first "
        f"{settings.torch_kf_tracks}. Peers run "
        "with their fastest options: simdkalman states and covariances only "
        "(`observations=False`), torch-kf its defaults (explicit inverse of S, no Joseph "
        "form), measurements rearranged to its `[T, B, m, 1]` outside the timed call. Peak "
        "MB: each case once more in a fresh process (forked from a server that only imported "
        "the libraries, while the next configuration is timed) after a warm-up on one "
        "10-step track: the peak resident memory of the call above the resident memory "
        "before it (`VmHWM` reset through `/proc/self/clear_refs`); subsampled cases on "
        "their subsample.\n\n"
        f"![ns per track-step](results.png)\n\n{tables(results, sizes, settings)}\n\n"
        "## Max abs difference of the means\n\n"
        "Against torchsvs's float64 KF (filtered means) or RTS (smoothed means), on the "
        f"tracks each ran, in metres:\n\n{differences(results, sizes)}\n\n"
        f"## Reading\n\n{reading(results, sizes, settings)}\n"
    )


if __name__ == "__main__":
    main()
