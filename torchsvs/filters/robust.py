"""The robust Student's t based Kalman filter (RSTKF) of Huang et al. 2017."""

from __future__ import annotations

import torch
from torch import Tensor

from torchsvs.estimator import Inputs
from torchsvs.filters.gaussian import (
    GaussianFilter,
    Observation,
    Step,
    innovation_covariance,
    kalman_update,
)
from torchsvs.linalg import mask_measurement, matvec, psd_solve, symmetrize
from torchsvs.models.base import LinearModel


def _trace_solve(S: Tensor, A: Tensor) -> Tensor:
    """``tr(S⁻¹ A)`` for SPD ``S``."""
    return psd_solve(S, A).diagonal(dim1=-2, dim2=-1).sum(-1)


class RobustStudentTKalmanFilter(GaussianFilter):
    r"""Robust Student's t based Kalman filter (RSTKF), Huang, Zhang, Li, Wu, Chambers 2017.

    Heavy-tailed process and measurement noise are modelled by Student's t distributions written
    as Gaussian scale mixtures, and the posterior is approximated by variational Bayes (VB).

    Model (hierarchical Gaussian form). With the Kalman prediction
    ``x̂_{k|k-1} = F x̂_{k-1|k-1}``, ``P_{k|k-1} = F P F^T + Q``:

    .. math::
        p(x_k \mid z_{1:k-1}) = \int N(x_k; \hat x_{k|k-1}, \Sigma_k/\xi_k)\,
            G(\xi_k; \tfrac{\omega}{2}, \tfrac{\omega}{2})\,
            IW(\Sigma_k; \hat u_k, \hat U_k)\, d\xi_k\, d\Sigma_k,

        p(z_k \mid x_k) = \int N(z_k; H x_k, R/\lambda_k)\,
            G(\lambda_k; \tfrac{\nu}{2}, \tfrac{\nu}{2})\, d\lambda_k,

    a Student's t prediction with ``ω`` degrees of freedom whose scale matrix ``Σ_k`` is itself
    uncertain around ``P_{k|k-1}`` (inverse Wishart with ``û = n + τ + 1``, ``Û = τ P_{k|k-1}``,
    so ``E[Σ_k] = P_{k|k-1}``; large ``τ`` trusts the nominal ``Q``), and a Student's t likelihood
    with ``ν`` degrees of freedom.

    VB fixed point, ``N`` iterations from ``x̂ = x̂_{k|k-1}``, ``P = P_{k|k-1}``,
    ``E[Σ⁻¹] = P_{k|k-1}^{-1}``:

    .. math::
        D = P + (\hat x - \hat x_{k|k-1})(\hat x - \hat x_{k|k-1})^T,\qquad
        E = (z - H\hat x)(z - H\hat x)^T + H P H^T

        E[\xi] = \frac{n + \omega}{\omega + \mathrm{tr}(D\,E[\Sigma^{-1}])},\qquad
        E[\lambda] = \frac{m + \nu}{\nu + \mathrm{tr}(E R^{-1})}

        q(\Sigma) = IW(\hat u + 1,\ \hat U + E[\xi] D),\qquad
        E[\Sigma^{-1}] \approx E[\Sigma]^{-1} = (\hat u + 1 - n - 1)\,(\hat U + E[\xi] D)^{-1}

        \tilde P = E[\Sigma^{-1}]^{-1} / E[\xi],\quad \tilde R = R / E[\lambda],\quad
        K = \tilde P H^T (H\tilde P H^T + \tilde R)^{-1},

        \hat x = \hat x_{k|k-1} + K(z - H\hat x_{k|k-1}),\quad
        P = (I - KH)\tilde P(I - KH)^T + K\tilde R K^T

    (the Joseph form keeps ``P`` positive definite in float32; it equals ``P̃ − KHP̃`` for this
    optimal ``K``). As in Huang et al.'s algorithm, ``E[Σ⁻¹]`` is taken as the inverse of the mean
    of ``q(Σ)``; the exact inverse-Wishart moment ``(û + 1) U⁻¹`` makes ``P̃`` smaller than
    ``P_{k|k-1}`` and loses the ATC target in every turn.

    ``scale_shapes="derived"`` (default) uses the shapes above: ``n`` for the state scale ``ξ``,
    ``m`` for the measurement scale ``λ``. ``"swapped"`` exchanges the two (``(m + ω)`` for ``ξ``,
    ``(n + ν)`` for ``λ``), as a public Julia implementation of this filter does: it is the variant
    that reproduces Chen et al.'s Table 1 RSTKF, while the derived shapes take the turns' large
    innovations for measurement outliers and lose the target (both rows, measured, in
    ``experiments/results/svss_paper.md``).

    As ``ω, ν, τ → ∞``, ``E[ξ] = E[λ] = 1`` and ``E[Σ⁻¹] = P_{k|k-1}^{-1}``: the Kalman filter.
    A missing component drops its rows of ``H`` and ``R`` and its count from ``m``.

    Args:
        model: a :class:`~torchsvs.models.LinearModel`.
        dof_state: ``ω``, degrees of freedom of the predicted state (Chen et al. 2020: 5).
        dof_meas: ``ν``, degrees of freedom of the measurement noise (5).
        tau: ``τ``, confidence in the nominal predicted covariance (5).
        iterations: ``N``, VB iterations per step (10).
        scale_shapes: ``"derived"`` or ``"swapped"`` (see above).

    References:
        Huang, Zhang, Li, Wu, Chambers, "A Novel Robust Student's t-Based Kalman Filter", IEEE
        Trans. Aerosp. Electron. Syst. 53(3):1545-1554, 2017. doi:10.1109/TAES.2017.2651684 ·
        Chen, Xu, Yan, Li, Sensors 20(6):1781, 2020 (Table 1 settings).
    """

    paired_probes = True  # a Python loop over steps of small tensors (10 VB iterations each)

    def __init__(
        self,
        model: LinearModel,
        dof_state: float = 5.0,
        dof_meas: float = 5.0,
        tau: float = 5.0,
        iterations: int = 10,
        scale_shapes: str = "derived",
    ) -> None:
        super().__init__(model)
        for name, value in (("dof_state", dof_state), ("dof_meas", dof_meas), ("tau", tau)):
            if not (isinstance(value, (int, float)) and value > 0):
                raise ValueError(f"{name}: expected a number > 0, got {value!r}")
        if isinstance(iterations, bool) or not isinstance(iterations, int) or iterations < 1:
            raise ValueError(f"iterations: expected an integer >= 1, got {iterations!r}")
        if scale_shapes not in ("derived", "swapped"):
            raise ValueError(f"scale_shapes: expected 'derived' or 'swapped', got {scale_shapes!r}")
        self.scale_shapes = scale_shapes
        self.dof_state, self.dof_meas = float(dof_state), float(dof_meas)
        self.tau, self.iterations = float(tau), iterations

    def correct(
        self,
        x_pred: Tensor,
        P_pred: Tensor,
        obs: Observation,
        carried: Tensor | None,
        inputs: Inputs,
    ) -> Step:
        assert obs.H is not None
        z, mask, H, R = obs.z, obs.mask, obs.H, obs.R
        n = x_pred.shape[-1]
        if mask is not None:
            H, R = mask_measurement(H, R, mask)
            m_obs = mask.sum(-1).to(z.dtype)
        else:
            m_obs = torch.full(z.shape[:-1], float(z.shape[-1]), dtype=z.dtype)
        state_shape, meas_shape = (n, m_obs) if self.scale_shapes == "derived" else (m_obs, n)
        omega, nu, tau = self.dof_state, self.dof_meas, self.tau
        e_pred = z - matvec(H, x_pred)
        U_prior = tau * P_pred  # Û: inverse-Wishart scale, E[Σ] = P_{k|k-1}
        u_post = n + tau + 2.0  # û + 1
        x, P = x_pred, P_pred
        inv_sigma_scale = None  # E[Σ⁻¹] = (u − n − 1) U⁻¹, applied through solves with U
        U = U_prior
        for _ in range(self.iterations):
            dx = x - x_pred
            D = P + dx.unsqueeze(-1) * dx.unsqueeze(-2)
            residual = z - matvec(H, x)
            E = residual.unsqueeze(-1) * residual.unsqueeze(-2) + H @ P @ H.mT
            trace_D = (
                _trace_solve(P_pred, D)
                if inv_sigma_scale is None
                else inv_sigma_scale * _trace_solve(U, D)
            )
            E_xi = (state_shape + omega) / (omega + trace_D)
            E_lambda = (meas_shape + nu) / (nu + _trace_solve(R, E))
            U = symmetrize(U_prior + E_xi[..., None, None] * D)
            inv_sigma_scale = u_post - n - 1.0
            P_tilde = U / (inv_sigma_scale * E_xi[..., None, None])
            R_tilde = R / E_lambda[..., None, None]
            x, P, K, _, _ = kalman_update(x_pred, P_tilde, e_pred, H, R_tilde)
        if mask is not None:
            # Nothing measured: the prediction stands. The VB scales would otherwise come from
            # the prior alone and, with swapped shapes, inflate P at every empty step.
            empty = m_obs == 0
            x = torch.where(empty[..., None], x_pred, x)
            P = torch.where(empty[..., None, None], P_pred, P)
        S = innovation_covariance(H, P_pred @ H.mT, R)  # the nominal one, before reweighting
        return Step(x, P, e_pred, K, innovation_cov=S)
