"""An estimator's run on tracks with priors, without gradients (:func:`run_result`,
:func:`run_estimator`): what :mod:`torchsvs.estimating`, the error estimate's references
(:mod:`torchsvs.error_references`) and the experiments call."""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor, nn

from torchsvs.datasets import RecordedTracks
from torchsvs.filters import ParticleFilter


def run_result(
    estimator: nn.Module,
    tracks: RecordedTracks,
    generator: torch.Generator | None = None,
    keep: str = "all",
) -> Any:
    """An estimator's result on tracks with priors (no gradients; ``keep`` as every estimator
    takes it)."""
    assert tracks.x0 is not None and tracks.P0 is not None
    kwargs: dict[str, Any] = {"dt": tracks.dt, "keep": keep}
    if isinstance(estimator, ParticleFilter):
        kwargs["generator"] = (
            generator if generator is not None else torch.Generator().manual_seed(0)
        )
    with torch.no_grad():
        return estimator(tracks.z, tracks.x0, tracks.P0, **kwargs)


def run_estimator(
    estimator: nn.Module, tracks: RecordedTracks, generator: torch.Generator | None = None
) -> tuple[Tensor, Tensor]:
    """Mean ``[B, T, 2m]`` and covariance of an estimator on tracks with priors (no gradients)."""
    out = run_result(estimator, tracks, generator)
    return out.mean, out.cov
