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
from benchmarks.timing import alternating_best, best_of
from torchsvs.evaluation import markdown_table

RESULTS = Path(__file__).with_name("forward.md")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tracks", type=int, default=10_000)
    parser.add_argument("--steps", type=int, default=1_000)
    parser.add_argument("--filterpy-tracks", type=int, default=20)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args(argv)
    B, T = args.tracks, args.steps

    model = ts.models.ConstantVelocity(dt=1.0, q=0.16, r=200.0**2)
    x0 = torch.tensor([-25000.0, 120.0, -10000.0, 0.0])
    P0 = torch.diag(torch.tensor([1e4, 1e3, 1e4, 1e3]))
    _, z = model.simulate(x0.expand(B, 4), T, generator=torch.Generator().manual_seed(0))
    z = z.float().contiguous()
    kf = ts.KalmanFilter(model)
    svsf = ts.SVSF(model, psi=[800.0, 800.0], gamma=0.1, artificial=None)
    svsf_fd = ts.SVSF(model, psi=[800.0, 60.0, 800.0, 60.0], gamma=0.1)
    svss = ts.SVSS(svsf, lag=1)
    rts = ts.RTSSmoother(kf)

    def run_torch(
        est: torch.nn.Module, prior_cov: torch.Tensor = P0, keep: str = "all"
    ) -> Callable[[], object]:
        def call() -> object:
            with torch.no_grad():
                return est(z, x0, prior_cov, keep=keep)

        return call

    F, H = model.transition().numpy(), model.meas_matrix().numpy()
    Q, R = model.process_noise().numpy(), model.meas_cov().numpy()
    z_np = z.double().numpy()
    # simdkalman and filterpy take the prior at the first measurement: predict x0 once.
    m0, P_init = F @ x0.double().numpy(), F @ P0.double().numpy() @ F.T + Q

    import simdkalman
    from filterpy.kalman import KalmanFilter as FilterpyKF

    simd = simdkalman.KalmanFilter(F, Q, H, R)

    def run_simdkalman(fastest: bool = True) -> Callable[[], object]:
        def call() -> object:
            return simd.compute(
                z_np,
                0,
                initial_value=m0,
                initial_covariance=P_init,
                smoothed=False,
                filtered=True,
                observations=not fastest,
            )

        return call

    sub = z_np[: args.filterpy_tracks]

    def run_filterpy() -> object:
        for track in sub:
            f = FilterpyKF(dim_x=4, dim_z=2)
            f.x, f.P, f.F, f.H, f.Q, f.R = m0.copy(), P_init.copy(), F, H, Q, R
            f.batch_filter(list(track), update_first=True)
        return None

    print(
        f"B = {B} tracks × T = {T} steps; torch {torch.__version__}, "
        f"{torch.get_num_threads()} threads"
    )
    # Per-track P0 [B, n, n]: B covariance recursions, as simdkalman and filterpy run.
    per_track = P0.expand(B, 4, 4).contiguous()
    cases = {
        "torchsvs KF": kf,
        "torchsvs SVSF (H⁺ mode)": svsf,
        "torchsvs SVSF (finite-difference velocity)": svsf_fd,
        "torchsvs SVSS lag 1 (H⁺ mode)": svss,
        "torchsvs KF + RTS": rts,
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
    results["filterpy KF (float64)"] = best_of(run_filterpy, 1) / (len(sub) * T)

    simd_time = results[fastest]
    rows = [[name, f"{1e9 * sec:,.1f}", f"{simd_time / sec:.1f}×"] for name, sec in results.items()]
    table = markdown_table(
        ["implementation", "ns / track-step", "simdkalman (fastest) ÷ this"], rows
    )
    with torch.no_grad():
        ours = kf(z.double(), x0.double(), per_track.double()).mean.numpy()
    theirs = run_simdkalman(True)().filtered.states.mean
    svsf_time = results["torchsvs SVSF (H⁺ mode) (float32)"]
    svss_time = results["torchsvs SVSS lag 1 (H⁺ mode) (float32)"]
    svss_moments = results["torchsvs SVSS lag 1 (H⁺ mode), keep='moments' (float32)"]
    svsf_moments = results["torchsvs SVSF (H⁺ mode), keep='moments' (float32)"]
    text = (
        f"# Forward passes on B = {B:,} tracks × T = {T:,} steps\n\n"
        f"Generated by `python -m benchmarks.forward --repeats {args.repeats}`: torch "
        f"{torch.__version__}, {torch.get_num_threads()} threads, best of the rounds (the "
        "implementations alternating), per-track priors `P0 [B, 4, 4]`, no gradients, the same "
        "data for every library in one process. A torchsvs pass keeps its whole result "
        "(means, covariances, predictions, innovations, gains, S) by default, or with "
        "`keep='moments'` the means and covariances of every step (the covariance history), "
        "as simdkalman's fastest options do: they compute the filtered means and covariances "
        f"only (`observations=False`). filterpy ran once on {len(sub)} tracks, scaled per "
        f"track-step.\n\n{table}\n\n"
        f"max |x̂ torchsvs − x̂ simdkalman| (float64 KF): {abs(ours - theirs).max():.2e}; "
        f"SVSS lag 1 ÷ SVSF: {svss_time / svsf_time:.2f} (whole results), "
        f"{svss_moments / svsf_moments:.2f} (both keeping their moments).\n"
    )
    RESULTS.write_text(text)
    print(text)


if __name__ == "__main__":
    main()
