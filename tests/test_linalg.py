"""Numerical building blocks of torchsvs.linalg."""

from __future__ import annotations

import torch

from torchsvs.linalg import holds_inf, holds_nan


def test_inf_and_nan_checks_see_through_overflowing_sums():
    """holds_inf / holds_nan sum first and look element by element only when the sum is not
    finite: a sum that overflows (no inf, no NaN present) is not a false alarm, and an inf or
    a NaN anywhere is found, whatever else the tensor holds."""
    huge = torch.tensor([3e38, 3e38, -3e38, -3e38], dtype=torch.float32)
    assert not holds_inf(huge) and not holds_nan(huge)
    for bad in (float("inf"), float("-inf")):
        assert holds_inf(torch.cat([huge, torch.tensor([bad])]))
        assert holds_inf(torch.cat([huge, torch.tensor([bad, float("nan")])]))
        assert holds_nan(torch.cat([huge, torch.tensor([bad, float("nan")])]))
    assert holds_nan(torch.tensor([1.0, float("nan")])) and not holds_inf(
        torch.tensor([1.0, float("nan")])
    )
    assert not holds_nan(torch.zeros(3, requires_grad=True))
