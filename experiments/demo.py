"""`make demo`: learn ψ and γ from a bad guess, then track the paper's scenarios with them.

Then recorded ADS-B flights with radar-like noise: the KS, SVSS and SVSTPS with the rules of
thumb and self-tuned without truth on half of the flights, scored on the other half.

For the ATC sensor and the complex-maneuver sensor of Chen et al. 2020, an SVSS starts from
ψ = 100 m, γ = 0.1 and is trained for about half a minute each (Lightning, supervised, on random
maneuvers; configs shipped in ``torchsvs/training/configs/``). Then the paper's scenarios (never
seen in training; 500 Monte Carlo runs in one batch each) are tracked by the KF, KS, SVSF, SVSTPS and
SVSS with the paper's hand-tuned ψ and by the SVSS with the learned ψ, beside the paper's numbers
(Tables 1 and 3 of Chen et al. 2020).

    python -m experiments.demo [--epochs 4] [--batches 20] [--runs 500]
"""

from __future__ import annotations

import argparse
import time
import warnings
from functools import partial

import torch

import torchsvs as ts
from experiments.learn_psi import FAMILIES, train
from experiments.svss_paper import TABLE1, TABLE3
from torchsvs.evaluation import markdown_table
from torchsvs.metrics import accumulative_rmse, pooled_rmse

PAPER_ROW = {
    "KF": "KF",
    "KS": "KS",
    "SVSF, paper ψ": "SVSF",
    "SVSTPS, paper ψ": "SVSTPS",
    "SVSS, paper ψ": "SVSS",
}
PAPER = {
    "ATC": {k: (v[0], v[1]) for k, v in TABLE1.items()},
    "complex": {k: (v[0], v[2]) for k, v in TABLE3.items()},
}


def demo(epochs: int = 4, batches: int = 20, runs: int = 500, seed: int = 0) -> str:
    rows, learned = [], {}
    for family, (_, make_scenario, paper_psi) in FAMILIES.items():
        svss, run = train(family, "SVSS", "supervised", epochs, batches, seed, progress=True)
        learned[family] = (run.psi, run.gamma, run.seconds)
        sc = make_scenario(runs, torch.Generator().manual_seed(seed))
        artificial = svss.filter.artificial

        paper_svsf = partial(ts.SVSF, sc.model, psi=paper_psi, gamma=0.1, artificial=artificial)
        estimators = {
            "KF": ts.KalmanFilter(sc.model),
            "KS": ts.RTSSmoother(ts.KalmanFilter(sc.model), lag=1),
            "SVSF, paper ψ": paper_svsf(),
            "SVSTPS, paper ψ": ts.RTSSmoother(paper_svsf(), lag=1),
            "SVSS, paper ψ": ts.SVSS(paper_svsf()),
            "SVSS, learned ψ": svss,
        }
        for name, est in estimators.items():
            with torch.no_grad():
                rmse = accumulative_rmse(est(sc.z, sc.x0, sc.P0).mean, sc.truth)
            paper = PAPER[family].get(PAPER_ROW.get(name, ""), ("—", "—"))
            rows.append([family, name, rmse[0].item(), paper[0], rmse[2].item(), paper[1]])
    lines = [
        "Learned from random maneuvers (start ψ = 100 m, γ = 0.1, supervised):",
        *[
            f"  {family}: ψ = {[round(p) for p in psi]}, γ = {gamma:.2f} ({seconds:.0f} s of training)"
            for family, (psi, gamma, seconds) in learned.items()
        ],
        f"  paper: ATC ψ = {FAMILIES['ATC'][2]}, complex ψ = {FAMILIES['complex'][2]}, γ = 0.1",
        "",
        f"Paper scenarios ({runs} Monte Carlo runs each, never seen in training), position accumulative RMSE:",
        "",
        markdown_table(["scenario", "estimator", "x (m)", "paper x", "y (m)", "paper y"], rows),
    ]
    return "\n".join(lines)


def recorded_flights(sigma: float = 100.0, seed: int = 0) -> str:
    """Recorded flights with radar-like noise: the KS and the SVSS self-tuned without truth on
    half of them, scored on the other half (a short form of ``experiments/real_flights.py``)."""
    from experiments.flight_data import load_flights, noisy, split
    from experiments.real_flights import evaluate, rule_of_thumb
    from torchsvs.fitting.tuning import self_tune

    try:
        flights = load_flights()
    except ImportError as err:
        return f"Recorded flights skipped: {err}"
    train, test = split(noisy(flights, sigma, seed))
    raw = pooled_rmse(test.z, test.truth[..., [0, 2]], test.mask)  # type: ignore[index]
    rows: list[list[object]] = [["measurements", "—", f"{raw:.1f}", "—"]]
    for name, lag in (("ks", None), ("svss", 5), ("svstps", 5)):
        base = rule_of_thumb(name, train, sigma, **({"lag": lag} if lag else {}))
        fit = self_tune(base, train)
        rows.append(
            [
                name.upper() + (f" lag {lag}" if lag else ""),
                f"{evaluate(base, test)['position']:.1f}",
                f"{evaluate(fit.settings, test)['position']:.1f}",
                f"{fit.seconds:.1f}",
            ]
        )
    return "\n".join(
        [
            f"Recorded ADS-B flights ({len(test)} held out of {len(flights)} calibration flights, "
            f"{sigma:.0f} m noise), position RMSE per axis (m):",
            "",
            markdown_table(
                [
                    "estimator",
                    "rules of thumb",
                    "self-tuned on the other half, no truth",
                    "fit (s)",
                ],
                rows,
            ),
        ]
    )


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--epochs", type=int, default=4, help="training epochs (default 4)")
    parser.add_argument("--batches", type=int, default=20, help="training batches per epoch")
    parser.add_argument("--runs", type=int, default=500, help="Monte Carlo runs (default 500)")
    parser.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    args = parser.parse_args(argv)
    warnings.filterwarnings("ignore", message=".*LeafSpec.*")
    warnings.filterwarnings("ignore", message=".*does not have many workers.*")
    start = time.perf_counter()
    print(demo(args.epochs, args.batches, args.runs, args.seed))
    print()
    print(recorded_flights())
    print(f"\n(total {time.perf_counter() - start:.0f} s)")


if __name__ == "__main__":
    main()
