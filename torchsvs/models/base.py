"""The interface every linear(ised) state-space model offers to the estimators.

A model says what the system is: ``x_t = F_t x_{t-1} + w_t``, ``z_t = H x_t + v_t`` with
``w_t ~ N(0, Q_t)`` and ``v_t ~ N(0, R)`` (Eq. (1), Chen et al. 2020). It never imports an
estimator.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn


class LinearModel(nn.Module):
    """Base class: subclasses define :meth:`transition`, :meth:`process_noise`, ``H`` and ``R``.

    ``dt`` is ``None`` (the model's own interval), a 0-d tensor, or a tensor ``[B, T]`` of
    per-step intervals; matrices come back with the leading shape of ``dt``.
    """

    state_dim: int
    meas_dim: int
    #: whether ``dt`` changes F and Q (motion models) or is meaningless (fixed matrices).
    uses_dt: bool = False

    def transition(self, dt: Tensor | None = None) -> Tensor:
        """``F`` of shape ``[*dt.shape, n, n]`` (``[n, n]`` for ``dt=None``)."""
        raise NotImplementedError

    def process_noise(self, dt: Tensor | None = None) -> Tensor:
        """``Q`` of shape ``[*dt.shape, n, n]`` (``[n, n]`` for ``dt=None``)."""
        raise NotImplementedError

    def meas_matrix(self) -> Tensor:
        """``H`` of shape ``[m, n]``."""
        raise NotImplementedError

    def meas_cov(self) -> Tensor:
        """``R`` of shape ``[m, m]``."""
        raise NotImplementedError

    def sample(
        self,
        x0: Tensor,
        steps: int,
        generator: torch.Generator | None = None,
        process_noise: bool = True,
    ) -> tuple[Tensor, Tensor]:
        """Simulates ``steps`` steps from ``x0 [B, n]`` in its dtype.

        Returns truth ``[B, T, n]`` and measurements ``[B, T, m]``, with the model's own ``dt``;
        randomness comes only from ``generator``.
        """
        dtype = x0.dtype
        F, Q = self.transition().to(dtype), self.process_noise().to(dtype)
        H, R = self.meas_matrix().to(dtype), self.meas_cov().to(dtype)
        x = x0
        states = []
        for _ in range(steps):
            x = x @ F.mT
            if process_noise:
                x = x + _gaussian(Q, x.shape[:-1], generator)
            states.append(x)
        truth = torch.stack(states, dim=1)
        z = truth @ H.mT + _gaussian(R, truth.shape[:-1], generator)
        return truth, z


def _gaussian(cov: Tensor, batch_shape: torch.Size, generator: torch.Generator | None) -> Tensor:
    """Samples ``N(0, cov)`` of shape ``[*batch_shape, d]`` (``cov`` may be singular)."""
    eigval, eigvec = torch.linalg.eigh(cov)
    root = eigvec * eigval.clamp_min(0).sqrt().unsqueeze(-2)
    eps = torch.randn(
        *batch_shape, cov.shape[-1], generator=generator, dtype=cov.dtype, device=cov.device
    )
    return eps @ root.mT
