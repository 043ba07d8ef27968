"""The one-track convention of the separate-modeling blocks: a tensor with or without its
batch axis."""

from __future__ import annotations

from torch import Tensor


def batched(x: Tensor, name: str, rank: int) -> tuple[Tensor, bool]:
    """``x`` with a batch axis (added for one track of rank ``rank - 1``) and whether added."""
    if not isinstance(x, Tensor):
        raise TypeError(f"{name}: expected a tensor, got {type(x).__name__}")
    if not x.is_floating_point():
        raise TypeError(f"{name}: expected a floating-point tensor, got {x.dtype}")
    if x.ndim == rank - 1:
        return x.unsqueeze(0), True
    if x.ndim != rank:
        raise ValueError(
            f"{name}: expected rank {rank} (or {rank - 1} for one track), got {x.ndim}"
        )
    return x, False
