"""City buses on a street grid reporting every 30 s (kind ``bus`` of
:mod:`experiments.recorded_sets`): long straight runs at a steady speed, stops, red lights and
right-angle corners, driven along a route rather than steered (:mod:`experiments.vehicle_sets`).

Between two reports 30 s apart a bus drives a block or two at a steady speed, or stands at a
stop or a light, or turns a corner. Its second differences covary two and three reports apart
as noise would (a run follows a run), so they read as 40-50 m of noise for a 5 m sensor and the
check two reports apart (:mod:`torchsvs.datasets.noise_lags`) does not see it; the many still
or straight stretches do (:mod:`torchsvs.datasets.noise_ceiling`). A probe's buses, on which
the Kalman smoother was 3-10 times the measurements' error without a word, were of this kind.

A route is a grid of arc length (:data:`STEP`) with a curvature and a speed limit at each point
(the block's cruising speed, a corner's ``sqrt(lateral · radius)``, 0 at a stop or a red light);
the speed is the fastest within the limits, the acceleration and the braking (a forward and a
backward pass); the bus stands at each stop for its dwell.
"""

from __future__ import annotations

import math
from collections import Counter

import numpy as np

from experiments.track_truth import Piece, Truth, truth_rows
from experiments.vehicle_sets import REPORTS

STEP = 2.0  #: the route's grid (m of arc length)
BLOCK = (100.0, 220.0)  #: a block's length (m)
SPEEDS = (9.0, 14.0)  #: a block's cruising speed (m/s)
TURN_SHARE = 0.3  #: the share of junctions where the bus turns (90° either way) ...
RADIUS = (12.0, 20.0)  #: ... on a corner of this radius (m)
RED_SHARE = 0.3  #: the share of junctions where it waits at a red light ...
RED = (5.0, 50.0)  #: ... this long (s)
STOP_EVERY = (300.0, 500.0)  #: stops are this far apart (m) ...
DWELL = (10.0, 45.0)  #: ... the bus stands this long at each (s) ...
SKIP = 0.15  #: ... and passes this share of them without stopping
ACCEL, BRAKE, LATERAL = 1.0, 1.2, 1.5  #: at most (m/s²)
INTERVAL = 30.0  #: between reports (s)


def route(rng: np.random.Generator, length: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``[n]`` curvature (1/m) and speed limit (m/s) on the grid, and ``[n]`` the time the bus
    stands at each point (s): blocks, their stops, and the junctions after them."""
    curvature: list[np.ndarray] = []
    limit: list[np.ndarray] = []
    stand: list[np.ndarray] = []
    to_stop = rng.uniform(*STOP_EVERY)

    def add(metres: float, kappa: float, speed: float) -> None:
        n = max(1, int(round(metres / STEP)))
        curvature.append(np.full(n, kappa))
        limit.append(np.full(n, speed))
        stand.append(np.zeros(n))

    def halt(seconds: float) -> None:
        limit[-1][-1], stand[-1][-1] = 0.0, seconds

    done = 0.0
    while done < length:
        block, cruise = rng.uniform(*BLOCK), rng.uniform(*SPEEDS)
        left = block
        while to_stop < left:  # (the block's stops)
            add(to_stop, 0.0, cruise)
            left -= to_stop
            if rng.random() >= SKIP:
                halt(rng.uniform(*DWELL))
            to_stop = rng.uniform(*STOP_EVERY)
        add(left, 0.0, cruise)
        to_stop -= left
        done += block
        if rng.random() < RED_SHARE:
            halt(rng.uniform(*RED))
        if rng.random() < TURN_SHARE:
            radius = rng.uniform(*RADIUS)
            sign = rng.choice([-1.0, 1.0])
            add(math.pi / 2 * radius, sign / radius, min(cruise, math.sqrt(LATERAL * radius)))
            done += math.pi / 2 * radius
    kappa, cap, hold = (np.concatenate(parts) for parts in (curvature, limit, stand))
    cap[0] = cap[-1] = 0.0  # (from a standstill to one)
    return kappa, cap, hold


def speeds(cap: np.ndarray) -> np.ndarray:
    """The fastest speed on the grid within the limits ``cap``, :data:`ACCEL` and
    :data:`BRAKE`: ``v²`` at most ``cap²``, ``v_j² + 2a(s_i − s_j)`` behind and
    ``v_j² + 2b(s_j − s_i)`` ahead (prefix minima, exact for constant ``a`` and ``b``)."""
    s = STEP * np.arange(len(cap))
    v2 = cap**2
    ahead = np.minimum.accumulate((v2 + 2 * BRAKE * s)[::-1])[::-1] - 2 * BRAKE * s
    v2 = np.minimum(v2, ahead)
    behind = np.minimum.accumulate(v2 - 2 * ACCEL * s) + 2 * ACCEL * s
    return np.sqrt(np.maximum(np.minimum(v2, behind), 0.0))


def bus_piece(rng: np.random.Generator, track_id: str, reports: int) -> Piece:
    """One bus reporting ``reports`` times every :data:`INTERVAL` s along its route."""
    kappa, cap, hold = route(rng, reports * INTERVAL * SPEEDS[1])
    v = speeds(cap)
    heading = rng.uniform(0, 2 * math.pi) + np.concatenate([[0.0], np.cumsum(kappa[:-1] * STEP)])
    east = np.concatenate([[0.0], np.cumsum(np.cos(heading[:-1]) * STEP)])
    north = np.concatenate([[0.0], np.cumsum(np.sin(heading[:-1]) * STEP)])
    pace = STEP / np.maximum(0.5 * (v[:-1] + v[1:]), 0.05)
    arrive = np.concatenate([[0.0], np.cumsum(pace)]) + np.concatenate(
        [[0.0], np.cumsum(hold)[:-1]]
    )
    leave = arrive + hold  # (standing from arrival to leaving: the point twice on the time axis)
    clock = np.stack([arrive, leave], 1).reshape(-1)
    times = rng.uniform(0, INTERVAL) + INTERVAL * np.arange(reports)
    times = times[times < clock[-1]]
    position = np.stack([np.interp(times, clock, np.repeat(axis, 2)) for axis in (east, north)], 1)
    return Piece(track_id, times, position, np.full(len(times), np.nan))


def bus_truth(rows: int, seed: int) -> Truth:
    """Buses of up to ``rows`` rows in all, seeded."""
    rng = np.random.default_rng(seed)
    pieces: list[Piece] = []
    total = 0
    while total < rows:
        piece = bus_piece(rng, f"bus/{len(pieces):03d}", int(rng.integers(*REPORTS, endpoint=True)))
        pieces.append(piece)
        total += len(piece)
    return Truth(
        "bus", truth_rows(pieces), ["simulation"], Counter({"tracks simulated": len(pieces)}), {}
    )
