"""Building the compiled loops (:mod:`torchsvs.kernels.build`): one compiled unit and the
headers it includes, all in the cache key and in the package data."""

from __future__ import annotations

import fnmatch
import re
from pathlib import Path

import pytest

from torchsvs.kernels import build

ROOT = Path(__file__).resolve().parents[1]


def test_every_included_header_is_a_source_and_package_data():
    """``cpp/fused.cpp`` includes every header of ``cpp/`` (none left out of the build), each is
    among the sources the cache key hashes, and pyproject.toml's package data ships them all, so
    an installed wheel can build the library."""
    sources = {p.name for p in build.sources()}
    headers = {name for name in sources if name.endswith(".h")}
    unit = (build.SOURCE_DIR / build.UNIT).read_text()
    assert set(re.findall(r'#include "([\w.]+)"', unit)) == headers
    assert build.UNIT in sources
    tomllib = pytest.importorskip("tomllib")  # (Python 3.11 on)
    patterns = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"][
        "package-data"
    ]["torchsvs"]
    package = ROOT / "torchsvs"
    for path in build.sources():
        relative = str(path.relative_to(package))
        assert any(fnmatch.fnmatch(relative, p) for p in patterns), relative


@pytest.mark.skipif(build._compiler() is None, reason="no C++ compiler")
def test_a_changed_header_builds_a_library_of_its_own(tmp_path, monkeypatch):
    """The cached library's key hashes every source, headers included: editing a header that
    the unit includes gives a new build, never the stale library (a small stand-in unit, so
    that the test compiles in a fraction of a second)."""
    sources = tmp_path / "cpp"
    sources.mkdir()
    (sources / build.UNIT).write_text('#include "part.h"\nextern "C" int answer() { return A; }\n')
    header = sources / "part.h"
    header.write_text("#define A 1\n")
    monkeypatch.setattr(build, "SOURCE_DIR", sources)
    monkeypatch.setenv("TORCHSVS_CACHE", str(tmp_path / "cache"))
    compiler = build._compiler()
    assert compiler is not None
    first = build._build(compiler)
    assert build._build(compiler) == first  # unchanged: the cached library
    header.write_text("#define A 2\n")
    second = build._build(compiler)
    assert second != first
    assert first.exists() and second.exists()
