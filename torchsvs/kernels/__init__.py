"""Structure-exploiting kernels the estimators pick by themselves (exact: tested against the
general path). :func:`general_path` turns them off, for comparisons and benchmarks;
:func:`eager_loops` keeps the per-axis kernel but runs its time loops as tensor operations
instead of the compiled ones (:mod:`torchsvs.kernels.fused_axes`, built by
:mod:`torchsvs.kernels.build`; also the IMM(CV, CT) and its smoother of ``track --estimator
imm``, :mod:`torchsvs.kernels.fused_imm`). :func:`compiled_steps` compiles
the general path's predict-correct step with ``torch.compile``
(:mod:`torchsvs.kernels.compiled`)."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

#: Whether estimators may use the per-axis kernel (:mod:`torchsvs.kernels.axes`), and its
#: compiled loops (with gradients through their compiled reverse modes).
AXIS_KERNEL = {"enabled": True, "fused": True}

#: Whether the Gaussian filters' general steps run through ``torch.compile``
#: (:mod:`torchsvs.kernels.compiled`): off by default, see :func:`compiled_steps`.
COMPILED_STEPS: dict[str, Any] = {"enabled": False, "chunk": 4, "backend": "inductor"}


@contextmanager
def _setting(key: str, value: bool) -> Iterator[None]:
    before = AXIS_KERNEL[key]
    AXIS_KERNEL[key] = value
    try:
        yield
    finally:
        AXIS_KERNEL[key] = before


@contextmanager
def general_path() -> Iterator[None]:
    """Within this block every estimator runs its general (dense-matrix) code: no per-axis
    kernel. Linear models' dense steps still run compiled unless :func:`eager_loops` too."""
    with _setting("enabled", False):
        yield


@contextmanager
def eager_loops() -> Iterator[None]:
    """Within this block the per-axis kernel runs its time loops as tensor operations, never
    the compiled ones, and the IMM(CV, CT) runs its tensor path (the reference for the compiled
    loops and their gradients; and the path for higher derivatives, which the compiled reverse
    mode does not give)."""
    with _setting("fused", False):
        yield


@contextmanager
def compiled_steps(
    enabled: bool = True,
    *,
    chunk: int | None = None,
    backend: str | None = None,
) -> Iterator[None]:
    """Within this block the Gaussian filters' general steps (EKF, UKF, the SVSF on nonlinear
    models, any linear filter the compiled loops of :mod:`~torchsvs.kernels.fused_dense` do not
    cover, and every step with gradients) run compiled with ``torch.compile``: one compilation
    per estimator, shapes, dtype and grad mode, reused by every step and later run
    (:mod:`torchsvs.kernels.compiled`; ``TORCHSVS_COMPILE=0`` turns it off everywhere).

    Args:
        enabled: ``False`` turns compiled steps off within the block.
        chunk: steps per compiled call (default 4: fewer calls per step, a longer compilation).
        backend: the ``torch.compile`` backend (default ``"inductor"``).
    """
    before = dict(COMPILED_STEPS)
    COMPILED_STEPS["enabled"] = enabled
    for key, value in (("chunk", chunk), ("backend", backend)):
        if value is not None:
            COMPILED_STEPS[key] = value
    try:
        yield
    finally:
        COMPILED_STEPS.update(before)
