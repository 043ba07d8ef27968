"""The benchmark matrix (benchmarks/matrix.py) on a tiny problem: its measurements, its
report's structure, and the peers' estimates against torchsvs's on the same data."""

from __future__ import annotations

import json
import math

import pytest

pytest.importorskip("filterpy")
pytest.importorskip("simdkalman")
pytest.importorskip("torch_kf")

from benchmarks import matrix  # noqa: E402
from benchmarks.common import CVProblem  # noqa: E402

CASES = ["torchsvs KF", "torchsvs RTS", "torchsvs SVSF", "simdkalman KF + RTS"]
CASES += ["filterpy KF", "torch-kf KF + RTS"]


def test_tiny_matrix_structure_and_agreement(tmp_path):
    settings = matrix.Settings(steps=20, filterpy_tracks=2)
    problem = CVProblem(3, settings.steps)
    reference = matrix.reference_means(problem)
    results = []
    for dtype in ("float32", "float64"):
        results += matrix.run_configuration(problem, dtype, settings, 1, CASES, reference)

    # torchsvs rows in both dtypes and passes; float64-only peers once; torch-kf in both.
    keys = {(r.implementation, r.mode, r.dtype) for r in results}
    assert ("torchsvs SVSF", matrix.BACKWARD, "float32") in keys
    assert ("simdkalman KF + RTS", matrix.FORWARD, "float32") not in keys
    assert ("torch-kf KF + RTS", matrix.FORWARD, "float32") in keys
    assert len(results) == 2 * 6 + 1 + 1 + 2
    for r in results:
        assert r.seconds > 0 and r.ns > 0 and math.isfinite(r.ratio)
        if r.implementation == "torchsvs KF":
            assert r.ratio == 1.0
    filterpy = next(r for r in results if r.implementation == "filterpy KF")
    assert filterpy.tracks == 2  # subsampled
    # Every checked estimate agrees with torchsvs's float64 KF / RTS on the same data.
    checked = [r for r in results if r.max_abs_diff is not None]
    assert {r.implementation for r in checked} >= {"filterpy KF", "simdkalman KF + RTS"}
    for r in checked:
        assert r.max_abs_diff < (1e-6 if r.dtype == "float64" else 1.0), r

    tables = matrix.tables(results, [3], settings)
    assert tables.count("### float") == 2
    assert "| torchsvs KF | forward | " in tables
    assert "first 2 tracks when B is larger" in tables
    assert "- B = 3: " in matrix.differences(results, [3])
    matrix.plot(results, [3], tmp_path / "results.png")
    assert (tmp_path / "results.png").stat().st_size > 0


def test_memory_case_reports_json():
    settings = matrix.Settings(steps=20)
    probe = matrix.memory_case("torchsvs KF", 2, "float64", matrix.FORWARD, settings)
    json.dumps(probe)
    assert set(probe) == {"baseline_mb", "peak_mb", "seconds", "reset"}
    assert probe["baseline_mb"] > 0 and probe["peak_mb"] >= 0
