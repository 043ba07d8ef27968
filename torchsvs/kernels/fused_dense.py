"""The dense linear filters' predict-correct step, compiled (``cpp/dense.h``; built by
:mod:`torchsvs.kernels.build`).

:func:`dense_run` is the predict-correct step of a dense linear model (KF, or the SVSF's H⁺
mode with a selection ``H``) per track, over one step (an online ``step`` call: a Python-level
step costs dozens of tensor operations; :class:`OnlineStep`) or a whole run of a model the
per-axis kernel does not cover. Its twin is the tensor path (``GaussianFilter.predict``, then
the Kalman update of ``torchsvs.filters.gaussian.kalman_update`` or the SVSF's correction):
tests hold both to 1e-10 in float64.
"""

from __future__ import annotations

import ctypes
import functools
import math
import threading
from collections.abc import Sequence
from typing import Any

import torch
from torch import Tensor

from torchsvs.kernels import build
from torchsvs.kernels.build import fresh, pointers

#: Largest state or measurement size of :func:`dense_run` (``kMax`` in ``cpp/dense.h``).
DENSE_MAX = 16


class DenseMatrices:
    """``F, Q, H, R`` of a run of compiled online steps (contiguous, one dtype) and their
    pointers, built once."""

    def __init__(self, matrices: Sequence[Tensor]) -> None:
        self.tensors = list(matrices)
        self.pointers = pointers(self.tensors)
        self.meas_dim = self.tensors[2].shape[0]  #: rows of H


def dense_run(
    rule: str,
    gamma: float,
    x: Tensor,
    P: Tensor,
    z: Tensor,
    memory: Tensor,
    psi: Tensor,
    matrices: DenseMatrices,
    lead: tuple[int, ...],
    keep: str = "all",
) -> tuple[Tensor | None, ...] | None:
    """Predict-correct steps of a dense linear-Gaussian filter, compiled: ``B`` tracks from
    ``x [B, n]``, ``P [B, n, n]`` over ``z [B, T, m]`` (NaN: missing), the SVSF's ``memory
    [B, m]`` and ``psi`` (``[B, T, m]`` or ``[m]``); all contiguous, one dtype. ``rule``
    ``"kalman"`` or ``"svsf"`` (``H`` with orthonormal rows). ``lead``: the outputs' leading
    shape (``(B, T)``; ``(B,)`` or ``()`` for one step). Returns ``x, P, x_pred, P_pred, e, K,
    S, log_likelihood, e_post, observed`` (with ``keep`` other than ``"all"``: ``None`` for
    those it leaves out, written to a scratch buffer; the covariance, the Kalman rule's
    log-likelihood and the SVSF's ``e_post`` stay, a state needs them), or ``None`` when ``z``
    holds an infinity or a Cholesky factor failed."""
    lib = build.library()  # loaded: usable() said so
    assert isinstance(lib, ctypes.CDLL)
    B, n = x.shape
    T, m = z.shape[-2:] if z.ndim == 3 else (1, z.shape[-1])
    dtype = x.dtype
    shapes = ((n,), (n, n), (n,), (n, n), (m,), (n, m), (m, m), (), (m,), (m,))
    # A state needs the covariance, the log-likelihood (Kalman) and the memory (SVSF).
    kept = _KEPT[keep, rule]
    make = fresh if T > 1 else torch.empty  # one step's outputs are small
    out: list[Tensor | None] = [
        make(lead + shape, dtype=torch.bool if i == 9 else dtype) if i in kept else None
        for i, shape in enumerate(shapes)
    ]
    per_track = psi.ndim > 1
    addresses, _scratch_held = _addresses(out, shapes, (lead, dtype, kept))  # held in the call
    call = lib.dense_run_f32 if dtype == torch.float32 else lib.dense_run_f64
    failed = call(
        B,
        T,
        n,
        m,
        0 if rule == "kalman" else 1,
        float(gamma),
        x.data_ptr(),
        P.data_ptr(),
        z.data_ptr(),
        memory.data_ptr(),
        psi.data_ptr(),
        T * m if per_track else 0,
        m if per_track and T > 1 else 0,
        matrices.pointers,
        *addresses,
        None,
        None,
    )
    return None if failed else tuple(out)


class OnlineStep:
    """:func:`dense_run` for one step of ``B`` tracks (results of leading shape ``lead``),
    keeping what ``keep`` keeps, with everything but the step's own tensors formed once: the
    outputs' prototypes, the scratch addresses of those not kept, the call's other arguments
    (in the arrays ``dense_step`` reads). An online step then costs its allocations and one
    call of three arguments (against filterpy: ``benchmarks/one_track.md``). One
    thread's: the arguments and scratch are written by every call."""

    def __init__(
        self,
        rule: str,
        gamma: float,
        matrices: DenseMatrices,
        n: int,
        lead: tuple[int, ...],
        dtype: torch.dtype,
        keep: str,
    ) -> None:
        lib = build.library()
        assert isinstance(lib, ctypes.CDLL)
        m = matrices.meas_dim
        B = math.prod(lead)
        shapes = ((n,), (n, n), (n,), (n, n), (m,), (n, m), (m, m), (), (m,), (m,))
        self.kept = _KEPT[keep, rule]
        self.prototypes = [
            torch.empty(lead + shapes[i], dtype=torch.bool if i == 9 else dtype) for i in self.kept
        ]
        given: list[Tensor | None] = [None] * 10
        for i, x in zip(self.kept, self.prototypes, strict=True):
            given[i] = x
        outs, self._scratch = _addresses(given, shapes, (lead, dtype, self.kept))
        self.totals = torch.empty(B, dtype=dtype) if rule == "kalman" else None
        self.sizes = (ctypes.c_int64 * 5)(B, n, m, 0 if rule == "kalman" else 1, 0)
        # x, P, z, memory, psi, F, Q, H, R, the outputs, the totals in and out
        self.arguments = (ctypes.c_void_p * 21)(*[None] * 5, *matrices.pointers, *outs)
        # The kept outputs' slots as runs of consecutive ones (a slice assignment each).
        self.runs: list[tuple[int, int, int]] = []  # slot start, output start, output stop
        for j, i in enumerate(self.kept):
            if self.runs and self.runs[-1][0] + j - self.runs[-1][1] == 9 + i:
                self.runs[-1] = (*self.runs[-1][:2], j + 1)
            else:
                self.runs.append((9 + i, j, j + 1))
        self.matrices = matrices  # (alive while its pointers are used)
        call = lib.dense_step_f32 if dtype == torch.float32 else lib.dense_step_f64
        self.call = functools.partial(call, self.sizes, gamma, self.arguments)

    def __call__(
        self, x: Tensor, P: Tensor, z: Tensor, memory: Tensor, psi: Tensor, total: Tensor | None
    ) -> tuple[list[Tensor], Tensor | None] | None:
        """The kept outputs (in :func:`dense_run`'s order) of the step from ``x [B, n]``,
        ``P [B, n, n]`` over ``z [B, m]``, with the SVSF's ``memory [B, m]`` and ``psi`` (``[m]``
        or ``[B, m]``), all contiguous; and the running log-likelihood ``total [B]`` (``None``:
        from 0) plus the step's (Kalman rule; else ``None``). ``None`` as for :func:`dense_run`."""
        out = [torch.empty_like(p) for p in self.prototypes]
        a = self.arguments
        a[0], a[1], a[2], a[3], a[4] = (
            x.data_ptr(),
            P.data_ptr(),
            z.data_ptr(),
            memory.data_ptr(),
            psi.data_ptr(),
        )
        pointers: list[Any] = [y.data_ptr() for y in out]
        for slot, start, stop in self.runs:
            a[slot : slot + stop - start] = pointers[start:stop]
        after = None
        if self.totals is not None:
            after = torch.empty_like(self.totals)
            a[19], a[20] = None if total is None else total.data_ptr(), after.data_ptr()
        self.sizes[4] = psi.shape[-1] if psi.ndim > 1 else 0
        return None if self.call() else (out, after)


#: dense_run's outputs written to tensors, by (keep, rule): those the result and state keep
_KEPT = {
    ("all", "kalman"): (0, 1, 2, 3, 4, 5, 6, 7, 9),
    ("all", "svsf"): tuple(range(10)),
    **{(keep, "kalman"): (0, 1, 7) for keep in ("moments", "mean")},
    **{(keep, "svsf"): (0, 1, 8) for keep in ("moments", "mean")},
}
_scratch = threading.local()  # per thread: a buffer is never written by two calls at once
_SCRATCH_CACHED = 1 << 16  # bytes: one step's outputs; a whole run's are allocated per call


def _addresses(
    outputs: Sequence[Tensor | None],
    shapes: Sequence[tuple[int, ...]],
    key: tuple[tuple[int, ...], torch.dtype, tuple[int, ...]],
) -> tuple[list[int], Tensor | None]:
    """The outputs' addresses, those not kept (``None``) parts of a scratch buffer nobody
    reads (the compiled step reads back what it wrote, so the parts are disjoint); and that
    buffer, which the caller holds through the call. ``key``: the outputs' leading shape,
    dtype and which are kept."""
    lead, dtype, _ = key
    cached = getattr(_scratch, "layouts", {}).get(key)
    if cached is not None:
        offsets, buffer = cached
    else:
        # Sizes in bytes, rounded up to 64 (aligned parts).
        sizes = [-(-math.prod(lead) * math.prod(s) * dtype.itemsize // 64) * 64 for s in shapes]
        offsets, total = [], 0
        for x, size in zip(outputs, sizes, strict=True):
            offsets.append(total if x is None else -1)
            total += size if x is None else 0
        buffer = torch.empty(total, dtype=torch.uint8) if total else None
        if total <= _SCRATCH_CACHED:
            _scratch.__dict__.setdefault("layouts", {})[key] = (offsets, buffer)
    base = 0 if buffer is None else buffer.data_ptr()
    return [
        base + at if x is None else x.data_ptr() for x, at in zip(outputs, offsets, strict=True)
    ], buffer
