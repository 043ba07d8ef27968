"""Gadsden, Habibi, Kirubarajan 2012 (the SPVSF paper): Tables 1, 2, 4, 5 beside ours.

Ballistic re-entry (Sec 5.1, nominal and with the gravity error at 15 s) and the EHA (Sec 5.2,
constant and changing bulk modulus), EKF, UKF, PF, SVSF and SPVSF, Monte Carlo runs as one
batch each. RMSE as the paper computes it: per run over all steps including the initial
estimate, then averaged over runs. Writes ``experiments/results/spvsf_paper.md``.

Beside the paper's rows: a PF whose prior covers the initial error, the SVSF and SPVSF with the
artificial ballistic coefficient of Eq. (47), a ψ study, and Table 4 with a second reading of
the EHA noise; the results file discusses every difference over 10%. Figures 5-9 show the
first run.

    python -m experiments.spvsf_paper [--runs 100] [--eha-runs 20] [--seed 0]
"""

from __future__ import annotations

import argparse
import inspect
import time
from pathlib import Path
from typing import Any

import torch
from torch import Tensor
from tqdm.auto import tqdm

import torchsvs as ts
from torchsvs.evaluation import markdown_table
from torchsvs.filters.spvsf import Proposal
from torchsvs.metrics import paper_rmse, run_rmse
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
# Not given in the paper: the ψ whose SVSF row matches the paper's SVSF row (464/122 against
# 471/119 m, m/s); the ψ study below shows SVSF and SPVSF over ψ.
BALLISTIC_PSI = [1e4, 8e3]
PSI_STUDY = ([500.0, 100.0], [2e3, 1e3], [5e3, 3e3], [1e4, 8e3], [2e4, 1e4])
EQ47_PSI = [1e4, 8e3, 1e5]  # ψ₃ wide: the artificial β is mostly noise (see the Eq 47 section)
EHA_PSI = [5e-4, 5e-3, 0.5, 1e6]  # ψ = 5 V_max (Sec 5.2); 1e6 Pa for the modulus: our choice
EHA_NOISE_AT_3_SIGMA = 1.0 / (3.0 * 5.0**0.5)  # truth noise with V_max, W_max at 3σ
# The SPVSF's other readings of Eqs. (30)-(31) (rows "SPVSF" use the default, "adapted").
READINGS: dict[str, Proposal] = {
    "SPVSF, Eqs 30-31 as printed": "estimate",
    "SPVSF, particle proposal": "particles",
}
DEFAULT_READING: Proposal = inspect.signature(ts.SPVSF).parameters["proposal"].default

#: Where `python -m` writes the report: the tracked results of the checkout.
RESULTS = Path(__file__).parent / "results"


def estimators(
    model: ts.models.StateSpaceModel, psi: list[float], proposal: Proposal = DEFAULT_READING
) -> dict[str, torch.nn.Module]:
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
            proposal=proposal,
        ),
    }


def variants(sc: Scenario, psi: list[float]) -> dict[str, tuple[torch.nn.Module, Tensor]]:
    """Rows beside the paper's: the SPVSF's other two readings (:data:`READINGS`), a PF whose
    prior covers the initial error (ballistic: 10% of x̂0 per component; EHA: a modulus standard
    deviation of 0.6·10⁸ Pa, the initial error, added to P0), and for the ballistic case the SVSF
    and SPVSF with Eq. (47)."""
    rows: dict[str, tuple[torch.nn.Module, Tensor]] = {}
    for name, proposal in READINGS.items():
        rows[name] = (estimators(sc.model, psi, proposal)["SPVSF"], sc.P0)
    pf = ts.ParticleFilter(sc.model, num_particles=350, resample_threshold=0.8)
    if not isinstance(sc.model, ts.models.BallisticReentry):
        wide = sc.P0 + torch.diag(torch.tensor([0.0, 0.0, 0.0, 0.6e8**2], dtype=sc.P0.dtype))
        return rows | {"PF, prior covering the modulus": (pf, wide)}
    eq47 = ts.filters.BallisticCoefficientFromDrag()
    return rows | {
        "PF, prior (10% x̂0)²": (pf, torch.diag((0.1 * sc.x0).square())),
        "SVSF + Eq 47": (ts.SVSF(sc.model, psi=EQ47_PSI, gamma=0.1, artificial=eq47), sc.P0),
        "SPVSF + Eq 47": (ts.SPVSF(sc.model, psi=EQ47_PSI, gamma=0.1, artificial=eq47), sc.P0),
    }


def run(est: torch.nn.Module, sc: Scenario, P0: Tensor, seed: int) -> Tensor:
    """The estimate ``[B, T, n]`` of one estimator on a scenario (particle filters seeded)."""
    kwargs: dict = {"u": sc.u}
    if isinstance(est, ts.ParticleFilter):
        kwargs["generator"] = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        return est(sc.z, sc.x0, P0, **kwargs).mean


def settling_time(mean: Tensor, truth: Tensor, dt: float, bound: float) -> Tensor:
    """Per run ``[B]``, the time (s) from which the first component's error stays within
    ``bound`` (``inf`` if it is outside at the last step)."""
    outside = (mean[..., 0] - truth[..., 0]).abs() > bound  # [B, T]
    T = outside.shape[1]
    last = T - 1 - outside.flip(1).to(torch.int64).argmax(1)  # last step outside
    last = torch.where(outside.any(1), last, torch.full_like(last, -1))
    time = (last + 2).to(truth.dtype) * dt  # step k ends at (k + 1) dt
    return torch.where(last == T - 1, torch.full_like(time, float("inf")), time)


def evaluate(
    sc: Scenario,
    true_x0: Tensor,
    psi: list[float],
    seed: int,
    tracks: dict | None = None,
    variants: dict[str, tuple[torch.nn.Module, Tensor]] | None = None,
    settling: dict | None = None,
) -> dict[str, Tensor]:
    """Per-run RMSE ``[B, n]`` per filter (and variant); the first run's estimates go into
    ``tracks``, and with ``settling``, each filter's :func:`settling_time` ``[B, 2]`` within
    three and ten standard deviations of the first measured component's noise."""
    runs = {name: (est, sc.P0) for name, est in estimators(sc.model, psi).items()}
    runs.update(variants or {})
    out = {}
    std = float(sc.model.meas_cov()[0, 0]) ** 0.5
    for name, (est, P0) in runs.items():
        mean = run(est, sc, P0, seed)
        out[name] = run_rmse(mean, sc.truth, initial=(sc.x0, true_x0))
        if settling is not None:
            settling[name] = torch.stack(
                [settling_time(mean, sc.truth, sc.dt, k * std) for k in (3.0, 10.0)], -1
            )
        if tracks is not None and "Eq 47" not in name:
            tracks[name] = mean[0]
    if tracks is not None:
        tracks["truth"] = sc.truth[0]
    return out


def psi_study(
    scenarios: dict[str, Scenario],
    true_x0: Tensor,
    seed: int,
    path: Path,
    known: dict[tuple[str, str], Tensor],
) -> tuple[str, dict[tuple[str, str, int], Tensor]]:
    """SVSF and SPVSF altitude/velocity RMSE over ψ, nominal and gravity error; table + figure.
    ``known`` holds the RMSEs already measured at :data:`BALLISTIC_PSI` (scenario, filter)."""
    results = {}
    for label, sc in scenarios.items():
        for i, psi in enumerate(tqdm(PSI_STUDY, desc=f"ψ study ({label})", leave=False)):
            for name in ("SVSF", "SPVSF"):
                if psi == BALLISTIC_PSI and (label, name) in known:
                    results[label, name, i] = known[label, name]
                    continue
                est = estimators(sc.model, psi)[name]
                mean = run(est, sc, sc.P0, seed)
                results[label, name, i] = paper_rmse(mean, sc.truth, initial=(sc.x0, true_x0))
    rows = []
    for i, psi in enumerate(PSI_STUDY):
        cells = [f"[{psi[0]:.0f}, {psi[1]:.0f}]"]
        for label in scenarios:
            for name in ("SVSF", "SPVSF"):
                r = results[label, name, i]
                cells.append(f"{r[0]:.0f} / {r[1]:.1f}")
        rows.append(cells)
    header = ["ψ (m, m/s)"] + [
        f"{name}, {label}" for label in scenarios for name in ("SVSF", "SPVSF")
    ]
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    x = [psi[0] for psi in PSI_STUDY]
    for k, (ax, what) in enumerate(zip(axes, ("altitude (m)", "velocity (m/s)"), strict=True)):
        for label, style in zip(scenarios, ("-", "--"), strict=True):
            for name, marker in (("SVSF", "o"), ("SPVSF", "s")):
                y = [float(results[label, name, i][k]) for i in range(len(PSI_STUDY))]
                ax.plot(x, y, style, marker=marker, label=f"{name}, {label}")
        ax.set(xscale="log", xlabel="ψ altitude (m)", ylabel=f"RMSE, {what}")
    axes[0].legend(fontsize=8)
    fig.suptitle("Ballistic re-entry: SVSF and SPVSF over the boundary layer ψ")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return markdown_table(header, rows), results


def eq47_diagnostics(sc: Scenario) -> dict[str, float]:
    """How informative Eq. (47) is: drag signal against the noise of its speed difference."""
    model: Any = sc.model
    y, _, _ = ts.filters.BallisticCoefficientFromDrag()(sc.z, model, None)
    formed = ~torch.isnan(y[..., 2])
    sigma_d = float((2.0 * model.meas_cov()[1, 1] + model.process_noise()[1, 1]).sqrt())
    signal = model.dt * model.drag(sc.truth)  # T·D: the speed the drag takes per step
    error = (y[..., 2] - sc.truth[..., 2]).abs() / sc.truth[..., 2]
    return {
        "sigma_d": sigma_d,
        "peak_signal": float(signal.median(0).values.max()),
        "formed": float(formed.float().mean()),
        "median_error": float(error[formed].median()) if bool(formed.any()) else float("nan"),
    }


def figure(
    tracks: dict[str, Tensor],
    component: int,
    dt: float,
    title: str,
    path: Path,
    zoom=None,
    xlim=None,
) -> None:
    """One state component of the first run over time, truth and every filter."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(10, 4))
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
    if xlim is not None:
        ax.set_xlim(*xlim)
    ax.legend(fontsize=8, loc="center left", bbox_to_anchor=(1.01, 0.5))  # off the traces
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def convergence_section(settle: dict[str, Tensor]) -> list[str]:
    """The convergence paragraph and table from settling times ``[B, 2]`` per filter."""
    rows = []
    for name, times in settle.items():
        cells = [name]
        for k in range(2):
            never = int(torch.isinf(times[:, k]).sum())
            cells += [f"{float(times[:, k].median()):.1f}", f"{never} of {len(times)}"]
        rows.append(cells)
    header = ["filter", "within 300 m from (s)", "never within 300 m"]
    header += ["within 1 km from (s)", "never within 1 km"]
    return [
        'Convergence (Sec 5.1: "the SPVSF converged to the true state trajectory the fastest. '
        "Next was the PF, followed closely by the SVSF. The UKF [...] converging in about 3 "
        'seconds. The EKF [...] nearly 10 seconds"): time from which the altitude error stays '
        "within 300 m (3σ of the altitude measurement) or 1 km (what a plot of the 60 km descent "
        "shows as converged), median over runs.",
        "",
        markdown_table(header, rows),
    ]


def table(ours: dict[str, Tensor], paper: dict, labels: list[str], scale: list[float]) -> str:
    """Ours (paper) per filter from per-run RMSEs ``[B, n]``; "—" where the paper has no such
    row, "Failed" where it failed."""
    rows = []
    for name, values in ours.items():
        cells = []
        for i, v in enumerate(values.mean(0).tolist()):
            if name not in paper:
                ref = "—"
            else:
                ref = "Failed" if paper[name] is None else f"{paper[name][i]:.3g}"
            cells.append(f"{v / scale[i]:.3g} ({ref})")
        rows.append([name, *cells])
    return markdown_table(["filter", *labels], rows)


def main(argv: list[str] | None = None, prog: str | None = None, out: Path = RESULTS) -> None:
    parser = argparse.ArgumentParser(prog=prog, description=__doc__.splitlines()[0])
    parser.add_argument(
        "--runs", type=int, default=100, help="Monte Carlo runs per scenario (default 100)"
    )
    parser.add_argument(
        "--eha-runs", type=int, default=20, help="Monte Carlo runs of the EHA (default 20)"
    )
    parser.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    parser.add_argument(
        "--out", type=Path, default=out, help=f"where the report and figures go (default {out})"
    )
    args = parser.parse_args(argv)
    start = time.perf_counter()
    true_b = torch.tensor(BALLISTIC_TRUE_X0, dtype=torch.float64)
    true_e = torch.tensor([0.0, 0.0, 0.0, 2.1e8], dtype=torch.float64)
    seeded = lambda: torch.Generator().manual_seed(args.seed)  # noqa: E731
    scenarios = {
        "nominal": ballistic_scenario(args.runs, seeded()),
        "gravity error": ballistic_scenario(args.runs, seeded(), gravity_error_at=15.0),
        "EHA constant": eha_scenario(args.eha_runs, seeded()),
        "EHA changing": eha_scenario(args.eha_runs, seeded(), changing=True),
        "EHA constant, 3σ": eha_scenario(args.eha_runs, seeded(), noise_scale=EHA_NOISE_AT_3_SIGMA),
    }
    ballistic = (["altitude (m)", "velocity (m/s)", "ballistic coefficient"], [1.0, 1.0, 1.0])
    # The paper's modulus RMSE reads as relative to 2.1e8 Pa.
    eha = (
        ["position (m)", "velocity (m/s)", "acceleration (m/s²)", "bulk modulus (rel.)"],
        [1.0, 1.0, 1.0, 2.1e8],
    )
    studies = {  # title: scenario, truth at 0, ψ, paper table, columns, figures
        "Table 1 (ballistic, nominal)": (
            "nominal", true_b, BALLISTIC_PSI, TABLE1, ballistic,
            [("spvsf_fig5_altitude.png", 0, "Fig 5: altitude (m)", None),
             ("spvsf_fig5_altitude_first_5s.png", 0, "Fig 5, first 5 s: altitude (m)",
              (4.2e4, 7e4))],
        ),
        "Table 2 (ballistic, gravity doubled at 15 s)": (
            "gravity error", true_b, BALLISTIC_PSI, TABLE2, ballistic,
            [("spvsf_fig6_altitude_gravity_error.png", 0,
              "Fig 6: altitude (m), gravity error at 15 s", None)],
        ),
        "Table 4 (EHA, constant modulus)": (
            "EHA constant", true_e, EHA_PSI, TABLE4, eha,
            [("spvsf_fig7_modulus.png", 3, "Fig 7: effective bulk modulus (Pa)", None),
             ("spvsf_fig8_modulus_zoom.png", 3, "Fig 8: bulk modulus, zoomed (Pa)",
              (1.9e8, 2.3e8))],
        ),
        "Table 5 (EHA, changing modulus)": (
            "EHA changing", true_e, EHA_PSI, TABLE5, eha,
            [("spvsf_fig9_modulus_changing.png", 3, "Fig 9: bulk modulus, changing (Pa)", None)],
        ),
        "Table 4 again, truth noise with V_max and W_max at 3σ": (
            "EHA constant, 3σ", true_e, EHA_PSI, TABLE4, eha, [],
        ),
    }  # fmt: skip
    args.out.mkdir(parents=True, exist_ok=True)
    per_run: dict[str, dict[str, Tensor]] = {}
    settled: dict[str, Tensor] = {}  # nominal ballistic case: settling times [B, 2] per filter
    sections = {}
    for title, (key, true_x0, psi, paper, (labels, scale), figs) in tqdm(
        studies.items(), desc="spvsf paper"
    ):
        sc = scenarios[key]
        tracks: dict[str, Tensor] = {}
        extra = variants(sc, psi)
        settle: dict[str, Tensor] | None = {} if "nominal" in title else None
        per_run[title] = ours = evaluate(sc, true_x0, psi, args.seed, tracks, extra, settle)
        lines = [f"## {title}", "", table(ours, paper, labels, scale), ""]
        for name, component, caption, zoom in figs:
            xlim = (0.0, 5.0) if "first 5 s" in caption else None
            figure(tracks, component, sc.dt, caption, args.out / name, zoom, xlim)
            lines.append(f"![{caption}]({name})")
        if settle:
            settled = settle
            lines += ["", *convergence_section(settle)]
        sections[title] = "\n".join([*lines, ""])
    results = {t: {k: v.mean(0) for k, v in r.items()} for t, r in per_run.items()}
    known = {
        (label, name): results[title][name]
        for label, title in (
            ("nominal", "Table 1 (ballistic, nominal)"),
            ("gravity error", "Table 2 (ballistic, gravity doubled at 15 s)"),
        )
        for name in ("SVSF", "SPVSF")
    }
    psi_table, by_psi = psi_study(
        {k: scenarios[k] for k in ("nominal", "gravity error")},
        true_b,
        args.seed,
        args.out / "spvsf_psi_study.png",
        known,
    )
    eq47 = eq47_diagnostics(scenarios["nominal"])

    def med(times: Tensor) -> float:
        return float(times.median())

    t1, t2 = (
        results["Table 1 (ballistic, nominal)"],
        results["Table 2 (ballistic, gravity doubled at 15 s)"],
    )
    t4, t5 = results["Table 4 (EHA, constant modulus)"], results["Table 5 (EHA, changing modulus)"]
    t4s = results["Table 4 again, truth noise with V_max and W_max at 3σ"]
    floor = 6100.0 / (scenarios["nominal"].truth.shape[1] + 1) ** 0.5
    alt = {name: float(v[0]) for name, v in t1.items()}
    spvsf_wins = [
        i for i in range(len(PSI_STUDY))
        if all(by_psi[k, "SPVSF", i][0] < by_psi[k, "SVSF", i][0] for k in ("nominal", "gravity error"))
    ]  # fmt: skip
    others = [i for i in range(len(PSI_STUDY)) if i not in spvsf_wins]
    narrow_gap = max(
        (
            float(by_psi[k, "SPVSF", i][0] / by_psi[k, "SVSF", i][0] - 1)
            for i in others
            for k in ("nominal", "gravity error")
        ),
        default=0.0,
    )
    spvsf_speed = [float(v[1]) for (_, name, _), v in by_psi.items() if name == "SPVSF"]
    at_5000 = float(by_psi["nominal", "SPVSF", PSI_STUDY.index([5e3, 3e3])][0])
    mod = {name: float(v[3] / 2.1e8) for name, v in t5.items()}
    wide_pf = (t4["PF, prior covering the modulus"] / torch.tensor([1, 1, 1, 2.1e8])).tolist()
    # Each reading of the SPVSF against issue 5's done-when; the modulus paired over runs.
    paired = per_run["Table 5 (EHA, changing modulus)"]

    def modulus_gap(rmse: Tensor) -> tuple[float, float]:
        """Mean and standard error over runs of this modulus RMSE minus the SVSF's."""
        gap = (rmse[:, 3] - paired["SVSF"][:, 3]) / 2.1e8
        return float(gap.mean()), float(gap.std() / len(gap) ** 0.5)

    def yes(ok: bool, what: str) -> str:
        return f"**{what}**" if ok else f"**NOT {what}**"

    # The rows of each reading: "SPVSF" (the default) and the two of READINGS.
    reading = {name: f'`"{READINGS.get(name, DEFAULT_READING)}"`' for name in ("SPVSF", *READINGS)}
    rows, met = [], {}
    for name in reading:
        below = all(alt[name] < alt[other] for other in ("SVSF", "UKF", "EKF"))
        drift = float(t2[name][0] / t1[name][0] - 1)
        gap = modulus_gap(paired[name])
        as_good = mod[name] < mod["PF"] and gap[0] <= 0.0
        met[name] = below and abs(drift) <= 0.1 and as_good
        rows.append([
            reading[name] + (" (default)" if name == "SPVSF" else ""),
            f"{alt[name]:.0f}: {yes(below, 'below')}",
            f"{100 * drift:+.2f}%: {yes(abs(drift) <= 0.1, 'within 10%')}",
            f"{mod[name]:.5f}, {gap[0]:+.1e} ± {gap[1]:.1e}: {yes(as_good, 'at least as good')}",
        ])  # fmt: skip
    PRINTED, GUIDED = READINGS  # the printed reading's and the particle proposal's rows
    kinematic = [  # readings below the SVSF in every EHA kinematic column, 3σ noise reading
        label
        for name, label in reading.items()
        if all(t4s[name][i] < t4s["SVSF"][i] for i in range(3))
    ]
    faithful = [  # readings for which the paper's SPVSF-below-SVSF orderings all hold
        label
        for name, label in reading.items()
        if all(t[name][0] < t["SVSF"][0] for t in (t1, t2))
        and all(t[name][3] < t["SVSF"][3] for t in (t4, t5))
    ]
    # The printed reading's gap with ten times the particles: is it the particle mean's noise?
    changing = scenarios["EHA changing"]
    many = variants(changing, EHA_PSI)[PRINTED][0]
    assert isinstance(many, ts.SPVSF)
    many.num_particles = 3500
    mean = run(many, changing, changing.P0, args.seed)
    many_gap = modulus_gap(run_rmse(mean, changing.truth, initial=(changing.x0, true_e)))
    checks = [
        "## Done-when checks (issue 5)",
        "",
        f"Ballistic altitude RMSE (m) against SVSF {alt['SVSF']:.0f}, UKF {alt['UKF']:.0f} and EKF "
        f"{alt['EKF']:.0f}; its change with the gravity error; EHA changing-modulus RMSE "
        f"(relative to 2.1·10⁸ Pa) against SVSF {mod['SVSF']:.5f} and PF {mod['PF']:.3f}, with the "
        f"SPVSF's minus the SVSF's per run (mean ± standard error over {len(paired['SVSF'])} "
        "runs; at least as good: a mean gap ≤ 0 and below the PF), for each reading of Eqs 30-31 "
        "(`proposal=`, see the readings item below).",
        "",
        markdown_table(
            ["SPVSF reading", "ballistic altitude", "gravity error", "EHA modulus, − SVSF"], rows
        ),
        "",
        f"Issue 5's points hold for the default SPVSF: {yes(met['SPVSF'], 'all met')}. Eqs 30-31 "
        "as printed move the modulus only by the sampling noise of the particle mean around the "
        "SVSF's (their weights do not see the modulus); with 3500 particles their gap is "
        f"{many_gap[0]:+.1e} ± {many_gap[1]:.1e}. The particle proposal honours the narrow stated "
        "prior and is slower on the ballistic track.",
        "",
    ]
    discussion = [
        "## Differences over 10%, and why",
        "",
        f"- **Every altitude RMSE includes the initial estimate**, 6100 m off: that alone puts "
        f"{floor:.0f} m under every number of Tables 1-2 (6100/√(T+1) with T = "
        f"{scenarios['nominal'].truth.shape[1]} steps). The paper's 360-370 m for SPVSF and PF mean "
        "they converge within a step or two; differences between filters live in the remainder.",
        f"- **SVSF ψ (ballistic)** is not given. We use the ψ whose SVSF row matches the paper's "
        f"({float(t1['SVSF'][0]):.0f} / {float(t1['SVSF'][1]):.0f} against 471 / 119), so the SPVSF, "
        "which shares that ψ, is a prediction, not a fit. The ψ study shows the picture at other "
        f"ψ (table above): the SPVSF is below the SVSF in altitude in both cases for ψ = "
        f"{', '.join(str([int(v) for v in PSI_STUDY[i]]) for i in spvsf_wins) or 'none'}. At the "
        f"other ψ, narrow ones where the SVSF already follows the measurements closely, the SPVSF "
        f"is at most {100 * narrow_gap:.1f}% above the SVSF in altitude. The SPVSF's velocity stays at "
        f"{min(spvsf_speed):.0f}-{max(spvsf_speed):.0f} m/s over the whole range while the SVSF's "
        "grows with ψ_vel.",
        f"- **SPVSF altitude {float(t1['SPVSF'][0]):.0f} against 360 (+"
        f"{100 * (float(t1['SPVSF'][0]) / 360 - 1):.0f}%)**: at this ψ (ψ_alt = 10 km, wider than the "
        "initial error) the SVSF step does not saturate at first, so the SPVSF's altitude error "
        f"takes {med(settled['SPVSF'][:, 0]):.1f} s (median) to stay within 300 m instead of the "
        f"step or two the paper's number implies. With ψ = [5000, 3000] it is {at_5000:.0f} m (ψ study); no single ψ "
        "gives both the paper's SVSF row and its SPVSF row.",
        f"- **SVSF velocity with the gravity error {float(t2['SVSF'][1]):.0f} against 311 m/s**: the "
        "direction is the paper's (SVSF velocity grows, SPVSF's does not), the size is not; it grows "
        "with ψ_vel (ψ study).",
        "- **Three readings of the SPVSF** (`SPVSF` docstring; one row each in every table, the "
        "done-when table compares them). Eqs 30-31 as printed draw fresh particles around the "
        "SVSF estimate and weight each by the likelihood of its draw: not a consistent particle "
        "filter (on a linear-Gaussian model it misses the KF by over 0.5σ on average with "
        "2000 particles over 100 runs, tested), but blind to the narrow stated prior, so it converges in the "
        f"ballistic case ({alt[PRINTED]:.0f} m); its weights never see the modulus, which stays "
        f"the SVSF's ({mod[PRINTED]:.5f} against {mod['SVSF']:.5f}). The construction the paper "
        'names ("similar to the EPF and UPF") moves each particle, corrects it with the SVSF '
        "gain and gives it the full importance weight: consistent (it approaches the KF, tested), "
        f"so it honours P0 = 10Q and its ballistic altitude ({alt[GUIDED]:.0f} m) carries the "
        "prior's slow start in part, like the EKF's; in the EHA, where model and prior are right, "
        f"it weighs each particle's modulus through its dynamics ({mod[GUIDED]:.5f}). The default "
        "moves and corrects the particles in the same way but weights each by the likelihood of "
        "its own prediction (the weight of the optimal proposal): like the printed reading it is "
        f"not held back by the prior ({alt['SPVSF']:.0f} m), like the consistent one it sees the "
        f"modulus ({mod['SPVSF']:.5f}). The paper's SPVSF is below its SVSF in the altitude "
        "columns of Tables 1-2 and the modulus columns of Tables 4-5; all four orderings hold for "
        f"{' and '.join(faithful) or 'no reading'}. The default does not reproduce the paper's EHA "
        "kinematic ordering (see the EHA kinematics item), and it is "
        f"{alt['SPVSF'] - alt[PRINTED]:.0f} m behind the printed reading in the ballistic case.",
        "- **Convergence (Sec 5.1, table under Table 1)**: within 1 km, SPVSF "
        f"{med(settled['SPVSF'][:, 1]):.1f} s, SVSF {med(settled['SVSF'][:, 1]):.1f} s, UKF "
        f"{med(settled['UKF'][:, 1]):.1f} s, EKF {med(settled['EKF'][:, 1]):.1f} s, and the PF with "
        f"the covering prior {med(settled['PF, prior (10% x̂0)²'][:, 1]):.1f} s; within 300 m, SPVSF "
        f"{med(settled['SPVSF'][:, 0]):.1f} s and SVSF {med(settled['SVSF'][:, 0]):.1f} s. The paper's order "
        "(SPVSF, then PF, then SVSF closely, UKF about 3 s, EKF nearly 10 s) holds except that this "
        "PF is the fastest (its prior, which we had to choose, already covers the truth) and our "
        "UKF converges with our EKF (see the UKF item). Within 300 m the SVSF at this ψ never "
        f"settles in {int(torch.isinf(settled['SVSF'][:, 0]).sum())} of "
        f"{len(settled['SVSF'])} runs: its 10 km boundary layer lets the altitude error wander.",
        f"- **UKF altitude {alt['UKF']:.0f} against 1060** (Table 2: 852): our UKF equals our EKF to 4 "
        "digits here, as it should: with P0 = 10Q the prior spread is 5.8 m in altitude and the drag "
        "is nearly linear over it, so sigma points and linearisation agree. Our UKF equals filterpy's "
        "on this model (test). The paper's UKF row cannot be reproduced from the text (shared/papers "
        "README); a UKF converging faster than the EKF needs a wider prior than stated.",
        f"- **PF altitude {alt['PF']:.0f} against 370**: the bootstrap PF starts from P0 = 10Q, whose "
        "altitude spread (5.8 m) is a thousandth of the initial error; its particles never reach the "
        'truth. With a prior that covers a 10% error, P0 = diag((0.1 x̂0)²) (row "PF, prior"), it '
        f"gives {float(t1['PF, prior (10% x̂0)²'][0]):.0f} m and a ballistic-coefficient RMSE of "
        f"{float(t1['PF, prior (10% x̂0)²'][2]):.0f}, worse than its prior: the paper's PF also "
        "fails on β (12325). We read the paper's PF as having such a prior.",
        "- **Ballistic coefficient**: no filter moves β off its 10% initial error (1917 ≈ the "
        "paper's 1923 for EKF, SVSF, SPVSF): with q2 = 10 and drag a tiny part of the speed change, "
        "β is barely observable.",
        f"- **Eq 47 (artificial β)**: the drag's speed loss per step, T·D, peaks at "
        f"{eq47['peak_signal']:.0f} m/s (median over runs) against a noise of σ_d = "
        f"{eq47['sigma_d']:.0f} m/s on the speed difference Eq 47 divides by (two speed measurements "
        "and one step of process noise). Gated at 3σ_d, "
        f"{100 * eq47['formed']:.1f}% of steps give a β measurement, with a median relative error of "
        f"{eq47['median_error']:.2f}: noise that passed the gate. Used by the SVSF and SPVSF (rows "
        f'"+ Eq 47", ψ₃ = {EQ47_PSI[2]:.0e}), β worsens to '
        f"{float(t1['SVSF + Eq 47'][2]):.0f} / {float(t1['SPVSF + Eq 47'][2]):.0f}. The paper's "
        "SVSF and SPVSF β (1923, 1919) equal the EKF's, i.e. their β did not move either. The "
        "printed Eq 47 also has the sign of the speed change reversed (see "
        "`BallisticCoefficientFromDrag`).",
        f"- **EHA modulus**: SPVSF and SVSF {float(t4['SPVSF'][3] / 2.1e8):.4f} / "
        f"{float(t4['SVSF'][3] / 2.1e8):.4f} against 0.0284 / 0.0334 (constant), "
        f"{mod['SPVSF']:.4f} / {mod['SVSF']:.4f} against 0.0185 / 0.0732 (changing). Our SVSF "
        "measures the modulus through `ModulusFromAcceleration` (Eq 51 solved for x₄, our "
        "construction; the paper does not say how its SVSF saw x₄), so it tracks the changes "
        f"nearly as well as the SPVSF (changing case: {100 * (mod['SVSF'] / mod['SPVSF'] - 1):.0f}% "
        "behind it, where the paper's SVSF has four times its SPVSF's error). Our EKF/UKF are better than the paper's (0.0068 against 0.164/0.0683): "
        'the paper says its EKF needed Q₄₄ "increased significantly" without a value; ours has '
        "the stated modulus random walk of the model.",
        "- **EHA PF**: from P0 = 10Q the modulus prior does not cover 2.1·10⁸ Pa, so the PF fails "
        "in both cases (the paper's fails only in the changing case). A prior covering the initial "
        f'error (row "PF, prior covering the modulus") brings its modulus to {wide_pf[3]:.3f} '
        f"(constant; paper PF 0.0134) but not its kinematics (position {wide_pf[0]:.1e} m): 350 "
        "particles in four dimensions with a kinematic Q far below the prior spread degenerate. "
        "In the changing case it loses the modulus after the first change "
        f"({float(t5['PF, prior covering the modulus'][3] / 2.1e8):.3f}), as the paper's PF does.",
        f"- **EHA kinematics**: with the truth's noise at the filters' covariances (Eqs 58-59), "
        f"position RMSE is {float(t4['SPVSF'][0]):.2e} m for SPVSF (SVSF "
        f"{float(t4['SVSF'][0]):.2e}, printed reading {float(t4[PRINTED][0]):.2e}) against "
        "2.44·10⁻⁵ (the measurement noise alone is 2.2·10⁻⁴); the paper's EKF/UKF kinematic "
        "errors (velocity 0.14-0.37 m/s, a hundred times the noise) follow from their modulus "
        "errors. The paper's SPVSF, PF and SVSF values lie below its own measurement noise, so "
        "its truth noise must be smaller than R. Reading W_max, V_max as 3σ amplitudes (last "
        f"table), the printed reading gives {float(t4s[PRINTED][0]):.1e} / "
        f"{float(t4s[PRINTED][1]):.1e} / {float(t4s[PRINTED][2]):.2g} against the paper's SPVSF "
        f"2.44·10⁻⁵ / 2.58·10⁻³ / 0.0287 (position and acceleration "
        f"{float(t4s[PRINTED][0]) / 2.44e-5:.1f}× and {float(t4s[PRINTED][2]) / 0.0287:.1f}× the "
        f"paper's, velocity {2.58e-3 / float(t4s[PRINTED][1]):.0f}× lower) "
        f"and the SVSF {float(t4s['SVSF'][0]):.1e} / {float(t4s['SVSF'][1]):.1e} / "
        f"{float(t4s['SVSF'][2]):.2g}; the default SPVSF gives {float(t4s['SPVSF'][0]):.1e} / "
        f"{float(t4s['SPVSF'][1]):.1e} / {float(t4s['SPVSF'][2]):.2g}. The paper's SPVSF is below "
        "its SVSF in all three kinematic columns; under this reading that holds for "
        f"{' and '.join(kinematic) or 'no reading'} (we have not isolated why the default does "
        "worse than the printed reading here). The velocity column (above its own measurement "
        "noise) is not reproducible from the text.",
        "",
    ]
    text = "\n".join(
        [
            "# Gadsden et al. 2012 (SPVSF): Tables 1, 2, 4, 5 and Figs 5-9",
            "",
            f"`python -m experiments.spvsf_paper`: {args.runs} ballistic runs, {args.eha_runs} EHA "
            f"runs per table, seed {args.seed}, {time.perf_counter() - start:.0f} s. Ours (paper). RMSE per "
            "run over all steps including the initial estimate, averaged over runs. Ballistic SVSF "
            f"ψ = {BALLISTIC_PSI}, γ = 0.1 (not given in the paper: see below). EHA ψ = 5 V_max "
            "(Sec 5.2) and 10⁶ Pa for the modulus, γ = 0.1; its modulus column is divided by "
            "2.1·10⁸ Pa (the paper's values read as relative errors). PF and SPVSF: 350 particles, "
            "resampling (systematic) when N_eff < 0.8 N. Rows marked (—) are ours only; rows "
            f'"SPVSF" use the default reading of Eqs 30-31 (`proposal="{DEFAULT_READING}"`), the '
            "other two have rows of their own (see the readings item).",
            "",
            *checks,
            *sections.values(),
            "## ψ study (ballistic)",
            "",
            "Altitude / velocity RMSE (m, m/s) of SVSF and SPVSF over ψ = [ψ_altitude, ψ_velocity], "
            "γ = 0.1, same runs as Tables 1 and 2.",
            "",
            psi_table,
            "",
            "![ψ study](spvsf_psi_study.png)",
            "",
            *discussion,
        ]
    )
    (args.out / "spvsf_paper.md").write_text(text + "\n")
    print(text)


if __name__ == "__main__":
    main()
