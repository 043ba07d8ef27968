"""The simulated vehicles of the benchmark (experiments.vehicle_sets): seeded, with the report
times and the motion limits each kind declares."""

from __future__ import annotations

import math

import numpy as np
import pytest

from experiments import recorded_sets as rs
from experiments import vehicle_sets as vs


def _per_track(rows, column):
    return [g[column].to_numpy() for _, g in rows.groupby("track_id", sort=False)]


@pytest.mark.parametrize("name", sorted(vs.VEHICLES))
def test_a_kind_keeps_its_reports_and_its_limits(name: str) -> None:
    v = vs.VEHICLES[name]
    truth = rs.KINDS[name].build(3000, 5)
    again = rs.KINDS[name].build(3000, 5)
    assert truth.rows.equals(again.rows), "seeded"
    assert not truth.rows.equals(rs.KINDS[name].build(3000, 6).rows)
    assert len(truth.rows) >= 3000 and truth.rows["track_id"].nunique() >= 3
    for t, x, y in zip(*(_per_track(truth.rows, c) for c in ("time", "x", "y")), strict=True):
        assert vs.REPORTS[0] * 0.5 <= len(t) <= vs.REPORTS[1]
        gaps = np.diff(t)
        if v.interval:  # regular, but for the dropouts
            assert np.allclose(np.round(gaps / v.interval), gaps / v.interval)
            if not v.dropout_every:
                assert np.allclose(gaps, v.interval)
        else:
            assert gaps.min() >= v.gaps[1] - 1e-9 and gaps.max() <= v.gaps[2] + 1e-9
        # speeds between reports: never above the fastest cruise (a path's chord is shorter)
        speed = np.hypot(np.diff(x), np.diff(y)) / gaps
        assert speed.max() <= v.speeds[1] * (1 + 1e-9)
    # the path: speed changes within the limits, turns within the lateral acceleration (on
    # the fine grid, where the integration runs)
    rng = np.random.default_rng(0)
    speed = vs.speed_profile(rng, v, 20_000)
    change = np.diff(speed) / v.step
    assert change.max() <= v.accel + 1e-9 and change.min() >= -v.brake - 1e-9
    assert (speed == 0).any() == (v.stop_share > 0)
    quiet = vs.Vehicle(**{**v.__dict__, "wander": 0.0})
    heading = vs.heading_profile(rng, quiet, speed)
    rate = np.abs(np.diff(heading)) / v.step
    assert rate.max() <= math.radians(v.turn_rate) + 1e-9
    assert (rate * speed[1:]).max() <= v.lateral + 1e-6
    assert rate.max() > 0.5 * min(math.radians(v.turn_rate), v.lateral / v.speeds[1])


def test_the_default_kinds_are_the_recorded_ones_and_unknown_kinds_are_refused() -> None:
    assert set(rs.DEFAULT_KINDS) | set(vs.VEHICLES) | {"bus"} == set(rs.KINDS)
    assert not set(rs.DEFAULT_KINDS) & set(vs.VEHICLES)
    with pytest.raises(ValueError, match="kinds: expected names among"):
        rs.build_sets(["boat"], rows=100)


def test_buses_keep_to_their_limits_and_stand_at_their_stops() -> None:
    """The route's speed is within its limits, the acceleration, the braking and the lateral
    acceleration; the bus stands at its stops and lights, and some reports 30 s apart find it
    standing (the still stretches the noise check reads)."""
    from experiments import bus_routes as br

    rng = np.random.default_rng(0)
    kappa, cap, hold = br.route(rng, 8000.0)
    v = br.speeds(cap)
    assert (v <= cap + 1e-9).all() and v.max() > br.SPEEDS[0] - 1e-9
    change = np.diff(v**2) / (2 * br.STEP)
    assert change.max() <= br.ACCEL + 1e-9 and change.min() >= -br.BRAKE - 1e-9
    assert (v**2 * np.abs(kappa) <= br.LATERAL + 1e-9).all()
    assert (hold > 0).sum() >= 10 and (v[hold > 0] == 0).all()
    piece = br.bus_piece(rng, "bus/0", 300)
    assert np.allclose(np.diff(piece.time), br.INTERVAL)
    still = np.linalg.norm(np.diff(piece.position, axis=0), axis=1) < 1e-9
    assert 0 < still.sum() < 0.5 * len(still)
