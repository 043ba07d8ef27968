"""Blending the Kalman and IMM smoothers: one weight per file, or one per track.

``auto`` blends its chosen candidate with the next best at one weight for the file, the one of
the least estimated MSE (:mod:`torchsvs.blending`). This measures, on the benchmark's sets,
whether a weight per track would add: each track's own least-SURE weight, shrunk toward the
file's by ``κ`` times the file's mean curvature per track (``κ = 0``: the track's own; ``∞``:
the file's), against the file's weight, the better of the two smoothers per file, and each
track's best weight by the truth (the room, on a grid of 21).

Both smoothers run as ``torchsvs track`` runs them (:func:`~torchsvs.track_table.estimate_block`
with the plan read off the set, the IMM with the smoother's noise, so their SUREs pair). No
guard of ``auto`` (:func:`~torchsvs.selection.compared`) is applied: this is the weight alone.
Not a product feature: a prototype whose numbers say whether one is worth building.

    python -m experiments.blend_weights [--kinds own,car]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import NamedTuple

import numpy as np
import pandas as pd
import torch

from experiments.recorded_sets import DEFAULT_KINDS, BenchSet, build_sets
from experiments.vehicle_sets import VEHICLES
from torchsvs.accuracy import RiskTerms
from torchsvs.datasets.tables import block_of
from torchsvs.recipes import Settings
from torchsvs.track_plan import plan_tracks
from torchsvs.track_table import estimate_block, new_run

RESULTS = Path(__file__).parent / "results"
#: The shrinkage strengths tried (∞: the file's weight).
KAPPAS = (0.0, 0.5, 1.0, 2.0, 4.0, np.inf)


class Run(NamedTuple):
    """One smoother on a set: its estimates by row and its SURE terms."""

    table: pd.DataFrame  #: track_id, time, x, vx, y, vy, outlier
    terms: RiskTerms  #: the chunks' ``track`` an index into ``ids``
    meas_var: list[float]
    ids: list[str]


def run(bench: BenchSet, settings: Settings) -> Run:
    data = bench.measurements
    plan = plan_tracks(data, settings)
    assert plan.settings.meas_var is not None
    block = block_of(data, plan.columns)
    found = estimate_block(block, plan, plan.estimator(), new_run(plan))
    terms = RiskTerms.concat(found.risk, len(plan.settings.meas_var))
    table = found.table(block, "float64").to_pandas()
    return Run(table, terms, list(plan.settings.meas_var), list(block.steps.ids))


def measure(bench: BenchSet) -> dict[str, float]:
    """Every rule's RMSE over the Kalman smoother's on ``bench``."""
    ks = run(bench, Settings(estimator="ks"))
    imm = run(bench, Settings(estimator="imm", meas_var=ks.meas_var))
    if ks.ids != imm.ids:
        raise ValueError("ks, imm: not the same tracks")
    rows = bench.measurements.merge(ks.table, on=["track_id", "time"], suffixes=("", "_k"))
    rows = rows.merge(imm.table, on=["track_id", "time"], suffixes=("", "_i"))
    rows = rows.merge(bench.truth.rows, on=["track_id", "time"], suffixes=("", "_t"))
    assert len(rows) == len(bench.measurements), "every row estimated"
    used = ~(rows["outlier"] | rows["outlier_i"])
    B = len(ks.ids)
    track = rows["track_id"].map({t: k for k, t in enumerate(ks.ids)}).to_numpy()
    counts = ks.terms.count.sum(axis=0)
    # each track's SURE of the blend, a quadratic in w: slope and curvature (blending's w*)
    slope, curvature = np.zeros(B), np.zeros(B)
    for i, axis in enumerate("xy"):
        ok = (used & rows[axis].notna()).to_numpy()
        z, g, f = (rows[axis + s].to_numpy() for s in ("", "_k", "_i"))
        inner = np.bincount(track[ok], ((z - g) * (f - g))[ok], B)
        spread = np.bincount(track[ok], ((f - g) ** 2)[ok], B)
        moved = np.bincount(imm.terms.track, imm.terms.divergence[:, i], B) - np.bincount(
            ks.terms.track, ks.terms.divergence[:, i], B
        )
        slope += (inner - ks.meas_var[i] * moved) / counts[i]
        curvature += spread / counts[i]
    w_file = float(np.clip(slope.sum() / curvature.sum(), 0.0, 1.0))

    def rmse(weights: np.ndarray) -> float:
        w = weights[track]
        ex = (1 - w) * rows["x_k"] + w * rows["x_i"] - rows["x_t"]
        ey = (1 - w) * rows["y_k"] + w * rows["y_i"] - rows["y_t"]
        return float(np.sqrt((ex**2 + ey**2).mean()))

    base = rmse(np.zeros(B))
    found = {"ks": base, "w_file": w_file, "imm": rmse(np.ones(B)) / base}
    found["better per file"] = min(1.0, found["imm"])
    scale = curvature.mean()
    for kappa in KAPPAS:
        if np.isinf(kappa):
            weights = np.full(B, w_file)
        else:
            own = slope + kappa * scale * w_file
            weights = np.clip(own / np.maximum(curvature + kappa * scale, 1e-300), 0.0, 1.0)
        found[f"κ {kappa:g}"] = rmse(weights) / base
    grid = np.linspace(0.0, 1.0, 21)
    best = np.zeros(B)
    for b in range(B):
        mine = track == b
        ex, ey = (tuple(rows[f"{a}{s}"].to_numpy()[mine] for s in ("_k", "_i", "_t")) for a in "xy")
        errors = [
            (((1 - v) * ex[0] + v * ex[1] - ex[2]) ** 2).sum()
            + (((1 - v) * ey[0] + v * ey[1] - ey[2]) ** 2).sum()
            for v in grid
        ]
        best[b] = grid[int(np.argmin(errors))]
    found["per track by the truth"] = rmse(best) / base
    return found


def report(found: dict[str, dict[str, float]], seconds: float, command: str) -> str:
    columns = ["imm", "better per file", *(f"κ {k:g}" for k in KAPPAS), "per track by the truth"]
    names = {"κ inf": "the file's w"}
    head = ["set", "ks RMSE m", "file's w", *(names.get(c, c) for c in columns)]
    lines = [
        "# Blending the Kalman and IMM smoothers: one weight per file, or one per track",
        "",
        f"Generated by `python -m experiments.blend_weights{command}` in {seconds / 60:.1f} min; "
        "every number below is printed by that run. The module's docstring says what each "
        "column is. Sets: the benchmark's (rows ~5,000, seed 0), default mode. Ratios are over "
        "the Kalman smoother's RMSE; κ: the shrinkage of each track's weight toward the file's.",
        "",
        "| " + " | ".join(head) + " |",
        "|" + "---|" * len(head),
    ]
    for name, f in found.items():
        cells = [name, f"{f['ks']:.2f}", f"{f['w_file']:.2f}", *(f"{f[c]:.4f}" for c in columns)]
        lines.append("| " + " | ".join(cells) + " |")
    for label, pick in (("mean", np.mean), ("worst", np.max)):
        cells = [
            f"**{label}**",
            "",
            "",
            *(f"{pick([f[c] for f in found.values()]):.4f}" for c in columns),
        ]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join([*lines, ""])


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    every = ",".join([*DEFAULT_KINDS, *VEHICLES])
    parser.add_argument("--kinds", default=every, help="kinds of track (comma-separated)")
    parser.add_argument("--rows", type=int, default=5000, help="rows per set (about)")
    parser.add_argument("--out", default=str(RESULTS / "blend_weights.md"))
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    from tqdm.auto import tqdm

    start = time.perf_counter()
    sets = build_sets(args.kinds.split(","), rows=args.rows, seed=0)
    found = {b.name: measure(b) for b in tqdm(sets, desc="sets")}
    given = sys.argv[1:] if argv is None else argv
    command = "".join(f" {a}" for a in given)
    text = report(found, time.perf_counter() - start, command)
    Path(args.out).write_text(text, encoding="utf-8")
    print(text)


if __name__ == "__main__":
    main()
