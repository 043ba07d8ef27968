"""MkDocs hook: the experiments' and benchmarks' reports join the site where they are written.

The reports (``experiments/results/*.md`` with their figures, ``benchmarks/*.md``) are written by
their commands next to the code; copying them into ``docs/`` would make a second copy to drift.
The site serves them at the same paths (``experiments/results/…``, ``benchmarks/…``).
"""

from __future__ import annotations

from pathlib import Path

from mkdocs.config.defaults import MkDocsConfig
from mkdocs.structure.files import File, Files

ROOT = Path(__file__).resolve().parents[2]
REPORTS = ("experiments/results", "benchmarks")
SUFFIXES = {".md", ".png"}


def on_files(files: Files, config: MkDocsConfig) -> Files:
    for folder in REPORTS:
        for path in sorted((ROOT / folder).iterdir()):
            if path.suffix in SUFFIXES:
                src_uri = f"{folder}/{path.name}"
                files.append(File.generated(config, src_uri, abs_src_path=str(path)))
    return files
