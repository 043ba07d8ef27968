"""Benchmark sets of recorded tracks: a truth, and measurements = truth + seeded Gaussian noise.

Each kind of track (:data:`KINDS`) is built reproducibly from the ADS-B samples of the
``traffic`` wheel (read by :func:`torchsvs.datasets.flights.flight_steps`: one east-north frame
per flight, flights split at gaps over 600 s, repeated positions read as missing) or from a
seeded simulation, then measured at each noise level σ: ``x, y`` of every row get independent
Gaussian noise of standard deviation σ (m). The truth stays beside the measurements and is never
written into the input file.

The truth is cleaned (:func:`recorded_pieces`, every count reported):

* a flight with a move the loader flags as implausible (faster than
  :data:`torchsvs.datasets.flights.MAX_SPEED` between two reports) is dropped whole;
* the samples' positions are stamped with a time up to a fraction of a second off their
  reception (OpenSky resamples to a 1 s grid): at 150 m/s a report lies ~25 m ahead of or behind
  where the aircraft was at its time stamp, along its track, while across the track it is within
  ~3 m (measured: :func:`roughness`). White truth errors that size are indistinguishable from
  measurement noise at σ = 10 m, so where the record is dense (reports on both sides within
  :data:`DEJITTER_WINDOW` s), each position is moved *along its direction of motion* to a
  local-quadratic fit of the record in time (:func:`dejitter`); the path across the track is kept
  as recorded, so turns stay as flown. Sparse records (10 s and longer) are kept as recorded,
  but for a report stamped seconds off its time (:func:`timing_glitches`: a readsb trace holds
  one 12 s off, 2.9 km along the track at 241 m/s), which is dropped; a piece is split where
  its record jumps further than its target flies (:func:`isolated_jumps`);
* pieces shorter than :data:`MIN_ROWS` rows are dropped; pieces longer than :data:`MAX_ROWS`
  are cut, so that a sample of pieces covers many flights.

A set is a seeded sample of pieces up to a row budget.
"""

from __future__ import annotations

import functools
import math
import zlib
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import NamedTuple

import numpy as np
import pandas as pd

from experiments.bus_routes import bus_truth
from experiments.flight_data import _thin
from experiments.track_truth import Piece, Truth, truth_rows
from experiments.vehicle_sets import simulated_truth
from torchsvs.accuracy import RiskTerms
from torchsvs.datasets.adsb import sample_files
from torchsvs.datasets.flights import MAX_SPEED, flight_steps
from torchsvs.datasets.tables import block_of
from torchsvs.recipes import Settings
from torchsvs.track_plan import plan_tracks
from torchsvs.track_table import estimate_block, new_run

#: Half-width (s) of the local-quadratic fit that re-times dense records (:func:`dejitter`).
DEJITTER_WINDOW = 10.0
#: Fewest reports on each side of a position, within the window, for it to be re-timed.
DEJITTER_MIN_SIDE = 2
#: Below this speed (m/s) a position is not re-timed (no direction of motion to move along).
DEJITTER_MIN_SPEED = 1.0
#: A report whose position along the straight path between its neighbours is this many seconds
#: off its time stamp is a time-stamp glitch and dropped (:func:`timing_glitches`) ...
GLITCH_SECONDS = 5.0
#: ... where the path is straight (the report this far across it at most, relative to along) ...
GLITCH_STRAIGHT = 0.25
#: ... and the target keeps its speed: the speeds into the neighbours and across the report agree
#: within this fraction.
GLITCH_STEADY = 0.1
#: A step this many times faster than the piece's 90th-percentile step speed (and over
#: :data:`JUMP_MIN_SPEED`), between steps no faster than twice it, is a jump no target of the
#: piece flies: the record joins two tracks (a glider's id reused 2.7 km away); the piece is
#: split there (:func:`isolated_jumps`).
JUMP_FACTOR = 4.0
JUMP_MIN_SPEED = 50.0
#: Fewest rows of a piece of track kept in a set.
MIN_ROWS = 30
#: Longest piece (rows); longer pieces are cut into pieces this long.
MAX_ROWS = 400
#: Taxiing: the reported ground speed above which a ground report is a take-off or landing
#: roll, not taxiing (kt; 30 kt = 15.4 m/s).
TAXI_MAX_KT = 30.0
#: Taxiing: a piece's median speed must lie in this range (m/s): moving, not parked.
TAXI_SPEED = (2.0, 15.0)
#: Taxiing, 1 s scans: a piece is cut at a gap between reports longer than this (s).
TAXI_MAX_GAP = 30.0
SCAN1_MAX_GAP = 1.5


@dataclass(frozen=True)
class Kind:
    """A kind of track: where its truth comes from and the noise levels it is measured at."""

    name: str
    title: str
    sigmas: tuple[float, ...]  #: default noise levels (m)
    build: Callable[[int, int], Truth]  #: (rows, seed) → truth
    note: str = ""


# --- cleaning ----------------------------------------------------------------------------------


def local_quadratic(
    time: np.ndarray, position: np.ndarray, half_width: float, min_side: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Local-quadratic regression of ``position [n, m]`` on ``time [n]`` (sorted), tricube
    weights of half-width ``half_width`` (Cleveland 1979, doi:10.1080/01621459.1979.10481038).

    Returns:
        The fitted position ``[n, m]`` and velocity ``[n, m]`` at each time, and ``[n]`` whether
        the fit is supported (at least ``min_side`` reports on each side within the window;
        elsewhere both are NaN).
    """
    n = len(time)
    lo = np.searchsorted(time, time - half_width, side="left")
    hi = np.searchsorted(time, time + half_width, side="right")
    width = int((hi - lo).max(initial=1))
    index = lo[:, None] + np.arange(width)[None, :]
    inside = index < hi[:, None]
    index = np.minimum(index, n - 1)
    offset = np.where(inside, time[index] - time[:, None], 0.0)
    u = np.clip(np.abs(offset) / half_width, 0.0, 1.0)
    weight = np.where(inside, (1.0 - u**3) ** 3, 0.0)
    here = np.arange(n)[:, None]
    used = inside & (weight > 0)
    supported = ((used & (index < here)).sum(1) >= min_side) & (
        (used & (index > here)).sum(1) >= min_side
    )
    basis = np.stack([np.ones_like(offset), offset, offset * offset], -1)  # [n, W, 3]
    fitted = np.full((n, 3, position.shape[1]), np.nan)
    if supported.any():
        w, X, y = weight[supported], basis[supported], position[index[supported]]
        gram = np.einsum("nw,nwi,nwj->nij", w, X, X)
        moment = np.einsum("nw,nwi,nwk->nik", w, X, y)
        fitted[supported] = np.linalg.solve(gram, moment)
    return fitted[:, 0], fitted[:, 1], supported


def dejitter(
    time: np.ndarray, position: np.ndarray, half_width: float = DEJITTER_WINDOW
) -> tuple[np.ndarray, np.ndarray]:
    """Positions moved along their direction of motion to the local-quadratic fit of the record
    (:func:`local_quadratic`): a time-stamp error moves a report along the track, so only that
    component is corrected and the path across the track stays as recorded.

    Returns:
        The positions ``[n, 2]`` and ``[n]`` whether each was moved (supported fit, speed at
        least :data:`DEJITTER_MIN_SPEED`).
    """
    fitted, velocity, moved = local_quadratic(time, position, half_width, DEJITTER_MIN_SIDE)
    speed = np.linalg.norm(velocity, axis=1)
    moved &= np.nan_to_num(speed) >= DEJITTER_MIN_SPEED
    out = position.copy()
    direction = velocity[moved] / speed[moved, None]
    along = ((fitted[moved] - position[moved]) * direction).sum(1)
    out[moved] = position[moved] + along[:, None] * direction
    return out, moved


def timing_glitches(time: np.ndarray, position: np.ndarray) -> np.ndarray:
    """``[n]`` bool: reports stamped at the wrong time (a glitch of the record, not motion).

    A report ``i`` whose neighbours ``i-1, i+1`` span a straight, steady stretch: it lies
    near the chord between them (its offset across the chord at most :data:`GLITCH_STRAIGHT`
    of its offset along), and the speeds ``i-2 → i-1`` and ``i+1 → i+2`` agree with the speed
    across it within :data:`GLITCH_STEADY`. On such a stretch the target passes the report's
    position at the time its fraction of the chord gives; more than :data:`GLITCH_SECONDS` from
    its time stamp, the stamp is wrong. A turn or a speed change between the neighbours fails
    the conditions, so only glitches on straight flight are found (the ones a filter can tell
    from the path, and would be scored against).
    """
    n = len(time)
    found = np.zeros(n, dtype=bool)
    if n < 5:
        return found
    i = np.arange(2, n - 2)
    chord = position[i + 1] - position[i - 1]
    length = np.linalg.norm(chord, axis=1)
    span = time[i + 1] - time[i - 1]
    ok = (length > 0) & (span > 0)
    unit = chord / np.where(length > 0, length, 1.0)[:, None]
    offset = position[i] - position[i - 1]
    along = (offset * unit).sum(1)
    across = np.abs(offset[:, 0] * unit[:, 1] - offset[:, 1] * unit[:, 0])
    speed = np.where(ok, length / np.where(span > 0, span, 1.0), np.nan)
    # how far along the chord the report is, against how far its time stamp puts it
    shift = np.abs(along - (time[i] - time[i - 1]) * speed)
    steps = speeds(time, position)  # steps[k]: from report k to k + 1
    before, after = steps[i - 2], steps[i + 1]
    steady = (np.abs(before / speed - 1) <= GLITCH_STEADY) & (
        np.abs(after / speed - 1) <= GLITCH_STEADY
    )
    straight = across <= GLITCH_STRAIGHT * shift
    found[i] = ok & steady & straight & (shift > GLITCH_SECONDS * speed)
    return found


def isolated_jumps(piece: Piece) -> np.ndarray:
    """``[n]`` bool: the reports a piece jumps to (:data:`JUMP_FACTOR` times its 90th-percentile
    step speed, over :data:`JUMP_MIN_SPEED`) from a normal step and leaves by one (at most twice
    that speed): the record of two targets joined, not a maneuver (a take-off roll's speeds
    grow over many steps)."""
    speed = step_speeds(piece)
    found = np.zeros(len(piece), dtype=bool)
    if len(speed) < 3:
        return found
    usual = np.percentile(speed, 90)
    jump = (speed > JUMP_FACTOR * usual) & (speed > JUMP_MIN_SPEED)
    calm = speed <= 2.0 * usual
    inner = np.arange(1, len(speed) - 1)
    found[inner + 1] = jump[inner] & calm[inner - 1] & calm[inner + 1]
    return found


def roughness(pieces: Sequence[Piece], max_interval: float = 1.5) -> dict[str, float]:
    """Per-report white error of the positions, along and across the track (m, RMS).

    At each report with neighbours at most ``max_interval`` s away on both sides, the
    position's offset from the time-interpolation of its neighbours is ``e₁ − (w e₀ + (1−w) e₂)``
    plus a motion term of ``a·Δt²/2`` (under 2 m at 3 m/s² and 1 s): for white errors of
    standard deviation ``s`` its variance is ``s² (1 + w² + (1−w)²)`` (1.5 s² at equal
    intervals), from which ``s`` is read. Sparse records give NaN.
    """
    along, across, factor = [], [], []
    for piece in pieces:
        t, p = piece.time, piece.position
        if len(t) < 3:
            continue
        before, after = t[1:-1] - t[:-2], t[2:] - t[1:-1]
        close = (before <= max_interval) & (after <= max_interval)
        w = after / (before + after)  # weight of the earlier neighbour
        middle = w[:, None] * p[:-2] + (1 - w)[:, None] * p[2:]
        offset = p[1:-1] - middle
        chord = p[2:] - p[:-2]
        length = np.linalg.norm(chord, axis=1)
        close &= length > 0
        unit = chord[close] / length[close, None]
        along.append((offset[close] * unit).sum(1))
        across.append(offset[close, 0] * unit[:, 1] - offset[close, 1] * unit[:, 0])
        factor.append(1 + w[close] ** 2 + (1 - w[close]) ** 2)
    if not along or not sum(len(a) for a in along):
        return {"along": math.nan, "across": math.nan, "reports": 0.0}
    a, c, f = (np.concatenate(x) for x in (along, across, factor))
    return {
        "along": float(np.sqrt(np.mean(a**2 / f))),
        "across": float(np.sqrt(np.mean(c**2 / f))),
        "reports": float(len(a)),
    }


def speeds(time: np.ndarray, position: np.ndarray) -> np.ndarray:
    """[n-1] speed (m/s) between successive reports."""
    elapsed = np.diff(time)
    return np.linalg.norm(np.diff(position, axis=0), axis=1) / np.maximum(elapsed, 1e-9)


def step_speeds(piece: Piece) -> np.ndarray:
    """[n-1] speed (m/s) between successive reports of a piece."""
    return speeds(piece.time, piece.position)


def split_at(piece: Piece, cut: np.ndarray) -> list[Piece]:
    """A piece cut before every report ``k`` where ``cut[k]`` (``cut [n]`` bool), suffixed
    ``~1, ~2, ...`` when cut."""
    starts = np.flatnonzero(cut[1:]) + 1
    bounds = np.concatenate([[0], starts, [len(piece)]])
    if len(bounds) == 2:
        return [piece]
    return [
        piece.take(np.arange(a, b), f"~{i + 1}")
        for i, (a, b) in enumerate(zip(bounds[:-1], bounds[1:], strict=True))
        if b > a
    ]


def recorded_pieces(
    names: Sequence[str], ground: bool = False, counts: Counter[str] | None = None
) -> tuple[list[Piece], list[Piece], list[str]]:
    """The recorded tracks of sample files (``"folder/name"`` or folder names), cleaned.

    Args:
        names: sample files as ``"collections/quickstart.json.gz"``, or whole folders; each
            piece's ``source`` is the entry it was read through.
        ground: the reports the loader sets aside as on the ground (``on_ground``), instead of
            the airborne ones.
        counts: where to add the counts of what the cleaning did.

    Returns:
        The pieces as recorded (new positions only) and de-jittered (:func:`dejitter`), both
        after dropping flights with implausible jumps, and the files read.
    """
    raw, clean, files, done = _read_pieces(tuple(names), ground)
    if counts is not None:
        counts.update(done)
    return list(raw), list(clean), list(files)


@functools.lru_cache(maxsize=8)
def _read_pieces(
    names: tuple[str, ...], ground: bool
) -> tuple[tuple[Piece, ...], tuple[Piece, ...], tuple[str, ...], Counter[str]]:
    counts: Counter[str] = Counter()
    files = select_files(names)
    source_of = {path.name.split(".")[0]: name for name, path in files}
    paths = [path for _, path in files]
    steps, _ = flight_steps(paths, airborne=True)
    if ground:
        every, _ = flight_steps(paths, airborne=False)
        # The rows the airborne read sets aside and the full read places are on the ground.
        row_ground = (steps.row_step < 0) & (every.row_step >= 0)
        step_ground = np.zeros(len(every.time), dtype=bool)
        step_ground[every.row_step[row_ground]] = True
        steps = every
    raw: list[Piece] = []
    clean: list[Piece] = []
    for k in range(steps.num_tracks):
        first, length = steps.start[k], steps.length[k]
        span = np.arange(first, first + length)
        keep = np.isfinite(steps.position[span, :2]).all(axis=1)
        if ground:
            keep &= step_ground[span]
        span = span[keep]
        if len(span) < 2:
            continue
        track_id = steps.ids[k]
        piece = Piece(
            track_id,
            steps.time[span],
            steps.position[span, :2],
            steps.extra["groundspeed_kt"][span],
            source=source_of[track_id.split("/")[0]],
        )
        counts["flights read"] += 1
        if (step_speeds(piece) > MAX_SPEED).any():
            counts["flights dropped: implausible jump (loader's rule)"] += 1
            continue
        raw.append(piece)
        counts["reports"] += len(piece)
        glitch = timing_glitches(piece.time, piece.position)
        if glitch.any():
            counts[f"reports dropped: time stamp over {GLITCH_SECONDS:g} s off (glitch)"] += int(
                glitch.sum()
            )
            piece = piece.take(np.flatnonzero(~glitch))
        position, moved = dejitter(piece.time, piece.position)
        counts["reports re-timed along track"] += int(moved.sum())
        whole = Piece(track_id, piece.time, position, piece.groundspeed_kt, source=piece.source)
        jumps = isolated_jumps(whole)
        if jumps.any():
            counts["pieces split where the record jumps (two tracks joined)"] += int(jumps.sum())
        clean.extend(split_at(whole, jumps))
    short = tuple(f"{path.parent.name}/{path.name}" for path in paths)
    return tuple(raw), tuple(clean), short, counts


def select_files(names: Sequence[str]) -> list[tuple[str, Path]]:
    """Sample files by ``"folder/name"`` or by folder, each with the name it was chosen by."""
    files = sample_files()
    chosen = []
    for name in names:
        match = [p for p in files if f"{p.parent.name}/{p.name}" == name or p.parent.name == name]
        if not match:
            raise ValueError(f"names: no sample file or folder {name!r} in the traffic wheel")
        chosen += [(name, path) for path in match]
    return chosen


def sample_pieces(
    pieces: Sequence[Piece], rows: int, seed: int, counts: Counter[str]
) -> list[Piece]:
    """Pieces cut to at most :data:`MAX_ROWS` rows, those under :data:`MIN_ROWS` dropped, then a
    seeded sample of them up to ``rows`` rows (the last one may cross it), drawn in turn from
    each source so that every source has a share (a small one gives all it has)."""
    cut: list[Piece] = []
    for piece in pieces:
        if len(piece) < MIN_ROWS:
            counts[f"pieces dropped: fewer than {MIN_ROWS} rows"] += 1
            continue
        parts = math.ceil(len(piece) / MAX_ROWS)
        if parts == 1:
            cut.append(piece)
            continue
        bounds = np.linspace(0, len(piece), parts + 1).round().astype(int)
        for i in range(parts):
            cut.append(piece.take(np.arange(bounds[i], bounds[i + 1]), f"/{i + 1}"))
    rng = np.random.default_rng(seed)
    queues = {}
    for source in sorted({p.source for p in cut}):
        mine = [p for p in cut if p.source == source]
        queues[source] = [mine[i] for i in rng.permutation(len(mine))]
    taken = dict.fromkeys(queues, 0)
    chosen: list[Piece] = []
    total = 0
    while total < rows and any(queues.values()):
        # the source with the fewest rows so far gives its next piece
        source = min((s for s in queues if queues[s]), key=lambda s: (taken[s], s))
        piece = queues[source].pop()
        chosen.append(piece)
        taken[source] += len(piece)
        total += len(piece)
    counts["pieces available"] = len(cut)
    counts["pieces chosen"] = len(chosen)
    return sorted(chosen, key=lambda p: p.track_id)


# --- kinds -------------------------------------------------------------------------------------


def recorded_truth(
    kind: str,
    names: Sequence[str],
    rows: int,
    seed: int,
    select: Callable[[Piece], list[Piece]] = lambda piece: [piece],
    ground: bool = False,
) -> Truth:
    """The truth of a recorded kind: the cleaned pieces of ``names``
    (:func:`recorded_pieces`), each turned into the kind's pieces by ``select``, sampled up to
    ``rows`` rows (:func:`sample_pieces`); with the record's :func:`roughness` as recorded (of
    the flights sampled)."""
    counts: Counter[str] = Counter()
    raw, clean, files = recorded_pieces(names, ground=ground, counts=counts)
    pieces = [part for piece in clean for part in select(piece)]
    chosen = sample_pieces(pieces, rows, seed, counts)
    origins = {p.origin for p in chosen}
    recorded = roughness([p for p in raw if p.origin in origins])
    return Truth(kind, truth_rows(chosen), files, counts, recorded)


def airliners_own(rows: int, seed: int) -> Truth:
    """Airliners at their own report times, every report with a new position: OpenSky's 1 s
    grid with its gaps (quickstart), decoded Mode S messages at their reception times (~0.5 s
    apart, irregular: rs1090), a readsb trace (2-20 s)."""
    names = ["collections/quickstart.json.gz", "rs1090", "readsb"]
    return recorded_truth("own", names, rows, seed)


def airliners_10s(rows: int, seed: int) -> Truth:
    """Airliners on 10 s scans: the reports at least 10 s apart (greedy from the first)."""

    def thin(piece: Piece) -> list[Piece]:
        return [piece.take(_thin(piece.time, 10.0))]

    return recorded_truth("scan10", ["collections/quickstart.json.gz"], rows, seed, thin)


def one_second(rows: int, seed: int) -> Truth:
    """1 s position reports: ambulance helicopters, calibration aircraft, military jets; cut at
    gaps longer than 1.5 s."""

    def runs(piece: Piece) -> list[Piece]:
        gap = np.concatenate([[False], np.diff(piece.time) > SCAN1_MAX_GAP])
        return split_at(piece, gap)

    names = ["ambulances", "collections/savan.json.gz", "military"]
    return recorded_truth("scan1", names, rows, seed, runs)


def taxiing(rows: int, seed: int) -> Truth:
    """Aircraft taxiing on the ground (the reports the loader sets aside as on the ground),
    at their own report times: a stand-in for ships."""
    counts: Counter[str] = Counter()

    def taxi(piece: Piece) -> list[Piece]:
        # A report faster than taxiing (take-off or landing roll) or a long stop cuts the piece.
        fast = piece.groundspeed_kt > TAXI_MAX_KT
        gap = np.concatenate([[False], np.diff(piece.time) > TAXI_MAX_GAP])
        parts = split_at(piece, fast | gap)
        kept = []
        for part in parts:
            slow = part.groundspeed_kt <= TAXI_MAX_KT
            part = part.take(np.flatnonzero(slow | np.isnan(part.groundspeed_kt)))
            if len(part) < 2:
                continue
            speed = float(np.median(step_speeds(part)))
            if TAXI_SPEED[0] <= speed <= TAXI_SPEED[1]:
                kept.append(part)
            else:
                counts["taxi pieces dropped: median speed outside 2-15 m/s"] += 1
        return kept

    names = [
        "collections/quickstart.json.gz",
        "collections/savan.json.gz",
        "onground",
        "readsb",
        "rs1090",
    ]
    truth = recorded_truth("taxi", names, rows, seed, taxi, ground=True)
    truth.counts.update(counts)
    return truth


def irregular(rows: int, seed: int) -> Truth:
    """Other aircraft at their own irregular report times (3-60 s): FlightRadar24 dumps,
    gliders, survey aircraft."""
    return recorded_truth("irregular", ["fr24", "gliders", "surveys"], rows, seed)


#: Simulated turns: speed range (m/s), turn rates (deg/s), scan (s), steps per track.
TURN_SPEED = (100.0, 250.0)
TURN_RATE_DEG = (3.0, 6.0)
TURN_DT = 2.0
TURN_STEPS = 200


def turning(rows: int, seed: int) -> Truth:
    """Simulated tracks alternating straight legs and coordinated turns of 3-6 deg/s
    (:func:`torchsvs.scenarios.random_maneuvers`, 2 s scans)."""
    import torch

    from torchsvs.scenarios import ManeuverRanges, random_maneuvers

    ranges = ManeuverRanges(
        steps=TURN_STEPS,
        dt=TURN_DT,
        speed=TURN_SPEED,
        segment_duration=(10.0, 60.0),
        turn_rate_deg=TURN_RATE_DEG,
        kind_weights=(0.35, 0.65, 0.0, 0.0),  # straight legs and constant-rate turns only
    )
    count = max(1, math.ceil(rows / TURN_STEPS))
    batch = random_maneuvers(count, ranges, torch.Generator().manual_seed(seed))
    truth = batch.truth.numpy()
    pieces = [
        Piece(
            f"turn/{b:03d}",
            TURN_DT * np.arange(1, TURN_STEPS + 1),
            truth[b][:, [0, 2]],
            np.full(TURN_STEPS, np.nan),
        )
        for b in range(count)
    ]
    counts = Counter({"tracks simulated": count})
    return Truth("turning", truth_rows(pieces), ["simulation"], counts, {})


KINDS: dict[str, Kind] = {
    k.name: k
    for k in (
        Kind(
            "own",
            "airliners at their own report times",
            (10.0, 50.0, 100.0),
            airliners_own,
            "rows with a new position, not a resampled grid",
        ),
        Kind("scan10", "airliners on 10 s scans", (50.0, 100.0), airliners_10s),
        Kind(
            "scan1",
            "1 s scans: helicopters, calibration aircraft, military jets",
            (10.0, 50.0),
            one_second,
        ),
        Kind(
            "taxi",
            "aircraft taxiing on the ground (stand-in for ships)",
            (10.0, 50.0),
            taxiing,
            "slow targets, 2-15 m/s, with stops and turns onto taxiways",
        ),
        Kind(
            "irregular",
            "other aircraft at irregular report times (FR24, gliders, surveys)",
            (50.0,),
            irregular,
        ),
        Kind("turning", "simulated hard turns (3-6 deg/s, 2 s scans)", (50.0,), turning),
        Kind(
            "walker",
            "simulated people walking (1 s GPS)",
            (3.0, 10.0),
            functools.partial(simulated_truth, "walker"),
            "1-1.6 m/s, waits and corners",
        ),
        Kind(
            "car",
            "simulated cars in town (1 s GPS, tunnels)",
            (3.0, 10.0),
            functools.partial(simulated_truth, "car"),
            "stop-and-go at 8-20 m/s, right-angle turns, dropouts of 10-30 s",
        ),
        Kind(
            "ship",
            "simulated ships (AIS, 2-180 s apart)",
            (10.0, 50.0),
            functools.partial(simulated_truth, "ship"),
            "3-10 m/s, course changes of 10-60 deg",
        ),
        Kind(
            "drone",
            "simulated multirotor drones (10 Hz GPS)",
            (1.0, 3.0),
            functools.partial(simulated_truth, "drone"),
            "hovering and 3-15 m/s, sharp turns",
        ),
        Kind(
            "van",
            "simulated delivery vans in town (fleet trackers, 60 s)",
            (5.0, 20.0),
            functools.partial(simulated_truth, "van"),
            "the cars' driving; a block or two and a turn between reports",
        ),
        Kind(
            "bus",
            "simulated city buses (30 s)",
            (5.0, 10.0),
            bus_truth,
            "blocks at a steady 9-14 m/s, stops, red lights, right-angle corners",
        ),
        Kind(
            "satship",
            "simulated ships by satellite AIS (5-60 min apart)",
            (10.0, 50.0),
            functools.partial(simulated_truth, "satship"),
            "the AIS ships' sailing, course changes between reports",
        ),
    )
}
#: The kinds a benchmark runs unless told (the simulated vehicles of :mod:`experiments.
#: vehicle_sets` are their own benchmark: ``make recorded-vehicles``).
DEFAULT_KINDS = ("own", "scan10", "scan1", "taxi", "irregular", "turning")


# --- sets --------------------------------------------------------------------------------------


@dataclass
class BenchSet:
    """One benchmark set: a kind's truth measured with noise σ (and :func:`add_faults`)."""

    kind: Kind
    sigma: float
    truth: Truth
    measurements: pd.DataFrame  #: track_id, time, x, y: the truth plus noise
    faults: bool = False  #: measured with :func:`add_faults`
    noise: str = "white"  #: the noise's kind (:data:`NOISE_KINDS`)

    @property
    def name(self) -> str:
        noise = "" if self.noise == "white" else f" {self.noise}"
        return f"{self.kind.name} σ{self.sigma:g}" + (" faults" if self.faults else "") + noise

    @property
    def slug(self) -> str:
        noise = "" if self.noise == "white" else f"_{self.noise}"
        return f"{self.kind.name}_s{self.sigma:g}" + ("_faults" if self.faults else "") + noise

    def write(self, folder: Path) -> tuple[Path, Path]:
        """The input file (measurements only) and the truth beside it, as CSV."""
        folder.mkdir(parents=True, exist_ok=True)
        source, truth = folder / f"{self.slug}.csv", folder / f"{self.slug}.truth.csv"
        self.measurements.to_csv(source, index=False)
        self.truth.rows.to_csv(truth, index=False)
        return source, truth


#: The kinds of measurement noise (:func:`measure`), each of standard deviation σ per axis:
#: ``white`` independent Gaussian (what the estimators and their error estimate assume);
#: ``mixed`` the same, each track's σ drawn from σ/:data:`MIXED_RANGE` to σ·MIXED_RANGE
#: (log-uniform: sensors of different quality in one file); ``heavy`` Student's t with
#: :data:`HEAVY_DOF` degrees of freedom (a heavy-tailed sensor); ``correlated`` Gaussian with
#: correlation exp(-Δt / :data:`CORRELATION_TIME`) between a track's reports (a GPS's slowly
#: wandering error, which positions alone cannot tell from motion).
NOISE_KINDS = ("white", "mixed", "heavy", "correlated")
MIXED_RANGE = 3.0
HEAVY_DOF = 3.0
CORRELATION_TIME = 20.0


def measure(truth: pd.DataFrame, sigma: float, seed: int, noise: str = "white") -> pd.DataFrame:
    """The truth's rows with noise of standard deviation ``sigma`` (m) on ``x`` and ``y`` of the
    kind ``noise`` (:data:`NOISE_KINDS`), seeded; for a kind other than white, each row's
    standard deviation beside them in a column ``sigma`` (as a sensor states its accuracy:
    ``track --noise-col sigma``)."""
    if not sigma > 0:
        raise ValueError(f"sigma: expected a standard deviation > 0 (m), got {sigma!r}")
    if noise not in NOISE_KINDS:
        raise ValueError(f"noise: expected one of {list(NOISE_KINDS)}, got {noise!r}")
    rng = np.random.default_rng(seed)
    n = len(truth)
    if noise == "heavy":  # (t's variance is dof / (dof − 2) times its scale's square)
        scale = sigma * math.sqrt((HEAVY_DOF - 2.0) / HEAVY_DOF)
        error = rng.standard_t(HEAVY_DOF, size=(n, 2)) * scale
    else:
        error = rng.normal(0.0, sigma, size=(n, 2))
    stated = np.full(n, float(sigma))  # (the sensor's stated accuracy per row)
    if noise in ("mixed", "correlated"):
        ids = truth["track_id"].to_numpy()
        starts = np.flatnonzero(np.r_[True, ids[1:] != ids[:-1]])
        ends = np.r_[starts[1:], n]
        time = truth["time"].to_numpy(dtype=float)
        for a, b in zip(starts, ends, strict=True):
            if noise == "mixed":
                own = math.exp(rng.uniform(-1.0, 1.0) * math.log(MIXED_RANGE))
                error[a:b] *= own
                stated[a:b] *= own
                continue
            rho = np.exp(-np.diff(time[a:b]) / CORRELATION_TIME)
            for k in range(1, b - a):  # AR(1) at the reports' own intervals, variance kept
                i = a + k
                error[i] = rho[k - 1] * error[i - 1] + math.sqrt(1.0 - rho[k - 1] ** 2) * error[i]
    measured = truth.assign(x=truth["x"] + error[:, 0], y=truth["y"] + error[:, 1])
    # (beside noise other than white, each row's stated standard deviation: --noise-col sigma)
    return measured if noise == "white" else measured.assign(sigma=stated)


#: Faults (:func:`add_faults`): this share of positions off by :data:`OUTLIER_SIGMAS` σ ...
OUTLIER_SHARE = 0.01
OUTLIER_SIGMAS = 10.0
#: ... this share of rows lost, in runs of :data:`DROPOUT_RUN` rows on average ...
DROPOUT_SHARE = 0.05
DROPOUT_RUN = 5.0
#: ... time stamps off by this standard deviation (s; within 0.4 of the intervals beside) ...
JITTER_STD = 0.1
#: ... and a sensor bias of :data:`BIAS_SIGMAS` σ in one direction over one stretch of this
#: share of each track's rows (it comes and goes).
BIAS_SHARE = 0.2
BIAS_SIGMAS = 3.0
#: Fewest rows a track keeps through the dropouts.
FAULT_MIN_ROWS = 10


def directions(rng: np.random.Generator, size: int) -> np.ndarray:
    """``[size, 2]`` unit vectors at uniform random angles."""
    angle = rng.uniform(0.0, 2.0 * np.pi, size)
    return np.stack([np.cos(angle), np.sin(angle)], 1)


def bias_stretch(rows: int, rng: np.random.Generator) -> tuple[int, int]:
    """The rows of a track of ``rows`` rows that :func:`add_faults`' bias covers: one stretch of
    :data:`BIAS_SHARE` of them at a random place (its first row, and the row past its end)."""
    length = max(1, int(round(BIAS_SHARE * rows)))
    first = int(rng.integers(0, rows - length + 1))
    return first, first + length


def add_faults(
    truth: pd.DataFrame, measured: pd.DataFrame, sigma: float, seed: int
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Realistic faults on measured rows (issue 29, item 6), seeded: outliers, dropouts, time
    jitter and a bias that comes and goes (the constants above). Rows lost are dropped from
    both frames; the truth keeps each row's true position under its reported time, so the
    jitter's displacement along the track is error no estimator can remove.

    Returns:
        The truth and the measurements, row for row (same order, same ``track_id, time``).
    """
    rng = np.random.default_rng(seed)
    n = len(measured)
    xy = measured[["x", "y"]].to_numpy(copy=True)
    time = measured["time"].to_numpy(dtype=float, copy=True)
    ids = measured["track_id"].to_numpy()
    starts = np.flatnonzero(np.r_[True, ids[1:] != ids[:-1]])
    ends = np.r_[starts[1:], n]

    keep = np.ones(n, dtype=bool)
    for a, b in zip(starts, ends, strict=True):
        first, end = bias_stretch(b - a, rng)
        xy[a + first : a + end] += BIAS_SIGMAS * sigma * directions(rng, 1)
        # dropouts: runs that start at random, geometric lengths
        lost = np.zeros(b - a, dtype=bool)
        for k in np.flatnonzero(rng.random(b - a) < DROPOUT_SHARE / DROPOUT_RUN):
            lost[k : k + int(rng.geometric(1.0 / DROPOUT_RUN))] = True
        if (~lost).sum() >= FAULT_MIN_ROWS:
            keep[a:b] = ~lost
        # jitter: within 0.4 of the intervals on either side, so the order stays
        gaps = np.diff(time[a:b])
        room = 0.4 * np.minimum(np.r_[np.inf, gaps], np.r_[gaps, np.inf])
        shift = np.clip(rng.normal(0.0, JITTER_STD, b - a), -room, room)
        time[a:b] += shift
    outliers = rng.random(n) < OUTLIER_SHARE
    xy[outliers] += OUTLIER_SIGMAS * sigma * directions(rng, int(outliers.sum()))
    measured = measured.assign(time=time, x=xy[:, 0], y=xy[:, 1])
    truth = truth.assign(time=time)
    return truth[keep].reset_index(drop=True), measured[keep].reset_index(drop=True)


def set_seed(seed: int, kind: str, sigma: float | None = None) -> int:
    """A stable seed per kind (and noise level) from the run's seed."""
    text = kind if sigma is None else f"{kind}/{sigma:g}"
    return (seed * 1_000_003 + zlib.crc32(text.encode())) % (2**32)


def build_sets(
    kinds: Sequence[str] | None = None,
    rows: int = 5000,
    seed: int = 0,
    sigmas: Sequence[float] | None = None,
    progress: bool = False,
    faults: bool = False,
    noise: str = "white",
) -> list[BenchSet]:
    """The benchmark sets: every kind of ``kinds`` (default :data:`DEFAULT_KINDS`) at its noise levels
    (or at ``sigmas``), about ``rows`` rows each; with ``faults``, measured with
    :func:`add_faults` too."""
    from tqdm.auto import tqdm

    names = list(DEFAULT_KINDS) if kinds is None else list(kinds)
    unknown = [k for k in names if k not in KINDS]
    if unknown:
        raise ValueError(f"kinds: expected names among {sorted(KINDS)}, got {unknown}")
    sets = []
    for name in tqdm(names, desc="sets", disable=not progress, leave=False):
        kind = KINDS[name]
        truth = kind.build(rows, set_seed(seed, name))
        for sigma in sigmas or kind.sigmas:
            noisy = measure(truth.rows, sigma, set_seed(seed, name, sigma), noise)
            if faults:
                kept, noisy = add_faults(truth.rows, noisy, sigma, set_seed(seed, name, -sigma))
                faulty = replace(truth, rows=kept)
                sets.append(BenchSet(kind, float(sigma), faulty, noisy, True, noise))
            else:
                sets.append(BenchSet(kind, float(sigma), truth, noisy, noise=noise))
    return sets


class SetStats(NamedTuple):
    """What a set holds."""

    tracks: int
    rows: int
    interval: np.ndarray  #: [4] 10th, 50th, 90th percentiles and the longest report interval (s)
    speed: np.ndarray  #: [3] the same of the truth's speed between reports (m/s)
    raw_rmse: float  #: 2-D RMSE of the measurements (m)


def describe(bench: BenchSet) -> SetStats:
    """Tracks, rows, report intervals and speeds (percentiles), raw RMSE of a set."""
    rows = bench.truth.rows
    ids = rows["track_id"].to_numpy()
    same = ids[1:] == ids[:-1]
    elapsed = np.diff(rows["time"].to_numpy())[same]
    moved = np.hypot(np.diff(rows["x"].to_numpy()), np.diff(rows["y"].to_numpy()))[same]
    speed = moved / np.maximum(elapsed, 1e-9)
    error = bench.measurements[["x", "y"]].to_numpy() - rows[["x", "y"]].to_numpy()

    def spread(values: np.ndarray) -> np.ndarray:
        return np.percentile(values, [10, 50, 90]) if len(values) else np.full(3, np.nan)

    longest = float(elapsed.max()) if len(elapsed) else math.nan
    return SetStats(
        int(rows["track_id"].nunique()),
        len(rows),
        np.append(spread(elapsed), longest),
        spread(speed),
        float(np.sqrt(np.mean((error**2).sum(axis=1)))),
    )


class SetRun(NamedTuple):
    """An estimator on a set as ``torchsvs track`` runs it (:func:`run_as_track`)."""

    table: pd.DataFrame  #: the output rows: track_id, time, x, vx, y, vy (, outlier)
    terms: RiskTerms  #: SURE's sums per chunk, the chunks' ``track`` an index into ``ids``
    meas_var: list[float]  #: the noise variances the run used
    ids: list[str]  #: the tracks, in the run's order


def run_as_track(bench: BenchSet, settings: Settings) -> SetRun:
    """``settings``' estimator on ``bench``'s measurements as ``torchsvs track`` runs it: the
    plan read off the set (:func:`~torchsvs.track_plan.plan_tracks`), every track in one block
    (:func:`~torchsvs.track_table.estimate_block`), float64 output."""
    data = bench.measurements
    plan = plan_tracks(data, settings)
    assert plan.settings.meas_var is not None
    block = block_of(data, plan.columns)
    found = estimate_block(block, plan, plan.estimator(), new_run(plan))
    terms = RiskTerms.concat(found.risk, len(plan.settings.meas_var))
    table = found.table(block, "float64").to_pandas()
    return SetRun(table, terms, list(plan.settings.meas_var), list(block.steps.ids))
