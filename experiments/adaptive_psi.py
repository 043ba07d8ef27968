"""An estimator as a layer: a small network reads recent innovations and sets a per-step ψ_t
that drives the SVSS through its per-step override, trained end to end with Lightning.

The network sees the normalised innovations of a Kalman filter pre-pass (a maneuver shows up as
a run of large innovations before the SVSF's own error grows), through a causal 1-D convolution
over the last ``window`` steps, and scales a learnable base ψ:
``ψ_t = ψ_base · exp(g(|ẽ_{t−w+1..t}|))``. It is compared with the best constant ψ (the grid
sweep of ``experiments/learn_psi.py``, and a constant ψ, γ trained on the same data) on the paper's
complex scenario and on held-out random maneuvers. Writes ``experiments/results/adaptive_psi.md``.

    python -m experiments.adaptive_psi [--epochs 6]
"""

from __future__ import annotations

import argparse
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import lightning as L
import torch
from torch import Tensor, nn

import torchsvs as ts
from experiments import common
from experiments.common import RESULTS, render
from experiments.learn_psi import COMPLEX_GRID, load, position_rmse
from torchsvs.evaluation import markdown_table, psi_sweep
from torchsvs.scenarios import complex_scenario
from torchsvs.training import EstimatorModule
from torchsvs.training.quiet import quiet_lightning, tool_trainer


class AdaptivePsiSVSS(nn.Module):
    """SVSS whose boundary layer is set per step by a causal network of recent innovations.

    Args:
        svss: the smoother (its SVSF's ψ is the learnable base width).
        window: steps of innovation history the network sees.
        hidden: channels of the hidden layer.
    """

    def __init__(self, svss: ts.SVSS, window: int = 6, hidden: int = 16) -> None:
        super().__init__()
        self.svss = svss
        self.window = window
        m_in, m_out = svss.model.meas_dim, svss.filter.psi.numel()
        self.net = nn.Sequential(
            nn.Conv1d(m_in, hidden, window), nn.Tanh(), nn.Conv1d(hidden, m_out, 1)
        )
        nn.init.zeros_(self.net[2].weight)  # start at the constant base ψ
        nn.init.zeros_(self.net[2].bias)
        self.pre = ts.KalmanFilter(svss.model)

    @property
    def model(self) -> ts.models.LinearModel:
        return self.svss.model

    def psi(self, z: Tensor, x0: Tensor, P0: Tensor) -> Tensor:
        """The per-step widths ``[B, T, m']``."""
        with torch.no_grad():
            kf = self.pre(z, x0, P0)
        scale = kf.innovation_cov.diagonal(dim1=-2, dim2=-1).sqrt()
        features = (kf.innovation / scale).abs().mT  # [B, m, T]
        padded = nn.functional.pad(features, (self.window - 1, 0))  # causal: steps t−w+1..t
        base = self.svss.filter.psi
        log_scale = self.net(padded.to(self.net[0].weight.dtype)).mT.to(base.dtype)  # [B, T, m']
        return base * log_scale.exp()

    def forward(self, z: Tensor, x0: Tensor, P0: Tensor, **kwargs: Any) -> Any:
        return self.svss(z, x0, P0, psi=self.psi(z, x0, P0).to(z.dtype))


def fit(module: nn.Module, data: Any, epochs: int, lr: float) -> float:
    with quiet_lightning():
        trainer = tool_trainer(max_epochs=epochs)
        start = time.perf_counter()
        trainer.fit(EstimatorModule(module, loss="supervised", lr=lr), data)
    return time.perf_counter() - start


def figure(adaptive: AdaptivePsiSVSS, sc: ts.scenarios.Scenario, path: Path) -> None:
    """ψ_t over the complex scenario (median and 10-90% band over runs) beside the RMSE."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    with torch.no_grad():
        psi = adaptive.psi(sc.z, sc.x0, sc.P0)
    t = torch.arange(1, psi.shape[1] + 1)
    fig, ax = plt.subplots(figsize=(8, 4))
    for c, label in ((0, "ψ x position"), (1, "ψ x velocity")):
        q = torch.quantile(psi[..., c], torch.tensor([0.1, 0.5, 0.9], dtype=psi.dtype), dim=0)
        ax.plot(t, q[1], label=label)
        ax.fill_between(t, q[0], q[2], alpha=0.25)
    for edge in (20, 75, 100):  # maneuver changes of Sec 4.2
        ax.axvline(edge, color="0.6", ls=":")
    ax.set(
        yscale="log",
        xlabel="time (s)",
        ylabel="ψ_t",
        title="Adaptive ψ_t on the complex scenario (median, 10-90%)",
    )
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


@dataclass
class Results:
    """The trained models and the scores the report and the figure need."""

    epochs: int
    constant: Any  #: the SVSS with a learned constant ψ, γ
    adaptive: AdaptivePsiSVSS
    constant_time: float  #: training time (s)
    adaptive_time: float
    paper: ts.scenarios.Scenario  #: the complex scenario of the paper
    #: per test set: grid-best constant, learned constant, adaptive RMSE, change, ψ_t range
    rows: list[list[object]] = field(default_factory=list)


def reproduce(epochs: int = 6, runs: int = 500, seed: int = 0) -> Results:
    """Trains both models on the same random maneuvers and scores them, and the best constant
    ψ of a grid, on the paper's complex scenario (``runs`` runs) and held-out maneuvers."""
    warnings.filterwarnings("ignore", message=".*LeafSpec.*")
    warnings.filterwarnings("ignore", message=".*does not have many workers.*")
    L.seed_everything(seed, verbose=False)

    constant, data = load("complex", epochs)
    constant_time = fit(constant, data, epochs, lr=0.1)
    adaptive_base, _ = load("complex", epochs)
    adaptive = AdaptivePsiSVSS(adaptive_base)
    adaptive_time = fit(adaptive, data, epochs, lr=0.03)

    paper_sc = complex_scenario(runs, torch.Generator().manual_seed(seed))
    data.setup("test")
    held_out = data.datasets["test"]
    tests = {
        "complex scenario (paper)": (paper_sc.z, paper_sc.x0, paper_sc.P0, paper_sc.truth),
        "held-out random maneuvers": tuple(
            torch.cat([getattr(held_out[i], f) for i in range(len(held_out))])
            if f != "P0"
            else held_out[0].P0
            for f in ("z", "x0", "P0", "truth")
        ),
    }
    grid_best = {}
    fixed = ts.SVSS(
        ts.SVSF(
            constant.model, psi=1.0, gamma=0.1, learn=False, artificial=constant.filter.artificial
        )
    )
    grid = [(a, b, a, b) for a in COMPLEX_GRID for b in COMPLEX_GRID]
    for name, (z, x0, P0, truth) in tests.items():
        scores = psi_sweep(fixed, z, x0, P0, truth, grid, position_rmse)
        grid_best[name] = min(smoothed for _, smoothed in scores)

    rows: list[list[object]] = []
    for name, (z, x0, P0, truth) in tests.items():
        with torch.no_grad():
            c = position_rmse(constant(z, x0, P0).mean, truth)
            a = position_rmse(adaptive(z, x0, P0).mean, truth)
            psi_t = adaptive.psi(z, x0, P0)
        rows.append(
            [
                name,
                grid_best[name],
                c,
                a,
                f"{100 * (a / c - 1):+.1f}%",
                f"{psi_t[..., 0].min():.0f}-{psi_t[..., 0].max():.0f}",
            ]
        )
    return Results(epochs, constant, adaptive, constant_time, adaptive_time, paper_sc, rows)


def figures(res: Results, out: Path) -> list[str]:
    """ψ_t over the complex scenario; returns the file name."""
    figure(res.adaptive, res.paper, out / "adaptive_psi.png")
    return ["adaptive_psi.png"]


def report(res: Results, pngs: list[str]) -> str:
    """The results file: the prose of ``templates/adaptive_psi.md`` around the table."""
    constant, adaptive = res.constant, res.adaptive
    header = [
        "test set",
        "grid-best constant ψ (γ = 0.1)",
        "learned constant ψ, γ",
        "adaptive ψ_t",
        "adaptive vs constant",
        "ψ_t range (position)",
    ]
    return (
        render(
            "adaptive_psi",
            "report",
            epochs=res.epochs,
            window=adaptive.window,
            weights=sum(p.numel() for p in adaptive.net.parameters()),
            constant_time=f"{res.constant_time:.0f}",
            adaptive_time=f"{res.adaptive_time:.0f}",
            table=markdown_table(header, res.rows),
            constant_psi=[round(p) for p in constant.filter.psi.tolist()],
            constant_gamma=f"{constant.filter.gamma.item():.3f}",
            adaptive_psi=[round(p) for p in adaptive.svss.filter.psi.tolist()],
            adaptive_gamma=f"{adaptive.svss.filter.gamma.item():.3f}",
        )
        + "\n"
    )


def _epochs(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--epochs", type=int, default=6, help="training epochs (default 6)")


def main(argv: list[str] | None = None, out: Path = RESULTS) -> None:
    common.main(
        "adaptive_psi",
        __doc__,
        lambda args: reproduce(args.epochs, args.runs, args.seed),
        figures,
        report,
        runs=500,
        options=_epochs,
        argv=argv,
        out=out,
    )


if __name__ == "__main__":
    main()
