"""Tidy output (issue 30, item 5): ``torchsvs track`` prints each line once and clears its bar
before its summary, as a terminal shows it; Lightning's banners and tips stay out of the runs
torchsvs makes, and ``torchsvs fit`` drops only the tips."""

from __future__ import annotations

import io
import logging
import re
import sys

import pytest
from lightning.pytorch.utilities.rank_zero import rank_zero_info
from lightning_utilities.core import rank_zero

from tests.test_accuracy import _wandering_csv
from torchsvs.cli import main
from torchsvs.training.quiet import RANK_ZERO_LOGGERS, quiet_lightning, without_tips


class Terminal(io.StringIO):
    """Standard error as a terminal: tqdm draws its bar here."""

    def isatty(self) -> bool:
        return True


def rendered(text: str) -> list[str]:
    """The lines a terminal shows for ``text``: a carriage return goes back to the line's start
    and what follows overwrites it (what it does not overwrite stays); escape sequences are
    dropped."""
    lines: list[str] = []
    for raw in re.sub(r"\x1b\[[0-9;]*[A-Za-z]", "", text).split("\n"):
        cells: list[str] = []
        column = 0
        for char in raw:
            if char == "\r":
                column = 0
                continue
            if column < len(cells):
                cells[column] = char
            else:
                cells.append(char)
            column += 1
        lines.append("".join(cells).rstrip())
    return [line for line in lines if line]


def test_rendering_keeps_what_a_carriage_return_does_not_overwrite():
    """The oracle of the track test: a summary written over a bar that was not cleared keeps
    the bar's tail on its line."""
    assert rendered("tracks: 5 tracks [00:00, 9 tracks/s]\r12 rows\n") == [
        "12 rows 5 tracks [00:00, 9 tracks/s]"
    ]
    assert rendered("tracks: 5 tracks\r" + " " * 16 + "\r12 rows\n") == ["12 rows"]


def test_track_prints_each_line_once_and_clears_its_bar_before_the_summary(tmp_path, monkeypatch):
    """On tracks whose noise reading is lowered (read and fitted twice), a terminal shows the
    reading kept once (one ``model:``, one ``fit:`` line, no line twice), the bar drawn and then
    cleared, and the summary from the start of its own line."""
    source, target = tmp_path / "in.csv", tmp_path / "out.csv"
    _wandering_csv(source)
    terminal = Terminal()
    monkeypatch.setattr(sys, "stderr", terminal)
    main(["track", str(source), "-o", str(target), "--fit", "--estimator", "ks"])
    text = terminal.getvalue()
    assert "tracks/s]" in text  # the bar was drawn
    lines = rendered(text)
    assert len(lines) == len(set(lines)), [line for line in lines if lines.count(line) > 1]
    assert [line.split(":")[0] for line in lines].count("fit") == 1
    assert [line.split(":")[0] for line in lines].count("model") == 1
    assert any(line.startswith("noise: at ") for line in lines)  # the lowering, said once
    assert not any("tracks/s" in line for line in lines)  # nothing of the bar left
    assert any(line.startswith("1440 rows in 12 tracks") for line in lines)


@pytest.fixture
def rank_zero_messages():
    """The messages Lightning's rank-zero logger lets through (its level and filters applied),
    whatever handlers Lightning set up under pytest."""
    seen: list[str] = []

    class Keep(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            seen.append(record.getMessage())

    handler = Keep()
    assert rank_zero.log.name in RANK_ZERO_LOGGERS  # the logger rank_zero_info writes to
    rank_zero.log.addHandler(handler)
    yield seen
    rank_zero.log.removeHandler(handler)


def test_quiet_lightning_holds_back_the_info_lines_then_restores_them(rank_zero_messages):
    tip = "💡 Tip: For seamless cloud logging, try a service"
    with quiet_lightning():
        rank_zero_info("GPU available: False, used: False")
        rank_zero_info(tip)
    assert rank_zero_messages == []
    rank_zero_info("GPU available: False, used: False")
    assert rank_zero_messages == ["GPU available: False, used: False"]


def test_without_tips_drops_the_tips_alone(rank_zero_messages):
    with without_tips():
        rank_zero_info("💡 Tip: For seamless cloud uploads, try a service")
        rank_zero_info("GPU available: False, used: False")
    rank_zero_info("💡 Tip: after")
    assert rank_zero_messages == ["GPU available: False, used: False", "💡 Tip: after"]
