"""Reproduce Chen et al. 2020 (the SVSS paper): Tables 1, 2, 3, A2, the lag study, Figs 4-9.

Every Monte Carlo study is one batch. Writes ``experiments/results/svss_paper.md`` (each paper
number beside ours, with a discussion of every difference over 10%) and the figures as PNGs.

    python -m experiments.svss_paper [--runs 500] [--seed 0] [--out experiments/results]
    make reproduce   (with the other reproductions)
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import torch
from torch import Tensor
from tqdm.auto import tqdm

import torchsvs as ts
from experiments import common
from experiments.common import RESULTS, render
from torchsvs.estimator import Estimator
from torchsvs.evaluation import evaluate, markdown_table, psi_sweep, save_figure
from torchsvs.metrics import accumulative_rmse, rmse_over_time
from torchsvs.scenarios import Scenario, atc_scenario, complex_scenario

# The paper's numbers. Table 1: position accumulative RMSE (m) x, y and single-step time (µs).
TABLE1 = {
    "KF": (413.0, 413.0, 44.0),
    "KS": (387.0, 387.0, 68.0),
    "RSTKF": (145.0, 144.0, 1192.0),
    "SVSF": (146.0, 148.0, 48.0),
    "SVSS": (113.0, 117.0, 72.0),
}
# Table 2: ψ → (SVSF x, SVSS x, SVSF y, SVSS y).
TABLE2 = {
    100.0: (200.0, 143.0, 200.0, 143.0),
    500.0: (174.0, 127.0, 175.0, 129.0),
    1000.0: (142.0, 110.0, 145.0, 117.0),
    1500.0: (164.0, 118.0, 167.0, 134.0),
    2000.0: (197.0, 131.0, 201.0, 160.0),
    2500.0: (232.0, 142.0, 235.0, 186.0),
    3000.0: (264.0, 151.0, 266.0, 209.0),
}
# Table 3: estimator → (x position, x velocity, y position, y velocity).
TABLE3 = {
    "KF": (461.0, 160.0, 297.0, 113.0),
    "KS": (335.0, 141.0, 218.0, 102.0),
    "SVSF": (95.0, 86.0, 92.0, 78.0),
    "SVSTPS": (75.0, 73.0, 75.0, 69.0),
    "SVSS": (65.0, 57.0, 65.0, 52.0),
}
# Table A2: single-step run time (µs).
TABLE_A2 = {"SVSF": 48.0, "SVSS lag 1": 72.0, "SVSS lag 2": 120.0, "SVSS lag 3": 180.0}

ATC_PSI, COMPLEX_PSI, GAMMA = [800.0, 800.0], [500.0, 600.0, 500.0, 600.0], 0.1


def _svsf(model: ts.models.LinearModel, psi: list[float], **kw: object) -> ts.SVSF:
    # The ATC rows run in the paper's H⁺ mode (Sec. 4.1) unless an artificial measurement is given.
    return ts.SVSF(model, psi=psi, gamma=GAMMA, **{"artificial": None, **kw})  # type: ignore[arg-type]


def table1_estimators(model: ts.models.LinearModel) -> dict[str, Estimator]:
    return {
        "KF": ts.KalmanFilter(model),
        "KS": ts.RTSSmoother(ts.KalmanFilter(model), lag=1),
        "RSTKF": ts.RobustStudentTKalmanFilter(model, scale_shapes="swapped"),
        "SVSF": _svsf(model, ATC_PSI),
        "SVSTPS": ts.RTSSmoother(_svsf(model, ATC_PSI), lag=1),
        "SVSS": ts.SVSS(_svsf(model, ATC_PSI), lag=1),
        "RSTKF (derived shapes)": ts.RobustStudentTKalmanFilter(model),
    }


def table3_estimators(model: ts.models.LinearModel, **artificial: bool) -> dict[str, Estimator]:
    fd = ts.FiniteDifferenceVelocity(**artificial)
    return {
        "KF": ts.KalmanFilter(model),
        "KS": ts.RTSSmoother(ts.KalmanFilter(model), lag=1),
        "SVSF": _svsf(model, COMPLEX_PSI, artificial=fd),
        "SVSTPS": ts.RTSSmoother(_svsf(model, COMPLEX_PSI, artificial=fd), lag=1),
        "SVSS": ts.SVSS(_svsf(model, COMPLEX_PSI, artificial=fd), lag=1),
    }


def run(est: Estimator, sc: Scenario, **kw: object) -> Tensor:
    """The estimate of every run, ``[B, T, n]``, without gradients."""
    with torch.no_grad():
        return est(sc.z, sc.x0, sc.P0, **kw).mean


def single_track_us_per_step(est: Estimator, sc: Scenario, repeats: int = 3) -> float:
    """Wall time per step of one track (the paper's "single step run time"), best of repeats."""
    best = float("inf")
    with torch.no_grad():
        est(sc.z[0, :10], sc.x0, sc.P0)  # warm-up
        for _ in range(repeats):
            start = time.perf_counter()
            est(sc.z[0], sc.x0, sc.P0)
            best = min(best, time.perf_counter() - start)
    return 1e6 * best / sc.z.shape[1]


def pct(ours: float, paper: float) -> str:
    return f"{100 * (ours / paper - 1):+.0f}%"


@dataclass
class Results:
    """Everything the report and the figures need."""

    runs: int
    table1: dict[str, tuple[float, float, float, float]] = field(default_factory=dict)
    table1_turns: dict[str, tuple[float, ...]] = field(default_factory=dict)
    table2: dict[float, tuple[float, float, float, float]] = field(default_factory=dict)
    lags: dict[str, tuple[float, float, float]] = field(default_factory=dict)
    table3: dict[str, tuple[float, float, float, float]] = field(default_factory=dict)
    table3_ablation: dict[str, tuple[float, ...]] = field(default_factory=dict)
    curves: dict[str, dict[str, Tensor]] = field(default_factory=dict)
    tracks: dict[str, dict[str, Tensor]] = field(default_factory=dict)
    seconds: float = 0.0


def reproduce(runs: int = 500, seed: int = 0, progress: bool = True) -> Results:
    """Runs every study of the paper; ``runs`` Monte Carlo runs each, seeded."""
    start = time.perf_counter()
    res = Results(runs)
    atc = atc_scenario(runs, torch.Generator().manual_seed(seed))
    cplx = complex_scenario(runs, torch.Generator().manual_seed(seed + 1))

    def do_table1() -> None:
        curves, track = {}, {"truth": atc.truth[0], "z": atc.z[0]}
        ests = table1_estimators(atc.model)
        for row in evaluate(ests, atc, progress=False):  # one timed batch run each
            single = single_track_us_per_step(ests[row.name], atc)
            x, y = row.rmse[0].item(), row.rmse[2].item()
            res.table1[row.name] = (x, y, single, row.us_per_track_step)
            curves[row.name] = rmse_over_time(row.mean, atc.truth)
            track[row.name] = row.mean[0]
        res.curves["atc"], res.tracks["atc"] = curves, track

    def do_turns() -> None:
        for directions in [(-1, 1), (-1, -1), (1, -1), (1, 1)]:
            sc = atc_scenario(runs, torch.Generator().manual_seed(seed), turn_directions=directions)
            svsf = accumulative_rmse(run(_svsf(sc.model, ATC_PSI), sc), sc.truth)
            svss = accumulative_rmse(run(ts.SVSS(_svsf(sc.model, ATC_PSI)), sc), sc.truth)
            wide = ts.SVSS(_svsf(sc.model, [3000.0, 3000.0]))
            with torch.no_grad():
                out = wide(sc.z, sc.x0, sc.P0)
            wide_svsf = accumulative_rmse(out.filtered.mean, sc.truth)
            wide_svss = accumulative_rmse(out.mean, sc.truth)
            label = "-".join("ccw" if d > 0 else "cw" for d in directions)
            res.table1_turns[label] = (
                svsf[0].item(),
                svsf[2].item(),
                svss[0].item(),
                svss[2].item(),
                wide_svsf[2].item(),
                wide_svss[2].item(),
            )

    def do_table2() -> None:
        svss = ts.SVSS(_svsf(atc.model, ATC_PSI))
        grid = [(p, p) for p in TABLE2]
        scores = psi_sweep(svss, atc.z, atc.x0, atc.P0, atc.truth, grid, accumulative_rmse)
        for p, (f, s) in zip(TABLE2, scores, strict=True):
            res.table2[p] = (f[0].item(), s[0].item(), f[2].item(), s[2].item())

    def do_lags() -> None:
        curves = {}
        ests: dict[str, Estimator] = {"SVSF": _svsf(atc.model, ATC_PSI)}
        ests.update({f"SVSS lag {L}": ts.SVSS(_svsf(atc.model, ATC_PSI), lag=L) for L in (1, 2, 3)})
        for row in evaluate(ests, atc, progress=False):
            single = single_track_us_per_step(ests[row.name], atc)
            res.lags[row.name] = (row.rmse[0].item(), row.rmse[2].item(), single)
            curves[row.name] = rmse_over_time(row.mean, atc.truth)
        res.curves["lags"] = curves

    def do_table3() -> None:
        curves, track = {}, {"truth": cplx.truth.mean(0)}
        for row in evaluate(table3_estimators(cplx.model), cplx, progress=False):
            res.table3[row.name] = tuple(row.rmse.tolist())  # type: ignore[assignment]
            curves[row.name] = rmse_over_time(row.mean, cplx.truth)
            track[row.name] = row.mean.mean(0)
        res.curves["complex"], res.tracks["complex"] = curves, track

    def do_table3_ablation() -> None:
        diag = table3_estimators(cplx.model, correlated=False)
        for name in ("SVSTPS", "SVSS"):
            rmse = accumulative_rmse(run(diag[name], cplx), cplx.truth)
            res.table3_ablation[f"{name}, diagonal artificial noise"] = tuple(rmse.tolist())
        fd = ts.FiniteDifferenceVelocity()
        for lag in (2, 3):
            est = ts.RTSSmoother(_svsf(cplx.model, COMPLEX_PSI, artificial=fd), lag=lag)
            rmse = accumulative_rmse(run(est, cplx), cplx.truth)
            res.table3_ablation[f"SVSTPS, lag {lag}"] = tuple(rmse.tolist())
        for directions in [(1, -1), (-1, 1), (1, 1), (-1, -1)]:
            sc = complex_scenario(
                runs, torch.Generator().manual_seed(seed + 1), turn_directions=directions
            )
            kf = accumulative_rmse(run(ts.KalmanFilter(sc.model), sc), sc.truth)
            label = "-".join("ccw" if d > 0 else "cw" for d in directions)
            res.table3_ablation[f"KF, turns {label}"] = tuple(kf.tolist())

    steps: list[tuple[str, Callable[[], None]]] = [
        ("Table 1 (ATC)", do_table1),
        ("turn directions", do_turns),
        ("Table 2 (ψ sweep)", do_table2),
        ("lags, Table A2", do_lags),
        ("Table 3 (complex)", do_table3),
        ("Table 3 ablations", do_table3_ablation),
    ]
    for _, step in tqdm(steps, desc="svss paper", disable=not progress):
        step()
    res.seconds = time.perf_counter() - start
    return res


def figures(res: Results, out: Path) -> list[str]:
    """Figs 4-9 of the paper as PNGs; returns the file names."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = []

    def save(fig: plt.Figure, name: str) -> None:
        names.append(save_figure(fig, out / name, dpi=110))

    tr = res.tracks["atc"]
    fig, ax = plt.subplots(figsize=(7, 5))
    ax.plot(tr["z"][:, 0], tr["z"][:, 1], ".", ms=2, color="0.7", label="measurements")
    for name, style in [("truth", "k-"), ("KF", "C0-"), ("SVSF", "C1-"), ("SVSS", "C2-")]:
        data = tr[name]
        ax.plot(data[:, 0], data[:, 2], style, lw=1.2 if name != "truth" else 2, label=name)
    ax.set(xlabel="x (m)", ylabel="y (m)", title="Fig 4: ATC position trajectory, one run")
    ax.legend()
    save(fig, "svss_fig4_trajectory.png")

    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for axis, (ax, label) in enumerate(zip(axes, ["x", "y"], strict=True)):
        for name in ["KF", "KS", "RSTKF", "SVSF", "SVSS"]:
            ax.plot(res.curves["atc"][name][:, 2 * axis], label=name)
        ax.set(xlabel="time (s)", ylabel=f"{label} position RMSE (m)", ylim=(0, 1200))
        ax.set_title(f"Fig 5{'ab'[axis]}: ATC position RMSE, {label}")
        ax.legend()
    save(fig, "svss_fig5_rmse.png")

    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    psis = list(TABLE2)
    for axis, (ax, label) in enumerate(zip(axes, ["x", "y"], strict=True)):
        for col, name in [(0, "SVSF"), (1, "SVSS")]:
            c = 2 * axis + col
            ax.plot(psis, [res.table2[p][c] for p in psis], "o-", label=f"{name} (torchsvs)")
            ax.plot(psis, [TABLE2[p][c] for p in psis], "x--", label=f"{name} (paper)")
        ax.set(xlabel="ψ (m)", ylabel=f"{label} accumulative RMSE (m)")
        ax.set_title(f"Fig 6: RMSE against boundary layer, {label}")
        ax.legend()
    save(fig, "svss_fig6_psi_sweep.png")

    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for axis, (ax, label) in enumerate(zip(axes, ["x", "y"], strict=True)):
        for name, curve in res.curves["lags"].items():
            ax.plot(curve[:, 2 * axis], label=name)
        ax.set(xlabel="time (s)", ylabel=f"{label} position RMSE (m)", ylim=(0, 400))
        ax.set_title(f"Fig 7{'ab'[axis]}: SVSS lags, {label}")
        ax.legend()
    save(fig, "svss_fig7_lags.png")

    tr = res.tracks["complex"]
    fig, ax = plt.subplots(figsize=(7, 5))
    for name in ["truth", "KF", "KS", "SVSF", "SVSTPS", "SVSS"]:
        ax.plot(tr[name][:, 0], tr[name][:, 2], lw=2 if name == "truth" else 1.2, label=name)
    ax.set(xlabel="x (m)", ylabel="y (m)", title="Fig 8: complex scenario, average trajectory")
    ax.legend()
    save(fig, "svss_fig8_complex_trajectory.png")

    fig, axes = plt.subplots(2, 2, figsize=(11, 7))
    panels = [
        (0, "x position (m)"),
        (2, "y position (m)"),
        (1, "x velocity (m/s)"),
        (3, "y velocity (m/s)"),
    ]
    for ax, (c, label) in zip(axes.flat, panels, strict=True):
        for name, curve in res.curves["complex"].items():
            ax.plot(curve[:, c], label=name)
        ax.set(xlabel="time (s)", ylabel=f"RMSE {label}", ylim=(0, 600 if c % 2 == 0 else 250))
        ax.legend(fontsize=7)
    fig.suptitle("Fig 9: complex scenario RMSE")
    save(fig, "svss_fig9_complex_rmse.png")
    return names


def report(res: Results, pngs: list[str]) -> str:
    """The results file: tables side by side, the prose of ``templates/svss_paper.md``."""
    t1 = res.table1
    rows1 = []
    for name, (x, y, single, batch) in t1.items():
        paper = TABLE1.get(name)
        if paper is None:
            rows1.append([name, x, "—", "", y, "—", "", single, "—", batch])
            continue
        rows1.append(
            [
                name,
                x,
                paper[0],
                pct(x, paper[0]),
                y,
                paper[1],
                pct(y, paper[1]),
                single,
                paper[2],
                batch,
            ]
        )
    rows2 = []
    for p, ours in res.table2.items():
        paper = TABLE2[p]
        rows2.append(
            [f"{p:.0f}"]
            + [f"{o:.0f} ({q:.0f}, {pct(o, q)})" for o, q in zip(ours, paper, strict=True)]
        )
    rows_lag = [[n, x, y, us, TABLE_A2[n]] for n, (x, y, us) in res.lags.items()]
    rows3 = []
    for name, ours in res.table3.items():
        paper = TABLE3[name]
        rows3.append(
            [name] + [f"{o:.0f} ({q:.0f}, {pct(o, q)})" for o, q in zip(ours, paper, strict=True)]
        )
    turns = [[k, *v] for k, v in res.table1_turns.items()]
    abl3 = [[k] + [f"{v:.0f}" for v in vals] for k, vals in res.table3_ablation.items()]

    big = []
    for name, (x, y, *_rest) in t1.items():
        if name in TABLE1 and name != "RSTKF (derived shapes)":
            for axis, (o, q) in enumerate([(x, TABLE1[name][0]), (y, TABLE1[name][1])]):
                if abs(o / q - 1) > 0.1:
                    big.append(f"Table 1 {name} {'xy'[axis]}: {o:.0f} vs {q:.0f} ({pct(o, q)})")
    for p, ours in res.table2.items():
        for c, (o, q) in enumerate(zip(ours, TABLE2[p], strict=True)):
            if abs(o / q - 1) > 0.1:
                label = ["SVSF x", "SVSS x", "SVSF y", "SVSS y"][c]
                big.append(f"Table 2 ψ={p:.0f} {label}: {o:.0f} vs {q:.0f} ({pct(o, q)})")
    for name, ours in res.table3.items():
        for c, (o, q) in enumerate(zip(ours, TABLE3[name], strict=True)):
            if abs(o / q - 1) > 0.1:
                label = ["x position", "x velocity", "y position", "y velocity"][c]
                big.append(f"Table 3 {name} {label}: {o:.0f} vs {q:.0f} ({pct(o, q)})")

    return (
        render(
            "svss_paper",
            "report",
            runs=res.runs,
            seconds=f"{res.seconds:.0f}",
            table1=markdown_table(
                [
                    "estimator",
                    "x",
                    "paper x",
                    "±",
                    "y",
                    "paper y",
                    "±",
                    "µs/step, 1 track",
                    "paper µs/step",
                    "µs/track-step, batch",
                ],
                rows1,
            ),
            table2=markdown_table(["ψ", "SVSF x", "SVSS x", "SVSF y", "SVSS y"], rows2),
            lags=markdown_table(
                ["estimator", "x RMSE (m)", "y RMSE (m)", "µs/step, 1 track", "paper µs/step"],
                rows_lag,
            ),
            table3=markdown_table(
                [
                    "estimator",
                    "x position (m)",
                    "x velocity (m/s)",
                    "y position (m)",
                    "y velocity (m/s)",
                ],
                rows3,
            ),
            orderings="\n".join(f"- {line}" for line in _orderings(res)),
            turns=markdown_table(
                [
                    "turns",
                    "SVSF x",
                    "SVSF y",
                    "SVSS x",
                    "SVSS y",
                    "SVSF y, ψ=3000",
                    "SVSS y, ψ=3000",
                ],
                turns,
            ),
            ablations=markdown_table(["variant", "x pos", "x vel", "y pos", "y vel"], abl3),
            differences="\n".join(f"- {b}" for b in big) or "- none",
        )
        + "\n"
    )


def _orderings(res: Results) -> list[str]:
    t1, t2, t3 = res.table1, res.table2, res.table3
    checks = []
    for axis, label in ((0, "x"), (1, "y")):
        v = {k: t1[k][axis] for k in ("KF", "KS", "RSTKF", "SVSF", "SVSS")}
        ok = (
            v["SVSS"] < v["SVSF"]
            and v["SVSS"] < v["RSTKF"]
            and max(v["SVSF"], v["RSTKF"]) < v["KS"] < v["KF"]
        )
        close = abs(v["SVSF"] / v["RSTKF"] - 1)
        checks.append(
            f"Table 1 {label}: SVSS {v['SVSS']:.0f} < SVSF {v['SVSF']:.0f} ≈ RSTKF {v['RSTKF']:.0f} "
            f"(differ by {100 * close:.0f}%) < KS {v['KS']:.0f} < KF {v['KF']:.0f}: {'holds' if ok else 'FAILS'}"
        )
    svss_below = all(s[1] < s[0] and s[3] < s[2] for s in t2.values())
    best = min(t2, key=lambda p: t2[p][0] + t2[p][2])
    checks.append(
        f"Table 2: SVSS < SVSF at every ψ: {'holds' if svss_below else 'FAILS'}; SVSF best at ψ = {best:.0f} m"
    )
    for c, label in ((0, "x"), (2, "y")):
        order = ["SVSS", "SVSTPS", "SVSF", "KS", "KF"]
        vals = [t3[k][c] for k in order]
        ok = all(a < b for a, b in zip(vals, vals[1:], strict=False))
        checks.append(
            f"Table 3 {label} position: "
            + " < ".join(f"{k} {v:.0f}" for k, v in zip(order, vals, strict=True))
            + f": {'holds' if ok else 'FAILS'}"
        )
    return checks


def main(argv: list[str] | None = None, out: Path = RESULTS) -> None:
    common.main(
        "svss_paper",
        __doc__,
        lambda args: reproduce(args.runs, args.seed),
        figures,
        report,
        runs=500,
        argv=argv,
        out=out,
    )


if __name__ == "__main__":
    main()
