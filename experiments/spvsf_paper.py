"""Gadsden, Habibi, Kirubarajan 2012 (the SPVSF paper): Tables 1, 2, 4, 5 beside ours.

Ballistic re-entry (Sec 5.1, nominal and with the gravity error at 15 s) and the EHA (Sec 5.2,
constant and changing bulk modulus), EKF, UKF, PF, SVSF and SPVSF, Monte Carlo runs as one
batch each. RMSE as the paper computes it: per run over all steps including the initial
estimate, then averaged over runs. Writes ``experiments/results/spvsf_paper.md``.

This is the first pass of the reproduction (issue 5): the numbers are reported as measured,
with the gaps to the paper. Figures 5-9 show the first run.

    python -m experiments.spvsf_paper [--runs 100] [--eha-runs 20] [--seed 0]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch
from torch import Tensor
from tqdm.auto import tqdm

import torchsvs as ts
from torchsvs.evaluation import markdown_table
from torchsvs.scenarios import Scenario, ballistic_scenario, eha_scenario

BALLISTIC_TRUE_X0 = (61000.0, 3048.0, 19161.0)
# Paper tables: filter → RMSE per state; None where the paper reports "Failed".
TABLE1 = {
    "EKF": (1873.0, 29.7, 1923.0),
    "UKF": (1060.0, 30.6, 2071.0),
    "PF": (370.0, 34.8, 12325.0),
    "SVSF": (471.0, 119.0, 1923.0),
    "SPVSF": (360.0, 32.7, 1923.0),
}
TABLE2 = {
    "EKF": (1867.0, 61.1, 1920.0),
    "UKF": (852.0, 94.6, 2369.0),
    "PF": None,
    "SVSF": (568.0, 311.0, 1919.0),
    "SPVSF": (360.0, 35.0, 1919.0),
}
TABLE4 = {
    "EKF": (4.68e-4, 2.05e-1, 3.07, 1.64e-1),
    "UKF": (2.95e-4, 1.44e-1, 9.50e-1, 6.83e-2),
    "PF": (2.23e-5, 2.15e-3, 2.67e-2, 1.34e-2),
    "SVSF": (6.05e-5, 3.25e-3, 1.37e-1, 3.34e-2),
    "SPVSF": (2.44e-5, 2.58e-3, 2.87e-2, 2.84e-2),
}
TABLE5 = {
    "EKF": (1.07e-3, 2.85e-1, 4.54, 2.31e-1),
    "UKF": (1.01e-3, 3.70e-1, 3.27, 1.34e-1),
    "PF": None,
    "SVSF": (5.30e-5, 3.19e-3, 1.33e-1, 7.32e-2),
    "SPVSF": (2.55e-5, 2.48e-3, 2.96e-2, 1.85e-2),
}
BALLISTIC_PSI = [500.0, 100.0]  # not given in the paper: our choice (≈ 5× the noise std)
EHA_PSI = [5e-4, 5e-3, 0.5, 1e6]  # ψ = 5 V_max (Sec 5.2); 1e6 Pa for the modulus: our choice


def paper_rmse(mean: Tensor, truth: Tensor, x0: Tensor, true_x0: Tensor) -> Tensor:
    """Per-run RMSE over all steps including the initial estimate, averaged over runs, ``[n]``."""
    B = truth.shape[0]
    err = torch.cat([(x0 - true_x0).expand(B, 1, -1), mean - truth], dim=1)
    return err.square().mean(1).sqrt().mean(0)


def estimators(model: ts.models.StateSpaceModel, psi: list[float]) -> dict[str, torch.nn.Module]:
    # The EHA's SVSF measures the modulus through the artificial measurement of its dynamics.
    eha = isinstance(model, ts.models.ElectrohydrostaticActuator)
    artificial = ts.filters.ModulusFromAcceleration() if eha else None
    return {
        "EKF": ts.ExtendedKalmanFilter(model),
        "UKF": ts.UnscentedKalmanFilter(model),
        "PF": ts.ParticleFilter(model, num_particles=350, resample_threshold=0.8),
        "SVSF": ts.SVSF(model, psi=psi, gamma=0.1, artificial=artificial),
        "SPVSF": ts.SPVSF(
            model,
            psi=psi,
            gamma=0.1,
            num_particles=350,
            resample_threshold=0.8,
            artificial=artificial,
        ),
    }


def evaluate(
    sc: Scenario, true_x0: Tensor, psi: list[float], seed: int, tracks: dict | None = None
) -> dict[str, Tensor]:
    """RMSE per filter; the first run's estimates go into ``tracks`` for the figures."""
    out = {}
    for name, est in estimators(sc.model, psi).items():
        kwargs: dict = {"u": sc.u}
        if name in ("PF", "SPVSF"):
            kwargs["generator"] = torch.Generator().manual_seed(seed)
        with torch.no_grad():
            mean = est(sc.z, sc.x0, sc.P0, **kwargs).mean
        out[name] = paper_rmse(mean, sc.truth, sc.x0, true_x0)
        if tracks is not None:
            tracks[name] = mean[0]
    if tracks is not None:
        tracks["truth"] = sc.truth[0]
    return out


def figure(
    tracks: dict[str, Tensor], component: int, dt: float, title: str, path: Path, zoom=None
) -> None:
    """One state component of the first run over time, truth and every filter."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 4))
    for name, values in tracks.items():
        t = dt * torch.arange(1, values.shape[0] + 1)
        ax.plot(
            t,
            values[:, component],
            "k-" if name == "truth" else "-",
            lw=2 if name == "truth" else 1,
            label=name,
        )
    ax.set(xlabel="time (s)", title=title)
    if zoom is not None:
        ax.set_ylim(*zoom)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def table(ours: dict[str, Tensor], paper: dict, labels: list[str], scale: list[float]) -> str:
    rows = []
    for name, values in ours.items():
        ref = paper.get(name)
        cells = []
        for i, v in enumerate(values.tolist()):
            mine = v / scale[i]
            cells.append(f"{mine:.3g} ({'Failed' if ref is None else f'{ref[i]:.3g}'})")
        rows.append([name, *cells])
    return markdown_table(["filter", *labels], rows)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=100)
    parser.add_argument("--eha-runs", type=int, default=20)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results")
    args = parser.parse_args(argv)
    start = time.perf_counter()
    true_b = torch.tensor(BALLISTIC_TRUE_X0, dtype=torch.float64)
    true_e = torch.tensor([0.0, 0.0, 0.0, 2.1e8], dtype=torch.float64)
    studies = {
        "Table 1 (ballistic, nominal)": (
            lambda g: ballistic_scenario(args.runs, g),
            true_b,
            BALLISTIC_PSI,
            TABLE1,
        ),
        "Table 2 (ballistic, gravity doubled at 15 s)": (
            lambda g: ballistic_scenario(args.runs, g, gravity_error_at=15.0),
            true_b,
            BALLISTIC_PSI,
            TABLE2,
        ),
        "Table 4 (EHA, constant modulus)": (
            lambda g: eha_scenario(args.eha_runs, g),
            true_e,
            EHA_PSI,
            TABLE4,
        ),
        "Table 5 (EHA, changing modulus)": (
            lambda g: eha_scenario(args.eha_runs, g, changing=True),
            true_e,
            EHA_PSI,
            TABLE5,
        ),
    }
    figures = {
        "Table 1 (ballistic, nominal)": [
            ("spvsf_fig5_altitude.png", 0, "Fig 5: altitude (m)", None)
        ],
        "Table 2 (ballistic, gravity doubled at 15 s)": [
            (
                "spvsf_fig6_altitude_gravity_error.png",
                0,
                "Fig 6: altitude (m), gravity error at 15 s",
                None,
            )
        ],
        "Table 4 (EHA, constant modulus)": [
            ("spvsf_fig7_modulus.png", 3, "Fig 7: effective bulk modulus (Pa)", None),
            ("spvsf_fig8_modulus_zoom.png", 3, "Fig 8: bulk modulus, zoomed (Pa)", (1.9e8, 2.3e8)),
        ],
        "Table 5 (EHA, changing modulus)": [
            ("spvsf_fig9_modulus_changing.png", 3, "Fig 9: bulk modulus, changing (Pa)", None)
        ],
    }
    args.out.mkdir(parents=True, exist_ok=True)
    sections = []
    for title, (make, true_x0, psi, paper) in tqdm(studies.items(), desc="spvsf paper"):
        sc = make(torch.Generator().manual_seed(args.seed))
        tracks: dict[str, Tensor] = {}
        ours = evaluate(sc, true_x0, psi, args.seed, tracks)
        for name, component, caption, zoom in figures[title]:
            figure(tracks, component, sc.dt, caption, args.out / name, zoom)
            sections.append(f"![{caption}]({name})")
        if "EHA" in title:
            labels = [
                "position (m)",
                "velocity (m/s)",
                "acceleration (m/s²)",
                "bulk modulus (rel.)",
            ]
            scale = [1.0, 1.0, 1.0, 2.1e8]  # the paper's modulus RMSE reads as relative to 2.1e8
        else:
            labels, scale = (
                ["altitude (m)", "velocity (m/s)", "ballistic coefficient"],
                [1.0, 1.0, 1.0],
            )
        sections[-len(figures[title]) :] = [
            f"## {title}",
            "",
            table(ours, paper, labels, scale),
            "",
            *sections[-len(figures[title]) :],
            "",
        ]
    text = "\n".join(
        [
            "# Gadsden et al. 2012 (SPVSF): first reproduction pass",
            "",
            f"`python -m experiments.spvsf_paper`: {args.runs} ballistic runs, {args.eha_runs} EHA runs, "
            f"{time.perf_counter() - start:.0f} s. Ours (paper). RMSE per run over all steps including the "
            "initial estimate, averaged over runs. SVSF ψ for the ballistic case is our choice "
            f"({BALLISTIC_PSI}); for the EHA ψ = 5 V_max, γ = 0.1. The EHA modulus column is divided "
            "by 2.1·10⁸ Pa (the paper's values read as relative errors).",
            "",
            *sections,
            "## Status",
            "",
            "- Issue 5 is not resolved. The EHA's SVSF and SPVSF measure the modulus through "
            "`ModulusFromAcceleration` (Eq 51 solved for x4); the ballistic coefficient has no artificial "
            "measurement yet (Eq 47 is noise at these altitudes: the drag's velocity change per step is far "
            "below the 31.6 m/s noise); the bootstrap PF starting from P0 = 10Q does not reach the "
            "ballistic truth 10% away, nor the EHA modulus.",
        ]
    )
    (args.out / "spvsf_paper.md").write_text(text + "\n")
    print(text)


if __name__ == "__main__":
    main()
