"""Gaussian log-densities and reparameterised Gaussian draws of particle clouds ``[B, N, n]``:
the pieces the particle filters' importance weights and proposals are made of."""

from __future__ import annotations

import torch
from torch import Tensor

from torchsvs.linalg import cholesky, gaussian_log_density, mask_covariance
from torchsvs.models.base import gaussian_noise


def log_normal(x: Tensor, mean: Tensor, L: Tensor) -> Tensor:
    """``log N(x; mean, L Lᵀ)`` up to ``−(n/2) log 2π``: ``[B, N]`` for ``x, mean [B, N, n]`` and
    ``L [B|1, n, n]`` or ``[n, n]``."""
    L = L if L.ndim == 3 else L.unsqueeze(0)
    return gaussian_log_density(x - mean, L.unsqueeze(1), 0.0)


def measurement_log_density(z: Tensor, mask: Tensor, predicted: Tensor, cov: Tensor) -> Tensor:
    """``log N(z; predicted_i, cov)`` over the observed components of ``z [B, m]`` (NaN filled,
    ``mask [B, m]``), per particle ``[B, N]`` for ``predicted [B, N, m]``, ``cov [B|1, m, m]``
    or ``[m, m]``."""
    L = cholesky(mask_covariance(cov, mask))  # identity where missing
    L = L if L.ndim == 3 else L.unsqueeze(0)
    observed = mask.unsqueeze(1)  # missing components: zero residual, unit variance
    residual = (z.unsqueeze(1) - predicted) * observed
    return gaussian_log_density(residual, L.unsqueeze(1), mask.sum(-1, keepdim=True).to(z.dtype))


def gaussian_draws(mean: Tensor, cov: Tensor, count: int, gen: torch.Generator) -> Tensor:
    """``count`` reparameterised draws per track from ``N(mean [B, n], cov [B|1, n, n])``."""
    return mean.unsqueeze(1) + gaussian_noise(cov, (mean.shape[0], count), gen)
