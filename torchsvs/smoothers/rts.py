"""Backward smoothing over a stored filter pass: the RTS smoother and its fixed-lag form."""

from __future__ import annotations

from typing import Any, NamedTuple

import torch
from torch import Tensor

from torchsvs.estimator import Estimator, Inputs, at_step, drop_batch
from torchsvs.filters.gaussian import GaussianFilter
from torchsvs.kernels import axes_smoother
from torchsvs.linalg import mask_measurement, matvec, psd_solve, seen_from_here_on, symmetrize
from torchsvs.models.base import StateSpaceModel
from torchsvs.types import FilterResult, FilterState, SmootherResult


def steps_after_first(A: Tensor) -> Tensor:
    """A stored model matrix at steps ``1..T-1`` (unchanged when constant, ``[1, 1, r, c]``)."""
    return A if A.shape[1] == 1 else A[:, 1:]


class Backward(NamedTuple):
    """Per-step quantities of the backward recursion, for ``k = 0..T-2`` (index ``k+1`` inside)."""

    C: Tensor  #: smoother gain C_k = P_{k|k} F_{k+1}ᵀ P_{k+1|k}⁻¹, [B, T-1, n, n]
    d: Tensor  #: increment Γ_{k+1} e_{k+1}, [B, T-1, n]
    GHF: Tensor  #: Γ_{k+1} H F_{k+1}, [B, T-1, n, n]
    GSG: Tensor  #: Γ_{k+1} S_{k+1} Γ_{k+1}ᵀ, [B, T-1, n, n]
    GX: Tensor  #: Γ_{k+1} E[e_{k+1} x̃_{k+1|k+1}ᵀ], [B, T-1, n, n]
    AF: Tensor  #: (I − K_{k+1} H) F_{k+1}, [B, T-1, n, n]


def _shared_moments(result: FilterResult) -> FilterResult:
    """The result with track-independent covariances and gains cut to one track.

    A filter whose covariance recursion ran once for all tracks (shared ``P0``, nothing
    track-specific in the gain) returns broadcast views (batch stride 0); the smoother's gain and
    covariance recursions then run once too, and only the means use every track.
    """
    shared = [result.cov, result.pred_cov, result.gain]
    if result.innovation_cov is not None:
        shared.append(result.innovation_cov)
    if result.mean.shape[0] == 1 or any(t.stride(0) != 0 for t in shared):
        return result
    S = result.innovation_cov
    return result._replace(
        cov=result.cov[:1],
        pred_cov=result.pred_cov[:1],
        gain=result.gain[:1],
        innovation_cov=None if S is None else S[:1],
        mask=result.mask[:1],  # nothing is missing when the covariances are shared
    )


def _inert_past_the_end(result: FilterResult) -> FilterResult:
    """The result with the steps after each track's last measurement (a padded batch's shorter
    tracks) made inert: covariances the identity, gains and innovations 0. The backward
    recursion's terms are exactly 0 from there on either way, and the estimates the same; but a
    covariance predicted over many empty steps can lose its definiteness to rounding (an SVSF's,
    near rank 1, at a tiny ``q``), and the recursion carried NaN into every estimate of the
    track (:func:`~torchsvs.kernels.axes_smoother.smooth_axes` does the same per axis)."""
    later = seen_from_here_on(result.mask.any(-1))  # [B, T]
    if bool(later.all()):
        return result
    after = ~later

    def identity(x: Tensor) -> Tensor:  # [B, T, k, k]
        eye = torch.eye(x.shape[-1], dtype=x.dtype)
        return torch.where(after[..., None, None], eye, x)

    def zero(x: Tensor) -> Tensor:  # [B, T, ...]
        return torch.where(after.reshape(*after.shape, *([1] * (x.dim() - 2))), 0.0, x)

    S = result.innovation_cov
    return result._replace(
        cov=identity(result.cov),
        pred_cov=identity(result.pred_cov),
        gain=zero(result.gain),
        innovation=zero(result.innovation),
        innovation_cov=None if S is None else identity(S),
    )


class LagState(NamedTuple):
    """An online fixed-lag smoother's carry: the filter's state and its results of the last
    ``L + 1`` steps (each ``[B, 1, ...]``), which the smoothing of the window reuses."""

    filter: FilterState
    window: tuple[FilterResult, ...]


def _over_time(results: tuple[FilterResult, ...]) -> FilterResult:
    """Step results ``[B|1, 1, ...]`` joined along time (log-likelihoods summed)."""
    fields: list[Any] = []
    for name, parts in zip(FilterResult._fields, zip(*results, strict=True), strict=True):
        if name == "axes" or parts[0] is None:
            fields.append(None)
        elif name == "log_likelihood":
            fields.append(sum(parts[1:], parts[0]))
        else:
            batch = max(x.shape[0] for x in parts)
            fields.append(torch.cat([x.expand(batch, *x.shape[1:]) for x in parts], dim=1))
    return FilterResult(*fields)


class RTSSmoother(Estimator[SmootherResult]):
    r"""Rauch–Tung–Striebel smoother over any Gaussian filter, Eq. (17), Chen et al. 2020.

    Both smoothers of the library are one backward recursion over a stored filter pass. With the
    smoother gain ``C_k = P_{k|k} F_{k+1}^T P_{k+1|k}^{-1}`` and an innovation gain ``Γ_{k+1}``,

    .. math::
        \hat x^s_k = \hat x_{k|k} + g_k,\qquad g_k = C_k(\Gamma_{k+1} e_{k+1} + g_{k+1}),

    with ``g = 0`` past the end of the window. Here ``Γ = K``, the filter's own gain, so
    ``Γ e = x̂_{k+1|k+1} − x̂_{k+1|k}`` and the recursion is Eq. (17) unrolled;
    :class:`~torchsvs.smoothers.SVSS` replaces only ``Γ``.

    The covariance is the exact error covariance of that estimate under the model, given the
    gains the filter applied (the assumption under which the filter's own Joseph-form ``P`` is
    exact). Writing ``g_k = G_k x̃_{k|k} + (terms in later noise)`` and ``A = I − KH``:

    .. math::
        G_k = C_k(\Gamma H + G_{k+1} A)F,\qquad
        Z_k = C_k\big(\Gamma S \Gamma^T + \Gamma X G_{k+1}^T + G_{k+1} X^T\Gamma^T
              + Z_{k+1}\big)C_k^T,

        P^s_k = P_{k|k} - P_{k|k} G_k^T - G_k P_{k|k} + Z_k,\qquad
        X = E[e_{k+1}\tilde x_{k+1|k+1}^T] = H P_{k+1|k} A^T - R K^T

    (all at index ``k+1`` unless marked). With ``Γ = K`` this equals the textbook RTS covariance
    ``P_{k|k} + C_k(P^s_{k+1} − P_{k+1|k})C_k^T`` for any filter gain, optimal or not (``C_k``
    makes the two parts of the error uncorrelated); with the SVSS's ``Γ = B`` over an SVSF the
    textbook-style projection form is not the covariance of the estimate (see :class:`SVSS`), so
    one recursion that is exact for every ``Γ`` serves both.

    ``lag=None`` smooths the fixed interval (``x̂_{k|T}``, O(T), as filterpy's ``rts_smoother``).
    ``lag=L`` gives the fixed-lag estimate ``x̂_{k|k+L}`` (windows shorten at the end of the track)
    in ``L`` sweeps vectorised over time. The paper's "KS" is
    ``RTSSmoother(KalmanFilter(model), lag=1)``; over an :class:`~torchsvs.filters.SVSF`,
    ``lag=1`` is its "SVSTPS" (Gadsden & Lee 2017).

    Args:
        filter: a Gaussian filter (KF, SVSF); its result is consumed, never recomputed.
        lag: ``None`` for the fixed interval, or a positive integer lag.

    References:
        Rauch, Tung, Striebel, "Maximum likelihood estimates of linear dynamic systems", AIAA J.
        3(8), 1965. doi:10.2514/3.3166 ·
        Gadsden, Lee, "Advances of the smooth variable structure filter: square-root and
        two-pass formulations", J. Appl. Remote Sens. 11(1), 2017. doi:10.1117/1.JRS.11.015018
    """

    def __init__(self, filter: GaussianFilter, lag: int | None = None) -> None:
        super().__init__()
        if not isinstance(filter, GaussianFilter):
            raise TypeError(
                f"filter: expected a torchsvs Gaussian filter, got {type(filter).__name__}"
            )
        if lag is not None and (isinstance(lag, bool) or not isinstance(lag, int) or lag < 1):
            raise ValueError(f"lag: expected None (fixed interval) or an integer >= 1, got {lag!r}")
        self.filter = filter
        self.lag = lag

    @property
    def model(self) -> StateSpaceModel:  # type: ignore[override]
        return self.filter.model

    def run(self, inputs: Inputs) -> SmootherResult:
        # The filter's compiled pass may smooth as well (lag 1; other lags where less than the
        # whole record is kept); else the smoother reads the filter's whole record.
        smoothing = "projection" if self.projection_gain else "gain"
        result, smoothed = self.filter.smoother_pass(inputs, smoothing, self.lag)
        if smoothed is not None:
            return SmootherResult(*smoothed, result)
        return self.smooth(result)

    # --- Online fixed-lag smoothing: the filter steps, and x̂_{t-L|t} as measurements arrive. ---

    def init(self, x0: Any, P0: Any) -> LagState:
        """The state of an online fixed-lag run (:meth:`step`) before its first measurement."""
        self._online_lag()
        return LagState(self.filter.init(x0, P0), ())

    def step(
        self,
        state: LagState,
        z: Tensor,
        *,
        u: Tensor | None = None,
        dt: float | Tensor | None = None,
        psi: Tensor | None = None,
    ) -> tuple[LagState, SmootherResult | None]:
        """Takes the measurement of step ``t`` (as :meth:`GaussianFilter.step` does) and
        returns the fixed-lag estimate ``x̂_{t-L|t}`` of step ``t − L`` (``None`` during the
        first ``L`` steps): the offline fixed-lag result, step by step. The state keeps the
        filter's results of the last ``L + 1`` steps; each step filters once and smooths that
        window. :meth:`flush` ends the run."""
        lag = self._online_lag()
        if not isinstance(state, LagState):
            raise TypeError(f"state: expected a LagState (est.init), got {type(state).__name__}")
        single = state.filter.single

        def one_step(x: Any) -> Any:  # [B, ·] (or one track's [·]) as one step of a batch
            if not isinstance(x, Tensor) or x.ndim == 0:
                return x
            return x.reshape(1, 1, -1) if single else x.unsqueeze(1)

        if isinstance(dt, Tensor) and dt.ndim == 1:
            dt = dt.unsqueeze(1)
        batched = state.filter._replace(single=False)
        after, result = self.filter.scan(
            batched, one_step(z), u=one_step(u), dt=dt, psi=one_step(psi)
        )
        window = (*state.window, result)[-(lag + 1) :]
        new = LagState(after._replace(single=single), window)
        if len(window) < lag + 1:
            return new, None
        smoothed = self.smooth(_over_time(window))
        return new, at_step(drop_batch(smoothed) if single else smoothed, 0, 0 if single else 1)

    def flush(self, state: LagState) -> SmootherResult | None:
        """The last steps of an online run, smoothed with what came after them (as the offline
        fixed-lag result ends a track): ``[B, k, ...]`` for the ``k`` steps not yet returned."""
        lag = self._online_lag()
        if not state.window:
            return None
        smoothed = self.smooth(_over_time(state.window))
        if len(state.window) == lag + 1:  # its first step was returned already
            smoothed = SmootherResult(smoothed.mean[:, 1:], smoothed.cov[:, 1:], smoothed.filtered)
        return drop_batch(smoothed) if state.filter.single else smoothed

    def _online_lag(self) -> int:
        if self.lag is None:
            raise ValueError(
                "lag: online smoothing needs a fixed lag (the fixed interval waits for the end "
                "of the track: run the whole track instead)"
            )
        return self.lag

    def takes_psi(self) -> bool:
        return self.filter.takes_psi()

    #: Γ is the projection gain ``P Hᵀ S⁻¹`` (SVSS) rather than the filter's (per-axis kernel)
    projection_gain = False

    def innovation_gain(self, result: FilterResult, H: Tensor, PHt: Tensor, S: Tensor) -> Tensor:
        """``Γ_{k+1} [B, T-1, n, m]``: the filter's gain (RTS)."""
        return result.gain[:, 1:]

    def smooth(self, result: FilterResult) -> SmootherResult:
        """Smooths a batched filter result (``[B, T, ...]``) without re-running the filter."""
        B, T = result.mean.shape[:2]
        if T == 1:
            return SmootherResult(result.mean, result.cov, result)
        if result.axes is not None:  # the filter ran per axis: so does the smoother
            mean, cov = axes_smoother.smooth_axes(result.axes, self.projection_gain, self.lag)
            return SmootherResult(mean, cov, result)
        b = self._backward_terms(_shared_moments(_inert_past_the_end(result)))
        if self.lag is None or self.lag >= T - 1:
            g, G, Z = self._fixed_interval(b)
        else:
            g, G, Z = self._fixed_lag(b, self.lag)
        P = result.cov[: G.shape[0], :-1]
        PGt = P @ G.mT
        mean = torch.cat([result.mean[:, :-1] + g, result.mean[:, -1:]], dim=1)
        smoothed = symmetrize(P - PGt - PGt.mT + Z)
        cov = torch.cat([smoothed, result.cov[: G.shape[0], -1:]], dim=1).expand(B, -1, -1, -1)
        return SmootherResult(mean, cov, result)

    def _backward_terms(self, result: FilterResult) -> Backward:
        P_pred = result.pred_cov[:, 1:]
        H, R = mask_measurement(
            steps_after_first(result.meas_matrix),
            steps_after_first(result.meas_cov),
            result.mask[:, 1:],
        )
        PHt = P_pred @ H.mT
        assert result.innovation_cov is not None, "every Gaussian filter records S"
        S = result.innovation_cov[:, 1:]
        Gamma = self.innovation_gain(result, H, PHt, S)
        K = result.gain[:, 1:]
        F = steps_after_first(result.transition)
        eye = torch.eye(F.shape[-1], dtype=F.dtype, device=F.device)
        A = eye - K @ H
        X = PHt.mT @ A.mT - R @ K.mT  # E[e x̃_postᵀ]: the innovation's share in the posterior error
        # C_k = P_{k|k} F_{k+1}ᵀ P_{k+1|k}⁻¹ = (P_{k+1|k}⁻¹ F_{k+1} P_{k|k})ᵀ, all symmetric.
        C = psd_solve(P_pred, F @ result.cov[:, :-1]).mT
        return Backward(
            C=C,
            d=matvec(Gamma, result.innovation[:, 1:]),
            GHF=Gamma @ H @ F,
            GSG=Gamma @ S @ Gamma.mT,
            GX=Gamma @ X,
            AF=A @ F,
        )

    @staticmethod
    def _step(
        b: Backward, g: Tensor, G: Tensor, Z: Tensor, k: slice | int
    ) -> tuple[Tensor, Tensor, Tensor]:
        """One application of the recursion at steps ``k`` given the terms at ``k+1``."""
        C = b.C[:, k]
        cross = b.GX[:, k] @ G.mT
        g_new = matvec(C, b.d[:, k] + g)
        G_new = C @ (b.GHF[:, k] + G @ b.AF[:, k])
        Z_new = C @ (b.GSG[:, k] + cross + cross.mT + Z) @ C.mT
        return g_new, G_new, Z_new

    def _fixed_interval(self, b: Backward) -> tuple[Tensor, Tensor, Tensor]:
        g, G, Z = (
            torch.zeros_like(b.d[:, 0]),
            torch.zeros_like(b.C[:, 0]),
            torch.zeros_like(b.C[:, 0]),
        )
        out = []
        for k in range(b.C.shape[1] - 1, -1, -1):
            g, G, Z = self._step(b, g, G, Z, k)
            out.append((g, G, Z))
        g, G, Z = (torch.stack(v[::-1], dim=1) for v in zip(*out, strict=True))
        return g, G, Z

    def _fixed_lag(self, b: Backward, lag: int) -> tuple[Tensor, Tensor, Tensor]:
        # After sweep j, index k holds the window [k, k+j]; the terms past the end are zero.
        g, G, Z = torch.zeros_like(b.d), torch.zeros_like(b.C), torch.zeros_like(b.C)
        every = slice(None)
        for _ in range(lag):
            g_next, G_next, Z_next = (
                torch.cat([v[:, 1:], torch.zeros_like(v[:, :1])], dim=1) for v in (g, G, Z)
            )
            g, G, Z = self._step(b, g_next, G_next, Z_next, every)
        return g, G, Z
