"""Lightning's output kept to what a user acts on where torchsvs runs a Trainer as a tool (the
demo, the experiments, ``torchsvs track --processes``): no banners ("GPU available", "Seed set
to 0", "`Trainer.fit` stopped"), no advertising tips ("💡 Tip: ..."), no model summary, and a
training bar that ends cleanly (:class:`TidyProgressBar`). Lightning's warnings and errors
still show."""

from __future__ import annotations

import logging
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import lightning as L
from lightning.pytorch.callbacks import TQDMProgressBar
from lightning.pytorch.callbacks.progress.tqdm_progress import Tqdm

#: The loggers of Lightning's info lines (its rank-zero messages log under both).
LOGGERS = ("lightning.pytorch", "lightning.fabric")
#: The loggers Lightning's rank-zero messages (the tips among them) are made by.
RANK_ZERO_LOGGERS = tuple(f"{name}.utilities.rank_zero" for name in LOGGERS)


@contextmanager
def quiet_lightning() -> Iterator[None]:
    """Lightning's info lines held back (its loggers at WARNING) for the duration, then its
    levels restored: for Trainers the user did not ask to watch."""
    loggers = [logging.getLogger(name) for name in LOGGERS]
    levels = [one.level for one in loggers]
    for one in loggers:
        one.setLevel(logging.WARNING)
    try:
        yield
    finally:
        for one, level in zip(loggers, levels, strict=True):
            one.setLevel(level)


class _NoTips(logging.Filter):
    def filter(self, record: logging.LogRecord) -> bool:
        return not record.getMessage().lstrip().startswith("💡")


@contextmanager
def without_tips() -> Iterator[None]:
    """Lightning's other lines as they are, its tips (an ad per Trainer: "💡 Tip: For seamless
    cloud ...") dropped for the duration: for ``torchsvs fit``, where the banners are the
    user's."""
    tips = _NoTips()
    loggers = [logging.getLogger(name) for name in RANK_ZERO_LOGGERS]
    for one in loggers:
        one.addFilter(tips)
    try:
        yield
    finally:
        for one in loggers:
            one.removeFilter(tips)


class TidyProgressBar(TQDMProgressBar):
    """Lightning's training bar on one line of standard error, cleared when training ends (none
    left behind per epoch); no bars for the sanity check and validation (nested bars leave
    lines behind on many terminals), and none where standard error is not a terminal (a log
    would keep every carriage-return update)."""

    def init_sanity_tqdm(self) -> Tqdm:
        return Tqdm(disable=True)

    def init_validation_tqdm(self) -> Tqdm:
        return Tqdm(disable=True)

    def init_train_tqdm(self) -> Tqdm:
        return Tqdm(
            desc=self.train_description,
            disable=self.is_disabled or not sys.stderr.isatty(),
            leave=False,
            dynamic_ncols=True,
            file=sys.stderr,
            smoothing=0,
            bar_format=self.BAR_FORMAT,
        )


def tool_trainer(**options: Any) -> L.Trainer:
    """A Trainer run as a tool, on the CPU: one device, no logger, no checkpoints, no progress
    bar, no model summary, unless ``options`` say otherwise (they override these)."""
    settings: dict[str, Any] = {
        "accelerator": "cpu",
        "devices": 1,
        "logger": False,
        "enable_checkpointing": False,
        "enable_progress_bar": False,
        "enable_model_summary": False,
    }
    return L.Trainer(**(settings | options))
