r"""Per-axis recursions of the nearly-constant-velocity model: a structure-exploiting kernel.

A :class:`~torchsvs.models.ConstantVelocity` model with a diagonal ``R`` (and a prior without
cross-axis covariance) is ``m`` independent two-state problems, one per axis: state
:math:`(p, v)`, :math:`F = [[1, T], [0, 1]]`, :math:`Q = q[[T^3/3, T^2/2], [T^2/2, T]]`. The
Kalman filter, the SVSF (``H⁺`` mode or finite-difference velocities) and the RTS/SVSS backward
recursion then act on 2×2 blocks, written here element by element on ``[B, (T,) m]`` tensors:
a few dozen elementwise operations per step instead of batched 4×4 (or 6×6) matrix products,
which on a CPU cost far more per element than the arithmetic. Results are exactly the general
path's (tested to 1e-9 in float64): the estimators pick this kernel by themselves. The forward
loop runs compiled (:mod:`torchsvs.kernels.fused`, the same formulas in C++), with gradients
through its compiled reverse mode (:class:`_CompiledAxes`); so does the smoother's general
recursion (:class:`_CompiledSmoother`). A one-step-lag smoother (the paper's KS, SVSTPS and
SVSS) needs no pass of its own: the compiled forward loop smooths step ``k`` as soon as step
``k + 1`` is done (:func:`run_axes` with ``smoothing``; its adjoint takes the smoothing back
too), so the filter's record need not be written and read back. The tensor loops below are
the reference, the fallback without a compiler, and the path for higher derivatives.

Every axis has a two-component corrector measurement :math:`y = (y_p, y_v)` with ``H = I``;
position-only correctors (Kalman filter, the SVSF's ``H⁺`` mode) have :math:`y_v` always missing.
A 2×2 block is a tuple of ``[..., m]`` tensors: :class:`Sym2` ``(a, b, c)`` for
``[[a, b], [b, c]]`` and :class:`Mat2` ``(a, b, c, d)`` for ``[[a, b], [c, d]]``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any, NamedTuple, cast

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from torchsvs.kernels import fused
from torchsvs.linalg import boundary_inflation, svsf_gain_ratio


class Sym2(NamedTuple):
    """A symmetric 2×2 block ``[[a, b], [b, c]]``."""

    a: Tensor
    b: Tensor
    c: Tensor


class Mat2(NamedTuple):
    """A 2×2 block ``[[a, b], [c, d]]``."""

    a: Tensor
    b: Tensor
    c: Tensor
    d: Tensor


def full(S: Sym2) -> Mat2:
    return Mat2(S.a, S.b, S.b, S.c)


def mm(X: Mat2, Y: Mat2) -> Mat2:
    return Mat2(
        X.a * Y.a + X.b * Y.c,
        X.a * Y.b + X.b * Y.d,
        X.c * Y.a + X.d * Y.c,
        X.c * Y.b + X.d * Y.d,
    )


def t(X: Mat2) -> Mat2:
    return Mat2(X.a, X.c, X.b, X.d)


def add(*blocks: Mat2) -> Mat2:
    return Mat2(*(sum(parts[1:], parts[0]) for parts in zip(*blocks, strict=True)))


def sandwich(X: Mat2, S: Mat2) -> Sym2:
    """``X S Xᵀ``, symmetrised."""
    P = mm(mm(X, S), t(X))
    return Sym2(P.a, 0.5 * (P.b + P.c), P.d)


def mv(X: Mat2, u: tuple[Tensor, Tensor]) -> tuple[Tensor, Tensor]:
    return X.a * u[0] + X.b * u[1], X.c * u[0] + X.d * u[1]


def inverse(S: Sym2) -> Sym2:
    det = S.a * S.c - S.b * S.b
    return Sym2(S.c / det, -S.b / det, S.a / det)


def interleave(p: Tensor, v: Tensor) -> Tensor:
    """``[..., m]`` positions and velocities → ``[..., 2m]`` in state order ``p1, v1, p2, ...``."""
    return torch.stack([p, v], dim=-1).flatten(-2)


def block_diagonal(block: Mat2) -> Tensor:
    """Per-axis 2×2 blocks ``[..., m]`` → the block-diagonal ``[..., 2m, 2m]``."""
    *lead, m = block.a.shape
    out = block.a.new_zeros(*lead, m, 2, m, 2)
    diagonal = out.diagonal(dim1=-4, dim2=-2)  # a view [..., 2, 2, m] of the axes' own blocks
    for (row, col), part in zip(((0, 0), (0, 1), (1, 0), (1, 1)), block, strict=True):
        diagonal[..., row, col, :] = part
    return out.reshape(*lead, 2 * m, 2 * m)


def transition(T: Tensor) -> Mat2:
    one, zero = torch.ones_like(T), torch.zeros_like(T)
    return Mat2(one, T, zero, one)


def process_noise(q: Tensor, T: Tensor) -> Sym2:
    """``Q`` of Eq. (48), Chen et al. 2020, per axis."""
    return Sym2(q * T**3 / 3, q * T**2 / 2, q * T)


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
    noise: Sym2  #: R per axis, unmasked (users mask it by ``observed``: _masked_noise)
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


def _masked_noise(R: Sym2, seen_p: Tensor, seen_v: Tensor) -> Sym2:
    """``R`` with an identity on missing components (as :func:`~torchsvs.linalg.mask_covariance`
    does)."""
    p, v = seen_p.to(R.a.dtype), seen_v.to(R.a.dtype)
    return Sym2(R.a * p + (1 - p), R.b * p * v, R.c * v + (1 - v))


def _at(x: Tensor, t: int) -> Tensor:
    return x[:, t] if x.ndim == 3 else x


def joseph(P: Sym2, K: Mat2, R: Sym2) -> Sym2:
    """``(I − K) P (I − K)ᵀ + K R Kᵀ`` (``H = I`` per axis; masked components have zero columns
    of ``K``)."""
    A = Mat2(1 - K.a, -K.b, -K.c, 1 - K.d)
    X, Y = sandwich(A, full(P)), sandwich(K, full(R))
    return Sym2(X.a + Y.a, X.b + Y.b, X.c + Y.c)


def _forward_step(
    rule: str, gamma: Tensor, state: tuple[Tensor, ...], given: tuple[Tensor, ...]
) -> tuple[tuple[Tensor, ...], tuple[Tensor, ...]]:
    """One predict-correct step of every axis (see :func:`run_axes`); pure, so that a chunk of
    steps can be compiled."""
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
    return state, tuple(_time_major_stack(column) for column in zip(*outputs, strict=True))


def _time_major_stack(items: Sequence[Tensor]) -> Tensor:
    """Per-step ``[B, m]`` tensors → ``[B, T, m]`` (stacked contiguously in time first: far
    cheaper than interleaving the copies)."""
    return torch.stack(list(items), dim=0).transpose(0, 1).contiguous()


def _time_major(x: Tensor) -> Tensor:
    """A ``[B, T, m]`` per-step quantity as ``[T, B, m]`` contiguous; a constant (0-d, or one
    value per axis ``[m]``) as it is."""
    return x if x.ndim <= 1 else x.transpose(0, 1).contiguous()


class AxesPass(NamedTuple):
    """What :func:`run_axes` gives."""

    per_axis: AxisResult | None  #: the pass per axis (None: only the kept moments written)
    out: Interleaved  #: the pass in the general layout
    last: fused.Last  #: the state after the last step
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
    loop also gives the smoothed moments, of lag 1 as it steps (:func:`fused.forward`), and
    of other lags when keeping less than all (:func:`fused.filter_smoother`), with gradients
    through their adjoint; else ``smoothed`` is ``None`` and the pass keeps all, for
    :func:`smooth_axes`.

    Args:
        y: the corrector's measurements per axis.
        x0, P0: the prior per axis, ``[B, m]`` each.
        q: process noise spectral density (0-d).
        interval: ``T`` per step, 0-d or ``[B, T]``.
        rule: ``"kalman"`` (position-only corrector, gain ``P Hᵀ S⁻¹``, Eqs. (14)-(16), Chen et
            al. 2020) or ``"svsf"`` (``K = diag(ratio)`` on the observed components, Eq. (23)
            with ``H⁺ = I``; the ``H⁺`` mode has no velocity measurements).
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
    compiled = rule in ("kalman", "svsf")  # (the variable boundary layer: tensor loops)
    if compiled and m <= fused.MAX_AXES and fused.usable(*raw, *prior, gamma, differentiable=True):
        inputs = (*raw, *prior)
        shape = (B, steps, m)
        training = torch.is_grad_enabled() and any(x.requires_grad for x in (*inputs, gamma))
        # A lag other than 1 smooths in the filter's pass where less than all is kept (and
        # there is a step to smooth); else the smoother's own pass reads the whole record.
        together = smoothing is not None and lag != 1 and keep != "all" and steps > 1
        if together and not training:  # where it pays: see _TOGETHER
            together = B * m >= _TOGETHER["lanes"] and steps <= _TOGETHER["steps"]
        if smoothing is not None and lag != 1 and not together:
            keep, smoothing = "all", None
        if training:
            # Only what is kept is written, as without gradients: the adjoint recomputes the
            # steps' states, and the state after the last step is an output of its own.
            parts = _CompiledAxes.apply(
                rule, velocity, shape, keep, smoothing, lag, gamma, *inputs
            )  # fmt: skip
            out = Interleaved(*parts[:10])
            last = fused.Last(*parts[10:13])
            smoothed = None if smoothing is None else (parts[13], parts[14])
        else:
            outputs, last, smoothed = fused.filter_pass(
                rule, float(gamma), raw, prior, shape, velocity, keep, smoothing, lag
            )
            out = Interleaved(*cast(Any, outputs))  # the fields not kept are None
        if keep != "all":
            return AxesPass(None, out, last, smoothed)
        return AxesPass(per_axis(out, noise, T_all, velocity), out, last, smoothed)
    seen_p, seen_v = ~torch.isnan(y.position), ~torch.isnan(y.velocity)
    R_all = _masked_noise(y.noise, seen_p, seen_v)
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
        from torchsvs.kernels.scan import filter_scan

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
        stepped = _forward_chunk(rule, gamma, state, tuple(map(_time_major, inputs)), steps)[1]
    (p, v, a, b, c, pp, a1, b1, c1, ep, ev, ka, kb, kc, kd, mp, mv) = stepped
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
        post_innovation=None if rule == "kalman" else (mp, mv),
        log_likelihood=loglik,
    )
    out = interleaved(res, velocity)
    return AxesPass(res, out, _last(out))


#: Without gradients, the filter and a smoother of lag other than 1 run together
#: (:func:`fused.filter_smoother`) from this many lanes (tracks × axes: a vector of float32
#: lanes filled twice) and up to this many steps (a vector's record, ~2 kB a step, stays in
#: cache); else the record is written and smoothed after (one track of 100,000 steps: 8×
#: faster so, the RTS's own fixed-interval loop being lighter than the general recursion).
#: With gradients they always run together: the whole record's reverse mode costs far more.
_TOGETHER = {"lanes": 16, "steps": 4096}


def _last(out: Interleaved) -> fused.Last:
    """The state after a whole-history pass's last step."""
    post = out.post_innovation
    return fused.Last(out.mean[:, -1], out.cov[:, -1], None if post is None else post[:, -1])


class _CompiledAxes(torch.autograd.Function):
    """The compiled forward loop (:func:`fused.forward`) with its compiled reverse mode
    (:func:`fused.adjoint`): training runs the loop at inference speed. Inputs: the 11 given
    quantities and the 5 prior ones of :func:`run_axes`, in :func:`fused.forward`'s order;
    outputs: the :class:`Interleaved` fields (those ``keep`` leaves out ``None``), the state
    after the last step (:class:`fused.Last`) and, with ``smoothing``, the smoothed mean and
    covariance (else ``None``), 15 in all: of lag 1 inside the forward loop, else (``keep``
    ``"moments"`` or ``"mean"``) of ``lag`` by :func:`fused.filter_smoother`. First
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
        out, last, smoothed = fused.filter_pass(
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
        dgiven, dprior, dgamma = fused.adjoint(
            rule, float(gamma), given, prior, shape, velocity, differentiable, wanted[:11],
            smoothing, lag,
        )  # fmt: skip
        # rule, velocity, shape, keep, smoothing, lag
        result: list[Tensor | None] = [None] * 6
        result.append(dgamma.sum().reshape(gamma.shape) if ctx.needs_input_grad[6] else None)
        result += _summed_to(given, dgiven)
        for x, dx, w in zip(prior, dprior, wanted[11:], strict=True):
            result.append(dx.reshape(x.shape) if w else None)
        return tuple(result)


def _summed_to(inputs: Sequence[Tensor], grads: Sequence[Tensor | None]) -> list[Tensor | None]:
    """Gradients ``[B, T, m]`` of inputs given ``[B, T, m]``-broadcastable (0-d, ``[m]``,
    ``[B, T, 1]``, ...), summed over their broadcast dimensions."""
    out: list[Tensor | None] = []
    for x, dx in zip(inputs, grads, strict=True):
        if dx is not None and x.ndim == 3 and dx.shape[1] != x.shape[1]:
            dx = dx.expand(x.shape)  # summed over the steps already: x is constant in time
        broadcast = x.shape if x.ndim == 3 else (1, 1, x.numel())
        out.append(None if dx is None else dx.sum_to_size(broadcast).reshape(x.shape))
    return out


class _Views(NamedTuple):
    """How a Function's inputs stand to the tensors it is given: input ``i`` is ``tensors[j]``
    itself (``strides[i]`` None) or its view ``as_strided(size, stride, offset)``. Handing a
    Function the base of the views it reads, instead of the views, gives its gradient in one
    buffer: autograd would back-propagate each view into a zero-filled copy of the whole base
    and add those up (three full passes per view)."""

    source: tuple[int, ...]  #: per input, the index of its tensor
    strides: tuple[
        tuple[tuple[int, ...], tuple[int, ...], int] | None, ...
    ]  #: size, stride, offset

    @staticmethod
    def of(inputs: Sequence[Tensor]) -> tuple[_Views, list[Tensor]]:
        """The recipe and the tensors for ``inputs``: views of a base that needs a gradient,
        with no element twice (no zero stride), go through their base."""
        tensors: list[Tensor] = []
        source: list[int] = []
        strides: list[tuple[tuple[int, ...], tuple[int, ...], int] | None] = []
        for x in inputs:
            base = x._base
            if base is None or not base.requires_grad or 0 in x.stride() or x.ndim == 0:
                source.append(len(tensors))
                strides.append(None)
                tensors.append(x)
                continue
            found = next((j for j, t in enumerate(tensors) if t is base), None)
            if found is None:
                found = len(tensors)
                tensors.append(base)
            source.append(found)
            strides.append((tuple(x.shape), x.stride(), int(x.storage_offset())))
        return _Views(tuple(source), tuple(strides)), tensors

    def inputs(self, tensors: Sequence[Tensor]) -> list[Tensor]:
        return [
            tensors[j] if at is None else tensors[j].as_strided(*at)
            for j, at in zip(self.source, self.strides, strict=True)
        ]

    def gradients(
        self, tensors: Sequence[Tensor], grads: Sequence[Tensor | None]
    ) -> list[Tensor | None]:
        """The tensors' gradients from the inputs' (``[B, T, m]``, summed to broadcast
        inputs' shapes)."""
        inputs = self.inputs(tensors)
        out: list[Tensor | None] = [None] * len(tensors)
        for i, (j, at) in enumerate(zip(self.source, self.strides, strict=True)):
            grad = grads[i]
            if grad is None:
                continue
            if at is None:
                out[j] = _summed_to([inputs[i]], [grad])[0]
                continue
            buffer = out[j]
            if buffer is None:
                buffer = out[j] = torch.zeros_like(tensors[j])
            buffer.as_strided(*at).add_(grad)
        return out


class _CompiledSmoother(torch.autograd.Function):
    """The compiled backward recursion (:func:`fused.backward`: RTS or SVSS, fixed lag or
    interval) with its compiled reverse mode (:func:`fused.backward_adjoint`). Inputs: the 20
    of :func:`_backward_inputs`, given as :class:`_Views` of tensors (the filter's general
    layout); outputs: the smoothed mean and covariance (general layout)."""

    @staticmethod
    def forward(
        ctx: Any,
        shape: tuple[int, int, int],
        lag: int | None,
        projection: bool,
        views: _Views,
        *tensors: Tensor,
    ) -> tuple[Tensor, Tensor]:
        ctx.settings = (shape, lag, projection, views)
        ctx.save_for_backward(*tensors)
        ctx.set_materialize_grads(False)
        return fused.backward(views.inputs(tensors), shape, lag, projection)

    @staticmethod
    @once_differentiable
    def backward(ctx: Any, *grads: Tensor | None) -> tuple[Tensor | None, ...]:
        shape, lag, projection, views = ctx.settings
        tensors = ctx.saved_tensors
        needed = ctx.needs_input_grad[4:]
        wanted = [needed[j] for j in views.source]
        inputs = views.inputs(tensors)
        dinputs = fused.backward_adjoint(inputs, shape, lag, projection, grads, wanted)
        return (None, None, None, None, *views.gradients(tensors, dinputs))


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
    R = _masked_noise(res.noise, seen_p, seen_v)
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


def _pair(items: list[tuple[Tensor, Tensor]]) -> tuple[Tensor, Tensor]:
    return torch.stack([i[0] for i in items], dim=1), torch.stack([i[1] for i in items], dim=1)


def _later(x: Tensor) -> Tensor:
    """Steps ``1..T-1`` of a per-step tensor (unchanged when constant over time)."""
    return x[:, 1:] if x.ndim == 3 else x


class AxisBackward(NamedTuple):
    """The backward recursion's terms per axis at index ``k+1``, ``[B, T-1, m]`` (see
    :class:`~torchsvs.smoothers.rts.Backward`)."""

    C: Mat2
    d: tuple[Tensor, Tensor]
    GHF: Mat2
    GSG: Mat2
    GX: Mat2
    AF: Mat2


def backward_terms(res: AxisResult, projection: bool) -> AxisBackward:
    """``C, Γe, ΓHF, ΓSΓᵀ, ΓX, AF`` of :class:`~torchsvs.smoothers.RTSSmoother` per axis, with
    ``Γ = K`` (RTS) or, with ``projection``, ``Γ = P Hᵀ S⁻¹`` (SVSS, Eq. (42))."""
    Pp = full(Sym2(*(x[:, 1:] for x in res.pred_cov)))
    P = full(Sym2(*(x[:, :-1] for x in res.cov)))
    K = Mat2(*(x[:, 1:] for x in res.gain))
    seen = tuple(o[:, 1:] for o in res.observed)
    R = full(_masked_noise(Sym2(*(x[:, 1:] for x in res.noise)), *seen))
    fp, fv = (o.to(Pp.a.dtype) for o in seen)
    zero = torch.zeros_like(fp)
    H = Mat2(fp, zero, zero, fv)
    F = transition(_later(res.interval).expand_as(fp))
    PHt = mm(Pp, H)  # H is diagonal
    S = add(mm(H, PHt), R)
    Gamma = mm(PHt, full(inverse(Sym2(S.a, S.b, S.d)))) if projection else K
    A = Mat2(1 - K.a, -K.b, -K.c, 1 - K.d)  # I − K H (K has zero columns where H does)
    X = add(mm(t(PHt), t(A)), _neg(mm(R, t(K))))
    C = t(mm(full(inverse(Sym2(Pp.a, Pp.b, Pp.d))), mm(F, P)))  # P_{k|k} Fᵀ P_{k+1|k}⁻¹
    e = (res.innovation[0][:, 1:], res.innovation[1][:, 1:])
    return AxisBackward(
        C=C,
        d=mv(Gamma, e),
        GHF=mm(mm(Gamma, H), F),
        GSG=mm(mm(Gamma, S), t(Gamma)),
        GX=mm(Gamma, X),
        AF=mm(A, F),
    )


def _neg(X: Mat2) -> Mat2:
    return Mat2(-X.a, -X.b, -X.c, -X.d)


def _slice(X: Mat2, k: slice | int) -> Mat2:
    return Mat2(*(x[:, k] for x in X))


def _recurse(
    b: AxisBackward, g: tuple[Tensor, Tensor], G: Mat2, Z: Mat2, k: slice | int
) -> tuple[tuple[Tensor, Tensor], Mat2, Mat2]:
    """One application of the backward recursion at steps ``k`` given the terms at ``k+1``."""
    C = _slice(b.C, k)
    cross = mm(_slice(b.GX, k), t(G))
    d = (b.d[0][:, k], b.d[1][:, k])
    g_new = mv(C, (d[0] + g[0], d[1] + g[1]))
    G_new = mm(C, add(_slice(b.GHF, k), mm(G, _slice(b.AF, k))))
    inner = add(_slice(b.GSG, k), cross, t(cross), Z)
    Z_new = mm(mm(C, inner), t(C))
    return g_new, G_new, Z_new


def prefer_scan(tracks: int, steps: int) -> bool:
    """Whether an associative scan over time beats the step-by-step tensor loop: for few, long
    tracks (its ``O(log T)`` rounds do several times the arithmetic of the loop, which pays only
    where the loop's cost is the per-step overhead of small operations). The compiled loops
    beat both; this choice is for the tensor loops (:func:`~torchsvs.kernels.eager_loops`, no
    compiler, higher derivatives)."""
    return steps >= 64 and tracks * 16 <= steps * 4 + 4096


def _rts_interval(res: AxisResult) -> tuple[tuple[Tensor, Tensor], Sym2]:
    """The fixed-interval RTS recursion, Eq. (17), Chen et al. 2020:
    ``x̂ˢ_k = x̂_k + C_k (x̂ˢ_{k+1} − x̂_{k+1|k})``, ``Pˢ_k = P_k + C_k (Pˢ_{k+1} − P_{k+1|k}) C_kᵀ``.
    With the filter's own gain as ``Γ`` this equals the general recursion of
    :class:`~torchsvs.smoothers.RTSSmoother` for any gain, in a third of the operations."""
    steps = res.mean[0].shape[1]
    mean, pred = tuple(map(_time_major, res.mean)), tuple(map(_time_major, res.pred_mean))
    cov, pred_cov = Sym2(*map(_time_major, res.cov)), Sym2(*map(_time_major, res.pred_cov))
    interval = _time_major(res.interval)
    p_s, v_s = mean[0][-1], mean[1][-1]
    P_s = Sym2(*(x[-1] for x in cov))
    means, covs = [(p_s, v_s)], [P_s]
    for k in range(steps - 2, -1, -1):
        T = interval if interval.ndim == 0 else interval[k + 1]
        P = Sym2(*(x[k] for x in cov))
        Pp = Sym2(*(x[k + 1] for x in pred_cov))
        # C = P Fᵀ Pp⁻¹ with Fᵀ = [[1, 0], [T, 1]].
        PFt = Mat2(P.a + T * P.b, P.b, P.b + T * P.c, P.c)
        C = mm(PFt, full(inverse(Pp)))
        gp, gv = mv(C, (p_s - pred[0][k + 1], v_s - pred[1][k + 1]))
        p_s, v_s = mean[0][k] + gp, mean[1][k] + gv
        D = sandwich(C, Mat2(P_s.a - Pp.a, P_s.b - Pp.b, P_s.b - Pp.b, P_s.c - Pp.c))
        P_s = Sym2(P.a + D.a, P.b + D.b, P.c + D.c)
        means.append((p_s, v_s))
        covs.append(P_s)
    means.reverse()
    covs.reverse()
    smoothed = (_time_major_stack([m[0] for m in means]), _time_major_stack([m[1] for m in means]))
    return smoothed, Sym2(*(_time_major_stack(parts) for parts in zip(*covs, strict=True)))


def smooth_axes(res: AxisResult, projection: bool, lag: int | None) -> tuple[Tensor, Tensor]:
    """Smoothed mean ``[B, T, 2m]`` and covariance ``[B, T, 2m, 2m]`` in the general layout (see
    :meth:`~torchsvs.smoothers.RTSSmoother.smooth`): compiled (the RTS fixed interval by its own
    loop, Eq. (17), where no gradient is asked for; everything else by the general recursion,
    with its compiled reverse mode), else as tensor operations."""
    B, steps, m = res.mean[0].shape
    fixed_interval = not projection and (lag is None or lag >= steps - 1)
    if steps > 1 and fixed_interval:
        moments = (*res.mean, *res.cov, *res.pred_mean, *res.pred_cov, res.interval)
        if fused.usable(*moments):
            return fused.rts_interval(moments, (B, steps, m))
    if steps > 1:
        # The general recursion: the SVSS and fixed lags, and (with Γ = K it is the RTS) the
        # fixed interval when gradients are asked for, through its compiled reverse mode.
        filtered = _backward_inputs(res)
        if fused.usable(*filtered, differentiable=True):
            if torch.is_grad_enabled() and any(x.requires_grad for x in filtered):
                views, tensors = _Views.of(filtered)
                return _CompiledSmoother.apply((B, steps, m), lag, projection, views, *tensors)
            return fused.backward(filtered, (B, steps, m), lag, projection)
    (p, v), cov = _smooth_tensors(res, projection, lag, fixed_interval)
    return interleave(p, v), block_diagonal(full(cov))


def _backward_inputs(res: AxisResult) -> tuple[Tensor, ...]:
    """The compiled backward recursion's 20 inputs (see :func:`fused.backward`)."""
    dtype = res.mean[0].dtype
    return (
        *res.cov,
        *res.pred_cov,
        *res.gain,
        *res.noise,
        *(seen.to(dtype) for seen in res.observed),
        res.interval,
        *res.innovation,
        *res.mean,
    )


def _smooth_tensors(
    res: AxisResult, projection: bool, lag: int | None, fixed_interval: bool
) -> tuple[tuple[Tensor, Tensor], Sym2]:
    """:func:`smooth_axes` as tensor operations (differentiable), per axis."""
    steps = res.mean[0].shape[1]
    if steps == 1:
        return res.mean, res.cov
    if fixed_interval:
        if prefer_scan(res.mean[0].shape[0] * res.mean[0].shape[2], steps):
            from torchsvs.kernels.scan import smoother_scan

            return smoother_scan(res.mean, res.cov, res.pred_mean, res.pred_cov, res.interval)
        return _rts_interval(res)
    b = backward_terms(res, projection)
    zeros = torch.zeros_like(b.d[0])
    if lag is None or lag >= steps - 1:
        g = (zeros[:, 0], zeros[:, 0])
        G = Mat2(*(zeros[:, 0],) * 4)
        Z = G
        out = []
        for k in range(steps - 2, -1, -1):
            g, G, Z = _recurse(b, g, G, Z, k)
            out.append((g, G, Z))
        out.reverse()
        g = (torch.stack([o[0][0] for o in out], 1), torch.stack([o[0][1] for o in out], 1))
        G = Mat2(*(torch.stack([o[1][i] for o in out], 1) for i in range(4)))
        Z = Mat2(*(torch.stack([o[2][i] for o in out], 1) for i in range(4)))
    else:
        g, G, Z = (zeros, zeros), Mat2(*(zeros,) * 4), Mat2(*(zeros,) * 4)

        def shift(x: Tensor) -> Tensor:
            return torch.cat([x[:, 1:], torch.zeros_like(x[:, :1])], dim=1)

        for _ in range(lag):
            g, G, Z = _recurse(
                b,
                (shift(g[0]), shift(g[1])),
                Mat2(*(shift(x) for x in G)),
                Mat2(*(shift(x) for x in Z)),
                slice(None),
            )
    return _smoothed(res, g, G, Z)


def _smoothed(
    res: AxisResult, g: tuple[Tensor, Tensor], G: Mat2, Z: Mat2
) -> tuple[tuple[Tensor, Tensor], Sym2]:
    """``x̂ˢ_k = x̂_k + g_k``, ``Pˢ_k = P_k − P_k G_kᵀ − G_k P_k + Z_k`` (the last step as
    filtered)."""
    P = full(Sym2(*(x[:, :-1] for x in res.cov)))
    PGt = mm(P, t(G))
    cov = add(P, _neg(PGt), _neg(t(PGt)), Z)
    head = Sym2(cov.a, 0.5 * (cov.b + cov.c), cov.d)
    mean = tuple(torch.cat([res.mean[i][:, :-1] + g[i], res.mean[i][:, -1:]], 1) for i in range(2))
    smoothed = Sym2(*(torch.cat([h, x[:, -1:]], 1) for h, x in zip(head, res.cov, strict=True)))
    return (mean[0], mean[1]), smoothed
