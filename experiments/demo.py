"""`make demo`: the ATC scenario of Chen et al. 2020 (Sec. 4.1, Table 1) with torchsvs.

500 Monte Carlo runs as one batch: KF, KS (one-lag RTS), SVSF, SVSTPS (one-lag RTS over the
SVSF) and SVSS (lag 1), position accumulative RMSE beside the paper's Table 1.

    python -m experiments.demo [--runs 500] [--seed 0]
"""

from __future__ import annotations

import argparse
import time

import torch

import torchsvs as ts
from experiments.svss_paper import TABLE1
from torchsvs.evaluation import Evaluation, evaluate, markdown_table


def atc_estimators(model: ts.models.LinearModel, psi: float = 800.0, gamma: float = 0.1) -> dict:
    """The estimators of Table 1 (RSTKF comes with the full reproduction)."""

    def svsf() -> ts.SVSF:
        return ts.SVSF(model, psi=[psi, psi], gamma=gamma)

    return {
        "KF": ts.KalmanFilter(model),
        "KS": ts.RTSSmoother(ts.KalmanFilter(model), lag=1),
        "SVSF": svsf(),
        "SVSTPS": ts.RTSSmoother(svsf(), lag=1),
        "SVSS": ts.SVSS(svsf(), lag=1),
    }


def atc_table(num_runs: int = 500, seed: int = 0, progress: bool = True) -> list[Evaluation]:
    scenario = ts.scenarios.atc_scenario(num_runs, torch.Generator().manual_seed(seed))
    return evaluate(atc_estimators(scenario.model), scenario, progress=progress)


def report(rows: list[Evaluation], num_runs: int) -> str:
    header = ["estimator", "x RMSE (m)", "paper x", "y RMSE (m)", "paper y", "µs / track-step"]
    body = []
    for r in rows:
        paper = TABLE1.get(r.name, ("—", "—", None))
        body.append(
            [r.name, r.rmse[0].item(), paper[0], r.rmse[2].item(), paper[1], r.us_per_track_step]
        )
    by = {r.name: r.rmse[[0, 2]] for r in rows}
    gain_svsf = 1 - (by["SVSS"] / by["SVSF"])
    gain_ks = 1 - (by["KS"] / by["KF"])
    return "\n".join(
        [
            f"ATC scenario (Chen et al. 2020, Sec. 4.1): {num_runs} Monte Carlo runs in one batch, "
            "ψ = [800, 800] m, γ = 0.1, T = 490 steps",
            "",
            markdown_table(header, body),
            "",
            f"SVSS below SVSF by {100 * gain_svsf[0]:.0f}% (x) / {100 * gain_svsf[1]:.0f}% (y); "
            f"paper: about 22%. KS below KF by {100 * gain_ks[0]:.0f}% / {100 * gain_ks[1]:.0f}%; "
            "paper: about 7%.",
            "Times: torchsvs per track-step in a batch (CPU); "
            "paper per single-track step (MATLAB).",
        ]
    )


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=500)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    start = time.perf_counter()
    rows = atc_table(args.runs, args.seed)
    print(report(rows, args.runs))
    print(f"\n(total {time.perf_counter() - start:.1f} s)")


if __name__ == "__main__":
    main()
