"""Figures of merit: every RMSE the library and its experiments report, in one place.

All take estimates and truth ``[B, T, n]`` and an optional ``mask`` of the entries to count:
``[B, T]`` (steps: the real steps of padded recorded tracks) or ``[B, T, n]`` (entries: e.g. a
reported velocity that is missing). The RMSEs of Chen et al. 2020 (Sec. 4) average squared
errors over runs and steps; the SPVSF paper's (Gadsden et al. 2012) averages per-run RMSEs.
"""

from __future__ import annotations

import torch
from torch import Tensor


def _squared_error(estimate: Tensor, truth: Tensor, mask: Tensor | None) -> tuple[Tensor, Tensor]:
    """Squared errors and the weights (1 counted, 0 not) of every entry, ``[B, T, n]``."""
    if estimate.shape != truth.shape:
        raise ValueError(
            f"estimate: expected the shape of truth {tuple(truth.shape)}, "
            f"got {tuple(estimate.shape)}"
        )
    if mask is None:
        return (estimate - truth).square(), torch.ones_like(truth)
    mask = entries(truth, mask)
    weight = mask.to(truth.dtype)
    # Entries not counted may hold NaN (padding, missing truth): zero them, not multiply.
    error = torch.where(mask, estimate - truth, torch.zeros_like(truth)).square()
    return error, weight


def entries(truth: Tensor, mask: Tensor | None = None, known: bool = False) -> Tensor:
    """The counted entries ``[B, T, n]`` of ``mask`` (``[B, T]`` steps or ``[B, T, n]``
    entries; ``None``: all); ``known`` also leaves out missing truth (NaN)."""
    if mask is None:
        counted = torch.ones_like(truth, dtype=torch.bool)
    else:
        if mask.shape == truth.shape[:-1]:
            mask = mask.unsqueeze(-1)
        if (
            mask.dtype != torch.bool
            or mask.shape[:-1] != truth.shape[:-1]
            or (mask.shape[-1] not in (1, truth.shape[-1]))
        ):
            raise ValueError(
                f"mask: expected a bool tensor of shape {tuple(truth.shape[:-1])} (steps) or "
                f"{tuple(truth.shape)} (entries), got {mask.dtype} {tuple(mask.shape)}"
            )
        counted = mask.expand_as(truth)
    return counted & torch.isfinite(truth) if known else counted


def _rms(error: Tensor, weight: Tensor, dim: int | tuple[int, ...]) -> Tensor:
    return (error.sum(dim) / weight.sum(dim)).sqrt()


def rmse_over_time(estimate: Tensor, truth: Tensor, mask: Tensor | None = None) -> Tensor:
    """RMSE at each step over the runs: ``sqrt(mean_b err²)``, ``[B, T, n] → [T, n]``."""
    return _rms(*_squared_error(estimate, truth, mask), dim=0)


def accumulative_rmse(estimate: Tensor, truth: Tensor, mask: Tensor | None = None) -> Tensor:
    """The "accumulative RMSE" of Chen et al. 2020: ``sqrt`` of the mean squared error over all
    runs and all steps, per state component, ``[B, T, n] → [n]``."""
    return _rms(*_squared_error(estimate, truth, mask), dim=(0, 1))


def mean_squared_error(estimate: Tensor, truth: Tensor, mask: Tensor | None = None) -> Tensor:
    """The mean squared error over runs, steps and components, 0-d (0 when nothing is counted):
    differentiable, the supervised training loss."""
    error, weight = _squared_error(estimate, truth, mask)
    return error.sum() / weight.sum().clamp_min(1.0)


def pooled_rmse(estimate: Tensor, truth: Tensor, mask: Tensor | None = None) -> Tensor:
    """``sqrt`` of :func:`mean_squared_error` (e.g. position RMSE "per axis" over both axes:
    ``pooled_rmse(mean[..., [0, 2]], truth[..., [0, 2]])``), 0-d."""
    return mean_squared_error(estimate, truth, mask).sqrt()


def run_rmse(
    estimate: Tensor,
    truth: Tensor,
    mask: Tensor | None = None,
    initial: tuple[Tensor, Tensor] | None = None,
) -> Tensor:
    """RMSE of each run over its steps, per component, ``[B, T, n] → [B, n]``; with
    ``initial = (x̂0, x0)`` the prior's error counts as one more step (the SPVSF paper's
    tables include it)."""
    error, weight = _squared_error(estimate, truth, mask)
    if initial is not None:
        n = truth.shape[-1]
        first = (initial[0] - initial[1]).reshape(-1, 1, n).expand(truth.shape[0], 1, n)
        error = torch.cat([first.square(), error], dim=1)
        weight = torch.cat([torch.ones_like(first), weight], dim=1)
    return _rms(error, weight, dim=1)


def paper_rmse(
    estimate: Tensor,
    truth: Tensor,
    mask: Tensor | None = None,
    initial: tuple[Tensor, Tensor] | None = None,
) -> Tensor:
    """The SPVSF paper's RMSE (Gadsden et al. 2012, Tables 1-5): the per-run RMSE
    (:func:`run_rmse`) averaged over runs, ``[n]``."""
    return run_rmse(estimate, truth, mask, initial).mean(0)
