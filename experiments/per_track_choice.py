"""Choosing the model per track: the Kalman smoother or the IMM smoother, track by track.

``auto`` chooses one estimator for a whole file. On the benchmark's sets (issue 29, point 3:
the best estimator at 0.90x the self-tuned Kalman smoother on average), this measures how much
a per-track choice could add and how much of it a truth-free rule finds:

* **per file**: the better of the two over the file, by the truth;
* **per-track oracle**: each track's better one, by the truth (the room);
* **truth-free**: the file's choice by its SURE (the difference beyond :data:`FILE_MARGIN`
  standard errors, paired chunk by chunk), then a track switched to the other where its own
  SURE difference is beyond ``margin`` standard errors (:data:`MARGIN`; a track of one chunk
  has no error to judge by and keeps the file's).

Both run as ``torchsvs track`` runs them (:func:`~torchsvs.track_table.estimate_block` with
the plan read off the set, the IMM with the smoother's noise so their SUREs pair). Not a
product feature: a prototype whose numbers say whether one is worth building.

    python -m experiments.per_track_choice [--kinds own,scan10] [--margin 3]
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np
import pandas as pd
import torch

from experiments.recorded_sets import DEFAULT_KINDS, BenchSet, build_sets, run_as_track
from experiments.vehicle_sets import VEHICLES
from torchsvs.accuracy import RiskTerms
from torchsvs.recipes import Settings

RESULTS = Path(__file__).parent / "results"
#: A track leaves the file's choice where its SURE difference is beyond this many standard
#: errors of its chunks (at 2 the benchmark's scan1 σ50 switched tracks wrongly: 1.015x).
MARGIN = 3.0
#: The file's own choice: its SURE difference beyond this many standard errors.
FILE_MARGIN = 2.0


@dataclass
class Passes:
    """One estimator's run on a set: its SURE terms and each track's squared errors by the
    truth."""

    ids: list[str]
    terms: RiskTerms  #: SURE's sums per chunk (the chunks' ``track``: an index into ``ids``)
    truth_sq: pd.Series  #: per track id: the squared 2-D errors' sum by the truth (m²)


def run(bench: BenchSet, settings: Settings) -> tuple[Passes, list[float]]:
    """``settings``' estimator on the set as ``torchsvs track`` runs it: its passes and the
    noise variances it used."""
    found = run_as_track(bench, settings)
    both = bench.truth.rows.merge(found.table, on=["track_id", "time"], suffixes=("", "_e"))
    assert len(both) == len(bench.truth.rows), "every row estimated"
    square = (both["x_e"] - both["x"]) ** 2 + (both["y_e"] - both["y"]) ** 2
    passes = Passes(found.ids, found.terms, square.groupby(both["track_id"]).sum())
    return passes, found.meas_var


def paired(
    ks: Passes, imm: Passes, meas_var: list[float]
) -> tuple[tuple[float, float], np.ndarray, np.ndarray]:
    """The file's and each track's estimated MSE per point of the smoother less the IMM's
    (positive: the IMM lower) with standard errors, paired chunk by chunk
    (:meth:`~torchsvs.accuracy.RiskTerms.difference`; NaN for a track of one chunk)."""
    whole = ks.terms.difference(imm.terms, meas_var)
    change, error = np.full(len(ks.ids), np.nan), np.full(len(ks.ids), np.nan)
    for b in range(len(ks.ids)):
        mine = ks.terms.track == b
        if mine.any():
            change[b], error[b] = ks.terms.select(mine).difference(imm.terms.select(mine), meas_var)
    return whole, change, error


def choose(
    whole: tuple[float, float], change: np.ndarray, error: np.ndarray, margin: float
) -> tuple[bool, np.ndarray]:
    """The file's choice (the IMM or not: its difference beyond :data:`FILE_MARGIN` standard
    errors) and ``[B]`` each track's (True: the IMM), the file's unless the track's own
    difference is beyond ``margin`` the other way (an unknown error: the file's)."""
    file_imm = bool(whole[0] > FILE_MARGIN * whole[1])
    with np.errstate(invalid="ignore"):
        if file_imm:
            return True, ~(-change > margin * error)
        return False, change > margin * error


class Choice(NamedTuple):
    """One set's numbers (RMSE ratios over the Kalman smoother's)."""

    set: str
    tracks: int
    ks: float  #: the Kalman smoother's RMSE (m)
    imm: float
    per_file: float  #: the better of the two over the file, by the truth
    oracle: float  #: each track's better one, by the truth
    file_imm: bool  #: the file's choice by its SURE
    switched: int  #: tracks the truth-free rule took away from the file's choice
    truth_free: float


def measure(bench: BenchSet, margin: float) -> Choice:
    """Both estimators on ``bench`` and the choices between them."""
    ks, meas_var = run(bench, Settings(estimator="ks"))
    imm, _ = run(bench, Settings(estimator="imm", meas_var=meas_var))
    if ks.ids != imm.ids:
        raise ValueError("ks, imm: not the same tracks")
    file_imm, pick = choose(*paired(ks, imm, meas_var), margin)
    a = ks.truth_sq.reindex(ks.ids).to_numpy()
    b = imm.truth_sq.reindex(ks.ids).to_numpy()
    rows = len(bench.truth.rows)

    def rmse(values: np.ndarray) -> float:
        return float(np.sqrt(values.sum() / rows))

    base = rmse(a)
    return Choice(
        bench.name,
        len(ks.ids),
        base,
        rmse(b) / base,
        min(1.0, rmse(b) / base),
        rmse(np.minimum(a, b)) / base,
        file_imm,
        int((pick != file_imm).sum()),
        rmse(np.where(pick, b, a)) / base,
    )


def report(found: list[Choice], margin: float, seconds: float, command: str) -> str:
    """The markdown table of every set's :class:`Choice` and their means."""

    def mean(key: str) -> float:
        return float(np.mean([getattr(f, key) for f in found]))

    lines = [
        "# Choosing the model per track: the Kalman smoother or the IMM smoother",
        "",
        f"Generated by `python -m experiments.per_track_choice{command}` in "
        f"{seconds / 60:.1f} min; every number below is printed by that run. The module's "
        "docstring says what each column is. Sets: the benchmark's (rows ~5,000, seed 0), "
        f"default mode; margin {margin:g} standard errors. Ratios are over the Kalman "
        "smoother's RMSE.",
        "",
        "| set | tracks | ks RMSE m | imm | per file (truth) | per-track oracle | file's "
        "choice (SURE) | tracks switched | truth-free per track |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for f in found:
        lines.append(
            f"| {f.set} | {f.tracks} | {f.ks:.2f} | {f.imm:.3f} | {f.per_file:.3f} "
            f"| {f.oracle:.3f} | {'imm' if f.file_imm else 'ks'} | {f.switched} "
            f"| {f.truth_free:.3f} |"
        )
    lines += [
        f"| **mean** | | | {mean('imm'):.4f} | {mean('per_file'):.4f} | "
        f"{mean('oracle'):.4f} | | | {mean('truth_free'):.4f} |",
        "",
    ]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    every = ",".join([*DEFAULT_KINDS, *VEHICLES])
    parser.add_argument("--kinds", default=every, help="kinds of track (comma-separated)")
    parser.add_argument("--rows", type=int, default=5000, help="rows per set (about)")
    parser.add_argument("--margin", type=float, default=MARGIN, help="standard errors")
    parser.add_argument("--out", default=str(RESULTS / "per_track_choice.md"))
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    from tqdm.auto import tqdm

    start = time.perf_counter()
    sets = build_sets(args.kinds.split(","), rows=args.rows, seed=0)
    found = [measure(b, args.margin) for b in tqdm(sets, desc="sets")]
    given = sys.argv[1:] if argv is None else argv
    command = "".join(f" {a}" for a in given)
    text = report(found, args.margin, time.perf_counter() - start, command)
    Path(args.out).write_text(text, encoding="utf-8")
    print(text)


if __name__ == "__main__":
    main()
