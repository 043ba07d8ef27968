"""Simulated vehicles the ADS-B samples do not hold: people walking, cars in town, ships
reporting by AIS and multirotor drones, as truths for :mod:`experiments.recorded_sets` (kinds
``walker``, ``car``, ``ship``, ``drone``, and at sparse reports ``van``, ``satship``; city
buses driven along routes, ``bus``, are :mod:`experiments.bus_routes`'s).

Every recorded kind of the benchmark is an aircraft. These are other vehicles, other sampling
(1 s, 0.1 s, and 2-180 s apart at random) and other motion (stops, slow turns, right-angle
turns at junctions, hovering), seeded and in NumPy alone, so the benchmark sees what the
project's recorded tracks cannot show it.

A track is integrated on a fine grid (:attr:`Vehicle.step`) from a speed and a heading:

* the speed follows targets held for a while (a stop among them), changing at most at the
  vehicle's acceleration or braking;
* the heading turns at junctions or course changes: a turn of an angle at a rate that keeps
  the lateral acceleration ``v·ω`` within the vehicle's, plus a wander (a random walk);
* the reports sample the path at the vehicle's report times: a regular interval with
  dropouts (a car in a tunnel), or independent gaps (AIS).
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass, replace

import numpy as np

from experiments.track_truth import Piece, Truth, truth_rows


@dataclass(frozen=True)
class Vehicle:
    """How one kind of vehicle moves and reports."""

    name: str
    step: float  #: the fine grid its path is integrated on (s)
    speeds: tuple[float, float]  #: cruising speeds drawn from this range (m/s)
    stop_share: float  #: the share of held speeds that are a stop
    hold: tuple[float, float]  #: a target speed is held this long (s)
    accel: float  #: speeding up at most (m/s²)
    brake: float  #: slowing down at most (m/s²)
    turn_every: float  #: mean time between turns (s)
    turn_angle: tuple[float, float]  #: a turn's angle (deg, either way)
    turn_rate: float  #: the fastest turn (deg/s)
    lateral: float  #: lateral acceleration at most in a turn (m/s²)
    wander: float  #: the heading's random walk (deg/√s)
    interval: float  #: report interval (s); 0: independent gaps in ``gaps``
    gaps: tuple[float, float, float] = (0.0, 0.0, 0.0)  #: mean, shortest, longest gap (s)
    dropout_every: float = 0.0  #: mean time between dropouts (s); 0: none
    dropout: tuple[float, float] = (0.0, 0.0)  #: a dropout's length (s)


VEHICLES = {
    v.name: v
    for v in (
        # walking: 1-1.6 m/s, waits at crossings, turns at corners, phone GPS at 1 Hz
        Vehicle("walker", 0.1, (1.0, 1.6), 0.15, (10.0, 60.0), 0.5, 1.0, 40.0, (30.0, 120.0),
                45.0, 1.0, 2.0, 1.0),
        # urban driving: stop-and-go at 8-20 m/s, right-angle turns at junctions, 1 Hz with
        # tunnels of 10-30 s
        Vehicle("car", 0.1, (8.0, 20.0), 0.2, (10.0, 40.0), 2.0, 4.0, 60.0, (80.0, 100.0),
                30.0, 3.0, 0.3, 1.0, dropout_every=300.0, dropout=(10.0, 30.0)),
        # a ship at 3-10 m/s, course changes of 10-60 deg at 1 deg/s at most, AIS reports
        # 2-180 s apart (mean 30 s)
        Vehicle("ship", 1.0, (3.0, 10.0), 0.0, (300.0, 1200.0), 0.05, 0.05, 900.0,
                (10.0, 60.0), 1.0, 0.2, 0.05, 0.0, gaps=(30.0, 2.0, 180.0)),
        # a multirotor drone: hovers, 3-15 m/s, sharp turns, GPS at 10 Hz
        Vehicle("drone", 0.01, (3.0, 15.0), 0.15, (3.0, 15.0), 3.0, 4.0, 8.0, (20.0, 150.0),
                90.0, 6.0, 1.0, 0.1),
    )
}  # fmt: skip
# Vehicles reporting far apart, driving and sailing as the ones above: a delivery van in town
# whose fleet tracker reports every 60 s (a block or two and a turn between reports, no
# tunnels), and a ship seen by satellite AIS, reports 5-60 min apart (on a coarser grid).
VEHICLES["van"] = replace(VEHICLES["car"], name="van", interval=60.0, dropout_every=0.0,
                          dropout=(0.0, 0.0))  # fmt: skip
VEHICLES["satship"] = replace(VEHICLES["ship"], name="satship", step=5.0,
                              gaps=(1200.0, 300.0, 3600.0))  # fmt: skip

#: Reports per track are drawn from this range (the recorded kinds' pieces are at most 400
#: rows long: ``recorded_sets.MAX_ROWS``).
REPORTS = (120, 400)


def held(rng: np.random.Generator, v: Vehicle, steps: int) -> np.ndarray:
    """``[steps]`` the target speed at each fine step: targets held for a while each."""
    target = np.empty(steps)
    at = 0
    while at < steps:
        length = max(1, int(rng.uniform(*v.hold) / v.step))
        stop = rng.random() < v.stop_share
        target[at : at + length] = 0.0 if stop else rng.uniform(*v.speeds)
        at += length
    return target


def speed_profile(rng: np.random.Generator, v: Vehicle, steps: int) -> np.ndarray:
    """``[steps]`` the speed: following :func:`held`'s targets within the acceleration and
    braking limits, from the first target."""
    target = held(rng, v, steps)
    speed = np.empty(steps)
    now = target[0]
    up, down = v.accel * v.step, v.brake * v.step
    for k in range(steps):  # (a few thousand steps a track)
        now += min(max(target[k] - now, -down), up)
        speed[k] = now
    return speed


def heading_profile(rng: np.random.Generator, v: Vehicle, speed: np.ndarray) -> np.ndarray:
    """``[steps]`` the heading (rad): turns at random times, each step of a turn at the fastest
    rate the lateral acceleration allows at the speed there, plus the wander."""
    steps = len(speed)
    rate = np.zeros(steps)
    fastest = math.radians(v.turn_rate)
    k = 0
    while True:
        k += max(1, int(rng.exponential(v.turn_every) / v.step))
        if k >= steps:
            break
        left = math.radians(rng.uniform(*v.turn_angle))
        sign = rng.choice([-1.0, 1.0])
        while left > 0 and k < steps:  # (the rate follows the speed through the turn)
            omega = min(fastest, v.lateral / max(speed[k], 1e-3))
            turn = min(omega * v.step, left)
            rate[k] = sign * turn / v.step
            left -= turn
            k += 1
    wander = rng.normal(0.0, math.radians(v.wander) * math.sqrt(v.step), steps)
    moving = speed > 0.05  # (a stopped vehicle keeps its heading)
    return rng.uniform(0, 2 * math.pi) + np.cumsum((rate * v.step + wander) * moving)


def report_times(rng: np.random.Generator, v: Vehicle, reports: int) -> np.ndarray:
    """``[n]`` report times from 0: regular with dropouts, or independent gaps."""
    if v.interval == 0.0:
        mean, shortest, longest = v.gaps
        gaps = np.clip(rng.exponential(mean, reports), shortest, longest)
        return np.concatenate([[0.0], np.cumsum(gaps[:-1])])
    times = v.interval * np.arange(reports)
    keep = np.ones(reports, dtype=bool)
    if v.dropout_every > 0:
        at = 0.0
        while True:
            at += rng.exponential(v.dropout_every)
            if at >= times[-1]:
                break
            end = at + rng.uniform(*v.dropout)
            keep &= (times < at) | (times >= end)
            at = end
    keep[:2] = True  # (a track starts with two reports)
    return times[keep]


def simulated_piece(rng: np.random.Generator, v: Vehicle, track_id: str) -> Piece:
    """One track of ``v``: its reports' times and true positions (east, north, m)."""
    times = report_times(rng, v, int(rng.integers(*REPORTS, endpoint=True)))
    steps = int(math.ceil(times[-1] / v.step)) + 2
    speed = speed_profile(rng, v, steps)
    heading = heading_profile(rng, v, speed)
    east = np.concatenate([[0.0], np.cumsum(speed * np.cos(heading) * v.step)])[:steps]
    north = np.concatenate([[0.0], np.cumsum(speed * np.sin(heading) * v.step)])[:steps]
    grid = v.step * np.arange(steps)
    position = np.stack([np.interp(times, grid, east), np.interp(times, grid, north)], 1)
    return Piece(track_id, times, position, np.full(len(times), np.nan))


def simulated_truth(name: str, rows: int, seed: int) -> Truth:
    """The truth of the simulated kind ``name`` (:data:`VEHICLES`): tracks up to ``rows``
    rows, seeded."""
    v = VEHICLES[name]
    rng = np.random.default_rng(seed)
    pieces: list[Piece] = []
    total = 0
    while total < rows:
        piece = simulated_piece(rng, v, f"{name}/{len(pieces):03d}")
        pieces.append(piece)
        total += len(piece)
    counts = Counter({"tracks simulated": len(pieces)})
    return Truth(name, truth_rows(pieces), ["simulation"], counts, {})
