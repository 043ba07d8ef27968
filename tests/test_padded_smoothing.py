"""A padded batch's shorter tracks smoothed without NaN: the steps after a track's last
position are inert to the backward recursion (``smoothers.rts._inert_past_the_end``,
``kernels.axes_smoother._inert_past_the_end``, and the compiled record's own)."""

from __future__ import annotations

import math
from pathlib import Path

import pandas as pd
import pytest

from torchsvs.datasets import Columns
from torchsvs.kernels import build
from torchsvs.recipes import Settings
from torchsvs.tracking import track_file

#: Two city buses on 20 s reports, 181 and 92 positions (an outside probe's simulation, σ 5 m):
#: in one group the shorter is padded by 89 empty steps.
BUSES = Path(__file__).parent / "data" / "two_buses.csv"


@pytest.mark.parametrize("compiled", [True, False])
def test_a_short_tracks_padding_does_not_turn_its_estimates_to_nan(tmp_path, monkeypatch, compiled):
    """The SVSS that ``auto`` fitted on such buses (``q`` 3.8e-12, ψ 0.9, γ 0.989): its
    covariance, near rank 1, predicted over the padding lost its definiteness to rounding
    (determinant -8), and the shorter bus's 92 estimates came out NaN, and with them the run's
    error estimate (its probed run's NaN reached the control variate of every track)."""
    if not compiled:
        monkeypatch.setitem(build.AXIS_KERNEL, "fused", False)
    settings = Settings("svss", meas_var=[25.0, 25.0], q=3.818e-12, psi=[0.9011] * 2, gamma=0.9891)
    target = tmp_path / "out.csv"
    run = track_file(BUSES, target, settings, columns=Columns(), progress=False)
    out = pd.read_csv(target)
    assert len(out) == 273 and not out[["x", "y", "vx", "vy"]].isna().any().any()
    found = run.accuracy
    assert found is not None and math.isfinite(found.estimated_rmse)
    assert all(math.isfinite(v) for v in found.interval)


def test_estimates_that_break_down_are_said_not_written_empty_without_a_word(tmp_path, monkeypatch):
    """With the padding left as the filter predicted it (the tensor loops), the shorter bus's
    estimates are NaN again: the run then says so, naming how many tracks."""
    from torchsvs.kernels import axes_smoother
    from torchsvs.smoothers import rts

    monkeypatch.setitem(build.AXIS_KERNEL, "fused", False)
    monkeypatch.setattr(axes_smoother, "_inert_past_the_end", lambda res: res)
    monkeypatch.setattr(rts, "_inert_past_the_end", lambda result: result)
    settings = Settings("svss", meas_var=[25.0, 25.0], q=3.818e-12, psi=[0.9011] * 2, gamma=0.9891)
    run = track_file(BUSES, tmp_path / "out.csv", settings, columns=Columns(), progress=False)
    assert run.report.notes["tracks_not_finite"] == 1
    assert any("the estimates of 1 tracks came out NaN" in w for w in run.warnings)
