"""Learn the SVSF/SVSS boundary layer ψ and memory γ from random maneuvers, then evaluate on
the paper's ATC and complex scenarios (never seen in training) against the paper's hand-tuned ψ
and the best ψ of a fine grid sweep.

Training starts from ψ = 100 m (a bad guess), γ = 0.1, with a supervised loss (MSE to truth)
and a self-supervised one (Stein's unbiased risk estimate from the known sensor noise, no truth).
Writes ``experiments/results/learn_psi.md`` and PNGs (learning curves, learned vs grid).

    python -m experiments.learn_psi [--epochs 4] [--runs 500] [--quick]
"""

from __future__ import annotations

import argparse
import csv
import tempfile
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import lightning as L
import torch
from lightning.pytorch.loggers import CSVLogger
from tqdm.auto import tqdm

import torchsvs as ts
from experiments import common
from experiments.common import RESULTS, render
from torchsvs.evaluation import markdown_table, psi_sweep
from torchsvs.metrics import pooled_rmse
from torchsvs.scenarios import Scenario, atc_scenario, complex_scenario
from torchsvs.training import EstimatorModule, ManeuveringTargetDataModule, config_path
from torchsvs.training.cli import main as cli_main
from torchsvs.training.quiet import TidyProgressBar, quiet_lightning, tool_trainer

FAMILIES = {
    # name: (shipped config of `torchsvs fit --config`, paper scenario, paper ψ)
    "ATC": ("atc_svss", atc_scenario, [800.0, 800.0]),
    "complex": ("complex_svss", complex_scenario, [500.0, 600.0, 500.0, 600.0]),
}
ATC_GRID = [float(p) for p in range(100, 3001, 50)]
COMPLEX_GRID = [float(p) for p in range(100, 1601, 100)]


def load(
    family: str, epochs: int, batches: int | None = None
) -> tuple[ts.SVSS, ManeuveringTargetDataModule]:
    """The SVSS and data module of a family's YAML config (the one `torchsvs fit` uses)."""
    args = ["--config", str(config_path(FAMILIES[family][0])), "--trainer.max_epochs", str(epochs)]
    if batches is not None:
        args += ["--data.train_batches", str(batches)]
    cli = cli_main(args, run=False)
    return cli.model.estimator, cli.datamodule


def position_rmse(mean: torch.Tensor, truth: torch.Tensor) -> float:
    """Accumulative position RMSE over both axes (x at 0, y at 2 of the CV state)."""
    return float(pooled_rmse(mean[..., [0, 2]], truth[..., [0, 2]]))


def evaluate(est: ts.SVSS, sc: Scenario) -> tuple[float, float]:
    """(SVSF, SVSS) position RMSE of an SVSS and its own filter pass on a scenario."""
    with torch.no_grad():
        out = est(sc.z, sc.x0, sc.P0)
    return position_rmse(out.filtered.mean, sc.truth), position_rmse(out.mean, sc.truth)


def grid_sweep(
    family: str, svss: ts.SVSS, sc: Scenario
) -> dict[tuple[float, ...], tuple[float, float]]:
    """(SVSF, SVSS) RMSE for every ψ of the family's grid (γ = 0.1), batched via per-step ψ."""
    m = svss.filter.psi.numel()
    grid = (
        [(p, p) for p in ATC_GRID]
        if m == 2
        else [(a, b, a, b) for a in COMPLEX_GRID for b in COMPLEX_GRID]
    )
    fixed = ts.SVSS(
        ts.SVSF(svss.model, psi=1.0, gamma=0.1, learn=False, artificial=svss.filter.artificial)
    )
    scores = psi_sweep(fixed, sc.z, sc.x0, sc.P0, sc.truth, grid, position_rmse)
    return dict(zip(grid, scores, strict=True))


@dataclass
class Run:
    """One training run and what it reached."""

    family: str
    estimator: str  # "SVSS" or "SVSF": which output the loss sees
    loss: str
    psi: list[float]
    gamma: float
    rmse: tuple[float, float]  # (SVSF, SVSS) on the paper scenario
    seconds: float
    curve: list[dict[str, float]] = field(default_factory=list)


def train(
    family: str,
    estimator: str,
    loss: str,
    epochs: int,
    batches: int | None,
    seed: int,
    progress: bool = False,
) -> tuple[ts.SVSS, Run]:
    """Trains from ψ = 100 m; returns the trained SVSS (its filter for SVSF runs)."""
    svss, data = load(family, epochs, batches)
    target = svss if estimator == "SVSS" else svss.filter
    module = EstimatorModule(target, loss=loss, lr=0.1, seed=seed)
    logdir = tempfile.mkdtemp(prefix="learn_psi_")
    with quiet_lightning():  # no banners or tips; the bar, if any, ends cleanly
        trainer = tool_trainer(
            max_epochs=epochs,
            logger=CSVLogger(logdir, name="run"),
            enable_progress_bar=progress,
            callbacks=[TidyProgressBar()] if progress else [],
            log_every_n_steps=1,
        )
        L.seed_everything(seed, verbose=False)
        start = time.perf_counter()
        trainer.fit(module, data)
        seconds = time.perf_counter() - start
    with open(Path(trainer.logger.log_dir) / "metrics.csv") as f:  # type: ignore[union-attr]
        curve = [{k: float(v) for k, v in row.items() if v != ""} for row in csv.DictReader(f)]
    run = Run(
        family,
        estimator,
        loss,
        svss.filter.psi.tolist(),
        svss.filter.gamma.item(),
        (0.0, 0.0),
        seconds,
        curve,
    )
    return svss, run


def figures(runs: list[Run], grids: dict[str, dict], out: Path) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = []
    fig, axes = plt.subplots(2, 2, figsize=(11, 7))
    for col, family in enumerate(FAMILIES):
        for run in (r for r in runs if r.family == family):
            steps = [row["step"] for row in run.curve if "psi_0" in row]
            psi = [row["psi_0"] for row in run.curve if "psi_0" in row]
            axes[0, col].plot(steps, psi, label=f"{run.estimator}, {run.loss}")
            val = [(row["step"], row["val_rmse"]) for row in run.curve if "val_rmse" in row]
            axes[1, col].plot(*zip(*val, strict=True), "o-", label=f"{run.estimator}, {run.loss}")
        axes[0, col].set(
            title=f"{family}: ψ (position) during training",
            xlabel="step",
            ylabel="ψ₀ (m)",
            yscale="log",
        )
        axes[1, col].set(
            title=f"{family}: validation RMSE (random maneuvers)",
            xlabel="step",
            ylabel="position RMSE (m)",
        )
        axes[0, col].legend(fontsize=7)
        axes[1, col].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / "learn_psi_curves.png", dpi=110)
    plt.close(fig)
    names.append("learn_psi_curves.png")

    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    atc = grids["ATC"]
    axes[0].plot([p[0] for p in atc], [v[1] for v in atc.values()], label="SVSS, grid (γ = 0.1)")
    axes[0].plot([p[0] for p in atc], [v[0] for v in atc.values()], label="SVSF, grid (γ = 0.1)")
    for run in (r for r in runs if r.family == "ATC"):
        axes[0].plot(
            [sum(run.psi) / len(run.psi)],
            [run.rmse[1] if run.estimator == "SVSS" else run.rmse[0]],
            "*",
            ms=12,
            label=f"learned {run.estimator}, {run.loss}",
        )
    axes[0].set(
        title="ATC: position RMSE against ψ", xlabel="ψ (m)", ylabel="RMSE (m)", ylim=(90, 300)
    )
    axes[0].legend(fontsize=7)
    cx = grids["complex"]
    a_values = sorted({p[0] for p in cx})
    b_values = sorted({p[1] for p in cx})
    image = torch.tensor([[cx[(a, b, a, b)][1] for a in a_values] for b in b_values])
    shown = axes[1].imshow(
        image,
        origin="lower",
        extent=(a_values[0], a_values[-1], b_values[0], b_values[-1]),
        aspect="auto",
        cmap="viridis_r",
    )
    fig.colorbar(shown, ax=axes[1], label="SVSS RMSE (m)")
    for run in (r for r in runs if r.family == "complex" and r.estimator == "SVSS"):
        axes[1].plot(
            [run.psi[0]],
            [run.psi[1]],
            "r*" if run.loss == "supervised" else "w*",
            ms=12,
            label=f"learned ({run.loss})",
        )
    axes[1].plot([500], [600], "kx", ms=10, label="paper ψ")
    axes[1].set(
        title="complex: SVSS RMSE over (ψ position, ψ velocity)",
        xlabel="ψ position (m)",
        ylabel="ψ velocity (m/s)",
    )
    axes[1].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / "learn_psi_vs_grid.png", dpi=110)
    plt.close(fig)
    names.append("learn_psi_vs_grid.png")
    return names


@dataclass
class Results:
    """The training runs, grid sweeps and table rows the report and the figures need."""

    epochs: int
    runs: int  #: Monte Carlo runs of the paper scenarios
    trained: list[Run]
    grids: dict[str, dict]
    rows: list[list[object]]
    checks: list[str]
    seconds: float


def reproduce(
    epochs: int = 4, batches: int | None = None, runs: int = 500, seed: int = 0
) -> Results:
    """Trains ψ, γ of the SVSS and SVSF of each family with either loss, sweeps the grids and
    scores everything on the paper's scenarios (``runs`` runs, seeded)."""
    warnings.filterwarnings("ignore", message=".*LeafSpec.*")
    warnings.filterwarnings("ignore", message=".*does not have many workers.*")
    start = time.perf_counter()

    scenarios = {f: FAMILIES[f][1](runs, torch.Generator().manual_seed(seed)) for f in FAMILIES}
    trained: list[Run] = []
    jobs = [
        (f, e, loss) for f in FAMILIES for e in ("SVSS", "SVSF") for loss in ("supervised", "sure")
    ]
    for family, estimator, loss in tqdm(jobs, desc="training runs"):
        svss, run = train(family, estimator, loss, epochs, batches, seed)
        run.rmse = evaluate(svss, scenarios[family])
        trained.append(run)

    grids, rows, checks = {}, [], []
    for family in tqdm(FAMILIES, desc="grid sweeps"):
        svss, _ = load(family, 1)
        grids[family] = grid_sweep(family, svss, scenarios[family])
        paper_psi = FAMILIES[family][2]
        paper = evaluate(
            ts.SVSS(
                ts.SVSF(svss.model, psi=paper_psi, gamma=0.1, artificial=svss.filter.artificial)
            ),
            scenarios[family],
        )
        best = {k: min(grids[family].items(), key=lambda kv, k=k: kv[1][k]) for k in (0, 1)}
        with torch.no_grad():
            kf = position_rmse(
                ts.KalmanFilter(svss.model)(
                    scenarios[family].z, scenarios[family].x0, scenarios[family].P0
                ).mean,
                scenarios[family].truth,
            )
        for k, name in ((0, "SVSF"), (1, "SVSS")):
            psi_best, rmse_best = best[k]
            rows.append([family, name, "KF (baseline)", "—", "—", kf, kf / rmse_best[k]])
            rows.append(
                [
                    family,
                    name,
                    "paper ψ, γ = 0.1",
                    fmt(paper_psi),
                    0.1,
                    paper[k],
                    paper[k] / rmse_best[k],
                ]
            )
            rows.append(
                [family, name, "grid-best ψ, γ = 0.1", fmt(psi_best), 0.1, rmse_best[k], 1.0]
            )
            for run in (r for r in trained if r.family == family and r.estimator == name):
                ratio = run.rmse[k] / rmse_best[k]
                rows.append(
                    [
                        family,
                        name,
                        f"learned, {run.loss}",
                        fmt(run.psi),
                        round(run.gamma, 3),
                        run.rmse[k],
                        ratio,
                    ]
                )
                if name == "SVSS":
                    limit = 1.05 if run.loss == "supervised" else 1.15
                    checks.append(
                        f"{family} SVSS, {run.loss}: {ratio:.3f}× grid-best (target ≤ {limit}): {'met' if ratio <= limit else 'NOT met'}"
                    )
    return Results(epochs, runs, trained, grids, rows, checks, time.perf_counter() - start)


def _options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--epochs", type=int, default=4, help="training epochs (default 4)")
    parser.add_argument("--batches", type=int, default=None, help="training batches per epoch")


def main(argv: list[str] | None = None, out: Path = RESULTS) -> None:
    common.main(
        "learn_psi",
        __doc__,
        lambda args: reproduce(args.epochs, args.batches, args.runs, args.seed),
        lambda res, folder: figures(res.trained, res.grids, folder),
        report,
        runs=500,
        runs_help="Monte Carlo runs of the paper scenarios",
        options=_options,
        argv=argv,
        out=out,
    )


def fmt(psi: list[float] | tuple[float, ...]) -> str:
    return "[" + ", ".join(f"{p:.0f}" for p in psi) + "]"


def report(res: Results, pngs: list[str]) -> str:
    """The results file: the prose of ``templates/learn_psi.md`` around the table."""
    header = ["scenario", "output", "ψ, γ from", "ψ", "γ", "position RMSE (m)", "÷ grid-best"]
    times = ", ".join(f"{r.family} {r.estimator} {r.loss} {r.seconds:.0f} s" for r in res.trained)
    return (
        render(
            "learn_psi",
            "report",
            epochs=res.epochs,
            seconds=f"{res.seconds:.0f}",
            runs=res.runs,
            table=markdown_table(header, res.rows),
            checks="\n".join(f"- {c}" for c in res.checks),
            times=times,
        )
        + "\n"
    )


if __name__ == "__main__":
    main()
