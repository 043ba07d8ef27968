"""An IMM whose modes are an SVSF and a KF on the same model (robust + optimal), on the complex
maneuvering scenario of Chen et al. 2020 (Sec 4.2, Table 3), against each alone.

The scenario, its Monte Carlo seed, the model (``Q`` of Eq 48 with L = 15, 100 m noise), the
prior and the SVSF's settings (ψ = 500/600, γ = 0.1, the finite-difference artificial velocity
of Eq 51) are those of ``experiments/svss_paper.py``'s Table 3, so its rows reappear here
unchanged. The IMM compares its modes through their innovation likelihoods, so both must
measure the same thing: the SVSF of Table 3 corrects with ``[z, finite-difference velocity]``,
so the KF mode is the KF on that same artificial measurement
(:class:`~torchsvs.filters.ArtificialKalmanFilter`); the IMM of the SVSF in its ``H⁺`` mode and
the plain KF (both measure ``z``) is shown too. Writes ``experiments/results/imm_svsf_kf.md``
and two PNGs.

    python -m experiments.imm_svsf_kf [--runs 500] [--seed 0] [--out experiments/results]
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

import torchsvs as ts
from experiments import common
from experiments.common import RESULTS, render
from experiments.svss_paper import COMPLEX_PSI, GAMMA, table3_estimators
from torchsvs.estimator import Estimator, at_step
from torchsvs.evaluation import evaluate, markdown_table
from torchsvs.filters.imm import log_mode_likelihood
from torchsvs.linalg import cholesky, gaussian_log_density
from torchsvs.metrics import rmse_over_time
from torchsvs.scenarios import complex_scenario

#: The transition matrices compared (rows: from SVSF, from KF); the first is the main one.
TRANSITIONS = {
    "0.95": [[0.95, 0.05], [0.05, 0.95]],
    "0.80": [[0.80, 0.20], [0.20, 0.80]],
    "0.99": [[0.99, 0.01], [0.01, 0.99]],
    "0.50": [[0.50, 0.50], [0.50, 0.50]],
}
MAIN = "0.95"
#: The scenario's segments (step indices): straight, 3°/s turn, turn with angular acceleration,
#: linear acceleration (Sec 4.2 of the paper; ``complex_scenario``).
PHASES = {
    "straight (0-20 s)": (0, 20),
    "3°/s turn (20-75 s)": (20, 75),
    "accelerating turn (75-100 s)": (75, 100),
    "linear acceleration (100-125 s)": (100, 125),
}


def imm_name(key: str) -> str:
    return f"IMM(SVSF, KF), π_ii = {key}"


def estimators(model: ts.models.LinearModel) -> dict[str, Estimator]:
    """Table 3's rows, the KF on the SVSF's artificial measurement, the IMMs."""
    fd = ts.FiniteDifferenceVelocity()
    ests: dict[str, Estimator] = dict(table3_estimators(model))
    ests["KF on [z, FD velocity]"] = ts.ArtificialKalmanFilter(model, fd)
    for key, transition in TRANSITIONS.items():
        svsf = ts.SVSF(model, psi=COMPLEX_PSI, gamma=GAMMA, artificial=fd)
        ests[imm_name(key)] = ts.IMM([svsf, ts.ArtificialKalmanFilter(model, fd)], transition)
    hplus = ts.SVSF(model, psi=COMPLEX_PSI[::2], gamma=GAMMA, artificial=None)
    ests["SVSF, H⁺ mode"] = hplus
    ests["IMM(SVSF H⁺, KF), π_ii = 0.95"] = ts.IMM(
        [
            ts.SVSF(model, psi=COMPLEX_PSI[::2], gamma=GAMMA, artificial=None),
            ts.KalmanFilter(model),
        ],
        TRANSITIONS[MAIN],
    )
    return ests


#: What each row is, for the table.
KINDS = {
    "KF": "filter",
    "KS": "smoother, lag 1",
    "SVSF": "filter",
    "SVSTPS": "smoother, lag 1",
    "SVSS": "smoother, lag 1",
    "KF on [z, FD velocity]": "filter (the IMM's KF mode alone)",
    "SVSF, H⁺ mode": "filter",
}


@dataclass
class Results:
    runs: int
    rows: dict[str, tuple[list[float], float]] = field(default_factory=dict)
    curves: dict[str, Tensor] = field(default_factory=dict)
    mode_probs: dict[str, Tensor] = field(default_factory=dict)  #: [B, T] μ_SVSF per IMM
    mode_loglik: dict[str, Tensor] = field(default_factory=dict)  #: [B, T, 2] per IMM
    nis: dict[str, list[float]] = field(default_factory=dict)  #: per phase, per filter alone
    spread: dict[str, float] = field(default_factory=dict)  #: median P_xx per filter alone
    likelihood_check: float = 0.0
    seconds: float = 0.0


def normalised_innovations(result: Any) -> Tensor:
    """``eᵀ S⁻¹ e`` per track and step, and the number of observed components, ``[B, T]``
    each: a consistent filter has ``E[eᵀS⁻¹e] = dim``."""
    e, S, mask = result.innovation, result.innovation_cov, result.mask
    L = cholesky(S)
    w = torch.linalg.solve_triangular(L, e.unsqueeze(-1), upper=False).squeeze(-1)
    return w.square().sum(-1), mask.sum(-1).to(e.dtype)


def run(runs: int = 500, seed: int = 0) -> Results:
    start = time.perf_counter()
    sc = complex_scenario(runs, torch.Generator().manual_seed(seed + 1))  # as svss_paper
    res = Results(runs)
    ests = estimators(sc.model)
    for row in evaluate(ests, sc, progress=False):
        res.rows[row.name] = (row.rmse.tolist(), row.us_per_track_step)
        res.curves[row.name] = rmse_over_time(row.mean, sc.truth)
        if isinstance(row.result, ts.IMMResult):
            res.mode_probs[row.name] = row.result.mode_probs[..., 0]
            assert row.result.mode_log_likelihood is not None
            res.mode_loglik[row.name] = row.result.mode_log_likelihood
    for name in ("KF", "SVSF", "KF on [z, FD velocity]", "SVSF, H⁺ mode"):
        with torch.no_grad():
            out = ests[name](sc.z, sc.x0, sc.P0)
        nis, dims = normalised_innovations(out)
        res.nis[name] = [float(nis[:, a:b].sum() / dims[:, a:b].sum()) for a, b in PHASES.values()]
        res.spread[name] = float(out.cov[..., 0, 0].median())
        if name == "SVSF":
            # What the IMM scores an SVSF step with: no log-likelihood of its own, so the
            # Gaussian density of its innovation under its innovation covariance.
            assert out.log_likelihood is None and out.innovation_cov is not None
            step = at_step(out, 30)
            by_imm = log_mode_likelihood(step)
            direct = gaussian_log_density(
                step.innovation, cholesky(step.innovation_cov), step.mask.sum(-1).double()
            )
            res.likelihood_check = float((by_imm - direct).abs().max())
    res.seconds = time.perf_counter() - start
    return res


def figures(res: Results, out: Path) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = []
    steps = torch.arange(1, res.curves["KF"].shape[0] + 1)
    fig, axes = plt.subplots(2, 1, figsize=(10, 7), sharex=True)
    ax = axes[0]
    for (key, _), colour in zip(TRANSITIONS.items(), ("C3", "C0", "C2", "C4"), strict=True):
        mu = res.mode_probs[imm_name(key)]
        ax.plot(steps, mu.mean(0), color=colour, lw=1.6, label=f"π_ii = {key}: mean over runs")
        if key == MAIN:
            low, high = mu.quantile(0.1, dim=0), mu.quantile(0.9, dim=0)
            ax.fill_between(steps, low, high, color=colour, alpha=0.2, label="10-90% of runs")
    mu = res.mode_probs["IMM(SVSF H⁺, KF), π_ii = 0.95"]
    ax.plot(steps, mu.mean(0), "k:", lw=1.2, label="IMM(SVSF H⁺, KF), π_ii = 0.95")
    ax.set(ylabel="μ_SVSF = P(SVSF mode | z_1..t)", ylim=(0, 1))
    ax.set_title("Mode probability of the SVSF mode (the KF mode's is 1 − μ_SVSF)")
    ax.legend(fontsize=7, loc="upper left")
    ax = axes[1]
    for name in ("KF", "KF on [z, FD velocity]", "SVSF", imm_name(MAIN), "SVSS"):
        curve = res.curves[name]
        ax.plot(steps, (curve[:, 0] ** 2 + curve[:, 2] ** 2).div(2).sqrt(), label=name, lw=1.2)
    ax.set(xlabel="time (s)", ylabel="position RMSE per axis (m)", ylim=(0, 600))
    ax.legend(fontsize=7, loc="upper left")
    for ax in axes:
        for label, (a, b) in PHASES.items():
            if "straight" not in label:
                ax.axvspan(a + 0.5, b + 0.5, color="0.5", alpha=0.08 if a % 2 else 0.16, lw=0)
    axes[1].text(22, 560, "shaded: 3°/s turn, accelerating turn, linear acceleration", fontsize=7)
    fig.tight_layout()
    fig.savefig(out / "imm_svsf_kf_mode_probs.png", dpi=110)
    plt.close(fig)
    names.append("imm_svsf_kf_mode_probs.png")

    fig, axes = plt.subplots(1, 2, figsize=(12, 4))
    for ax, (c, label) in zip(axes, ((0, "position"), (1, "velocity")), strict=True):
        for name in ("KF", "SVSF", "KF on [z, FD velocity]", imm_name(MAIN), imm_name("0.80")):
            curve = res.curves[name]
            ax.plot(steps, (curve[:, c] ** 2 + curve[:, c + 2] ** 2).div(2).sqrt(), label=name)
        ax.set(xlabel="time (s)", ylabel=f"{label} RMSE per axis", ylim=(0, 600 if c == 0 else 250))
        ax.legend(fontsize=7)
    fig.suptitle("Complex scenario: RMSE over time (filters only)")
    fig.tight_layout()
    fig.savefig(out / "imm_svsf_kf_rmse.png", dpi=110)
    plt.close(fig)
    names.append("imm_svsf_kf_rmse.png")
    return names


def phase_rmse(res: Results) -> list[list[str]]:
    """Position and velocity RMSE per phase of the filters (from the per-step RMSE curves)."""
    rows = []
    names = ["KF", "KF on [z, FD velocity]", "SVSF", *(imm_name(k) for k in TRANSITIONS)]
    for name in names:
        curve = res.curves[name].square()
        cells = []
        for a, b in PHASES.values():
            pos = float((curve[a:b, 0] + curve[a:b, 2]).mean().div(2).sqrt())
            vel = float((curve[a:b, 1] + curve[a:b, 3]).mean().div(2).sqrt())
            cells.append(f"{pos:.0f} / {vel:.0f}")
        rows.append([name, *cells])
    return rows


def report(res: Results) -> str:
    """The results file: the prose of ``templates/imm_svsf_kf.md`` around the tables."""
    rows = []
    for name, (rmse, us) in res.rows.items():
        kind = KINDS.get(name, "IMM filter")
        rows.append([name, kind, *[f"{v:.1f}" for v in rmse], f"{us:.1f}"])
    main, svsf, kf = (res.rows[k][0] for k in (imm_name(MAIN), "SVSF", "KF"))
    fd_kf = res.rows["KF on [z, FD velocity]"][0]

    def pct(a: float, b: float) -> str:
        return f"{100 * (a / b - 1):+.0f}%"

    vs = [
        [
            comp,
            f"{main[c]:.1f}",
            f"{svsf[c]:.1f} ({pct(main[c], svsf[c])})",
            f"{kf[c]:.1f} ({pct(main[c], kf[c])})",
            f"{fd_kf[c]:.1f} ({pct(main[c], fd_kf[c])})",
        ]
        for c, comp in enumerate(["x position", "x velocity", "y position", "y velocity"])
    ]
    phase_rows = []
    for key in TRANSITIONS:
        mu = res.mode_probs[imm_name(key)]
        ll = res.mode_loglik[imm_name(key)]
        cells = []
        for a, b in PHASES.values():
            diff = (ll[:, a:b, 0] - ll[:, a:b, 1]).mean()
            cells.append(f"{float(mu[:, a:b].mean()):.2f} ({float(diff):+.2f})")
        inside = ((mu > 0.01) & (mu < 0.99)).double().mean()
        phase_rows.append([f"π_ii = {key}", *cells, f"{100 * float(inside):.1f}%"])
    mu_h = res.mode_probs["IMM(SVSF H⁺, KF), π_ii = 0.95"]
    ll_h = res.mode_loglik["IMM(SVSF H⁺, KF), π_ii = 0.95"]
    phase_rows.append(
        [
            "H⁺ SVSF and KF, π_ii = 0.95",
            *[
                f"{float(mu_h[:, a:b].mean()):.2f} "
                f"({float((ll_h[:, a:b, 0] - ll_h[:, a:b, 1]).mean()):+.2f})"
                for a, b in PHASES.values()
            ],
            f"{100 * float(((mu_h > 0.01) & (mu_h < 0.99)).double().mean()):.1f}%",
        ]
    )
    nis_rows = [
        [name, f"{res.spread[name]:.0f}", *[f"{v:.2f}" for v in values]]
        for name, values in res.nis.items()
    ]
    best = min(TRANSITIONS, key=lambda k: sum(res.rows[imm_name(k)][0]))
    ll_main = res.mode_loglik[imm_name(MAIN)]
    gaps = [float((ll_main[:, a:b, 0] - ll_main[:, a:b, 1]).mean()) for a, b in PHASES.values()]
    ll_half = res.mode_loglik[imm_name("0.50")]
    half_gap = float((ll_half[..., 0] - ll_half[..., 1]).abs().max())
    mu_main = res.mode_probs[imm_name(MAIN)].mean(0)
    straight = float(mu_main[5:20].mean())
    peaks = []
    for label, (a, b) in PHASES.items():
        if "straight" in label:
            continue
        k = a + int(mu_main[a:b].argmax())
        peaks.append(f"{float(mu_main[k]):.2f} at {k + 1} s in the {label.split(' (')[0]}")
    steady = float(mu_main[45:75].mean())
    hplus = res.rows["IMM(SVSF H⁺, KF), π_ii = 0.95"][0]
    rmse_header = [
        "estimator",
        "kind",
        "x position (m)",
        "x velocity (m/s)",
        "y position (m)",
        "y velocity (m/s)",
        "µs/track-step",
    ]
    versus_header = [
        "component",
        "IMM",
        "SVSF alone",
        "KF alone (position-only, Table 3)",
        "KF mode alone",
    ]
    return (
        render(
            "imm_svsf_kf",
            "report",
            runs=res.runs,
            seconds=f"{res.seconds:.0f}",
            likelihood_check=f"{res.likelihood_check:.1e}",
            spread_svsf=f"{res.spread['SVSF']:.0f}",
            spread_kf=f"{res.spread['KF on [z, FD velocity]']:.0f}",
            main=MAIN,
            gap_straight=f"{gaps[0]:+.2f}",
            gap_max=f"{max(gaps):+.2f}",
            gap_max_phase=list(PHASES)[gaps.index(max(gaps))].split(" (")[0],
            nis=markdown_table(["filter alone", "median P_xx (m²)", *PHASES], nis_rows),
            nis_svsf=f"{min(res.nis['SVSF']):.2f}-{max(res.nis['SVSF']):.2f}",
            nis_kf=f"{max(res.nis['KF']):.0f}",
            phases=markdown_table(["IMM", *PHASES, "μ inside (0.01, 0.99)"], phase_rows),
            straight=f"{straight:.2f}",
            peaks="; ".join(peaks),
            steady=f"{steady:.2f}",
            rows=markdown_table(rmse_header, rows),
            versus=markdown_table(versus_header, vs),
            best=best,
            half_gap=f"{half_gap:.1e}",
            hplus_position=f"{hplus[0]:.0f}/{hplus[2]:.0f}",
            hplus_velocity=f"{hplus[1]:.0f}/{hplus[3]:.0f}",
            phase_rmse=markdown_table(["estimator", *PHASES], phase_rmse(res)),
        )
        + "\n"
    )


def main(argv: list[str] | None = None, out: Path = RESULTS) -> None:
    common.main(
        "imm_svsf_kf",
        __doc__,
        lambda args: run(args.runs, args.seed),
        figures,
        lambda res, pngs: report(res),
        runs=500,
        argv=argv,
        out=out,
    )


if __name__ == "__main__":
    main()
