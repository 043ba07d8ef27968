"""Constrained parameters stored unconstrained, so an optimiser can move them freely.

* ψ > 0 (boundary layer): stored as ``log ψ``.
* 0 ≤ γ < 1 (memory): stored as ``logit γ`` when learnable, so a learnable γ lives in the open
  interval (0, 1) and a start at exactly 0 is refused; with ``learn=False`` the value is kept
  exactly (0 included) as a buffer.
* SPD matrices (Q, R): stored as a lower Cholesky factor with log-diagonal.
"""

from __future__ import annotations

import contextlib
import copy
import math
from collections.abc import Callable, Iterable, Iterator, Sequence

import torch
from torch import Tensor, nn

ArrayLike = float | Sequence[float] | Tensor


def as_tensor(value: ArrayLike, name: str) -> Tensor:
    """A float tensor from a number, sequence or tensor.

    Python numbers become float64, so a value like γ = 0.3 is not rounded to float32 before an
    estimator runs in float64; estimators cast parameters to the dtype of ``z`` at each call.
    """
    if isinstance(value, Tensor):
        if not value.is_floating_point():
            value = value.to(torch.float64)
        return value.detach().clone()
    try:
        return torch.as_tensor(value, dtype=torch.float64)
    except (TypeError, ValueError) as err:
        raise TypeError(f"{name}: expected a number, a sequence of numbers or a tensor") from err


class _Constrained(nn.Module):
    """Holds ``raw`` as a parameter (learn=True) or buffer and maps it to the constrained value."""

    def __init__(self, raw: Tensor, learn: bool) -> None:
        super().__init__()
        if learn:
            self.raw = nn.Parameter(raw)
        else:
            self.register_buffer("raw", raw)

    def forward(self) -> Tensor:
        raise NotImplementedError

    def scale_(self, factor: float) -> None:
        """The value times ``factor`` (> 0), in place, without gradients."""
        raise NotImplementedError


class Positive(_Constrained):
    """A positive tensor stored as its logarithm (``value = exp(raw)``)."""

    def __init__(self, value: ArrayLike, name: str, learn: bool = True) -> None:
        v = as_tensor(value, name)
        if not bool(torch.isfinite(v).all()) or bool((v <= 0).any()):
            raise ValueError(f"{name}: expected finite values > 0, got {v.tolist()}")
        super().__init__(v.log(), learn)

    def forward(self) -> Tensor:
        return self.raw.exp()

    def scale_(self, factor: float) -> None:
        with torch.no_grad():
            self.raw.add_(math.log(factor))


class UnitInterval(_Constrained):
    """A tensor in [0, 1): ``sigmoid(raw)`` when learnable, else the exact value as a buffer."""

    def __init__(self, value: ArrayLike, name: str, learn: bool = True) -> None:
        v = as_tensor(value, name)
        if not bool(torch.isfinite(v).all()) or bool((v < 0).any()) or bool((v >= 1).any()):
            raise ValueError(f"{name}: expected values in [0, 1), got {v.tolist()}")
        if learn and bool((v == 0).any()):
            raise ValueError(
                f"{name}: a learnable value lives in (0, 1) and cannot start at exactly 0; "
                "pass learn=False to fix it at 0, or start from a small positive value"
            )
        self.learn = learn
        super().__init__(torch.logit(v) if learn else v, learn)

    def forward(self) -> Tensor:
        return torch.sigmoid(self.raw) if self.learn else self.raw


class SPDMatrix(_Constrained):
    """A symmetric positive definite matrix ``L Lᵀ`` stored through its Cholesky factor ``L``.

    ``raw`` holds ``L`` with its diagonal replaced by ``log diag(L)``, so every value of ``raw``
    maps to an SPD matrix.
    """

    def __init__(self, value: ArrayLike, name: str, learn: bool = True) -> None:
        M = as_tensor(value, name)
        if M.ndim != 2 or M.shape[0] != M.shape[1]:
            raise ValueError(f"{name}: expected a square matrix, got shape {tuple(M.shape)}")
        if not bool(torch.isfinite(M).all()) or not torch.allclose(M, M.mT, rtol=1e-6, atol=0):
            raise ValueError(f"{name}: expected a finite symmetric matrix")
        L, info = torch.linalg.cholesky_ex(M)
        if int(info) != 0:
            raise ValueError(f"{name}: expected a positive definite matrix")
        raw = L.tril(-1) + torch.diag_embed(L.diagonal().log())
        super().__init__(raw, learn)

    def forward(self) -> Tensor:
        L = self.raw.tril(-1) + torch.diag_embed(self.raw.diagonal().exp())
        return L @ L.mT

    def scale_(self, factor: float) -> None:
        """``L Lᵀ`` times ``factor``: ``L`` times ``√factor``, its log-diagonal plus half the
        log."""
        with torch.no_grad():
            lower = self.raw.tril(-1).mul(math.sqrt(factor))
            diagonal = self.raw.diagonal().add(0.5 * math.log(factor))
            self.raw.copy_(lower + torch.diag_embed(diagonal))


@contextlib.contextmanager
def scaled_copy(
    module: nn.Module, factor: float, parameters: Callable[[nn.Module], Iterable[_Constrained]]
) -> Iterator[nn.Module]:
    """A copy of ``module`` whose constrained ``parameters(copy)`` are scaled by ``factor``
    (each once, however often it is listed: the IMM's modes share their model's ``R``);
    ``module`` itself where the factor is 1. ``module`` is never changed, so threads may share
    it (changed in place, a thread's tracks ran with another's ``q``: 92% of estimates off
    under Dask's threads)."""
    if factor == 1.0:
        yield module
        return
    scaled = copy.deepcopy(module)
    for parameter in {id(p): p for p in parameters(scaled)}.values():
        parameter.scale_(factor)
    yield scaled
