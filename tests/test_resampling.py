"""Resampling schemes are unbiased: mean offspring count N·w_i."""

from __future__ import annotations

import pytest
import torch

from tests.conftest import assert_close
from torchsvs.resampling import SCHEMES


@pytest.mark.parametrize("name", sorted(SCHEMES))
def test_offspring_counts_are_unbiased(name):
    gen = torch.Generator().manual_seed(0)
    N, reps = 8, 20000
    weights = torch.tensor([0.02, 0.3, 0.08, 0.1, 0.25, 0.05, 0.15, 0.05], dtype=torch.float64)
    log_w = weights.log().expand(reps, N)
    index = SCHEMES[name](log_w, gen)
    assert index.shape == (reps, N) and int(index.min()) >= 0 and int(index.max()) < N
    counts = torch.nn.functional.one_hot(index, N).sum(1).double()  # [reps, N]
    # Standard error of the mean count is below sqrt(N w (1 − w) / reps) ≈ 0.01.
    assert_close(counts.mean(0), N * weights, atol=0.05, rtol=0)
    if name == "systematic":  # every count is floor or ceil of N·w
        assert bool(((counts - N * weights).abs() < 1.0 + 1e-9).all())
    if name != "multinomial":  # lower variance than independent draws
        multi = SCHEMES["multinomial"](log_w, gen)
        spread = torch.nn.functional.one_hot(multi, N).sum(1).double().var(0).sum()
        assert counts.var(0).sum() < 0.7 * spread


@pytest.mark.parametrize("name", sorted(SCHEMES))
def test_reproducible_with_a_generator(name):
    log_w = torch.randn(3, 50, generator=torch.Generator().manual_seed(1)).log_softmax(-1)
    a = SCHEMES[name](log_w, torch.Generator().manual_seed(7))
    b = SCHEMES[name](log_w, torch.Generator().manual_seed(7))
    assert torch.equal(a, b)
