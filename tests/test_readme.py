"""The user guide's first examples run as written (on a small track file made here)."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def _python_blocks(page: str) -> list[str]:
    text = (ROOT / "docs" / "guide" / page).read_text(encoding="utf-8")
    return re.findall(r"```python\n(.*?)```", text, flags=re.S)


def test_recorded_track_examples_run(tmp_path, monkeypatch):
    gen = np.random.default_rng(0)
    rows = ["track_id,time,x,y"]
    for k in range(4):
        t = np.cumsum(gen.uniform(3.0, 7.0, 80))
        v = gen.normal(0, 100, 2)
        for ti in t:
            x, y = v * ti + gen.normal(0, 100, 2)
            rows.append(f"aircraft {k},{ti:.1f},{x:.1f},{y:.1f}")
    (tmp_path / "tracks.csv").write_text("\n".join(rows) + "\n")
    monkeypatch.chdir(tmp_path)
    first = _python_blocks("python.md")[0]  # read a file, an SVSS, write the estimates
    (second,) = _python_blocks("self_tuning.md")
    namespace: dict = {}
    exec(first, namespace)  # noqa: S102 - the README's own code
    exec(second, namespace)  # noqa: S102
    written = (tmp_path / "estimates.csv").read_text().splitlines()
    assert len(written) == len(rows)
    assert written[0].replace('"', "").startswith("track_id,time,x,vx,y,vy")
    assert "svss by SURE" in namespace["fit"].summary()


def test_online_example_runs():
    (block,) = _python_blocks("online.md")
    assert "svsf.step(" in block
    namespace: dict = {}
    exec("import torch\nimport torchsvs as ts\n" + block, namespace)  # noqa: S102
    state = namespace["state"]
    assert state.steps == 70 and state.single and state.mean.shape == (1, 4)
