r"""The backward pass of the per-axis kernel (:mod:`torchsvs.kernels.axes`): the RTS and SVSS
smoothers, fixed interval or fixed lag, on 2×2 blocks per axis (:mod:`torchsvs.kernels.blocks`).

The general backward recursion of :class:`~torchsvs.smoothers.RTSSmoother` (any gain ``Γ``:
:func:`backward_terms`, :func:`_recurse`, :func:`_smoothed`) and the RTS's own fixed-interval
recursion, Eq. (17) (:func:`_rts_interval`), as tensor loops: the reference, the fallback
without a compiler and the path for higher derivatives. Their compiled twins are in
``cpp/smoother.h`` (called through :mod:`torchsvs.kernels.fused_axes`), with a compiled reverse
mode (``cpp/adjoints.h``, :class:`_CompiledSmoother`); tests hold both to 1e-10 in float64.
For few, long tracks the fixed interval runs as an associative scan
(:func:`torchsvs.kernels.scan.smoother_scan`).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, NamedTuple

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from torchsvs.kernels import build, fused_axes
from torchsvs.kernels.axes import AxisResult, summed_to
from torchsvs.kernels.blocks import (
    Mat2,
    Sym2,
    add,
    block_diagonal,
    full,
    interleave,
    inverse,
    masked_noise,
    matmul,
    matvec,
    negate,
    sandwich,
    symmetric_part,
    time_major,
    time_major_stack,
    transition,
    transpose,
)
from torchsvs.kernels.scan import prefer_scan, smoother_scan
from torchsvs.linalg import seen_from_here_on


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
                out[j] = summed_to([inputs[i]], [grad])[0]
                continue
            buffer = out[j]
            if buffer is None:
                buffer = out[j] = torch.zeros_like(tensors[j])
            buffer.as_strided(*at).add_(grad)
        return out


class _CompiledSmoother(torch.autograd.Function):
    """The compiled backward recursion (:func:`fused_axes.backward`: RTS or SVSS, fixed lag or
    interval) with its compiled reverse mode (:func:`fused_axes.backward_adjoint`). Inputs: the 20
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
        return fused_axes.backward(views.inputs(tensors), shape, lag, projection)

    @staticmethod
    @once_differentiable
    def backward(ctx: Any, *grads: Tensor | None) -> tuple[Tensor | None, ...]:
        shape, lag, projection, views = ctx.settings
        tensors = ctx.saved_tensors
        needed = ctx.needs_input_grad[4:]
        wanted = [needed[j] for j in views.source]
        inputs = views.inputs(tensors)
        dinputs = fused_axes.backward_adjoint(inputs, shape, lag, projection, grads, wanted)
        return (None, None, None, None, *views.gradients(tensors, dinputs))


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
    res = _inert_past_the_end(res)
    Pp = full(Sym2(*(x[:, 1:] for x in res.pred_cov)))
    P = full(Sym2(*(x[:, :-1] for x in res.cov)))
    K = Mat2(*(x[:, 1:] for x in res.gain))
    seen = tuple(o[:, 1:] for o in res.observed)
    R = full(masked_noise(Sym2(*(x[:, 1:] for x in res.noise)), *seen))
    fp, fv = (o.to(Pp.a.dtype) for o in seen)
    zero = torch.zeros_like(fp)
    H = Mat2(fp, zero, zero, fv)
    F = transition(_later(res.interval).expand_as(fp))
    PHt = matmul(Pp, H)  # H is diagonal
    S = add(matmul(H, PHt), R)
    Gamma = matmul(PHt, full(inverse(Sym2(S.a, S.b, S.d)))) if projection else K
    A = Mat2(1 - K.a, -K.b, -K.c, 1 - K.d)  # I − K H (K has zero columns where H does)
    X = add(matmul(transpose(PHt), transpose(A)), negate(matmul(R, transpose(K))))
    C = transpose(
        matmul(full(inverse(Sym2(Pp.a, Pp.b, Pp.d))), matmul(F, P))
    )  # P_{k|k} Fᵀ P_{k+1|k}⁻¹
    e = (res.innovation[0][:, 1:], res.innovation[1][:, 1:])
    return AxisBackward(
        C=C,
        d=matvec(Gamma, e),
        GHF=matmul(matmul(Gamma, H), F),
        GSG=matmul(matmul(Gamma, S), transpose(Gamma)),
        GX=matmul(Gamma, X),
        AF=matmul(A, F),
    )


def _slice(X: Mat2, k: slice | int) -> Mat2:
    return Mat2(*(x[:, k] for x in X))


def _recurse(
    b: AxisBackward, g: tuple[Tensor, Tensor], G: Mat2, Z: Mat2, k: slice | int
) -> tuple[tuple[Tensor, Tensor], Mat2, Mat2]:
    """One application of the backward recursion at steps ``k`` given the terms at ``k+1``."""
    C = _slice(b.C, k)
    cross = matmul(_slice(b.GX, k), transpose(G))
    d = (b.d[0][:, k], b.d[1][:, k])
    g_new = matvec(C, (d[0] + g[0], d[1] + g[1]))
    G_new = matmul(C, add(_slice(b.GHF, k), matmul(G, _slice(b.AF, k))))
    inner = add(_slice(b.GSG, k), cross, transpose(cross), Z)
    Z_new = matmul(matmul(C, inner), transpose(C))
    return g_new, G_new, Z_new


def _rts_interval(res: AxisResult) -> tuple[tuple[Tensor, Tensor], Sym2]:
    """The fixed-interval RTS recursion, Eq. (17), Chen et al. 2020:
    ``x̂ˢ_k = x̂_k + C_k (x̂ˢ_{k+1} − x̂_{k+1|k})``, ``Pˢ_k = P_k + C_k (Pˢ_{k+1} − P_{k+1|k}) C_kᵀ``.
    With the filter's own gain as ``Γ`` this equals the general recursion of
    :class:`~torchsvs.smoothers.RTSSmoother` for any gain, in a third of the operations."""
    steps = res.mean[0].shape[1]
    mean, pred = tuple(map(time_major, res.mean)), tuple(map(time_major, res.pred_mean))
    cov, pred_cov = Sym2(*map(time_major, res.cov)), Sym2(*map(time_major, res.pred_cov))
    interval = time_major(res.interval)
    p_s, v_s = mean[0][-1], mean[1][-1]
    P_s = Sym2(*(x[-1] for x in cov))
    means, covs = [(p_s, v_s)], [P_s]
    for k in range(steps - 2, -1, -1):
        T = interval if interval.ndim == 0 else interval[k + 1]
        P = Sym2(*(x[k] for x in cov))
        Pp = Sym2(*(x[k + 1] for x in pred_cov))
        # C = P Fᵀ Pp⁻¹ with Fᵀ = [[1, 0], [T, 1]].
        PFt = Mat2(P.a + T * P.b, P.b, P.b + T * P.c, P.c)
        C = matmul(PFt, full(inverse(Pp)))
        gp, gv = matvec(C, (p_s - pred[0][k + 1], v_s - pred[1][k + 1]))
        p_s, v_s = mean[0][k] + gp, mean[1][k] + gv
        D = sandwich(C, Mat2(P_s.a - Pp.a, P_s.b - Pp.b, P_s.b - Pp.b, P_s.c - Pp.c))
        P_s = Sym2(P.a + D.a, P.b + D.b, P.c + D.c)
        means.append((p_s, v_s))
        covs.append(P_s)
    means.reverse()
    covs.reverse()
    smoothed = (time_major_stack([m[0] for m in means]), time_major_stack([m[1] for m in means]))
    return smoothed, Sym2(*(time_major_stack(parts) for parts in zip(*covs, strict=True)))


def smooth_axes(res: AxisResult, projection: bool, lag: int | None) -> tuple[Tensor, Tensor]:
    """Smoothed mean ``[B, T, 2m]`` and covariance ``[B, T, 2m, 2m]`` in the general layout (see
    :meth:`~torchsvs.smoothers.RTSSmoother.smooth`): compiled (the RTS fixed interval by its own
    loop, Eq. (17), where no gradient is asked for; everything else by the general recursion,
    with its compiled reverse mode), else as tensor operations."""
    B, steps, m = res.mean[0].shape
    fixed_interval = not projection and (lag is None or lag >= steps - 1)
    if steps > 1 and fixed_interval:
        moments = (*res.mean, *res.cov, *res.pred_mean, *res.pred_cov, res.interval)
        if build.usable(*moments):
            return fused_axes.rts_interval(moments, (B, steps, m))
    if steps > 1:
        # The general recursion: the SVSS and fixed lags, and (with Γ = K it is the RTS) the
        # fixed interval when gradients are asked for, through its compiled reverse mode.
        filtered = _backward_inputs(res)
        if build.usable(*filtered, differentiable=True):
            if torch.is_grad_enabled() and any(x.requires_grad for x in filtered):
                views, tensors = _Views.of(filtered)
                return _CompiledSmoother.apply((B, steps, m), lag, projection, views, *tensors)
            return fused_axes.backward(filtered, (B, steps, m), lag, projection)
    (p, v), cov = _smooth_tensors(res, projection, lag, fixed_interval)
    return interleave(p, v), block_diagonal(full(cov))


def _inert_past_the_end(res: AxisResult) -> AxisResult:
    """``res`` with the steps after each track's last position (an axis's: a padded batch's
    shorter tracks) made inert for :func:`backward_terms`: covariances the identity, gains and
    innovations 0. Nothing is learnt there, so the recursion's terms are exactly 0 from them on
    either way (the compiled loop sets its ``C`` to 0 there), and the smoothed estimates the
    same; but a filter's covariance predicted over many empty steps
    can lose its definiteness to rounding (an SVSF's, near rank 1, at ``q`` 4e-12: a bus padded
    by 89 steps of 20 s to its group's longest track), and the recursion carried NaN back into
    every estimate of the track."""
    later = seen_from_here_on(res.observed[0])
    if bool(later.all()):
        return res
    after = ~later  # [B, T, m]: no position from this step on

    def inert(x: Tensor, value: float) -> Tensor:
        return torch.where(after, torch.as_tensor(value, dtype=x.dtype), x)

    cov, pred = (
        Sym2(inert(c.a, 1.0), inert(c.b, 0.0), inert(c.c, 1.0)) for c in (res.cov, res.pred_cov)
    )
    return res._replace(
        cov=cov,
        pred_cov=pred,
        gain=Mat2(*(inert(x, 0.0) for x in res.gain)),
        innovation=(inert(res.innovation[0], 0.0), inert(res.innovation[1], 0.0)),
    )


def _backward_inputs(res: AxisResult) -> tuple[Tensor, ...]:
    """The compiled backward recursion's 20 inputs (see :func:`fused_axes.backward`)."""
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
    PGt = matmul(P, transpose(G))
    cov = add(P, negate(PGt), negate(transpose(PGt)), Z)
    head = symmetric_part(cov)
    mean = tuple(torch.cat([res.mean[i][:, :-1] + g[i], res.mean[i][:, -1:]], 1) for i in range(2))
    smoothed = Sym2(*(torch.cat([h, x[:, -1:]], 1) for h, x in zip(head, res.cov, strict=True)))
    return (mean[0], mean[1]), smoothed
