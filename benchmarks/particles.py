"""`make bench` (part 2): SPVSF against the SIR particle filter, same particles, same tracks.

The SPVSF adds one SVSF step per time step to the particle filter's work; the target is at most
1.3× the SIR time with 350 particles on 100 ballistic tracks (Gadsden et al. 2012, Sec. 5.1),
for each reading of its proposal (``proposal=``): the per-particle ones also move and correct
every particle, and ``"particles"`` evaluates three Gaussian densities per particle.

    python -m benchmarks.particles [--tracks 100] [--particles 350] [--repeats 3]
"""

from __future__ import annotations

import argparse

import torch

import torchsvs as ts
from benchmarks.timing import best_of
from torchsvs.evaluation import markdown_table


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tracks", type=int, default=100)
    parser.add_argument("--particles", type=int, default=350)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args(argv)
    sc = ts.scenarios.ballistic_scenario(args.tracks, torch.Generator().manual_seed(0))
    B, T = sc.z.shape[:2]
    pf = ts.ParticleFilter(sc.model, args.particles, resample_threshold=0.8)

    def timed(est: torch.nn.Module) -> float:
        def call() -> object:
            with torch.no_grad():
                return est(sc.z, sc.x0, sc.P0, generator=torch.Generator().manual_seed(1))

        call()  # warm-up
        return best_of(call, args.repeats)

    t_pf = timed(pf)
    rows = [["SIR particle filter", f"{1e6 * t_pf / (B * T):.1f}", "1.00×"]]
    for proposal in ts.filters.spvsf.PROPOSALS:
        spvsf = ts.SPVSF(
            sc.model, psi=[1e4, 8e3], gamma=0.1, num_particles=args.particles, proposal=proposal
        )
        t = timed(spvsf)
        rows.append(
            [f'SPVSF, proposal="{proposal}"', f"{1e6 * t / (B * T):.1f}", f"{t / t_pf:.2f}×"]
        )
    print(f"{B} tracks × {T} steps, {args.particles} particles, float64")
    print(markdown_table(["estimator", "µs / track-step", "time ÷ SIR"], rows))


if __name__ == "__main__":
    main()
