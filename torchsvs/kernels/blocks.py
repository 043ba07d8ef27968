"""2×2 blocks per axis, element by element, and the layouts they come in and go out in.

The per-axis kernel (:mod:`torchsvs.kernels.axes`, :mod:`torchsvs.kernels.axes_smoother`) and
its associative scans (:mod:`torchsvs.kernels.scan`) act on one 2×2 block per axis and track:
a block is a tuple of ``[..., m]`` tensors, :class:`Sym2` ``(a, b, c)`` for ``[[a, b], [b, c]]``
and :class:`Mat2` ``(a, b, c, d)`` for ``[[a, b], [c, d]]``, so a product of blocks is a few
elementwise operations on whole tensors instead of a batched product of small matrices. The
C++ loops (``cpp/``) write the same products out by hand (``M2`` in ``cpp/smoother.h``).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import torch
from torch import Tensor


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
    """The symmetric block ``S`` with both off-diagonal entries, for products."""
    return Mat2(S.a, S.b, S.b, S.c)


def matmul(X: Mat2, Y: Mat2) -> Mat2:
    """The block product ``X Y``."""
    return Mat2(
        X.a * Y.a + X.b * Y.c,
        X.a * Y.b + X.b * Y.d,
        X.c * Y.a + X.d * Y.c,
        X.c * Y.b + X.d * Y.d,
    )


def transpose(X: Mat2) -> Mat2:
    """``Xᵀ``."""
    return Mat2(X.a, X.c, X.b, X.d)


def add(*blocks: Mat2) -> Mat2:
    """The sum of the blocks, added left to right."""
    return Mat2(*(sum(parts[1:], parts[0]) for parts in zip(*blocks, strict=True)))


def negate(X: Mat2) -> Mat2:
    """``−X``."""
    return Mat2(-X.a, -X.b, -X.c, -X.d)


def symmetric_part(X: Mat2) -> Sym2:
    """``(X + Xᵀ) / 2`` of a block symmetric up to rounding."""
    return Sym2(X.a, 0.5 * (X.b + X.c), X.d)


def sandwich(X: Mat2, S: Mat2) -> Sym2:
    """``X S Xᵀ``, symmetrised."""
    return symmetric_part(matmul(matmul(X, S), transpose(X)))


def matvec(X: Mat2, u: tuple[Tensor, Tensor]) -> tuple[Tensor, Tensor]:
    """The block ``X`` times the per-axis 2-vector ``u = (u_0, u_1)``."""
    return X.a * u[0] + X.b * u[1], X.c * u[0] + X.d * u[1]


def inverse(S: Sym2) -> Sym2:
    """``S⁻¹`` of a symmetric block (by its determinant)."""
    det = S.a * S.c - S.b * S.b
    return Sym2(S.c / det, -S.b / det, S.a / det)


def inverse_general(X: Mat2) -> Mat2:
    """``X⁻¹`` of any invertible block (by its determinant)."""
    det = X.a * X.d - X.b * X.c
    return Mat2(X.d / det, -X.b / det, -X.c / det, X.a / det)


def transition(T: Tensor) -> Mat2:
    """``F = [[1, T], [0, 1]]`` of the nearly-constant-velocity model per axis."""
    one, zero = torch.ones_like(T), torch.zeros_like(T)
    return Mat2(one, T, zero, one)


def process_noise(q: Tensor, T: Tensor) -> Sym2:
    """``Q`` of Eq. (48), Chen et al. 2020, per axis."""
    return Sym2(q * T**3 / 3, q * T**2 / 2, q * T)


def masked_noise(R: Sym2, seen_p: Tensor, seen_v: Tensor) -> Sym2:
    """``R`` with an identity on missing components (as :func:`~torchsvs.linalg.mask_covariance`
    does)."""
    p, v = seen_p.to(R.a.dtype), seen_v.to(R.a.dtype)
    return Sym2(R.a * p + (1 - p), R.b * p * v, R.c * v + (1 - v))


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


def time_major(x: Tensor) -> Tensor:
    """A ``[B, T, m]`` per-step quantity as ``[T, B, m]`` contiguous; a constant (0-d, or one
    value per axis ``[m]``) as it is."""
    return x if x.ndim <= 1 else x.transpose(0, 1).contiguous()


def time_major_stack(items: Sequence[Tensor]) -> Tensor:
    """Per-step ``[B, m]`` tensors → ``[B, T, m]`` (stacked contiguously in time first: far
    cheaper than interleaving the copies)."""
    return torch.stack(list(items), dim=0).transpose(0, 1).contiguous()
