"""Structure-exploiting kernels the estimators pick by themselves (exact: tested against the
general path). :func:`general_path` turns them off, for comparisons and benchmarks."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

#: Whether estimators may use the per-axis kernel (:mod:`torchsvs.kernels.axes`).
AXIS_KERNEL = {"enabled": True}


@contextmanager
def general_path() -> Iterator[None]:
    """Within this block every estimator runs its general (dense-matrix) code."""
    before = AXIS_KERNEL["enabled"]
    AXIS_KERNEL["enabled"] = False
    try:
        yield
    finally:
        AXIS_KERNEL["enabled"] = before
