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

    # --- Simulation: the one place Gaussian trajectories are drawn. ---

    def propagate(
        self,
        x0: Tensor,
        steps: int,
        generator: torch.Generator | None = None,
        *,
        dt: Tensor | None = None,
        u: Tensor | None = None,
        cov: Tensor | None = None,
        noise_scale: float = 1.0,
    ) -> Tensor:
        """States ``x_t = f(x_{t-1}, dt_t, u_t) + w_t``, ``w_t ~ N(0, noise_scale² Q_t)`` (Eq. (1),
        Gadsden et al. 2012) from ``x0 [B, n]`` over ``steps`` steps: ``[B, T, n]`` in ``x0``'s
        dtype, randomness only from ``generator``.

        ``dt``: ``None``, 0-d or per step ``[B, T]``; ``u``: ``[B, T, p]``; ``cov``: the truth's
        process noise if it is not the model's ``Q`` (components of zero variance are not drawn;
        ``noise_scale=0`` draws nothing).
        """
        x = x0
        states = []
        for t in range(steps):
            dt_t = dt[:, t] if dt is not None and dt.ndim == 2 else dt
            x = self.f(x, dt_t, None if u is None else u[:, t])
            if noise_scale != 0.0:
                Q = self.process_noise(dt_t) if cov is None else cov
                x = x + gaussian_noise(Q.to(x.dtype), x.shape[:-1], generator, noise_scale)
            states.append(x)
        return torch.stack(states, dim=1)

    def observe(
        self,
        truth: Tensor,
        generator: torch.Generator | None = None,
        *,
        cov: Tensor | None = None,
        noise_scale: float = 1.0,
    ) -> Tensor:
        """Measurements ``z_t = h(x_t) + v_t``, ``v_t ~ N(0, noise_scale² R)`` (Eq. (2)) of
        ``truth [B, T, n]``: ``[B, T, m]``. ``cov``: the sensor's noise if it is not the model's
        ``R``, ``[m, m]`` or per track ``[B, m, m]``."""
        R = (self.meas_cov() if cov is None else cov).to(truth.dtype)
        noise = gaussian_noise(R, truth.shape[:-1], generator, noise_scale)
        return self.h(truth) + noise

    def simulate(
        self,
        x0: Tensor,
        steps: int,
        generator: torch.Generator | None = None,
        *,
        dt: Tensor | None = None,
        u: Tensor | None = None,
        process_noise: bool = True,
    ) -> tuple[Tensor, Tensor]:
        """Truth ``[B, T, n]`` (:meth:`propagate`) and its measurements ``[B, T, m]``
        (:meth:`observe`) from ``x0 [B, n]``, with the model's own ``Q`` and ``R``."""
        noise_scale = 1.0 if process_noise else 0.0
        truth = self.propagate(x0, steps, generator, dt=dt, u=u, noise_scale=noise_scale)
        return truth, self.observe(truth, generator)


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


def gaussian_noise(
    cov: Tensor,
    batch_shape: torch.Size | tuple[int, ...],
    generator: torch.Generator | None = None,
    scale: float = 1.0,
) -> Tensor:
    """Draws of ``N(0, scale² cov)`` of shape ``[*batch_shape, d]``: ``ε Lᵀ`` with ``L`` the
    Cholesky factor of ``cov``, ``[d, d]`` or one per leading index ``[*batch_shape[:-1], d, d]``
    (e.g. a covariance per track for ``batch_shape = (B, T)``). Components of zero variance in a
    ``[d, d]`` ``cov`` are not drawn (a parameter without process noise), so ``cov`` may be
    singular there; a singular ``cov`` of another kind (a noise entering through a gain of
    lower rank, as the coordinated turn's) is factored by :func:`noise_factor`."""
    d = cov.shape[-1]
    if cov.ndim == 2:
        active = cov.diagonal() > 0
        if not bool(active.all()):
            L = scale * noise_factor(cov[active][:, active])
            eps = torch.randn(
                *batch_shape, L.shape[-1], generator=generator, dtype=cov.dtype, device=cov.device
            )
            noise = torch.zeros(*batch_shape, d, dtype=cov.dtype, device=cov.device)
            noise[..., active] = eps @ L.mT
            return noise
    L = noise_factor(cov)
    if scale != 1.0:
        L = scale * L
    eps = torch.randn(*batch_shape, d, generator=generator, dtype=cov.dtype, device=cov.device)
    return eps @ L.mT


def noise_factor(cov: Tensor) -> Tensor:
    """A factor ``L`` with ``L Lᵀ = cov`` for drawing noise: the Cholesky factor of a positive
    definite ``cov`` (so draws are those of ``torch.linalg.cholesky``), else ``V diag(√λ)`` from
    the eigendecomposition of a positive semi-definite one (negative rounding clipped to 0)."""
    L, info = torch.linalg.cholesky_ex(cov)
    if not bool((info > 0).any()):
        return L
    values, vectors = torch.linalg.eigh(cov)
    root = vectors * values.clamp_min(0.0).sqrt().unsqueeze(-2)
    return torch.where((info > 0)[..., None, None], root, L)
