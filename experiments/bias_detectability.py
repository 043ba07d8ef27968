"""Can a sensor bias that comes and goes be found in the measurements alone? (issue 29, item 6)

The faults benchmark (``make recorded-faults``) adds to each track a bias of
:data:`~experiments.recorded_sets.BIAS_SIGMAS` σ in one direction over one stretch of
:data:`~experiments.recorded_sets.BIAS_SHARE` of its rows. That bias is most of every
estimator's error there (3σ over 20% of the rows: 1.34σ of RMSE), and no estimator removes it:
between its edges the biased stretch is a path as smooth as the truth, so only its two edges
(a jump of the measured position that no motion makes) give it away. This experiment measures
whether they do.

For every kind of recorded track at its noise levels (:func:`~experiments.recorded_sets.
build_sets`): the clean measurements (truth + noise), and the same with the benchmark's bias
alone, at known rows. At every boundary between two rows, a step test: a polynomial of degree
``d`` in time fitted to the ``w`` rows on each side (left and right free to differ in velocity
and acceleration: a turn's onset is not a step), both extrapolated to the boundary; the squared
length of their difference over its variance under the true σ (χ² with 2 degrees of freedom
where the polynomials hold). The paired test joins the stretch's two edges (the same bias on,
then off: its estimate's variance halves).

A detector flags a track where its largest statistic exceeds a threshold. The threshold is set
where 5% of the clean tracks would raise a false alarm (the 95th percentile of the clean tracks'
largest statistics), and the table gives the share of true bias edges (pairs) above it. The
truth's σ is given to the test; a detector working from the noise read off the data does no
better.

Run: ``python -m experiments.bias_detectability`` (writes
``experiments/results/bias_detectability.md``).
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pandas as pd

from experiments.common import RESULTS
from experiments.recorded_sets import (
    BIAS_SHARE,
    BIAS_SIGMAS,
    bias_stretch,
    build_sets,
    directions,
    set_seed,
)

#: Rows on each side of a boundary, and the polynomial degrees, of the step tests.
WINDOWS = (5, 10, 20, 40)
DEGREES = (1, 2)
#: Share of clean tracks a detector may flag: its threshold is the clean maxima's quantile.
FALSE_ALARMS = 0.05


def side_fits(
    t: np.ndarray, z: np.ndarray, w: int, degree: int, right: bool
) -> tuple[np.ndarray, np.ndarray]:
    """At every boundary ``k`` (between rows ``k - 1`` and ``k``, ``k = 1 … n - 1``), the
    least-squares polynomial of ``degree`` in time on the ``w`` rows before it (or from it,
    ``right``), extrapolated to the boundary's time: ``[n - 1, 2]`` positions and ``[n - 1]``
    their variance over σ² (NaN and ``inf`` where the side has too few rows)."""
    n = len(t)
    k = np.arange(1, n)
    span = np.arange(0, w) if right else np.arange(-w, 0)
    rows = k[:, None] + span[None, :]
    valid = (rows >= 0) & (rows < n)
    rows = np.clip(rows, 0, n - 1)
    boundary = 0.5 * (t[k - 1] + t[k])
    tau = t[rows] - boundary[:, None]
    scale = np.maximum(np.abs(np.where(valid, tau, 0.0)).max(1, keepdims=True), 1e-9)
    powers = (tau / scale)[..., None] ** np.arange(degree + 1)  # [K, w, d+1]
    weights = valid.astype(float)
    gram = np.einsum("kw,kwi,kwj->kij", weights, powers, powers)
    moments = np.einsum("kw,kwi,kwc->kic", weights, powers, z[rows])
    enough = valid.sum(1) >= degree + 2
    gram[~enough] = np.eye(degree + 1)
    inverse = np.linalg.inv(gram)
    value = np.where(enough[:, None], np.einsum("ki,kic->kc", inverse[:, 0, :], moments), np.nan)
    variance = np.where(enough, inverse[:, 0, 0], np.inf)
    return value, variance


def steps(
    t: np.ndarray, z: np.ndarray, sigma: float, w: int, degree: int
) -> tuple[np.ndarray, np.ndarray]:
    """Every boundary's step ``[n - 1, 2]`` (right minus left) and its variance ``[n - 1]``
    (m²)."""
    left, v_left = side_fits(t, z, w, degree, right=False)
    right, v_right = side_fits(t, z, w, degree, right=True)
    return right - left, sigma**2 * (v_left + v_right)


def single(step: np.ndarray, variance: np.ndarray) -> np.ndarray:
    """The step test's statistic at every boundary (0 where a side has too few rows)."""
    stat = (step**2).sum(1) / variance
    return np.where(np.isfinite(stat), stat, 0.0)


def paired(step: np.ndarray, variance: np.ndarray, w: int) -> np.ndarray:
    """``[K, K]`` the paired statistic of a bias on at boundary ``i`` and off at ``j > i + w``
    (0 elsewhere): the bias from both steps (the second's sign turned), weighted by their
    variances."""
    inv = np.where(np.isfinite(variance), 1.0 / variance, 0.0)
    total = inv[:, None] + inv[None, :]
    weighted = np.nan_to_num(step) * inv[:, None]
    bias = (weighted[:, None, :] - weighted[None, :, :]) / np.maximum(total, 1e-300)[..., None]
    stat = (bias**2).sum(-1) * total
    i, j = np.indices(stat.shape)
    return np.where((j > i + w) & (inv[:, None] > 0) & (inv[None, :] > 0), stat, 0.0)


def study(rows: int, seed: int, kinds: Sequence[str] | None) -> pd.DataFrame:
    """One row per set × window × degree: thresholds and detection shares."""
    from tqdm.auto import tqdm

    out = []
    sets = build_sets(kinds, rows=rows, seed=seed, progress=True)
    for bench in tqdm(sets, desc="sets", leave=False):
        rng = np.random.default_rng(set_seed(seed, bench.kind.name, -bench.sigma))
        tracks = []
        for _, g in bench.measurements.groupby("track_id", sort=False):
            t = g["time"].to_numpy(float)
            z = g[["x", "y"]].to_numpy(float)
            first, end = bias_stretch(len(t), rng)
            biased = z.copy()
            biased[first:end] += BIAS_SIGMAS * bench.sigma * directions(rng, 1)[0]
            tracks.append((t, z, biased, first, end))
        for w in WINDOWS:
            for degree in DEGREES:
                clean_single, clean_pair, edges, pairs = [], [], [], []
                for t, z, biased, first, end in tracks:
                    step, var = steps(t, z, bench.sigma, w, degree)
                    clean_single.append(single(step, var).max(initial=0.0))
                    clean_pair.append(paired(step, var, w).max(initial=0.0))
                    step, var = steps(t, biased, bench.sigma, w, degree)
                    stat = single(step, var)
                    # boundary k sits at index k - 1; an edge at the track's end is none
                    inside = [k for k in (first, end) if 0 < k < len(t)]
                    edges += [stat[k - 1] for k in inside]
                    if len(inside) == 2 and end - first > w:  # windows apart
                        pairs.append(paired(step, var, w)[first - 1, end - 1])
                single_cut = float(np.quantile(clean_single, 1 - FALSE_ALARMS))
                pair_cut = float(np.quantile(clean_pair, 1 - FALSE_ALARMS))
                out.append(
                    dict(
                        set=f"{bench.kind.name} σ{bench.sigma:g}",
                        tracks=len(tracks),
                        w=w,
                        degree=degree,
                        null_median=float(np.median(clean_single)),
                        single_cut=single_cut,
                        edge_median=float(np.median(edges)) if edges else np.nan,
                        found=float(np.mean(np.asarray(edges) > single_cut)) if edges else np.nan,
                        pair_cut=pair_cut,
                        pair_median=float(np.median(pairs)) if pairs else np.nan,
                        pair_found=float(np.mean(np.asarray(pairs) > pair_cut))
                        if pairs
                        else np.nan,
                    )
                )
    return pd.DataFrame(out)


def best_per_set(table: pd.DataFrame) -> pd.DataFrame:
    """Per set, the window and degree that find the most bias stretches (paired test)."""
    score = table.assign(score=table[["found", "pair_found"]].max(axis=1))
    order = score.sort_values(["set", "score"], ascending=[True, False], kind="stable")
    return order.groupby("set", sort=False).head(1)


def report(table: pd.DataFrame, seconds: float, options: str) -> str:
    def fmt(x: float, digits: int = 1) -> str:
        return "—" if not np.isfinite(x) else f"{x:.{digits}f}"

    def share(x: float) -> str:
        return "—" if not np.isfinite(x) else f"{x:.0%}"

    lines = [
        "# A sensor bias that comes and goes: can the measurements show it?",
        "",
        "Generated by `python -m experiments.bias_detectability`; every number below is "
        "printed by that run.",
        "",
        f"Options: {options}. Took {seconds / 60:.1f} min. The test is NumPy alone (no "
        "torchsvs estimator runs).",
        "",
        f"Each track gets the faults benchmark's bias alone ({BIAS_SIGMAS:g} σ in one "
        f"direction over one stretch of {BIAS_SHARE:.0%} of its rows). The step test "
        "at a boundary fits a polynomial of degree d to the w rows on each side and compares "
        "their ends (χ² with 2 degrees of freedom under the true σ where the polynomials "
        "hold). Threshold: the clean tracks' largest statistics' "
        f"{1 - FALSE_ALARMS:.0%} quantile (a false alarm on {FALSE_ALARMS:.0%} of the tracks "
        "with no bias). The paired test needs the stretch longer than w rows. Found: the share of the bias's edges (single) or on-off pairs "
        "(paired) above it.",
        "",
        "## The best window per set",
        "",
        "| set | tracks | w | d | clean median of the max | threshold | edge median | found | "
        "paired threshold | pair median | pairs found |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in best_per_set(table).itertuples():
        lines.append(
            f"| {r.set} | {r.tracks} | {r.w} | {r.degree} | {fmt(r.null_median)} | "
            f"{fmt(r.single_cut)} | {fmt(r.edge_median)} | {r.found:.0%} | {fmt(r.pair_cut)} | "
            f"{fmt(r.pair_median)} | {share(r.pair_found)} |"
        )
    lines += [
        "",
        "## Every window and degree",
        "",
        "| set | w | d | threshold | edge median | found | paired threshold | pair median "
        "| pairs found |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in table.itertuples():
        lines.append(
            f"| {r.set} | {r.w} | {r.degree} | {fmt(r.single_cut)} | {fmt(r.edge_median)} | "
            f"{r.found:.0%} | {fmt(r.pair_cut)} | {fmt(r.pair_median)} | {share(r.pair_found)} |"
        )
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--rows", type=int, default=5000, help="rows per set (default 5000)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--kinds", default=None, help="comma-separated kinds (default: all)")
    parser.add_argument("--out", type=Path, default=RESULTS / "bias_detectability.md")
    args = parser.parse_args(argv)
    kinds = None if args.kinds is None else args.kinds.split(",")
    tick = time.perf_counter()
    table = study(args.rows, args.seed, kinds)
    options = f"rows ~{args.rows:,} per set, seed {args.seed}"
    args.out.write_text(report(table, time.perf_counter() - tick, options))
    print(args.out.read_text())


if __name__ == "__main__":
    main()
