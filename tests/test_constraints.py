"""Constrained parameters: scaling a stored value in place (torchsvs.constraints)."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from torchsvs.constraints import Positive, SPDMatrix, scaled_copy


def test_scaling_a_constrained_value_scales_what_it_maps_to():
    """``scale_`` multiplies the value a parameter maps to, whatever its stored form (a log, a
    Cholesky factor with a log-diagonal), without gradients; the raw form stays finite."""
    q = Positive([0.5, 2.0], "q")
    R = SPDMatrix(torch.tensor([[4.0, 1.0], [1.0, 9.0]], dtype=torch.float64), "R")
    before_q, before_R = q().detach().clone(), R().detach().clone()
    for parameter in (q, R):
        parameter.scale_(3.0)
        assert parameter.raw.requires_grad and parameter.raw.grad is None
    torch.testing.assert_close(q(), 3.0 * before_q, rtol=1e-12, atol=0.0)
    torch.testing.assert_close(R(), 3.0 * before_R, rtol=1e-12, atol=0.0)


def test_a_scaled_copy_scales_each_parameter_once_and_leaves_the_module():
    """``scaled_copy`` scales a copy: a parameter listed twice (shared by two modes) is scaled
    once, the module itself is unchanged, and a factor of 1 gives the module itself."""
    shared = Positive(2.0, "q")
    module = nn.ModuleDict({"a": shared, "b": nn.ModuleDict({"again": shared})})
    with scaled_copy(module, 5.0, lambda m: [m["a"], m["b"]["again"]]) as scaled:
        assert scaled is not module
        assert scaled["a"]().item() == pytest.approx(10.0, rel=1e-12)  # (twice: 50)
        assert scaled["a"] is scaled["b"]["again"]
    assert module["a"]().item() == pytest.approx(2.0, rel=1e-15)
    with scaled_copy(module, 1.0, lambda m: [m["a"]]) as same:
        assert same is module
