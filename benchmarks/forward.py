"""`make bench`: KF and SVSF forward passes on B = 10,000 tracks × 1,000 steps, float32.

Reports nanoseconds per track-step beside simdkalman (vectorised NumPy, float64) and filterpy
(one track at a time; run on a subsample of tracks and scaled), all on the same data in the same
process, and the ratios between them. Machines are shared and noisy: read the ratios.

    python -m benchmarks.forward [--tracks 10000] [--steps 1000] [--filterpy-tracks 20]
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable

import torch

import torchsvs as ts
from torchsvs.evaluation import markdown_table


def best_of(fn: Callable[[], object], repeats: int) -> float:
    """The fastest of ``repeats`` wall-clock runs, in seconds."""
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return min(times)


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

    def run_torch(est: torch.nn.Module, prior_cov: torch.Tensor = P0) -> Callable[[], object]:
        def call() -> object:
            with torch.no_grad():
                return est(z, x0, prior_cov)

        return call

    F, H = model.transition().numpy(), model.meas_matrix().numpy()
    Q, R = model.process_noise().numpy(), model.meas_cov().numpy()
    z_np = z.double().numpy()
    # simdkalman and filterpy take the prior at the first measurement: predict x0 once.
    m0, P_init = F @ x0.double().numpy(), F @ P0.double().numpy() @ F.T + Q

    import simdkalman
    from filterpy.kalman import KalmanFilter as FilterpyKF

    simd = simdkalman.KalmanFilter(F, Q, H, R)

    def run_simdkalman() -> object:
        return simd.compute(
            z_np, 0, initial_value=m0, initial_covariance=P_init, smoothed=False, filtered=True
        )

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
    results = {}
    # A P0 shared by all tracks lets the KF run its (data-independent) covariance recursion once;
    # a per-track P0 [B, n, n] forces B covariance recursions, as simdkalman and filterpy do.
    results["torchsvs KF (float32)"] = best_of(run_torch(kf), args.repeats) / (B * T)
    per_track = P0.expand(B, 4, 4).contiguous()
    results["torchsvs KF, per-track P0 (float32)"] = best_of(
        run_torch(kf, per_track), args.repeats
    ) / (B * T)
    results["torchsvs SVSF (float32)"] = best_of(run_torch(svsf), args.repeats) / (B * T)
    results["simdkalman KF (float64)"] = best_of(run_simdkalman, args.repeats) / (B * T)
    results["filterpy KF (float64)"] = best_of(run_filterpy, 1) / (len(sub) * T)

    ours = results["torchsvs KF (float32)"]
    rows = [[name, f"{1e9 * sec:,.0f}", f"{sec / ours:.2f}×"] for name, sec in results.items()]
    print(markdown_table(["implementation", "ns / track-step", "time ÷ torchsvs KF"], rows))
    svsf_ratio = results["torchsvs SVSF (float32)"] / ours
    per_track_kf = results["torchsvs KF, per-track P0 (float32)"]
    print(
        f"\nsimdkalman ÷ torchsvs KF: {results['simdkalman KF (float64)'] / ours:.2f} "
        f"(per-track P0: {results['simdkalman KF (float64)'] / per_track_kf:.2f}); "
        f"filterpy ÷ torchsvs KF: {results['filterpy KF (float64)'] / ours:.0f}; "
        f"SVSF ÷ KF: {svsf_ratio:.2f}; "
        f"simdkalman ÷ torchsvs SVSF: "
        f"{results['simdkalman KF (float64)'] / results['torchsvs SVSF (float32)']:.2f}"
    )
    print(f"filterpy ran on {len(sub)} tracks and is scaled per track-step.")


if __name__ == "__main__":
    main()
