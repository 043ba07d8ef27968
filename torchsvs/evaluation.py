"""Run estimators side by side on a scenario and tabulate accuracy and cost."""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from typing import NamedTuple, TypeVar

import torch
from torch import Tensor

from torchsvs.estimator import Estimator
from torchsvs.metrics import accumulative_rmse
from torchsvs.scenarios.paper import Scenario

Score = TypeVar("Score")


class Evaluation(NamedTuple):
    """One estimator on one scenario."""

    name: str
    rmse: Tensor  #: accumulative RMSE per state component, [n]
    us_per_track_step: float  #: wall time per track and step, microseconds
    mean: Tensor  #: the estimates, [B, T, n]


def evaluate(
    estimators: Mapping[str, Estimator], scenario: Scenario, progress: bool = True
) -> list[Evaluation]:
    """Runs each estimator once on the whole batch (no gradients) and scores it against truth."""
    from tqdm.auto import tqdm

    rows = []
    B, T = scenario.z.shape[:2]
    for name, est in tqdm(estimators.items(), desc="estimators", disable=not progress, leave=False):
        with torch.no_grad():  # warm-up on two tracks, so one-off costs stay out of the timing
            est(scenario.z[:2], scenario.x0, scenario.P0)
        start = time.perf_counter()
        with torch.no_grad():
            out = est(scenario.z, scenario.x0, scenario.P0)
        seconds = time.perf_counter() - start
        rows.append(
            Evaluation(
                name, accumulative_rmse(out.mean, scenario.truth), 1e6 * seconds / (B * T), out.mean
            )
        )
    return rows


def markdown_table(header: Sequence[str], rows: Sequence[Sequence[object]]) -> str:
    """A GitHub markdown table; floats are printed with no decimals."""

    def cell(v: object) -> str:
        if isinstance(v, float):
            return f"{v:.0f}" if abs(v) >= 10 else f"{v:.2f}"
        return str(v)

    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(cell(v) for v in row) + " |" for row in rows]
    return "\n".join(lines)


def psi_sweep(
    smoother: Estimator,
    z: Tensor,
    x0: Tensor,
    P0: Tensor,
    truth: Tensor,
    grid: Sequence[Sequence[float]],
    score: Callable[[Tensor, Tensor], Score],
    max_tracks: int = 6000,
) -> list[tuple[Score, Score]]:
    """Scores an SVSF-based smoother at every boundary layer of ``grid`` in few large batches.

    Each ψ becomes a per-step override (``psi=`` of shape ``[B, T, m]``), so chunks of the grid
    run as one batch of ``len(chunk) × B`` tracks. Returns ``(score(filtered), score(smoothed))``
    per grid point, with ``score(mean [B, T, n], truth [B, T, n])``.
    """
    B, T = z.shape[:2]
    chunk = max(1, max_tracks // B)
    scores: list[tuple[Score, Score]] = []
    for start in range(0, len(grid), chunk):
        part = grid[start : start + chunk]
        psi = (
            torch.tensor(part, dtype=z.dtype).repeat_interleave(B, 0)[:, None, :].expand(-1, T, -1)
        )
        x0_all = x0.repeat(len(part), 1) if x0.ndim == 2 else x0
        with torch.no_grad():
            out = smoother(z.repeat(len(part), 1, 1), x0_all, P0, psi=psi)
        for i in range(len(part)):
            rows = slice(i * B, (i + 1) * B)
            scores.append((score(out.filtered.mean[rows], truth), score(out.mean[rows], truth)))
    return scores
