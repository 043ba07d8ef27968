"""`make bench`: KF, SVSF and smoother passes on B = 10,000 tracks × 1,000 steps, float32.

Reports nanoseconds per track-step beside simdkalman (vectorised NumPy, float64; with the
options that compute the most and at its fastest: filtered states and covariances only) and
filterpy (one track at a time; run on a subsample of tracks and scaled), all on the same data in
the same process, and the ratios between them, and the largest difference between torchsvs's
and simdkalman's filtered means. Every torchsvs pass runs twice: keeping the whole result
(covariance history, predictions, gains, S), and keeping the means and covariances only
(``keep="moments"``, what simdkalman's fastest options compute). Machines are shared and
noisy: read the ratios.

    python -m benchmarks.forward [--tracks 10000] [--steps 1000] [--filterpy-tracks 20]

Writes ``benchmarks/forward.md``.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path

import torch

import torchsvs as ts
from benchmarks.common import CVProblem, filterpy_run, simdkalman_run
from benchmarks.timing import alternating_best, best_of
from torchsvs.evaluation import markdown_table
from torchsvs.recipes import PSI_SMOOTHER_LIMIT_IN_SIGMAS

RESULTS = Path(__file__).with_name("forward.md")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tracks", type=int, default=10_000)
    parser.add_argument("--steps", type=int, default=1_000)
    parser.add_argument("--filterpy-tracks", type=int, default=20)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args(argv)
    B, T = args.tracks, args.steps

    problem = CVProblem(B, T)
    model, x0, P0, z = problem.model, problem.x0, problem.P0, problem.z
    kf = ts.KalmanFilter(model)
    svsf = ts.SVSF(model, psi=[800.0, 800.0], gamma=0.1, artificial=None)
    svsf_fd = ts.SVSF(model, psi=[800.0, 60.0, 800.0, 60.0], gamma=0.1)
    svss = ts.SVSS(svsf, lag=1)
    rts = ts.RTSSmoother(kf)
    # The variable boundary layer at `track`'s smoother limit (one λ per track, over its axes).
    vbl = ts.VariableBoundarySVSF(model, psi=PSI_SMOOTHER_LIMIT_IN_SIGMAS, gamma=0.1)
    vbl_svss = ts.SVSS(vbl, lag=1)

    def run_torch(
        est: torch.nn.Module, prior_cov: torch.Tensor = P0, keep: str = "all"
    ) -> Callable[[], object]:
        def call() -> object:
            with torch.no_grad():
                return est(z, x0, prior_cov, keep=keep)

        return call

    def run_simdkalman(fastest: bool = True) -> Callable[[], object]:
        return lambda: simdkalman_run(problem, observations=not fastest)

    def run_filterpy() -> object:
        return filterpy_run(problem, args.filterpy_tracks)

    print(
        f"B = {B} tracks × T = {T} steps; torch {torch.__version__}, "
        f"{torch.get_num_threads()} threads"
    )
    # Per-track P0 [B, n, n]: B covariance recursions, as simdkalman and filterpy run.
    per_track = problem.per_track_P0()
    cases = {
        "torchsvs KF": kf,
        "torchsvs SVSF (H⁺ mode)": svsf,
        "torchsvs SVSF (finite-difference velocity)": svsf_fd,
        "torchsvs SVSS lag 1 (H⁺ mode)": svss,
        "torchsvs KF + RTS": rts,
        "torchsvs SVSF (variable boundary layer)": vbl,
        "torchsvs SVSS lag 1 (variable boundary layer)": vbl_svss,
    }
    fastest = "simdkalman KF, filtered moments only (float64)"
    calls = {f"{name} (float32)": run_torch(est, per_track) for name, est in cases.items()}
    # What simdkalman's fastest options keep: the filtered (smoothed) means and covariances.
    for name, est in cases.items():
        calls[f"{name}, keep='moments' (float32)"] = run_torch(est, per_track, "moments")
    calls[fastest] = run_simdkalman(True)
    calls["simdkalman KF, also predicted observations (float64)"] = run_simdkalman(False)
    # Alternating, round by round: the machine's noise hits every implementation alike.
    timed = alternating_best(calls, args.repeats, progress="rounds")
    results = {name: seconds / (B * T) for name, seconds in timed.items()}
    filterpy_tracks = min(B, args.filterpy_tracks)
    filterpy_run(problem, 1)  # imports filterpy outside the timed call
    results["filterpy KF (float64)"] = best_of(run_filterpy, 1) / (filterpy_tracks * T)

    simd_time = results[fastest]
    rows = [[name, f"{1e9 * sec:,.1f}", f"{simd_time / sec:.1f}×"] for name, sec in results.items()]
    table = markdown_table(
        ["implementation", "ns / track-step", "simdkalman (fastest) ÷ this"], rows
    )
    with torch.no_grad():
        ours = kf(z.double(), x0.double(), per_track.double()).mean.numpy()
    theirs = run_simdkalman(True)()
    svsf_time = results["torchsvs SVSF (H⁺ mode) (float32)"]
    svss_time = results["torchsvs SVSS lag 1 (H⁺ mode) (float32)"]
    svss_moments = results["torchsvs SVSS lag 1 (H⁺ mode), keep='moments' (float32)"]
    svsf_moments = results["torchsvs SVSF (H⁺ mode), keep='moments' (float32)"]
    vbl_ratio = (
        results["torchsvs SVSS lag 1 (variable boundary layer) (float32)"]
        / results["torchsvs KF + RTS (float32)"]
    )
    text = (
        f"# Forward passes on B = {B:,} tracks × T = {T:,} steps\n\n"
        f"Generated by `python -m benchmarks.forward --repeats {args.repeats}`: torch "
        f"{torch.__version__}, {torch.get_num_threads()} threads, best of the rounds (the "
        "implementations alternating), per-track priors `P0 [B, 4, 4]`, no gradients, the same "
        "data for every library in one process. A torchsvs pass keeps its whole result "
        "(means, covariances, predictions, innovations, gains, S) by default, or with "
        "`keep='moments'` the means and covariances of every step (the covariance history), "
        "as simdkalman's fastest options do: they compute the filtered means and covariances "
        f"only (`observations=False`). filterpy ran once on {filterpy_tracks} tracks, scaled per "
        f"track-step.\n\n{table}\n\n"
        f"max |x̂ torchsvs − x̂ simdkalman| (float64 KF): {abs(ours - theirs).max():.2e}; "
        f"SVSS lag 1 ÷ SVSF: {svss_time / svsf_time:.2f} (whole results), "
        f"{svss_moments / svsf_moments:.2f} (both keeping their moments); the variable "
        f"boundary layer's SVSS lag 1 ÷ KF + RTS: {vbl_ratio:.2f} (whole results).\n"
    )
    RESULTS.write_text(text)
    print(text)


if __name__ == "__main__":
    main()
