"""Structure-exploiting kernels the estimators pick by themselves (exact: tested against the
general path). :func:`general_path` turns them off, for comparisons and benchmarks;
:func:`eager_loops` keeps the per-axis kernel but runs its time loops as tensor operations
instead of the compiled ones (:mod:`torchsvs.kernels.fused`)."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

#: Whether estimators may use the per-axis kernel (:mod:`torchsvs.kernels.axes`), and its
#: compiled loops (with gradients through their compiled reverse modes).
AXIS_KERNEL = {"enabled": True, "fused": True}


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
    the compiled ones (the reference for the compiled loops and their gradients; and the path
    for higher derivatives, which the compiled reverse mode does not give)."""
    with _setting("fused", False):
        yield
