"""The smooth variable structure smoother (SVSS)."""

from __future__ import annotations

from torch import Tensor

from torchsvs.filters.gaussian import GaussianFilter
from torchsvs.linalg import right_psd_solve
from torchsvs.smoothers.rts import RTSSmoother
from torchsvs.types import FilterResult


class SVSS(RTSSmoother):
    r"""Smooth variable structure smoother, Eq. (42) and Appendix A, Chen et al. 2020.

    The smoothed estimate is updated by the filter's a-priori innovations (projection theory,
    Eqs. (30)-(41)):

    .. math::
        \hat x_{k|N} = \hat x_{k|N-1} + \Big(\prod_{i=k}^{N-1} C_i\Big) B_N e_{N|N-1},\qquad
        C_i = P_{i|i}F^T P_{i+1|i}^{-1},\quad B_N = P_{N|N-1}H^T(HP_{N|N-1}H^T + R)^{-1}

    Summed over ``N`` this is the backward recursion of :class:`RTSSmoother` with the innovation
    gain ``Γ_N = B_N`` in place of the filter's gain. Over a Kalman filter ``B_N`` is the Kalman
    gain and SVSS equals the RTS smoother.

    Covariance: the exact error covariance of this estimate given the SVSF's gains (see
    :class:`RTSSmoother`). The paper's projection covariance ``P_{k|N−1} − M S_N Mᵀ`` is not used:
    Eq. (38) replaces ``I − KH`` by ``P_{k+1|k+1}P_{k+1|k}⁻¹``, true only for the Kalman gain, and
    over an SVSF with lag ≥ 2 it is indefinite at many steps.

    ``lag=1`` (default) is the one-step-lag smoother ``x̂_{k|k+1}`` of the paper's tables
    (Eq. (A21)); ``lag=L`` sums ``L`` terms; ``lag=None`` is the fixed interval ``x̂_{k|T}``, which
    over an SVSF on maneuvering data can diverge: the SVSF covariance is much larger than ``Q``, so
    the gains ``C_i`` approach ``F⁻¹`` and distant innovations keep their full weight (the lag
    study of ``experiments/results/svss_paper.md`` measures lags 1-3).

    Args:
        filter: usually an :class:`~torchsvs.filters.SVSF`; any Gaussian filter works.
        lag: ``1`` (default), an integer lag, or ``None`` for the fixed interval.

    References:
        Chen, Xu, Yan, Li, "A Novel Smooth Variable Structure Smoother for Robust Estimation",
        Sensors 20(6):1781, 2020. doi:10.3390/s20061781
    """

    def __init__(self, filter: GaussianFilter, lag: int | None = 1) -> None:
        super().__init__(filter, lag)

    projection_gain = True

    def innovation_gain(self, result: FilterResult, H: Tensor, PHt: Tensor, S: Tensor) -> Tensor:
        """``B_N = P_{N|N−1} Hᵀ S_N⁻¹`` (zero columns where missing)."""
        return right_psd_solve(PHt, S)
