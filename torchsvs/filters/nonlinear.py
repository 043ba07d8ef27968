"""Gaussian filters for nonlinear models: the extended and the unscented Kalman filter."""

from __future__ import annotations

import torch
from torch import Tensor

from torchsvs.estimator import Inputs
from torchsvs.filters.fast_paths import NO_FAST_PATHS, FastPaths
from torchsvs.filters.gaussian import (
    Observation,
    Prepared,
    Step,
    _at,
    kalman_correct,
    step_input,
    step_interval,
)
from torchsvs.filters.kalman import KalmanFilter
from torchsvs.linalg import cholesky, psd_solve, symmetrize
from torchsvs.models.base import StateSpaceModel


class ExtendedKalmanFilter(KalmanFilter):
    r"""Extended Kalman filter: the Kalman filter on the model linearised at each estimate.

    .. math::
        \hat x_{k+1|k} = f(\hat x_{k|k}),\quad P_{k+1|k} = F_k P_{k|k} F_k^T + Q,\quad
        F_k = \partial f/\partial x|_{\hat x_{k|k}}\ \text{(Eq. (3))}

        e = z_{k+1} - h(\hat x_{k+1|k}),\quad H_{k+1} = \partial h/\partial x|_{\hat x_{k+1|k}}
        \ \text{(Eq. (4))},

    then the Kalman correction in Joseph form (:class:`KalmanFilter`). Jacobians come from the
    model (autograd by default). The result stores the per-step ``F_k`` and ``H_k``, so the RTS
    and SVSS smoothers run on it unchanged. On a linear model it is the Kalman filter.
    ``adaptive_noise`` is :class:`KalmanFilter`'s: it reads the differenced ``z`` itself, so for
    a non-linear ``h`` it sees the noise plus the change of ``h``'s rate over its window
    (:mod:`torchsvs.filters.adaptive`).

    References:
        Gadsden, Habibi, Kirubarajan, Trans. CSME 36(2), 2012, Eqs. (3)-(4) · Bar-Shalom, Li,
        Kirubarajan, "Estimation with Applications to Tracking and Navigation", 2001.
    """

    model_type = StateSpaceModel
    #: for models that need linearising; on a CV model the KF has the per-axis kernel
    paths = FastPaths(dense="kalman")


class UnscentedKalmanFilter(ExtendedKalmanFilter):
    r"""Unscented Kalman filter with scaled sigma points (Julier; Wan & van der Merwe).

    ``2n + 1`` points ``χ = x̂ ± columns of chol((n + λ)P)``, ``λ = α²(n + κ) − n``, weights
    ``W_m = [λ/(n+λ), 1/(2(n+λ)), …]`` and ``W_c = W_m + [1 − α² + β, 0, …]``:

    .. math::
        \hat x_{k+1|k} = \sum_i W_m^i f(\chi^i),\quad
        P_{k+1|k} = \sum_i W_c^i (f(\chi^i) - \hat x_{k+1|k})(\cdot)^T + Q

        \hat z = \sum_i W_m^i h(\chi^i),\quad
        S = \sum_i W_c^i (h(\chi^i) - \hat z)(\cdot)^T + R,\quad
        P_{xz} = \sum_i W_c^i (\chi^i - \hat x_{k+1|k})(h(\chi^i) - \hat z)^T

    The correction ``K = P_{xz} S⁻¹`` is written as a Kalman correction with the statistically
    linearised ``H = P_{xz}ᵀ P_{k+1|k}⁻¹`` and ``R' = S − H P_{k+1|k} Hᵀ``, so it runs through the
    same Joseph-form update (``P = P − K S Kᵀ`` for this gain), drops missing components the
    same way, and stores ``H`` (and ``F = P_{x x'}ᵀ P_{k|k}⁻¹`` from the prediction) for the
    smoothers. On a linear model it is the Kalman filter.

    Args:
        model: any :class:`~torchsvs.models.StateSpaceModel`.
        alpha, beta, kappa: sigma-point spread, prior knowledge (2 for Gaussians), secondary scale.

    References:
        Wan, van der Merwe, "The unscented Kalman filter for nonlinear estimation", IEEE AS-SPCC
        2000. doi:10.1109/ASSPCC.2000.882463
    """

    paths = NO_FAST_PATHS  # sigma points, not the Kalman correction of F and H

    def __init__(
        self, model: StateSpaceModel, alpha: float = 0.5, beta: float = 2.0, kappa: float = 0.0
    ) -> None:
        super().__init__(model)
        n = model.state_dim
        if not alpha > 0:
            raise ValueError(f"alpha: expected a number > 0, got {alpha!r}")
        lam = alpha**2 * (n + kappa) - n
        if not n + lam > 0:
            raise ValueError(f"kappa: expected n + λ > 0, got n + λ = {n + lam} (alpha={alpha})")
        self.scale = n + lam
        wm = torch.full((2 * n + 1,), 0.5 / (n + lam), dtype=torch.float64)
        wm[0] = lam / (n + lam)
        wc = wm.clone()
        wc[0] += 1.0 - alpha**2 + beta
        self.register_buffer("wm", wm)
        self.register_buffer("wc", wc)

    def sigma_points(self, x: Tensor, P: Tensor) -> Tensor:
        """``[B, 2n+1, n]`` sigma points of ``N(x, P)``."""
        L = cholesky(self.scale * P.expand(x.shape[0], -1, -1))
        spread = L.mT  # rows are the columns of L
        return torch.cat([x.unsqueeze(1), x.unsqueeze(1) + spread, x.unsqueeze(1) - spread], dim=1)

    def _deviations(self, points: Tensor, image: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Weighted mean of ``image`` and the deviations of ``points`` and ``image`` from
        their weighted means. The sums are of offsets from the central point, not of the
        points themselves: a track 700 km out in float32 otherwise loses the spread to rounding
        in Σ W χ (the weights have mixed signs) and its covariance turns indefinite."""
        wm = self.wm.to(image.dtype)
        off_img, off_pts = image - image[:, :1], points - points[:, :1]
        shift_img = torch.einsum("s,bsi->bi", wm, off_img)
        d_img = off_img - shift_img.unsqueeze(1)
        d_pts = off_pts - torch.einsum("s,bsi->bi", wm, off_pts).unsqueeze(1)
        return image[:, 0] + shift_img, d_pts, d_img

    def _moments(self, points: Tensor, image: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Weighted mean of ``image``, its covariance and the cross-covariance with ``points``."""
        mean, d_pts, d_img = self._deviations(points, image)
        wc = self.wc.to(image.dtype)
        cov = torch.einsum("s,bsi,bsj->bij", wc, d_img, d_img)
        cross = torch.einsum("s,bsi,bsj->bij", wc, d_pts, d_img)
        return mean, cov, cross

    def predict(
        self, t: int, x: Tensor, P: Tensor, prep: Prepared, inputs: Inputs
    ) -> tuple[Tensor, Tensor, Tensor]:
        B, n = x.shape
        points = self.sigma_points(x, P)
        dt, u = step_interval(inputs, t), step_input(inputs, t)
        if dt is not None and dt.ndim == 1:
            dt = dt.repeat_interleave(points.shape[1])
        if u is not None:
            u = u.repeat_interleave(points.shape[1], dim=0)
        image = self.model.f(points.reshape(-1, n), dt, u).reshape(points.shape)
        x_pred, P_f, cross = self._moments(points, image)
        F_t = psd_solve(P.expand(B, n, n), cross).mT  # Cov(x', x) P⁻¹
        return x_pred, symmetrize(P_f + _at(prep.Q, t)), F_t

    def correct(
        self,
        x_pred: Tensor,
        P_pred: Tensor,
        obs: Observation,
        carried: Tensor | None,
        inputs: Inputs,
    ) -> Step:
        B, n = x_pred.shape
        points = self.sigma_points(x_pred, P_pred)
        image = self.model.h(points.reshape(-1, n)).reshape(B, points.shape[1], -1)
        z_pred, d_pts, d_img = self._deviations(points, image)
        wc = self.wc.to(image.dtype)
        cross = torch.einsum("s,bsi,bsj->bij", wc, d_pts, d_img)
        H_t = psd_solve(P_pred.expand(B, n, n), cross).mT  # P_xzᵀ P⁻¹
        # R' = R + S_h − H P Hᵀ, the second term as the weighted scatter of what the linear
        # fit leaves, Σ Wc (Δh − H Δχ)(·)ᵀ (the same sum, as H P = P_xzᵀ): the difference of
        # S_h and H P Hᵀ cancels catastrophically in float32 after a long gap (P ~ 1e6).
        left = d_img - d_pts @ H_t.mT
        R_eff = symmetrize(obs.R + torch.einsum("s,bsi,bsj->bij", wc, left, left))
        step = kalman_correct(x_pred, P_pred, obs.z - z_pred, obs.mask, H_t, R_eff)
        return step._replace(meas_matrix=H_t)
