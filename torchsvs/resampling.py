"""Resampling schemes for particle filters, as pure functions of log-weights.

Every scheme takes normalised log-weights ``[B, N]`` and a ``torch.Generator`` and returns
ancestor indices ``[B, N]``; each is unbiased: the expected number of copies of particle ``i``
is ``N·w_i``. No global random state is touched.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Literal

import torch
from torch import Tensor


def _from_positions(log_weights: Tensor, positions: Tensor) -> Tensor:
    """Inverts the weights' CDF at sorted ``positions`` in [0, 1), ``[B, N]``."""
    cdf = torch.cumsum(log_weights.exp(), dim=-1)
    cdf = cdf / cdf[..., -1:]  # exact 1 at the end despite rounding
    index = torch.searchsorted(cdf.contiguous(), positions.contiguous(), right=True)
    return index.clamp(max=log_weights.shape[-1] - 1)


def multinomial(log_weights: Tensor, generator: torch.Generator | None = None) -> Tensor:
    """``N`` independent draws from the weights."""
    weights = log_weights.exp()
    return torch.multinomial(weights, weights.shape[-1], replacement=True, generator=generator)


def stratified(log_weights: Tensor, generator: torch.Generator | None = None) -> Tensor:
    """One uniform draw in each of the ``N`` strata ``[i/N, (i+1)/N)``."""
    B, N = log_weights.shape
    u = torch.rand(B, N, generator=generator, dtype=log_weights.dtype)
    positions = (torch.arange(N, dtype=log_weights.dtype) + u) / N
    return _from_positions(log_weights, positions)


def systematic(log_weights: Tensor, generator: torch.Generator | None = None) -> Tensor:
    """One uniform offset shared by the ``N`` equally spaced positions."""
    B, N = log_weights.shape
    u = torch.rand(B, 1, generator=generator, dtype=log_weights.dtype)
    positions = (torch.arange(N, dtype=log_weights.dtype) + u) / N
    return _from_positions(log_weights, positions)


#: A resampling scheme's name.
Scheme = Literal["multinomial", "stratified", "systematic"]
SCHEMES: dict[Scheme, Callable[[Tensor, torch.Generator | None], Tensor]] = {
    "multinomial": multinomial,
    "stratified": stratified,
    "systematic": systematic,
}
