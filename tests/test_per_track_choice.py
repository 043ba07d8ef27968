"""The per-track model choice prototype (experiments.per_track_choice): its rule and its
bounds on a small set."""

from __future__ import annotations

import math

import numpy as np
import pytest

from experiments import per_track_choice as ptc
from experiments.recorded_sets import build_sets


def test_the_rule_keeps_the_files_choice_unless_a_track_is_sure() -> None:
    total = np.array([5.0, -1.0, 0.5, 3.0])
    se = np.ones(4)
    file_imm, pick = ptc.choose(total, se, 2.0)
    assert file_imm  # 7.5 > 2 · √4
    assert pick.tolist() == [True, True, True, True]  # no track surely better with ks
    file_imm, pick = ptc.choose(-total, se, 2.0)
    assert not file_imm and pick.tolist() == [False, False, False, False]
    _, pick = ptc.choose(np.array([5.0, -3.0, 0.5, 3.0]), se, 2.0)
    assert pick.tolist() == [True, False, True, True]
    _, pick = ptc.choose(np.array([5.0, -3.0, 0.5, 3.0]), se, math.inf)
    assert pick.all()


def test_chunks_that_do_not_pair_are_refused() -> None:
    a = ptc.Passes(["a"], np.array([0, 0]), np.array([1.0, 2.0]), None)  # type: ignore[arg-type]
    b = ptc.Passes(["a"], np.array([0]), np.array([1.0]), None)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="do not pair"):
        ptc.paired(a, b)


def test_a_set_measured_within_its_bounds() -> None:
    (bench,) = build_sets(["turning"], rows=600, seed=1)
    found = ptc.measure(bench, ptc.MARGIN)
    assert found.tracks == 3 and found.ks > 0
    assert found.per_file == pytest.approx(min(1.0, found.imm))
    assert found.oracle <= found.per_file + 1e-12
    assert found.oracle - 1e-12 <= found.truth_free <= max(1.0, found.imm) + 1e-12
    again = ptc.measure(bench, math.inf)  # no track leaves the file's choice
    assert again.switched == 0
    assert again.truth_free == pytest.approx(found.imm if found.file_imm else 1.0)
