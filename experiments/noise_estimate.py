"""The noise levels read off the data (``torchsvs track`` without ``--meas-std``), measured.

Simulated kinds of track (seeded): aircraft that fly straight legs and coordinated turns of 3-6
deg/s at 100-250 m/s (1 s, 10 s and irregular 1-10 s scans), slow ships (1-10 m/s, 9 s scans,
gentle turns and speed changes), fast airliners at 60 s scans, a drone's 1 s GPS, tracks of the
nearly-constant-velocity model itself (known q), and the project's random maneuvers
(:func:`torchsvs.scenarios.maneuver.random_maneuvers`: turns and accelerations of up to 20 m/s²
one after the other) at 1, 5 and 10 s. For each kind and noise level: the measurement noise read
by the former estimator (three-point residuals, least squares; commit cf1845e) and by
:func:`torchsvs.datasets.estimate_noise`, with its standard error and how much dropping 1% of the
rows moves each; then the position RMSE of a Kalman smoother (RTS) with the former noise and q,
with the new noise and the SURE q of :func:`torchsvs.fitting.noise.smoother_q` (and its
likelihood q), with the best q of a grid scanned with the truth (and the true noise), and of the
raw measurements.

Run: ``python -m experiments.noise_estimate`` (writes ``experiments/results/noise_estimate.md``).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from experiments.common import RESULTS, render
from torchsvs.datasets import two_point_prior
from torchsvs.filters import KalmanFilter
from torchsvs.models import ConstantVelocity
from torchsvs.scenarios.maneuver import ManeuverRanges, random_maneuvers
from torchsvs.smoothers import RTSSmoother

GRID_STEP = 0.1  #: s, the fine grid the truth is integrated on


@dataclass(frozen=True)
class Kind:
    """A kind of track: its motion and its sampling."""

    name: str
    tracks: int
    duration: float  #: s per track
    speed: tuple[float, float]  #: m/s, drawn per track
    turn_rate: tuple[float, float]  #: deg/s, magnitude drawn per turn
    heading_change: tuple[float, float]  #: deg per turn
    leg: tuple[float, float]  #: s of straight flight between turns
    accel: float = 0.0  #: m/s², standard deviation of the speed changes (per leg)
    scan: float | None = 1.0  #: s; None: irregular intervals drawn from ``irregular``
    irregular: tuple[float, float] = (1.0, 10.0)
    cv_q: float | None = None  #: tracks of the CV model itself with this q (the rest unused)
    #: tracks of :func:`torchsvs.scenarios.maneuver.random_maneuvers` at ``scan`` (the rest
    #: unused): segments of constant velocity, turns (1-6 deg/s, some with angular
    #: acceleration) and accelerations of 2-20 m/s², one after the other
    scenario: bool = False


KINDS = {
    "turns 1 s": Kind("turns 1 s", 8, 900.0, (100, 250), (3, 6), (45, 180), (30, 120)),
    "turns 10 s": Kind(
        "turns 10 s", 8, 4000.0, (100, 250), (3, 6), (45, 180), (60, 400), scan=10.0
    ),
    "turns irregular": Kind(
        "turns irregular", 8, 3000.0, (100, 250), (3, 6), (45, 180), (60, 300), scan=None
    ),
    "ships 9 s": Kind(
        "ships 9 s", 8, 7200.0, (1, 10), (0.2, 2), (20, 120), (300, 1200), accel=0.01, scan=9.0
    ),
    "fast 60 s": Kind(
        "fast 60 s", 8, 4 * 3600.0, (200, 250), (0.5, 1.5), (10, 60), (900, 3600), scan=60.0
    ),
    "drone 1 s": Kind("drone 1 s", 8, 600.0, (2, 15), (5, 20), (30, 180), (5, 40), accel=0.5),
    "CV q=1, 1 s": Kind("CV q=1, 1 s", 8, 600.0, (0, 0), (0, 0), (0, 0), (0, 0), cv_q=1.0),
    "CV q=0.05, 1-10 s": Kind(
        "CV q=0.05, 1-10 s", 8, 3000.0, (0, 0), (0, 0), (0, 0), (0, 0), scan=None, cv_q=0.05
    ),
    "maneuvers 1 s": Kind(
        "maneuvers 1 s", 8, 1200.0, (0, 0), (0, 0), (0, 0), (10, 40), scan=1.0, scenario=True
    ),
    "maneuvers 5 s": Kind(
        "maneuvers 5 s", 8, 3000.0, (0, 0), (0, 0), (0, 0), (20, 80), scan=5.0, scenario=True
    ),
    "maneuvers 10 s": Kind(
        "maneuvers 10 s", 8, 3000.0, (0, 0), (0, 0), (0, 0), (20, 80), scan=10.0, scenario=True
    ),
}


def sample_times(kind: Kind, rng: np.random.Generator) -> np.ndarray:
    """Measurement times on the fine grid, from 0 to the kind's duration."""
    if kind.scan is not None:
        times = np.arange(0.0, kind.duration, kind.scan)
        return times + rng.uniform(0, kind.scan)  # a random phase
    lo, hi = kind.irregular
    gaps = rng.uniform(lo, hi, int(kind.duration / lo) + 2)
    times = np.cumsum(gaps)
    times = np.round(times[times < kind.duration] / GRID_STEP) * GRID_STEP
    return times


def fine_path(kind: Kind, rng: np.random.Generator) -> np.ndarray:
    """Positions ``[N, 2]`` on the fine grid: legs and coordinated turns, smooth speed changes."""
    steps = int(kind.duration / GRID_STEP) + 2
    rate = np.zeros(steps)
    accel = np.zeros(steps)
    k = 0
    while k < steps:
        leg = int(rng.uniform(*kind.leg) / GRID_STEP)
        accel[k : k + leg] = rng.normal(0, kind.accel) if kind.accel else 0.0
        k += leg
        omega = math.radians(rng.uniform(*kind.turn_rate)) * rng.choice([-1, 1])
        turn = int(math.radians(rng.uniform(*kind.heading_change)) / abs(omega) / GRID_STEP)
        rate[k : k + turn] = omega
        k += turn
    lo, hi = kind.speed
    speed = rng.uniform(lo, hi) + np.cumsum(accel) * GRID_STEP
    # Keep the speed inside the kind's range by reflection (a smooth enough path: the speed's
    # derivative jumps, as at the legs' ends).
    width = hi - lo
    speed = lo + np.abs((speed - lo + width) % (2 * width) - width)
    heading = rng.uniform(0, 2 * math.pi) + np.cumsum(rate) * GRID_STEP
    vel = speed[:, None] * np.stack([np.cos(heading), np.sin(heading)], -1)
    pos = np.concatenate([np.zeros((1, 2)), np.cumsum(0.5 * (vel[1:] + vel[:-1]), 0) * GRID_STEP])
    return pos


def cv_path(times: np.ndarray, q: float, rng: np.random.Generator) -> np.ndarray:
    """Positions ``[T, 2]`` of the CV model (white acceleration of density ``q``) at ``times``."""
    out = np.zeros((len(times), 2))
    x = np.zeros((2, 2))  # (axis, [position, velocity])
    x[:, 1] = rng.normal(0, 10, 2)
    last = times[0]
    for i, t in enumerate(times):
        h = t - last
        last = t
        if h > 0:
            cov = q * np.array([[h**3 / 3, h**2 / 2], [h**2 / 2, h]])
            chol = np.linalg.cholesky(cov)
            x = x @ np.array([[1.0, 0.0], [h, 1.0]]) + rng.standard_normal((2, 2)) @ chol.T
        out[i] = x[:, 0]
    return out


@dataclass
class Simulated:
    z: Tensor  #: [B, T, 2] float64, NaN padded
    dt: Tensor  #: [B, T]
    truth: Tensor  #: [B, T, 2]


def simulate(kind: Kind, sigma: float, seed: int) -> Simulated:
    """The kind's tracks with white Gaussian noise ``sigma`` per axis, padded."""
    if kind.scenario:
        assert kind.scan is not None
        ranges = ManeuverRanges(
            steps=round(kind.duration / kind.scan),
            dt=kind.scan,
            segment_duration=kind.leg,
            meas_std=(sigma, sigma),
        )
        batch = random_maneuvers(kind.tracks, ranges, torch.Generator().manual_seed(seed))
        dt = torch.full(batch.z.shape[:2], kind.scan, dtype=torch.float64)
        return Simulated(batch.z, dt, batch.truth[..., [0, 2]])
    rng = np.random.default_rng(seed)
    zs, ts, truths = [], [], []
    for _ in range(kind.tracks):
        times = sample_times(kind, rng)
        if kind.cv_q is not None:
            truth = cv_path(times, kind.cv_q, rng)
        else:
            path = fine_path(kind, rng)
            truth = path[np.round(times / GRID_STEP).astype(int)]
        zs.append(truth + rng.normal(0, sigma, truth.shape))
        ts.append(times)
        truths.append(truth)
    T = max(len(t) for t in ts)
    B = kind.tracks
    z = torch.full((B, T, 2), math.nan, dtype=torch.float64)
    truth_t = torch.full((B, T, 2), math.nan, dtype=torch.float64)
    dt = torch.ones(B, T, dtype=torch.float64)
    for b in range(B):
        n = len(ts[b])
        z[b, :n] = torch.from_numpy(zs[b])
        truth_t[b, :n] = torch.from_numpy(truths[b])
        gaps = np.diff(ts[b])
        dt[b, 1:n] = torch.from_numpy(gaps)
        dt[b, 0] = float(np.median(gaps))
        dt[b, n:] = float(np.median(gaps))
    return Simulated(z, dt, truth_t)


def drop_rows(sim: Simulated, fraction: float, seed: int) -> Simulated:
    """The tracks with a random ``fraction`` of their observed rows removed (NaN)."""
    gen = torch.Generator().manual_seed(seed)
    observed = ~torch.isnan(sim.z[..., 0])
    drop = (torch.rand(observed.shape, generator=gen, dtype=torch.float64) < fraction) & observed
    z = sim.z.clone()
    z[drop] = math.nan
    return Simulated(z, sim.dt, sim.truth)


def ks_rmse(sim: Simulated, meas_var: float, q: float) -> float:
    """2-D position RMSE of a Kalman smoother (RTS) with these noise levels."""
    model = ConstantVelocity(ndim=2, q=q, r=meas_var).double()
    smoother = RTSSmoother(KalmanFilter(model))
    prior = two_point_prior(sim.z, sim.dt, meas_var)
    with torch.no_grad():
        out = smoother(sim.z, prior.x0, prior.P0, dt=sim.dt, keep="mean")
    error = out.mean[..., [0, 2]] - sim.truth
    ok = ~torch.isnan(sim.z[..., 0])
    return float(error[ok].square().sum(-1).mean().sqrt())


def raw_rmse(sim: Simulated) -> float:
    ok = ~torch.isnan(sim.z[..., 0])
    return float((sim.z - sim.truth)[ok].square().sum(-1).mean().sqrt())


def best_grid_q(sim: Simulated, meas_var: float, points: int = 29) -> tuple[float, float]:
    """The q of a log grid (1e-6 to 1e3) with the lowest smoother RMSE, refined once."""
    grid = np.logspace(-6, 3, points)
    rmse = [ks_rmse(sim, meas_var, float(q)) for q in grid]
    i = int(np.argmin(rmse))
    lo, hi = grid[max(i - 1, 0)], grid[min(i + 1, points - 1)]
    fine = np.geomspace(lo, hi, 9)
    rmse_f = [ks_rmse(sim, meas_var, float(q)) for q in fine]
    j = int(np.argmin(rmse_f))
    return float(fine[j]), float(rmse_f[j])


def old_estimator() -> Callable[[Tensor, Tensor], Any]:
    """``estimate_noise`` as it was before the robust estimator (commit cf1845e)."""
    import subprocess

    source = subprocess.run(
        ["git", "show", "cf1845e:torchsvs/datasets/priors.py"],
        cwd=Path(__file__).resolve().parent,
        check=True,
        capture_output=True,
        text=True,
    ).stdout
    namespace: dict[str, Any] = {"__name__": "old_priors"}
    exec(compile(source, "old_priors.py", "exec"), namespace)
    return namespace["estimate_noise"]


def dropped_change(
    estimate: Callable[[Tensor, Tensor], Any], sim: Simulated, drops: int = 5
) -> float:
    """The largest relative change of σ̂ over ``drops`` draws of 1% of the rows removed."""
    base = float(estimate(sim.z, sim.dt).meas_var.sqrt().mean())
    changes = []
    for seed in range(drops):
        fewer = drop_rows(sim, 0.01, seed + 1)
        changes.append(abs(float(estimate(fewer.z, fewer.dt).meas_var.sqrt().mean()) / base - 1))
    return max(changes)


def kind_rows(sigmas: tuple[float, ...], seed: int = 0) -> tuple[list[list[object]], list[str]]:
    """One row per kind and noise level (see the module's docstring), and the timings."""
    from torchsvs.datasets import estimate_noise
    from torchsvs.fitting.noise import smoother_q

    old = old_estimator()
    rows: list[list[object]] = []
    timings = []
    for name, kind in KINDS.items():
        for sigma in sigmas:
            sim = simulate(kind, sigma, seed)
            rows_n = int((~torch.isnan(sim.z[..., 0])).sum())
            before = old(sim.z, sim.dt)
            start = time.perf_counter()
            noise = estimate_noise(sim.z, sim.dt)
            middle = time.perf_counter()
            sure = smoother_q(sim.z, sim.dt, noise.meas_var)
            end = time.perf_counter()
            nll = smoother_q(sim.z, sim.dt, noise.meas_var, criterion="nll")
            timings.append(f"{rows_n} rows: {middle - start:.2f} s + {end - middle:.2f} s")
            r_old, r_new = float(before.meas_var.mean()), float(noise.meas_var.mean())
            grid_q, grid_rmse = best_grid_q(sim, sigma**2)
            ks_old = ks_rmse(sim, r_old, before.q)
            ks_new = ks_rmse(sim, r_new, sure.q)
            ks_nll = ks_rmse(sim, r_new, nll.q)
            assert noise.meas_std_se is not None
            rows.append(
                [
                    name,
                    rows_n,
                    f"{sigma:g}",
                    f"{math.sqrt(r_old):.1f}",
                    f"{100 * dropped_change(old, sim):.1f}%",
                    f"{math.sqrt(r_new):.1f} ± {float(noise.meas_std_se.mean()):.1f}",
                    f"{100 * dropped_change(estimate_noise, sim):.1f}%",
                    f"{ks_old:.1f}",
                    f"{ks_new:.1f} ({ks_new / grid_rmse:.3f})",
                    f"{ks_nll:.1f} ({ks_nll / grid_rmse:.3f})",
                    f"{grid_rmse:.1f}",
                    f"{raw_rmse(sim):.1f}",
                    f"{before.q:.3g}",
                    f"{sure.q:.3g}",
                    f"{grid_q:.3g}",
                ]
            )
            print(" | ".join(str(c) for c in rows[-1]), flush=True)
    return rows, timings


def seed_rows(sigma: float, seeds: int) -> list[list[object]]:
    """Per kind over ``seeds`` seeds at noise ``sigma``: mean and spread of σ̂/σ, the mean
    standard error, how often ±2 standard errors cover σ, the worst seed; the former estimator's
    worst seed."""
    from torchsvs.datasets import estimate_noise

    old = old_estimator()
    rows: list[list[object]] = []
    for name, kind in KINDS.items():
        ratio: list[float] = []
        se: list[float] = []
        old_ratio: list[float] = []
        for seed in range(100, 100 + seeds):
            sim = simulate(kind, sigma, seed)
            noise = estimate_noise(sim.z, sim.dt)
            assert noise.meas_std_se is not None
            ratio += (noise.meas_var.sqrt() / sigma).tolist()
            se += (noise.meas_std_se / sigma).tolist()
            old_ratio += (old(sim.z, sim.dt).meas_var.sqrt() / sigma).tolist()
        r, e, o = np.array(ratio), np.array(se), np.array(old_ratio)
        worst = r[np.argmax(np.abs(r - 1))]
        old_worst = o[np.argmax(np.abs(o - 1))]
        rows.append(
            [
                name,
                f"{r.mean():.3f}",
                f"{r.std(ddof=1):.3f}",
                f"{e.mean():.3f}",
                f"{100 * np.mean(np.abs(r - 1) <= 2 * e):.0f}%",
                f"{worst:.3f}",
                f"{old_worst:.3f}",
            ]
        )
        print(" | ".join(str(c) for c in rows[-1]), flush=True)
    return rows


def report(
    rows: list[list[object]], timings: list[str], spread: list[list[object]], seeds: int
) -> str:
    """The results file: the prose of ``templates/noise_estimate.md`` around the tables."""
    from torchsvs.evaluation import markdown_table

    kinds = markdown_table(
        [
            "kind",
            "rows",
            "σ",
            "former σ̂",
            "former: drop 1%",
            "new σ̂ ± se",
            "new: drop 1%",
            "KS former",
            "KS new (SURE q)",
            "KS new (likelihood q)",
            "KS best grid q",
            "raw",
            "former q",
            "SURE q",
            "grid q",
        ],
        rows,
    )
    spread_table = markdown_table(
        [
            "kind",
            "mean σ̂/σ",
            "sd",
            "mean se/σ",
            "σ within ±2 se",
            "worst σ̂/σ",
            "former: worst σ̂/σ",
        ],
        spread,
    )
    return render(
        "noise_estimate",
        "report",
        kinds=kinds,
        timings="; ".join(timings),
        seeds=seeds,
        spread=spread_table,
    )


def main(out: Path = RESULTS) -> None:
    torch.set_num_threads(1)
    sigmas = (10.0, 50.0, 200.0)
    rows, timings = kind_rows(sigmas)
    seeds = 20
    spread = seed_rows(50.0, seeds)
    path = out / "noise_estimate.md"
    path.write_text(report(rows, timings, spread, seeds))
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
