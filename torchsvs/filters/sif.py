"""The sliding innovation filter (SIF) of Gadsden and Al-Shabi 2020, the SVSF's successor."""

from __future__ import annotations

import torch
from torch import Tensor

from torchsvs.constraints import ArrayLike, Positive
from torchsvs.estimator import Inputs
from torchsvs.filters.gaussian import GaussianFilter, Observation, Step, innovation_covariance
from torchsvs.linalg import joseph_update, mask_measurement, masked_pinv, matvec, svsf_gain_ratio
from torchsvs.models.base import LinearModel


class SlidingInnovationFilter(GaussianFilter):
    r"""Sliding innovation filter: a switching gain that slides the estimate toward the
    measurement within a boundary layer ``δ`` around it (Gadsden & Al-Shabi 2020, Eqs. (9)-(13)).

    The prediction is the Kalman filter's; the correction, with ``e = z − H x̂_{k+1|k}``,

    .. math::
        K = H^{+}\,\mathrm{diag}\big(\overline{\mathrm{sat}}(|e| / \delta)\big),\quad
        \hat x_{k+1|k+1} = \hat x_{k+1|k} + K e,\quad
        P_{k+1|k+1} = (I - KH) P_{k+1|k} (I - KH)^T + K R K^T,

    where ``sat`` clips to ``[−1, 1]``: outside the layer (``|e| > δ``) the gain is ``H⁺`` and the
    estimate jumps onto the measurement; inside it the step shrinks in proportion. This is the
    SVSF's gain (Eq. (23) of Chen et al. 2020) without its memory term: ``sat(|e|/δ) =
    |e| / max(|e|, δ)``, :func:`~torchsvs.linalg.svsf_gain_ratio` with ``γ = 0``. A missing
    component has a zero column of ``K``. ``δ`` is learnable (stored as its logarithm). The
    paper suggests ``δ = 10 diag(R)`` as a start (in measurement units).

    Args:
        model: a :class:`~torchsvs.models.LinearModel`.
        delta: the boundary layer width ``δ``, a scalar or one per measured component.
        learn: make ``δ`` a learnable parameter.

    References:
        Gadsden, Al-Shabi, "The sliding innovation filter", IEEE Access 8:96129-96138, 2020.
        doi:10.1109/ACCESS.2020.2995345
    """

    def __init__(self, model: LinearModel, delta: ArrayLike, learn: bool = True) -> None:
        super().__init__(model)
        self.layer = Positive(delta, "delta", learn=learn)
        if self.layer.raw.ndim > 1 or self.layer.raw.numel() not in (1, model.meas_dim):
            raise ValueError(
                f"delta: expected a scalar or {model.meas_dim} widths, got shape "
                f"{tuple(self.layer.raw.shape)}"
            )

    @property
    def delta(self) -> Tensor:
        """Boundary layer widths ``δ`` (> 0)."""
        return self.layer()

    def correct(
        self,
        x_pred: Tensor,
        P_pred: Tensor,
        obs: Observation,
        carried: Tensor | None,
        inputs: Inputs,
    ) -> Step:
        assert obs.H is not None
        e = obs.z - matvec(obs.H, x_pred)
        if obs.mask is not None:
            e = e * obs.mask
        delta = self.delta.to(e.dtype)
        saturation = svsf_gain_ratio(e, torch.zeros_like(e), delta, torch.zeros((), dtype=e.dtype))
        K = masked_pinv(obs.H, obs.mask) * saturation.unsqueeze(-2)
        P = joseph_update(P_pred, K, obs.H, obs.R)
        H, R = (obs.H, obs.R) if obs.mask is None else mask_measurement(obs.H, obs.R, obs.mask)
        S = innovation_covariance(H, P_pred @ H.mT, R)
        return Step(x_pred + matvec(K, e), P, e, K, innovation_cov=S)
