"""Run estimators side by side on a scenario and tabulate accuracy and cost."""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any, NamedTuple, TypeVar

import torch
from torch import Tensor

from torchsvs.estimator import Estimator
from torchsvs.metrics import accumulative_rmse, entries

Score = TypeVar("Score")


class Evaluation(NamedTuple):
    """One estimator on one batch of tracks."""

    name: str
    rmse: Tensor  #: accumulative RMSE per scored state component, [k]
    us_per_track_step: float  #: wall time per track and step, microseconds
    mean: Tensor  #: the estimates, [B, T, n]
    result: Any  #: everything the estimator returned


def evaluate(
    estimators: Mapping[str, Estimator],
    data: Any,
    *,
    truth: Tensor | None = None,
    components: Sequence[int] | None = None,
    mask: Tensor | None = None,
    seed: int = 0,
    progress: bool = True,
) -> list[Evaluation]:
    """Runs each estimator once on the whole batch (no gradients, timed after a warm-up on two
    tracks) and scores it against truth (:func:`~torchsvs.metrics.accumulative_rmse`).

    Args:
        estimators: name → estimator (any torchsvs filter or smoother).
        data: a :class:`~torchsvs.scenarios.Scenario`, a training
            :class:`~torchsvs.training.TrackBatch`, :class:`~torchsvs.datasets.RecordedTracks`
            with a prior, or anything with ``z``, ``x0``, ``P0`` (per track or shared) and
            optionally ``dt`` (a per-step tensor; a float is the model's own interval), ``u``,
            ``truth`` and the steps to score (``scored`` or ``mask``, ``[B, T]``).
        truth, mask: replace ``data``'s (missing truth, NaN, is never scored).
        components: the state components ``truth`` holds, in its order (default: all).
        seed: every estimator gets ``torch.Generator().manual_seed(seed)`` (particle filters
            draw from it), so a rerun reproduces.
    """
    from tqdm.auto import tqdm

    z, x0, P0 = data.z, getattr(data, "x0", None), getattr(data, "P0", None)
    if x0 is None or P0 is None:
        raise ValueError(
            "data: expected a prior (x0, P0); recorded tracks get one from "
            "torchsvs.datasets.with_prior"
        )
    truth = truth if truth is not None else getattr(data, "truth", None)
    if truth is None:
        raise ValueError("truth: data has none; pass truth= to score the estimates")
    if mask is None:
        mask = getattr(data, "scored", None)
    if mask is None:
        mask = getattr(data, "mask", None)
    dt = getattr(data, "dt", None)
    options: dict[str, Any] = {
        "dt": dt if isinstance(dt, Tensor) else None,
        "u": getattr(data, "u", None),
    }
    B, T = z.shape[:2]
    index = list(components) if components is not None else None
    # Truth that is missing (NaN: padding, an unreported velocity) is not scored.
    scored = entries(truth, mask, known=True)

    def batch_of(value: Any, rows: slice) -> Any:
        return value[rows] if isinstance(value, Tensor) and value.ndim >= 2 else value

    def run(est: Estimator, rows: slice) -> Any:
        kwargs = {k: batch_of(v, rows) for k, v in options.items() if v is not None}
        prior = (x0[rows] if x0.ndim == 2 else x0, P0[rows] if P0.ndim == 3 else P0)
        generator = torch.Generator().manual_seed(seed)
        with torch.no_grad():
            return est(z[rows], *prior, generator=generator, **kwargs)

    rows = []
    for name, est in tqdm(estimators.items(), desc="estimators", disable=not progress, leave=False):
        run(est, slice(0, 2))  # one-off costs (kernel builds, caches) stay out of the timing
        start = time.perf_counter()
        out = run(est, slice(None))
        seconds = time.perf_counter() - start
        mean = out.mean if index is None else out.mean[..., index]
        if mean.shape != truth.shape:
            raise ValueError(
                f"truth: expected the estimates' shape {tuple(mean.shape)} (components= names "
                f"the state components truth holds), got {tuple(truth.shape)}"
            )
        rmse = accumulative_rmse(mean, truth, scored)
        rows.append(Evaluation(name, rmse, 1e6 * seconds / (B * T), out.mean, out))
    return rows


def save_figure(fig: Any, path: Path, dpi: int = 100) -> str:
    """A report's matplotlib figure laid out, written to ``path`` and closed; its file name."""
    import matplotlib.pyplot as plt

    fig.tight_layout()
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return path.name


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
