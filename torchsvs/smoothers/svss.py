"""The smooth variable structure smoother (SVSS)."""

from __future__ import annotations

from torch import Tensor

from torchsvs.filters.kalman import GaussianFilter
from torchsvs.linalg import mask_measurement, matvec, right_psd_solve, symmetrize
from torchsvs.smoothers.rts import RTSSmoother, _steps_after_first
from torchsvs.types import FilterResult


class SVSS(RTSSmoother):
    r"""Smooth variable structure smoother, Eq. (42) and Appendix A, Chen et al. 2020.

    The smoothed estimate is updated by the filter's a-priori innovations (projection theory,
    Eqs. (30)-(41)):

    .. math::
        \hat x_{k|N} = \hat x_{k|N-1} + \Big(\prod_{i=k}^{N-1} C_i\Big) B_N e_{N|N-1},\qquad
        C_i = P_{i|i}F^T P_{i+1|i}^{-1},\quad B_N = P_{N|N-1}H^T(HP_{N|N-1}H^T + R)^{-1}

    Summed over ``N`` this is the backward recursion of :class:`RTSSmoother` with the increment
    ``d_N = B_N e_N`` in place of the filter's correction; the covariance follows the same
    projection, ``P_{k|N} = P_{k|N-1} − M S_N Mᵀ`` with ``M = (∏C) B_N``, i.e. ``D_N = B_N S_N B_Nᵀ``.
    Over a Kalman filter ``B_N`` is the Kalman gain and SVSS equals the RTS smoother.

    ``lag=1`` (default) is the one-step-lag smoother ``x̂_{k|k+1}`` of the paper's tables (Eq. (A21));
    ``lag=L`` sums ``L`` terms; ``lag=None`` is the fixed interval ``x̂_{k|T}``, which over an SVSF on
    maneuvering data can diverge: the SVSF covariance is much larger than ``Q`` and the gains
    ``C_i`` approach ``F⁻¹``, so distant innovations keep their full weight.

    Args:
        filter: usually an :class:`~torchsvs.filters.SVSF`; any Gaussian filter works.
        lag: ``1`` (default), an integer lag, or ``None`` for the fixed interval.

    References:
        Chen, Xu, Yan, Li, "A Novel Smooth Variable Structure Smoother for Robust Estimation",
        Sensors 20(6):1781, 2020. doi:10.3390/s20061781
    """

    def __init__(self, filter: GaussianFilter, lag: int | None = 1) -> None:
        super().__init__(filter, lag)

    def increments(self, result: FilterResult) -> tuple[Tensor, Tensor]:
        P = result.pred_cov[:, 1:]
        H = _steps_after_first(result.meas_matrix)
        R = _steps_after_first(result.meas_cov)
        H, R = mask_measurement(H, R, result.mask[:, 1:])
        PHt = P @ H.mT
        S = result.innovation_cov
        S = symmetrize(H @ PHt + R) if S is None else S[:, 1:]
        gain = right_psd_solve(PHt, S)  # B_N
        return matvec(gain, result.innovation[:, 1:]), gain @ PHt.mT
