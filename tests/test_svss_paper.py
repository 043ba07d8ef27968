"""A reduced reproduction of Chen et al. 2020 (fewer runs): the paper's orderings hold."""

from __future__ import annotations

import pytest

from experiments.svss_paper import figures, report, reproduce


@pytest.fixture(scope="module")
def results():
    return reproduce(runs=40, seed=3, progress=False)


def test_table1_ordering(results):
    t1 = results.table1
    for axis in (0, 1):
        v = {k: t1[k][axis] for k in ("KF", "KS", "RSTKF", "SVSF", "SVSS")}
        assert v["SVSS"] < v["SVSF"] and v["SVSS"] < v["RSTKF"]
        # SVSF ≈ RSTKF (the paper: 146 and 145 m). Over six seeds of 40 runs the ratio is
        # 0.949-0.970 in x and 0.987-1.004 in y (500 runs: 0.96, 0.99): 10% leaves 4.9% beyond
        # the farthest, six standard deviations of the ratio between seeds (0.8%).
        assert abs(v["SVSF"] / v["RSTKF"] - 1) < 0.10
        assert max(v["SVSF"], v["RSTKF"]) < v["KS"] < v["KF"]
        # The derived-shape RSTKF loses the target in the turns (documented ablation).
        assert t1["RSTKF (derived shapes)"][axis] > v["KF"]


def test_table2_svss_below_svsf_and_svsf_best_near_1000(results):
    t2 = results.table2
    for svsf_x, svss_x, svsf_y, svss_y in t2.values():
        assert svss_x < svsf_x and svss_y < svsf_y
    assert min(t2, key=lambda p: t2[p][0] + t2[p][2]) == 1000.0


def test_table3_ordering(results):
    t3 = results.table3
    for c in (0, 2):
        order = [t3[k][c] for k in ("SVSS", "SVSTPS", "SVSF", "KS", "KF")]
        assert order == sorted(order)


def test_lags_improve_on_lag_one(results):
    lags = results.lags
    assert lags["SVSS lag 2"][0] < lags["SVSS lag 1"][0] < lags["SVSF"][0]


def test_report_and_figures(results, tmp_path):
    pngs = figures(results, tmp_path)
    assert len(pngs) == 6 and all((tmp_path / p).stat().st_size > 10_000 for p in pngs)
    text = report(results, pngs)
    for heading in ("## Table 1", "## Table 2", "## Table 3", "Table A2", "## Discussion"):
        assert heading in text
    assert "FAILS" not in text
