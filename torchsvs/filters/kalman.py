"""The Kalman filter."""

from __future__ import annotations

from torch import Tensor

from torchsvs.estimator import Inputs
from torchsvs.filters import factored
from torchsvs.filters.adaptive import AdaptiveNoise, check_adaptive_noise
from torchsvs.filters.fast_paths import FastPathFilter, FastPaths
from torchsvs.filters.gaussian import Observation, Step, kalman_correct
from torchsvs.models.base import StateSpaceModel


class KalmanFilter(FastPathFilter):
    r"""Batched, differentiable Kalman filter, Eqs. (11)-(16), Chen et al. 2020.

    .. math::
        S = H P_{k+1|k} H^T + R,\quad K = P_{k+1|k} H^T S^{-1},\quad
        \hat x_{k+1|k+1} = \hat x_{k+1|k} + K (z_{k+1} - H \hat x_{k+1|k}),

        P_{k+1|k+1} = (I - KH) P_{k+1|k} (I - KH)^T + K R K^T \quad\text{(Joseph form)}

    A missing component (NaN in ``z``) drops its rows of ``H`` and ``R``; an all-NaN step is a
    pure prediction. The result also carries ``S`` and the log-likelihood of the innovations.

    Args:
        model: a :class:`~torchsvs.models.LinearModel`.
        adaptive_noise: an :class:`~torchsvs.filters.AdaptiveNoise` to replace the model's ``R``
            by ``R_k`` from the spread of the differenced recent measurements (Eqs. (29)-(30),
            Bermúdez Ordoñez et al. 2020; the result's ``meas_cov`` is then ``[B, T, m, m]``),
            or ``None`` (the model's ``R``).
        covariance_form: how ``P`` is carried and updated: ``"joseph"`` (default, the form
            above), ``"conventional"`` (``P⁺ = (I − KH)P⁻``), ``"sqrt"`` (``P = SSᵀ``, QR of
            pre-arrays, Morf-Kailath update), ``"ud"`` (``P = UDUᵀ``, Thornton and Bierman) or
            ``"svd"`` (``P = UD²Uᵀ``, K-SVD, Bermúdez Ordoñez et al. 2020): the same filter in
            exact arithmetic, with different rounding (:mod:`torchsvs.filters.factored`). The
            factored forms run the general step loop (no fused or per-axis kernels); the
            result's ``cov`` is the full ``P`` and ``S`` and the log-likelihood are formed from
            the predicted ``P`` as in the Joseph form.

    References:
        Kalman, "A new approach to linear filtering and prediction problems", J. Basic Eng. 82,
        1960. doi:10.1115/1.3662552
    """

    paths = FastPaths(axis="kalman", dense="kalman")

    def __init__(
        self,
        model: StateSpaceModel,
        adaptive_noise: AdaptiveNoise | None = None,
        covariance_form: str = "joseph",
    ) -> None:
        super().__init__(model)
        self.adaptive_noise = check_adaptive_noise(adaptive_noise)
        self.covariance_form = factored.check_form(covariance_form)

    def correct(
        self,
        x_pred: Tensor,
        P_pred: Tensor,
        obs: Observation,
        carried: Tensor | None,
        inputs: Inputs,
    ) -> Step:
        fitted, H = obs.linearize(x_pred)  # Eq. (4) of Gadsden et al. 2012 for a nonlinear h
        e = obs.z - fitted
        step = kalman_correct(x_pred, P_pred, e, obs.mask, H, obs.R, obs.factor)
        return step if obs.H is not None else step._replace(meas_matrix=H)
