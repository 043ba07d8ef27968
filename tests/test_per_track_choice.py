"""The per-track model choice prototype (experiments.per_track_choice): its rule and its
bounds on a small set."""

from __future__ import annotations

import math

import numpy as np
import pytest

from experiments import per_track_choice as ptc
from experiments.recorded_sets import build_sets


def test_the_rule_keeps_the_files_choice_unless_a_track_is_sure() -> None:
    change = np.array([5.0, -1.0, 0.5, 3.0])
    error = np.ones(4)
    file_imm, pick = ptc.choose((2.5, 1.0), change, error, 2.0)
    assert file_imm  # 2.5 > 2 · 1
    assert pick.tolist() == [True, True, True, True]  # no track surely better with ks
    file_imm, pick = ptc.choose((-2.5, 1.0), -change, error, 2.0)
    assert not file_imm and pick.tolist() == [False, False, False, False]
    _, pick = ptc.choose((2.5, 1.0), np.array([5.0, -3.0, 0.5, 3.0]), error, 2.0)
    assert pick.tolist() == [True, False, True, True]
    _, pick = ptc.choose((2.5, 1.0), np.array([5.0, -3.0, 0.5, 3.0]), error, math.inf)
    assert pick.all()
    # a track without an error (one chunk) keeps the file's choice, whichever it is
    _, pick = ptc.choose((-2.5, 1.0), np.array([9.0]), np.array([np.nan]), 2.0)
    assert pick.tolist() == [False]
    _, pick = ptc.choose((2.5, 1.0), np.array([-9.0]), np.array([np.nan]), 2.0)
    assert pick.tolist() == [True]
    # the file's own choice: not sure, the smoother
    assert not ptc.choose((1.5, 1.0), change, error, 2.0)[0]


def test_each_tracks_difference_is_the_paired_one_of_its_chunks() -> None:
    from torchsvs.accuracy import RiskTerms

    rng = np.random.default_rng(0)
    count = np.full((7, 2), 32.0)
    track = np.array([0, 0, 0, 1, 1, 1, 2])

    def terms() -> RiskTerms:
        return RiskTerms(rng.uniform(0, 9, (7, 2)), rng.uniform(0, 9, (7, 2)), count, track)

    a, b = terms(), terms()
    ks = ptc.Passes(["p", "q", "r"], a, None)  # type: ignore[arg-type]
    imm = ptc.Passes(["p", "q", "r"], b, None)  # type: ignore[arg-type]
    whole, change, error = ptc.paired(ks, imm, [1.0, 1.0])
    assert whole == a.difference(b, [1.0, 1.0])
    first = RiskTerms(a.residual[:3], a.divergence[:3], count[:3], track[:3])
    other = RiskTerms(b.residual[:3], b.divergence[:3], count[:3], track[:3])
    assert (change[0], error[0]) == first.difference(other, [1.0, 1.0])
    assert math.isfinite(change[2]) and math.isnan(error[2])  # one chunk: no error
    short = ptc.Passes(["p", "q", "r"], b.select(np.arange(6)), None)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="the same chunks"):  # chunks that do not pair
        ptc.paired(ks, short, [1.0, 1.0])


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
