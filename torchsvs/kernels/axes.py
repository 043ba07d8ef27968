r"""Per-axis recursions of the nearly-constant-velocity model: a structure-exploiting kernel.

A :class:`~torchsvs.models.ConstantVelocity` model with a diagonal ``R`` (and a prior without
cross-axis covariance) is ``m`` independent two-state problems, one per axis: state
:math:`(p, v)`, :math:`F = [[1, T], [0, 1]]`, :math:`Q = q[[T^3/3, T^2/2], [T^2/2, T]]`. The
Kalman filter, the SVSF (``H⁺`` mode or finite-difference velocities) and the RTS/SVSS backward
recursion then act on 2×2 blocks (:mod:`torchsvs.kernels.blocks`), element by element on
``[B, (T,) m]`` tensors: a few dozen elementwise operations per step instead of batched 4×4 (or
6×6) matrix products, which on a CPU cost far more per element than the arithmetic. Results are
exactly the general path's (tested to 1e-9 in float64): the estimators pick this kernel by
themselves. This module holds the forward pass (:func:`run_axes`); the backward pass is
:mod:`torchsvs.kernels.axes_smoother`.

The forward loop runs compiled (:mod:`torchsvs.kernels.fused_axes`, the same formulas in C++),
with gradients through its compiled reverse mode (:class:`_CompiledAxes`). A one-step-lag
smoother (the paper's KS, SVSTPS and SVSS) needs no pass of its own: the compiled forward loop
smooths step ``k`` as soon as step ``k + 1`` is done (:func:`run_axes` with ``smoothing``; its
adjoint takes the smoothing back too), so the filter's record need not be written and read
back. The tensor loops below are the reference, the fallback without a compiler, and the path
for higher derivatives.

Every axis has a two-component corrector measurement :math:`y = (y_p, y_v)` with ``H = I``;
position-only correctors (Kalman filter, the SVSF's ``H⁺`` mode) have :math:`y_v` always missing.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any, NamedTuple, cast

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from torchsvs.kernels import build, fused_axes
from torchsvs.kernels.blocks import (
    Mat2,
    Sym2,
    block_diagonal,
    full,
    interleave,
    masked_noise,
    process_noise,
    time_major,
    time_major_stack,
)
from torchsvs.kernels.scan import filter_scan, prefer_scan
from torchsvs.linalg import boundary_inflation, svsf_gain_ratio


class AxisMeasurements(NamedTuple):
    """A corrector's measurements per axis, ``[B, T, m]`` each (NaN where missing)."""

    position: Tensor
    velocity: Tensor  #: all NaN for position-only correctors
    noise: Sym2  #: R per axis: ``(r_pp, r_pv, r_vv)``, ``[m]`` or ``[B, T, m]`` each


class AxisResult(NamedTuple):
    """A filter pass per axis, stacked over time: ``[B, T, m]`` tensors."""

    mean: tuple[Tensor, Tensor]  #: (p, v) filtered
    cov: Sym2
    pred_mean: tuple[Tensor, Tensor]
    pred_cov: Sym2
    innovation: tuple[Tensor, Tensor]  #: a-priori, 0 where missing
    gain: Mat2  #: per axis, columns (position, velocity measurement)
    observed: tuple[Tensor, Tensor]  #: masks of (y_p, y_v)
    noise: Sym2  #: R per axis, unmasked (users mask it by ``observed``: masked_noise)
    interval: Tensor  #: T of each step, [B, T, 1] or 0-d
    post_innovation: tuple[Tensor, Tensor] | None = None
    log_likelihood: Tensor | None = None  #: [B] summed over axes and steps


class Interleaved(NamedTuple):
    """A filter pass in the general layout (state ``p1, v1, p2, v2, ...``; block-diagonal
    covariances and gains): the fields of a :class:`~torchsvs.types.FilterResult`."""

    mean: Tensor  #: [B, T, 2m]
    cov: Tensor  #: [B, T, 2m, 2m]
    pred_mean: Tensor
    pred_cov: Tensor
    innovation: Tensor  #: [B, T, m_z]: m_z = 2m with velocity measurements, else m
    gain: Tensor  #: [B, T, 2m, m_z]
    innovation_cov: Tensor  #: [B, T, m_z, m_z]
    post_innovation: Tensor | None
    log_likelihood: Tensor | None
    mask: Tensor  #: [B, T, m_z]


def _forward_step(
    rule: str, gamma: Tensor, state: tuple[Tensor, ...], given: tuple[Tensor, ...]
) -> tuple[tuple[Tensor, ...], tuple[Tensor, ...]]:
    """One predict-correct step of every axis (see :func:`run_axes`); pure, so that a chunk of
    steps can be compiled.

    Deliberate twins (the Kalman update is written once per layout): the general update on
    dense matrices is ``torchsvs.filters.gaussian.kalman_update`` (this is it on 2×2 blocks
    with ``H = [1, 0]``; ``tests/test_kernels.py::test_kernel_equals_general_path`` holds them
    to 1e-9); the compiled loop's is ``predict_correct`` in ``cpp/axis_step.h``, transcribed
    line by line (``test_compiled_loops_equal_tensor_loops`` and
    ``test_compiled_loops_for_any_axis_count_on_threads``: 1e-10 in float64). The associative
    scan's first element (:func:`~torchsvs.kernels.scan.filter_scan`) updates the prior once
    more, in the scan's own form."""
    p, v, a, b, c, memory_p, memory_v = state
    T, Qa, Qb, Qc, fp, fv, yp, yv, rp, rpv, rvv, wp, wv = given
    # Prediction, Eqs. (11)-(12): F P Fᵀ + Q with F = [[1, T], [0, 1]].
    p_pred, v_pred = p + T * v, v
    bT = b + T * c
    a1 = a + T * (b + bT) + Qa
    b1 = bT + Qb
    c1 = c + Qc
    ep = (yp - p_pred) * fp
    if rule.startswith("vbl-"):  # the variable boundary layer: the Kalman rule on λ P
        excess = ep.abs() + gamma * memory_p.abs()
        inflation = boundary_inflation(excess, ep.abs(), wp, a1, rp, fp > 0, rule[4:])
        grown = inflation.unsqueeze(-1)  # one λ per track, for all its axes
        a1, b1, c1 = grown * a1, grown * b1, grown * c1
    if rule == "kalman" or rule.startswith("vbl-"):
        S = a1 * fp + rp  # 1 where missing (the masked identity)
        kp, kv_p = a1 * fp / S, b1 * fp / S  # K = [kp, kv_p]ᵀ for H = [1, 0]
        one_k = 1 - kp
        a2 = one_k * one_k * a1 + kp * kp * rp  # Joseph form
        b2 = one_k * (b1 - kv_p * a1) + kp * kv_p * rp
        c2 = c1 - 2 * kv_p * b1 + kv_p * kv_p * (a1 + rp)
        p, v = p_pred + kp * ep, v_pred + kv_p * ep
        zero = torch.zeros_like(kp)
        ev, gain = zero, (kp, zero, kv_p, zero)
        if rule != "kalman":  # Eq. (24): the a-posteriori innovation, carried where missing
            memory_p = torch.where(fp > 0, yp - p, memory_p)
    else:
        ev = (yv - v_pred) * fv
        kp = svsf_gain_ratio(ep, memory_p, wp, gamma) * fp
        kv = svsf_gain_ratio(ev, memory_v, wv, gamma) * fv
        # Joseph form with a diagonal gain, H = I: (I − K) P (I − K)ᵀ + K R Kᵀ.
        one_p, one_v = 1 - kp, 1 - kv
        a2 = one_p * one_p * a1 + kp * kp * rp
        b2 = one_p * one_v * b1 + kp * kv * rpv
        c2 = one_v * one_v * c1 + kv * kv * rvv
        p, v = p_pred + kp * ep, v_pred + kv * ev
        # Eq. (24): the a-posteriori innovation, carried where missing.
        memory_p = torch.where(fp > 0, yp - p, memory_p)
        memory_v = torch.where(fv > 0, yv - v, memory_v)
        zero = torch.zeros_like(kp)
        gain = (kp, zero, zero, kv)
    state = (p, v, a2, b2, c2, memory_p, memory_v)
    # The predicted velocity is the previous one: left out, and rebuilt after the loop.
    return state, (p, v, a2, b2, c2, p_pred, a1, b1, c1, ep, ev, *gain, memory_p, memory_v)


def _forward_chunk(
    rule: str, gamma: Tensor, state: tuple[Tensor, ...], given: tuple[Tensor, ...], steps: int
) -> tuple[tuple[Tensor, ...], tuple[Tensor, ...]]:
    """``steps`` steps in order. ``given`` holds time-major ``[T, B, m|1]`` tensors (each step a
    contiguous block, which elementwise kernels need to run fast) or 0-d constants; outputs
    come back stacked ``[B, T, m]``."""
    outputs = []
    for k in range(steps):
        now = tuple(x if x.ndim <= 1 else x[k] for x in given)
        state, out = _forward_step(rule, gamma, state, now)
        outputs.append(out)
    return state, tuple(time_major_stack(column) for column in zip(*outputs, strict=True))


class AxesPass(NamedTuple):
    """What :func:`run_axes` gives."""

    per_axis: AxisResult | None  #: the pass per axis (None: only the kept moments written)
    out: Interleaved  #: the pass in the general layout
    last: fused_axes.Last  #: the state after the last step
    #: the one-step-lag smoothed mean [B, T, 2m] and covariance [B, T, 2m, 2m], when asked for
    #: and computed in the compiled loop
    smoothed: tuple[Tensor, Tensor] | None = None


def run_axes(
    y: AxisMeasurements,
    x0: tuple[Tensor, Tensor],
    P0: Sym2,
    q: Tensor,
    interval: Tensor,
    rule: str,
    psi: Tensor | None = None,
    gamma: Tensor | None = None,
    velocity: bool = False,
    keep: str = "all",
    smoothing: str | None = None,
    lag: int | None = 1,
) -> AxesPass:
    """The forward pass of every axis, per axis and in the general layout, and the state after
    its last step. ``keep`` (:data:`torchsvs.estimator.KEEP`): ``"all"``, or the compiled loop
    writes only the filtered moments (``"moments"``) or means (``"mean"``) of each step (the
    other fields ``None``, no per-axis result), with gradients too. ``smoothing`` (``"gain"``:
    RTS, ``"projection"``: SVSS) with ``lag`` (``None``: the fixed interval): the compiled
    loop also gives the smoothed moments, of lag 1 as it steps (:func:`fused_axes.forward`), and
    of other lags when keeping less than all (:func:`fused_axes.filter_smoother`), with gradients
    through their adjoint; else ``smoothed`` is ``None`` and the pass keeps all, for
    :func:`smooth_axes`.

    Args:
        y: the corrector's measurements per axis.
        x0, P0: the prior per axis, ``[B, m]`` each.
        q: process noise spectral density (0-d).
        interval: ``T`` per step, 0-d or ``[B, T]``.
        rule: ``"kalman"`` (position-only corrector, gain ``P Hᵀ S⁻¹``, Eqs. (14)-(16), Chen et
            al. 2020), ``"svsf"`` (``K = diag(ratio)`` on the observed components, Eq. (23)
            with ``H⁺ = I``; the ``H⁺`` mode has no velocity measurements) or ``"vbl-*"`` (the
            Kalman rule on the prior inflated by the variable boundary layer's one λ per track,
            :func:`~torchsvs.linalg.boundary_inflation`; compiled where
            :func:`fused_axes.compiles`).
        psi: boundary layer ``[2, m]`` (rows: position, velocity widths) or per step
            ``[B, T, 2, m]``; gamma: memory (0-d). For ``"svsf"``.
        velocity: the corrector measures velocities (``H = I``), else positions only.
    """
    B, steps, m = y.position.shape
    dtype = y.position.dtype
    T_all = interval.unsqueeze(-1) if interval.ndim == 2 else interval
    Q_all = process_noise(q, T_all)
    if rule != "kalman":
        assert psi is not None and gamma is not None
        width_p, width_v = psi[..., 0, :], psi[..., 1, :]
    else:
        width_p = width_v = torch.ones((), dtype=dtype)
        gamma = torch.zeros((), dtype=dtype)

    def per_step(x: Tensor) -> Tensor:
        """``[B, T, m]`` view of a per-step, per-track or constant quantity."""
        x = x if x.ndim == 3 else x.reshape((1, 1, -1) if x.ndim == 1 else (1, 1, 1))
        return x.expand(B, steps, m)

    def given(*quantities: Tensor) -> tuple[Tensor, ...]:
        """Everything that does not depend on the estimates, for all steps at once."""
        return tuple(x if x.ndim in (0, 1, 3) else per_step(x) for x in quantities)

    noise = Sym2(*(per_step(x) for x in y.noise))
    prior = (x0[0], x0[1], P0.a, P0.b, P0.c)
    raw = given(T_all, *Q_all, y.position, y.velocity, *y.noise, width_p, width_v)
    usable = build.usable(*raw, *prior, gamma, differentiable=True)
    if usable and fused_axes.compiles(rule, m, dtype):
        inputs = (*raw, *prior)
        shape = (B, steps, m)
        training = torch.is_grad_enabled() and any(x.requires_grad for x in (*inputs, gamma))
        # A lag other than 1 smooths in the filter's pass where less than all is kept (and
        # there is a step to smooth); else the smoother's own pass reads the whole record.
        # Never chosen by the batch's size: a track's numbers must not depend on which tracks
        # share its batch (the two loops round differently, ~1e-13; torchsvs.track_table's
        # parts); and together was the faster at every size measured (float64, one thread:
        # 227 against 958 ns a step at 2000 x 8000, 111 against 150 at 20000 x 100).
        together = smoothing is not None and lag != 1 and keep != "all" and steps > 1
        if smoothing is not None and lag != 1 and not together:
            keep, smoothing = "all", None
        if training:
            # Only what is kept is written, as without gradients: the adjoint recomputes the
            # steps' states, and the state after the last step is an output of its own.
            parts = _CompiledAxes.apply(
                rule, velocity, shape, keep, smoothing, lag, gamma, *inputs
            )  # fmt: skip
            out = Interleaved(*parts[:10])
            last = fused_axes.Last(*parts[10:13])
            smoothed = None if smoothing is None else (parts[13], parts[14])
        else:
            outputs, last, smoothed = fused_axes.filter_pass(
                rule, float(gamma), raw, prior, shape, velocity, keep, smoothing, lag
            )
            out = Interleaved(*cast(Any, outputs))  # the fields not kept are None
        if keep != "all":
            return AxesPass(None, out, last, smoothed)
        return AxesPass(per_axis(out, noise, T_all, velocity), out, last, smoothed)
    seen_p, seen_v = ~torch.isnan(y.position), ~torch.isnan(y.velocity)
    R_all = masked_noise(y.noise, seen_p, seen_v)
    inputs = given(
        T_all,
        *Q_all,
        seen_p.to(dtype),
        seen_v.to(dtype),
        y.position.nan_to_num(0.0),
        y.velocity.nan_to_num(0.0),
        *R_all,
        width_p,
        width_v,
    )
    zero = torch.zeros(B, m, dtype=dtype)
    state = (*prior, zero, zero)
    if rule == "kalman" and prefer_scan(B * m, steps):
        # The filtered states by an associative scan over time, then every step's prediction,
        # gain and update from its predecessor at once (the same step function, vectorised).
        fp = seen_p.to(dtype)
        (pf, vf), Pf = filter_scan(
            y.position.nan_to_num(0.0) * fp, fp, per_step(R_all.a), x0, P0, Q_all, T_all
        )
        before = tuple(
            torch.cat([first.unsqueeze(1), x[:, :-1]], dim=1)
            for first, x in zip(state[:5], (pf, vf, *Pf), strict=True)
        )
        previous = (*before, zero.unsqueeze(1), zero.unsqueeze(1))
        stepped = _forward_step(rule, gamma, previous, inputs)[1]
    else:  # time-major: each step's slice is a contiguous block
        stepped = _forward_chunk(rule, gamma, state, tuple(map(time_major, inputs)), steps)[1]
    (p, v, a, b, c, pp, a1, b1, c1, ep, ev, ka, kb, kc, kd, memory_p, memory_v) = stepped
    vp = torch.cat([x0[1].unsqueeze(1), v[:, :-1]], dim=1)
    loglik = None
    if rule != "svsf":  # log N(e; 0, S) over the observed positions, Eq. (16)'s S
        fp = seen_p.to(dtype)
        S = a1 * fp + per_step(R_all.a)
        loglik = (-0.5 * (ep * ep / S + S.log() + fp * math.log(2 * math.pi))).sum((-2, -1))
    res = AxisResult(
        mean=(p, v),
        cov=Sym2(a, b, c),
        pred_mean=(pp, vp),
        pred_cov=Sym2(a1, b1, c1),
        innovation=(ep, ev),
        gain=Mat2(ka, kb, kc, kd),
        observed=(seen_p, seen_v),
        noise=noise,
        interval=T_all,
        post_innovation=None if rule == "kalman" else (memory_p, memory_v),
        log_likelihood=loglik,
    )
    out = interleaved(res, velocity)
    return AxesPass(res, out, _last(out))


def _last(out: Interleaved) -> fused_axes.Last:
    """The state after a whole-history pass's last step."""
    post = out.post_innovation
    return fused_axes.Last(out.mean[:, -1], out.cov[:, -1], None if post is None else post[:, -1])


class _CompiledAxes(torch.autograd.Function):
    """The compiled forward loop (:func:`fused_axes.forward`) with its compiled reverse mode
    (:func:`fused_axes.adjoint`): training runs the loop at inference speed. Inputs: the 11 given
    quantities and the 5 prior ones of :func:`run_axes`, in :func:`fused_axes.forward`'s order;
    outputs: the :class:`Interleaved` fields (those ``keep`` leaves out ``None``), the state
    after the last step (:class:`fused_axes.Last`) and, with ``smoothing``, the smoothed mean and
    covariance (else ``None``), 15 in all: of lag 1 inside the forward loop, else (``keep``
    ``"moments"`` or ``"mean"``) of ``lag`` by :func:`fused_axes.filter_smoother`. First
    derivatives only (``create_graph`` needs the tensor loops:
    :func:`torchsvs.kernels.eager_loops`)."""

    @staticmethod
    def forward(
        ctx: Any,
        rule: str,
        velocity: bool,
        shape: tuple[int, int, int],
        keep: str,
        smoothing: str | None,
        lag: int | None,
        gamma: Tensor,
        *inputs: Tensor,
    ) -> tuple[Tensor | None, ...]:
        given, prior = inputs[:11], inputs[11:]
        out, last, smoothed = fused_axes.filter_pass(
            rule, float(gamma), given, prior, shape, velocity, keep, smoothing, lag
        )
        ctx.settings = (rule, velocity, shape, smoothing, lag)
        ctx.save_for_backward(gamma, *inputs)
        if out[-1] is not None:  # the observed mask (kept with the whole record)
            ctx.mark_non_differentiable(out[-1])
        ctx.set_materialize_grads(False)
        return (*out, *last, *(smoothed or (None, None)))

    @staticmethod
    @once_differentiable
    def backward(ctx: Any, *grads: Tensor | None) -> tuple[Tensor | None, ...]:
        rule, velocity, shape, smoothing, lag = ctx.settings
        gamma, *inputs = ctx.saved_tensors
        wanted = ctx.needs_input_grad[7:]
        given, prior = inputs[:11], inputs[11:]
        differentiable = (*grads[:9], *grads[10:])  # not the observed mask
        dgiven, dprior, dgamma = fused_axes.adjoint(
            rule, float(gamma), given, prior, shape, velocity, differentiable, wanted[:11],
            smoothing, lag,
        )  # fmt: skip
        # rule, velocity, shape, keep, smoothing, lag
        result: list[Tensor | None] = [None] * 6
        result.append(dgamma.sum().reshape(gamma.shape) if ctx.needs_input_grad[6] else None)
        result += summed_to(given, dgiven)
        for x, dx, w in zip(prior, dprior, wanted[11:], strict=True):
            result.append(dx.reshape(x.shape) if w else None)
        return tuple(result)


def summed_to(inputs: Sequence[Tensor], grads: Sequence[Tensor | None]) -> list[Tensor | None]:
    """Gradients ``[B, T, m]`` of inputs given ``[B, T, m]``-broadcastable (0-d, ``[m]``,
    ``[B, T, 1]``, ...), summed over their broadcast dimensions."""
    out: list[Tensor | None] = []
    for x, dx in zip(inputs, grads, strict=True):
        if dx is not None and x.ndim == 3 and dx.shape[1] != x.shape[1]:
            dx = dx.expand(x.shape)  # summed over the steps already: x is constant in time
        broadcast = x.shape if x.ndim == 3 else (1, 1, x.numel())
        out.append(None if dx is None else dx.sum_to_size(broadcast).reshape(x.shape))
    return out


def interleaved(res: AxisResult, velocity: bool) -> Interleaved:
    """A pass per axis in the general layout (block-diagonal covariances and gains)."""
    seen_p, seen_v = res.observed

    def measured(pair: tuple[Tensor, Tensor]) -> Tensor:
        return interleave(*pair) if velocity else pair[0]

    gain = block_diagonal(res.gain)
    if not velocity:
        gain = gain[..., 0::2]  # the position columns
    # S = H P Hᵀ + R per axis, identity rows and columns where missing (masked noise).
    dtype = res.pred_cov.a.dtype
    fp, fv = seen_p.to(dtype), seen_v.to(dtype)
    R = masked_noise(res.noise, seen_p, seen_v)
    if velocity:
        S = Sym2(
            res.pred_cov.a * fp + R.a, res.pred_cov.b * fp * fv + R.b, res.pred_cov.c * fv + R.c
        )
        innovation_cov = block_diagonal(full(S))
    else:  # over the positions
        innovation_cov = torch.diag_embed(res.pred_cov.a * fp + R.a)
    return Interleaved(
        mean=interleave(*res.mean),
        cov=block_diagonal(full(res.cov)),
        pred_mean=interleave(*res.pred_mean),
        pred_cov=block_diagonal(full(res.pred_cov)),
        innovation=measured(res.innovation),
        gain=gain,
        innovation_cov=innovation_cov,
        post_innovation=None if res.post_innovation is None else measured(res.post_innovation),
        log_likelihood=res.log_likelihood,
        mask=measured(res.observed),
    )


def per_axis(out: Interleaved, noise: Sym2, interval: Tensor, velocity: bool) -> AxisResult:
    """The pass per axis as views of its general layout (no copies): the inverse of
    :func:`interleaved`."""

    def pair(x: Tensor) -> tuple[Tensor, Tensor]:  # [..., 2m] → (positions, velocities)
        return x[..., 0::2], x[..., 1::2]

    def sym(P: Tensor) -> Sym2:  # the axes' diagonal blocks
        diagonal = P.diagonal(dim1=-2, dim2=-1)
        return Sym2(diagonal[..., 0::2], P.diagonal(1, -2, -1)[..., 0::2], diagonal[..., 1::2])

    absent = out.innovation.new_zeros(()).expand(out.mean[..., 0::2].shape)
    K = out.gain
    if velocity:
        upper = sym(K)  # the diagonal and upper entries of the blocks; the lower one below
        gain = Mat2(upper.a, upper.b, K.diagonal(-1, -2, -1)[..., 0::2], upper.c)
        innovation, observed = pair(out.innovation), pair(out.mask)
        post = None if out.post_innovation is None else pair(out.post_innovation)
    else:  # position columns: K[2j, j], K[2j + 1, j]
        rows_p = K[..., 0::2, :].diagonal(dim1=-2, dim2=-1)
        rows_v = K[..., 1::2, :].diagonal(dim1=-2, dim2=-1)
        gain = Mat2(rows_p, absent, rows_v, absent)
        innovation = (out.innovation, absent)
        observed = (out.mask, torch.zeros((), dtype=torch.bool).expand(out.mask.shape))
        post = None if out.post_innovation is None else (out.post_innovation, absent)
    return AxisResult(
        mean=pair(out.mean),
        cov=sym(out.cov),
        pred_mean=pair(out.pred_mean),
        pred_cov=sym(out.pred_cov),
        innovation=innovation,
        gain=gain,
        observed=observed,
        noise=noise,
        interval=interval,
        post_innovation=post,
        log_likelihood=out.log_likelihood,
    )
