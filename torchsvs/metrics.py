"""Figures of merit of Chen et al. 2020 (Sec. 4): RMSE over runs, accumulated over time."""

from __future__ import annotations

from torch import Tensor


def _check(estimate: Tensor, truth: Tensor) -> None:
    if estimate.shape != truth.shape:
        raise ValueError(
            f"estimate: expected the shape of truth {tuple(truth.shape)}, "
            f"got {tuple(estimate.shape)}"
        )


def rmse_over_time(estimate: Tensor, truth: Tensor) -> Tensor:
    """RMSE at each step over the runs: ``sqrt(mean_b err²)``, ``[B, T, n] → [T, n]``."""
    _check(estimate, truth)
    return (estimate - truth).square().mean(dim=0).sqrt()


def accumulative_rmse(estimate: Tensor, truth: Tensor) -> Tensor:
    """The paper's "accumulative RMSE": ``sqrt`` of the mean squared error over all runs and all
    steps, per state component, ``[B, T, n] → [n]``."""
    _check(estimate, truth)
    return (estimate - truth).square().mean(dim=(0, 1)).sqrt()
