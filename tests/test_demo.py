"""`make demo` on a tiny budget: it trains, moves ψ off the bad guess and prints the table."""

from __future__ import annotations

import logging
import re

import pytest

from experiments.demo import demo


@pytest.mark.filterwarnings("ignore:.*does not have many workers.*", "ignore:.*LeafSpec.*")
def test_demo_trains_and_reports(capfd, caplog):
    caplog.set_level(logging.INFO)
    text = demo(epochs=1, batches=3, runs=20)
    # Quiet: none of Lightning's banners, tips, model summaries or bars (make demo's terminal
    # shows the tables); checked on the file descriptors and on the log records alike.
    out, err = capfd.readouterr()
    for said in (out + err, caplog.text):
        for noise in ("Tip", "GPU available", "Seed set", "stopped", "Epoch 0", "Sanity", "Params"):
            assert noise not in said, said
    for row in ("| ATC | KF |", "| ATC | SVSS, learned ψ |", "| complex | SVSS, paper ψ |"):
        assert row in text
    learned = re.findall(r"(ATC|complex): ψ = \[([0-9, ]+)\]", text)
    assert len(learned) == 2
    for _, widths in learned:  # three optimiser steps moved ψ off the 100 m start
        assert max(abs(int(w) - 100) for w in widths.split(",")) > 10
