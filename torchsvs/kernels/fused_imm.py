"""The IMM(CV, CT) of ``torchsvs track --estimator imm`` and Kim's smoother over it, compiled
(``cpp/imm.h``; built by :mod:`torchsvs.kernels.build`).

:func:`turn_imm_run` is the whole pass of a :class:`~torchsvs.TurnIMM` (the filter, ``lag=0``)
or a :class:`~torchsvs.smoothers.imm.TurnIMMSmoother` (a fixed lag, or the fixed interval) per
track (:meth:`~torchsvs.TurnIMM.compiled_pass` calls it; the estimators assemble their
results from its tensors): the mixing, the modes' Kalman and extended Kalman steps, the
combination, then the pairs' predictions and gains and Kim's backward recursion, each track's
steps in one compiled loop instead of dozens of tensor operations per step. Its twin is the
tensor path (:class:`~torchsvs.IMM` and :class:`~torchsvs.smoothers.imm.IMMSmoother`, the
formulas' home): ``tests/test_fused_imm.py`` holds both to 1e-9 in float64. It runs where the
tensor path's result is not needed whole: float64 on CPU, no gradients, the EKF turn mode, no
control input, ``keep`` ``"mean"`` or ``"moments"`` (the predictions, innovations and gains
of ``"all"`` stay the tensor path's); otherwise, and where a Cholesky factor fails (the tensor
path adds jitter there), the caller takes the tensor path. Eight tracks step together in a
vector of lanes (``cpp/imm.h``), blocks of them on threads.
"""

from __future__ import annotations

import ctypes
from typing import TYPE_CHECKING, Any, NamedTuple

import torch
from torch import Tensor

from torchsvs.kernels import build
from torchsvs.kernels.build import fresh, pointers

if TYPE_CHECKING:
    from torchsvs.types import Inputs


class TurnIMMPass(NamedTuple):
    """What :func:`turn_imm_run` computed, in the common state ``[x, vx, y, vy(, z, vz), ω]``
    (``B`` tracks, ``T`` steps, ``N`` components); the covariances ``None`` unless ``keep`` is
    ``"moments"``, the smoothed fields ``None`` for the filter alone (as the results that
    trim them)."""

    mean: Tensor  #: the filter's combined estimate [B, T, N]
    cov: Tensor  #: its covariance [B, T, N, N]
    mode_probs: Tensor  #: μ_j(t) [B, T, 2] of (CV, CT)
    modes: tuple[tuple[Tensor, Tensor], ...]  #: each mode's filtered (mean, cov)
    log_likelihood: Tensor  #: [B]
    mode_log_likelihood: Tensor  #: each mode filter's own total [B, 2]
    smoothed_mean: Tensor | None  #: [B, T, N]
    smoothed_cov: Tensor  #: (as cov: None unless keep is "moments")
    smoothed_mode_probs: Tensor | None  #: [B, T, 2]
    smoothed_modes: tuple[tuple[Tensor, Tensor], ...] | None


def usable(inputs: Inputs) -> bool:
    """Whether :func:`turn_imm_run` takes these checked, batched inputs: float64 on CPU, the
    library built, no control input, ``keep`` ``"mean"`` or ``"moments"``, ``dt`` ``None``,
    0-d or ``[B, T]``, at least one step. (No gradient is the caller's to check: the loop
    reads the model's noises as numbers.)"""
    if inputs.keep not in ("mean", "moments") or inputs.u is not None or inputs.steps == 0:
        return False
    dt = inputs.dt
    if inputs.z.dtype != torch.float64 or (dt is not None and dt.ndim not in (0, 2)):
        return False
    return build.usable(inputs.z, inputs.x0, inputs.P0)


def turn_imm_run(
    constants: Tensor, interval: float, inputs: Inputs, log_p0: Tensor, lag: int | None
) -> TurnIMMPass | None:
    """The IMM(CV, CT) pass over checked, batched ``inputs`` in the common state, from the log
    mode probabilities ``log_p0 [B, 2]``: the filter for ``lag=0``, then Kim's smoother of
    that lag (``None``: the fixed interval). ``constants``: float64 ``[q, turn_q,
    turn_rate_q, log π (4, row-major), R (D², row-major)]`` (the CV mode's spectral density,
    the turn mode's acceleration variance and turn-rate noise, the transition, the
    measurement noise); ``interval``: the model's own ``dt``. ``None`` where :func:`usable`
    says no or a Cholesky factor failed (the tensor path adds jitter there)."""
    if not usable(inputs):
        return None
    B, T, D = inputs.z.shape
    N, V = 2 * D + 1, 2 * D
    f64 = torch.float64
    params = constants.to(f64).contiguous()
    assert params.shape == (7 + D * D,), "constants: q, turn_q, turn_rate_q, log π, R"
    x0 = inputs.x0.contiguous()
    P0 = inputs.P0.expand(B, N, N).contiguous()
    z = inputs.z.contiguous()
    log_p0 = log_p0.to(f64).expand(B, 2).contiguous()
    dt, dt_track, dt_step = _intervals(inputs.dt, interval)
    cov = inputs.keep == "moments"
    smooth = lag != 0

    def out(*shape: int, wanted: bool = True) -> Tensor | None:
        return fresh((B, T, *shape), f64) if wanted else None

    outs: list[Any] = [
        out(N),
        out(N, N, wanted=cov),
        out(2),
        out(V),
        out(N),
        out(V, V, wanted=cov),
        out(N, N, wanted=cov),
        torch.empty(B, dtype=f64),
        torch.empty(B, 2, dtype=f64),
        out(N, wanted=smooth),
        out(N, N, wanted=smooth and cov),
        out(2, wanted=smooth),
        out(V, wanted=smooth),
        out(N, wanted=smooth),
        out(V, V, wanted=smooth and cov),
        out(N, N, wanted=smooth and cov),
    ]
    lib = build.library()
    assert isinstance(lib, ctypes.CDLL)
    failed = lib.turn_imm_f64(
        B,
        T,
        D,
        -1 if lag is None else lag,
        int(cov),
        build.threads(B, T),
        params.data_ptr(),
        pointers([x0, P0, z, dt, log_p0]),
        dt_track,
        dt_step,
        pointers(outs),
    )
    if failed:
        return None
    fmean, fcov, fprob, fx0, fx1, fP0, fP1, loglik, mode_ll = outs[:9]
    smean, scov, sprob, sx0, sx1, sP0, sP1 = outs[9:]
    return TurnIMMPass(
        fmean,
        fcov,
        fprob,
        ((fx0, fP0), (fx1, fP1)),
        loglik,
        mode_ll,
        smean,
        scov,
        sprob,
        ((sx0, sP0), (sx1, sP1)) if smooth else None,
    )


def _intervals(dt: Tensor | None, default: float) -> tuple[Tensor, int, int]:
    """The intervals as the loop reads them: a float64 tensor and its element strides per track
    and per step (0 where one value serves)."""
    if dt is None:
        return torch.tensor([default], dtype=torch.float64), 0, 0
    dt = dt.to(torch.float64).contiguous()
    if dt.ndim == 0:
        return dt.reshape(1), 0, 0
    return dt, dt.shape[1], 1
