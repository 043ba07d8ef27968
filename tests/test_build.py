"""Building the compiled loops (:mod:`torchsvs.kernels.build`): one compiled unit and the
headers it includes, all in the cache key and in the package data."""

from __future__ import annotations

import ctypes
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


needs_compiler = pytest.mark.skipif(build._compiler() is None, reason="no C++ compiler")


def _stand_in(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """A small stand-in for the compiled unit (one header, one function), built into a fresh
    cache: the build's logic is exercised in a fraction of a second, where the real library
    takes many (it is built once per test run, by the first test that runs a compiled loop)."""
    sources = tmp_path / "cpp"
    sources.mkdir()
    (sources / build.UNIT).write_text('#include "part.h"\nextern "C" int answer() { return A; }\n')
    header = sources / "part.h"
    header.write_text("#define A 1\n")
    monkeypatch.setattr(build, "SOURCE_DIR", sources)
    monkeypatch.setenv("TORCHSVS_CACHE", str(tmp_path / "cache"))
    monkeypatch.setattr(build, "_state", {"library": None, "failure": None})
    return header


@needs_compiler
def test_a_fresh_cache_gets_a_library_that_loads_and_runs(tmp_path, monkeypatch):
    _stand_in(tmp_path, monkeypatch)
    compiler = build._compiler()
    assert compiler is not None
    built = build._build(compiler)
    assert list((tmp_path / "cache").glob("fused-*.so")) == [built]
    assert build.BUILD["seconds"] > 0
    assert ctypes.CDLL(str(built)).answer() == 1


@needs_compiler
def test_a_compiler_that_refuses_the_native_flags_builds_the_plain_library(tmp_path, monkeypatch):
    _stand_in(tmp_path, monkeypatch)
    monkeypatch.setattr(build, "NATIVE", ("-fno-such-option-anywhere",))
    compiler = build._compiler()
    assert compiler is not None
    built = build._build(compiler)
    assert list((tmp_path / "cache").glob("fused-*.so")) == [built]
    assert ctypes.CDLL(str(built)).answer() == 1


@needs_compiler
def test_a_changed_header_builds_a_library_of_its_own(tmp_path, monkeypatch):
    """The cached library's key hashes every source, headers included: editing a header that
    the unit includes gives a new build, never the stale library."""
    header = _stand_in(tmp_path, monkeypatch)
    compiler = build._compiler()
    assert compiler is not None
    first = build._build(compiler)
    assert build._build(compiler) == first  # unchanged: the cached library
    header.write_text("#define A 2\n")
    second = build._build(compiler)
    assert second != first
    assert first.exists() and second.exists()
