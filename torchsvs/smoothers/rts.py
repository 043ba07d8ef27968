"""Backward smoothing over a stored filter pass: the RTS smoother and its fixed-lag form."""

from __future__ import annotations

import torch
from torch import Tensor

from torchsvs.estimator import Estimator, Inputs
from torchsvs.filters.kalman import GaussianFilter
from torchsvs.linalg import matvec, psd_solve, symmetrize
from torchsvs.models.base import LinearModel
from torchsvs.types import FilterResult, SmootherResult


def _steps_after_first(A: Tensor) -> Tensor:
    """A stored model matrix at steps ``1..T-1`` (unchanged when constant, ``[1, 1, r, c]``)."""
    return A if A.shape[1] == 1 else A[:, 1:]


class RTSSmoother(Estimator):
    r"""Rauch–Tung–Striebel smoother over any Gaussian filter, Eq. (17), Chen et al. 2020.

    Both smoothers of the library share one backward recursion. With the smoother gain
    ``C_k = P_{k|k} F_{k+1}^T P_{k+1|k}^{-1}`` and a per-step increment ``(d_{k+1}, D_{k+1})``,

    .. math::
        g_k = C_k (d_{k+1} + g_{k+1}),\quad W_k = C_k (D_{k+1} + W_{k+1}) C_k^T,\quad
        \hat x^s_k = \hat x_{k|k} + g_k,\quad P^s_k = P_{k|k} - W_k

    with ``g = 0, W = 0`` past the end of the window. For the RTS smoother the increment is the
    filter's own correction, ``d = x̂_{k+1|k+1} − x̂_{k+1|k}`` and ``D = P_{k+1|k} − P_{k+1|k+1}``, which
    unrolls Eq. (17) exactly. :class:`~torchsvs.smoothers.SVSS` replaces only the increment.

    ``lag=None`` smooths the fixed interval (``x̂_{k|T}``, O(T), as filterpy's ``rts_smoother``).
    ``lag=L`` gives the fixed-lag estimate ``x̂_{k|k+L}``, Eq. (17) run backward over the window
    ``[k, k+L]`` (the windows shorten at the end of the track), in ``L`` vectorised sweeps. The
    paper's "KS" is ``RTSSmoother(KalmanFilter(model), lag=1)``; over an
    :class:`~torchsvs.filters.SVSF`, ``lag=1`` is its "SVSTPS" (Gadsden & Lee 2017).

    Args:
        filter: a Gaussian filter (KF, SVSF); its result is consumed, never recomputed.
        lag: ``None`` for the fixed interval, or a positive integer lag.

    References:
        Rauch, Tung, Striebel, "Maximum likelihood estimates of linear dynamic systems", AIAA J.
        3(8), 1965. doi:10.2514/3.3166
    """

    def __init__(self, filter: GaussianFilter, lag: int | None = None) -> None:
        super().__init__()
        if not isinstance(filter, GaussianFilter):
            raise TypeError(f"filter: expected a torchsvs Gaussian filter, got {type(filter).__name__}")
        if lag is not None and (isinstance(lag, bool) or not isinstance(lag, int) or lag < 1):
            raise ValueError(f"lag: expected None (fixed interval) or an integer >= 1, got {lag!r}")
        self.filter = filter
        self.lag = lag

    @property  # type: ignore[override]
    def model(self) -> LinearModel:
        return self.filter.model

    def run(self, inputs: Inputs) -> SmootherResult:
        return self.smooth(self.filter.run(inputs))

    def increments(self, result: FilterResult) -> tuple[Tensor, Tensor]:
        """``d_{k+1} [B, T-1, n]`` and ``D_{k+1} [B, T-1, n, n]`` for ``k = 0..T-2``."""
        d = result.mean[:, 1:] - result.pred_mean[:, 1:]
        D = result.pred_cov[:, 1:] - result.cov[:, 1:]
        return d, D

    def smooth(self, result: FilterResult) -> SmootherResult:
        """Smooths a batched filter result (``[B, T, ...]``) without re-running the filter."""
        T = result.mean.shape[1]
        if T == 1:
            return SmootherResult(result.mean, result.cov, result)
        d, D = self.increments(result)
        F = _steps_after_first(result.transition)  # F_{k+1}
        # C_k = P_{k|k} F_{k+1}ᵀ P_{k+1|k}⁻¹ = (P_{k+1|k}⁻¹ F_{k+1} P_{k|k})ᵀ, all symmetric.
        C = psd_solve(result.pred_cov[:, 1:], F @ result.cov[:, :-1]).mT
        if self.lag is None or self.lag >= T - 1:
            g, W = self._fixed_interval(C, d, D)
        else:
            g, W = self._fixed_lag(C, d, D, self.lag)
        mean = torch.cat([result.mean[:, :-1] + g, result.mean[:, -1:]], dim=1)
        cov = torch.cat([symmetrize(result.cov[:, :-1] - W), result.cov[:, -1:]], dim=1)
        return SmootherResult(mean, cov, result)

    @staticmethod
    def _fixed_interval(C: Tensor, d: Tensor, D: Tensor) -> tuple[Tensor, Tensor]:
        g, W = torch.zeros_like(d[:, 0]), torch.zeros_like(D[:, 0])
        gs, Ws = [], []
        for k in range(C.shape[1] - 1, -1, -1):
            g = matvec(C[:, k], d[:, k] + g)
            W = C[:, k] @ (D[:, k] + W) @ C[:, k].mT
            gs.append(g)
            Ws.append(W)
        return torch.stack(gs[::-1], dim=1), torch.stack(Ws[::-1], dim=1)

    @staticmethod
    def _fixed_lag(C: Tensor, d: Tensor, D: Tensor, lag: int) -> tuple[Tensor, Tensor]:
        # After sweep j, g[:, k] holds the window [k, k+j]; g_{k+1} past the end is zero.
        g, W = torch.zeros_like(d), torch.zeros_like(D)
        for _ in range(lag):
            g_next = torch.cat([g[:, 1:], torch.zeros_like(g[:, :1])], dim=1)
            W_next = torch.cat([W[:, 1:], torch.zeros_like(W[:, :1])], dim=1)
            g = matvec(C, d + g_next)
            W = C @ (D + W_next) @ C.mT
        return g, W
