"""The front door and the docs site: the README's numbers are the ones its cited files hold,
its links lead somewhere, and the docs' example of an estimator as a layer trains."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
LINK = re.compile(r"\]\(([^)#\s]+)(?:#[^)]*)?\)")
NUMBER = re.compile(r"(?<![\w.])\d[\d,]*(?:\.\d+)?(?![\w])")


def _prose_lines(path: Path) -> list[tuple[int, str]]:
    """The lines outside fenced code blocks, numbered from 1."""
    lines, fenced = [], False
    for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), start=1):
        if line.lstrip().startswith("```"):
            fenced = not fenced
        elif not fenced:
            lines.append((number, line))
    return lines


def _quoted_numbers(line: str) -> list[str]:
    """The numbers a line states, leaving out link targets and inline code."""
    text = LINK.sub("]()", line)
    text = re.sub(r"`[^`]*`", "", text)
    return NUMBER.findall(text)


def _holds(number: str, text: str) -> bool:
    return re.search(rf"(?<![\d.,]){re.escape(number)}(?![\d]|[.,]\d)", text) is not None


def test_readme_links_lead_to_files() -> None:
    targets = [(n, t) for n, line in _prose_lines(README) for t in LINK.findall(line)]
    assert targets, "the README links nothing"
    missing = [(n, t) for n, t in targets if "://" not in t and not (ROOT / t).exists()]
    assert not missing, f"README links to files that do not exist (line, target): {missing}"


def test_readme_numbers_are_the_cited_files() -> None:
    """Every number on a README line that cites a file of the checkout is in that file, so a
    re-run that changes a result makes this fail until the README quotes the new one."""
    checked = 0
    for number, line in _prose_lines(README):
        cited = [ROOT / t for t in LINK.findall(line) if "://" not in t and t.endswith(".md")]
        quoted = _quoted_numbers(line)
        if not cited or not quoted:
            continue
        texts = [path.read_text(encoding="utf-8") for path in cited]
        absent = [q for q in quoted if not any(_holds(q, text) for text in texts)]
        assert not absent, f"README line {number} quotes {absent}, not in {cited}"
        checked += len(quoted)
    assert checked >= 30, f"only {checked} numbers checked: the README's results table is gone?"


def test_number_check_can_fail() -> None:
    """The matching the check above relies on: whole numbers only, not digits inside others."""
    assert _holds("26.7", "| ks | default | 26.7 | 0.38 |")
    assert not _holds("26.7", "| ks | default | 126.7 | 26.75 |")
    assert not _holds("6.0", "16.0 and 6.05")
    line = "| taxi, σ 10 m | 5.4 | [r.md](results/r2.md) `--lag 5`"
    assert _quoted_numbers(line) == ["10", "5.4"]


def test_layer_example_trains() -> None:
    """docs/guide/layer.md's example runs as printed, and its position RMSE falls."""
    page = (ROOT / "docs" / "guide" / "layer.md").read_text(encoding="utf-8")
    blocks = re.findall(r"```python\n(.*?)```", page, flags=re.S)
    assert len(blocks) == 1, "the page's one example"
    scope: dict = {"__name__": "layer_example"}
    exec(compile(blocks[0], "docs/guide/layer.md", "exec"), scope)
    losses = scope["losses"]
    assert len(losses) == 30 and all(map(lambda v: v == v, losses))
    assert losses[-1] < 0.95 * losses[0], losses


def test_every_docs_page_is_in_the_nav() -> None:
    """A page the nav does not list is unreachable on the site (``make docs`` warns, CI fails);
    checked here too so that ``make test`` says it first."""
    nav = (ROOT / "mkdocs.yml").read_text(encoding="utf-8")
    pages = [p.relative_to(ROOT / "docs").as_posix() for p in (ROOT / "docs").rglob("*.md")]
    assert pages
    unlisted = [p for p in pages if f": {p}" not in nav]
    assert not unlisted, f"docs pages missing from mkdocs.yml's nav: {unlisted}"


def test_readme_python_example_runs() -> None:
    """The README's first Python example runs as printed (on 8 runs of the scenario, not 500:
    the count is the only change), and its gradients reach ψ."""
    text = README.read_text(encoding="utf-8")
    (block,) = re.findall(r"```python\n(.*?)```", text, flags=re.S)
    assert "num_runs=500" in block
    scope: dict = {"__name__": "readme_example"}
    exec(compile(block.replace("num_runs=500", "num_runs=8"), "README.md", "exec"), scope)
    assert scope["out"].mean.shape == (8, 490, 4)
    assert scope["svsf"].boundary_layer.raw.grad is not None


def test_table_example_runs(tmp_path, monkeypatch) -> None:
    """The guide's table example runs as printed on a file of its columns, and gives one row
    per input row with the estimates' columns."""
    from benchmarks.million_tracks import write_tracks

    text = (ROOT / "docs" / "guide" / "python.md").read_text(encoding="utf-8")
    (block,) = [
        b for b in re.findall(r"```python\n(.*?)```", text, flags=re.S) if "track_table" in b
    ]
    monkeypatch.chdir(tmp_path)
    write_tracks(tmp_path / "tracks.parquet", 30, 40)
    scope: dict = {"__name__": "guide_example"}
    exec(compile(block, "python.md", "exec"), scope)
    out = scope["out"]
    assert len(out) == len(scope["rows"]) == 30 * 40
    assert list(out.columns[:6]) == ["track_id", "time", "x", "vx", "y", "vy"]
