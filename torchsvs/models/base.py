"""The interface every state-space model offers to the estimators.

A model says what the system is: ``x_t = f(x_{t-1}) + w_t``, ``z_t = h(x_t) + v_t`` with
``w_t ~ N(0, Q_t)`` and ``v_t ~ N(0, R)`` (Eqs. (1)-(2), Gadsden et al. 2012); a linear model
has ``f(x) = F x``, ``h(x) = H x`` (Eq. (1), Chen et al. 2020). It never imports an estimator.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn
from torch.func import jacrev, vmap


class StateSpaceModel(nn.Module):
    """Base class of all models: ``f``, ``h``, their Jacobians, ``Q`` and ``R``.

    ``f`` and ``h`` act on states ``[..., n]`` (batch first). ``dt`` is ``None`` (the model's own
    interval), a 0-d tensor, or a per-track tensor ``[B]`` at one step (``[B, T]`` when asking
    for matrices of a whole run). Jacobians default to autograd (``torch.func.jacrev`` under
    ``vmap``); a model may supply its own.
    """

    state_dim: int
    meas_dim: int
    #: whether ``dt`` changes the dynamics (motion models) or is meaningless (fixed matrices).
    uses_dt: bool = False
    #: size ``p`` of the control input ``u`` (0: the model takes none).
    input_dim: int = 0

    def f(self, x: Tensor, dt: Tensor | None = None, u: Tensor | None = None) -> Tensor:
        """The noise-free transition ``x_{t-1} ↦ x_t`` (input ``u [B, p]``), ``[B, n] → [B, n]``."""
        raise NotImplementedError

    def h(self, x: Tensor) -> Tensor:
        """The noise-free measurement ``x_t ↦ z_t``, ``[B, n] → [B, m]``."""
        raise NotImplementedError

    def f_jacobian(self, x: Tensor, dt: Tensor | None = None, u: Tensor | None = None) -> Tensor:
        """``∂f/∂x`` at each state, ``[B, n, n]`` (Eq. (3), Gadsden et al. 2012)."""
        per_track_dt = dt is not None and dt.ndim == 1

        def single(s: Tensor, d: Tensor | None, v: Tensor | None) -> Tensor:
            return self.f(s.unsqueeze(0), d, None if v is None else v.unsqueeze(0)).squeeze(0)

        in_dims = (0, 0 if per_track_dt else None, None if u is None else 0)
        return vmap(jacrev(single), in_dims=in_dims)(x, dt, u)

    def h_jacobian(self, x: Tensor) -> Tensor:
        """``∂h/∂x`` at each state, ``[B, m, n]`` (Eq. (4), Gadsden et al. 2012)."""
        return vmap(jacrev(lambda s: self.h(s.unsqueeze(0)).squeeze(0)))(x)

    def linearize(
        self, x: Tensor, dt: Tensor | None = None, u: Tensor | None = None
    ) -> tuple[Tensor, Tensor]:
        """``f(x)`` and ``F = ∂f/∂x`` at each state ``x [B, n]``: what a filter's prediction
        needs of the model (Eq. (3), Gadsden et al. 2012; for a linear model ``F x`` and ``F``)."""
        return self.f(x, dt, u), self.f_jacobian(x, dt, u)

    def linearize_h(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """``h(x)`` and ``H = ∂h/∂x`` at each state ``x [B, n]`` (Eq. (4), Gadsden et al. 2012;
        for a linear model ``H x`` and ``H``)."""
        return self.h(x), self.h_jacobian(x)

    def process_noise(self, dt: Tensor | None = None) -> Tensor:
        """``Q`` of shape ``[*dt.shape, n, n]`` (``[n, n]`` for ``dt=None``)."""
        raise NotImplementedError

    def meas_cov(self) -> Tensor:
        """``R`` of shape ``[m, m]``."""
        raise NotImplementedError


class LinearModel(StateSpaceModel):
    """Base class of linear models: subclasses define :meth:`transition`, :meth:`process_noise`,
    ``H`` and ``R``; ``f``, ``h`` and their Jacobians follow exactly.

    Matrices come back with the leading shape of ``dt`` (``[B, T, n, n]`` for per-step ``dt``).
    """

    def f(self, x: Tensor, dt: Tensor | None = None, u: Tensor | None = None) -> Tensor:
        F = self.transition(dt).to(x.dtype)
        return (F @ x.unsqueeze(-1)).squeeze(-1)

    def h(self, x: Tensor) -> Tensor:
        return x @ self.meas_matrix().to(x.dtype).mT

    def f_jacobian(self, x: Tensor, dt: Tensor | None = None, u: Tensor | None = None) -> Tensor:
        return self.transition(dt).to(x.dtype).expand(x.shape[0], -1, -1)

    def h_jacobian(self, x: Tensor) -> Tensor:
        return self.meas_matrix().to(x.dtype).expand(x.shape[0], -1, -1)

    def transition(self, dt: Tensor | None = None) -> Tensor:
        """``F`` of shape ``[*dt.shape, n, n]`` (``[n, n]`` for ``dt=None``)."""
        raise NotImplementedError

    def process_noise(self, dt: Tensor | None = None) -> Tensor:
        """``Q`` of shape ``[*dt.shape, n, n]`` (``[n, n]`` for ``dt=None``)."""
        raise NotImplementedError

    def meas_matrix(self) -> Tensor:
        """``H`` of shape ``[m, n]``."""
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
