"""Recorded ADS-B flights as tracks in local metric frames.

Each flight (one track of :mod:`torchsvs.datasets.adsb`, split at long gaps, repeated positions
read as missing) gets its own east-north-up frame at its median latitude and longitude
(:mod:`torchsvs.datasets.geodesy`); positions are ``east, north`` (m) and, with ``dims=3``, the
barometric altitude (m). The reported velocity (ground speed and track angle, vertical rate),
measured by the aircraft independently of its position, is carried per step in the same frame
as ``extra["ve"]``, ``extra["vn"]`` (and ``extra["vu"]``), m/s.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from torchsvs.datasets import geodesy
from torchsvs.datasets.rows import ParsedRows, RowReport
from torchsvs.datasets.steps import TrackSteps, group_rows


@dataclass
class FlightReport:
    """What reading a set of ADS-B files gave."""

    files: int = 0
    track_files: int = 0
    not_tracks: dict[str, str] = field(default_factory=dict)  #: file → why it is not a track file
    rows: RowReport = field(default_factory=RowReport)
    per_file: dict[str, tuple[int, int]] = field(default_factory=dict)  #: file → (rows, tracks)

    def summary(self) -> str:
        lines = [
            f"{self.files} files: {self.track_files} with tracks, {len(self.not_tracks)} not tracks"
        ]
        lines += [f"  not a track file: {name} ({why})" for name, why in self.not_tracks.items()]
        return "\n".join(lines) + "\n" + self.rows.summary()


def flight_steps(
    files: Sequence[str | Path] | None = None,
    dims: int = 2,
    max_gap: float = 600.0,
    airborne: bool = True,
) -> tuple[TrackSteps, FlightReport]:
    """Reads ADS-B files into the steps of local-frame tracks.

    Args:
        files: sample files (default: every file of the ``traffic`` wheel's samples).
        dims: 2 (east, north) or 3 (and altitude).
        max_gap: split a flight at gaps longer than this (s).
        airborne: set aside rows the source marks on the ground (their positions are taxiing,
            parked or repeated, not the flight's).

    Returns:
        The steps (extra columns ``ve, vn[, vu]`` in m/s, ``lat0, lon0`` per step, the frame
        of its track, and the reported ``altitude_ft, groundspeed_kt, track_deg,
        vertical_rate_fpm``) and a report counting files, tracks and every row.
    """
    import pandas as pd

    from torchsvs.datasets import adsb

    if dims not in (2, 3):
        raise ValueError(f"dims: expected 2 or 3, got {dims!r}")
    paths = [Path(p) for p in files] if files is not None else adsb.sample_files()
    report = FlightReport(files=len(paths))
    frames = []
    notes: Counter[str] = Counter()
    for path in paths:
        read = adsb.read_adsb_file(path)
        name = _short_name(path)
        if read.rows is None:
            report.not_tracks[name] = read.note or "not a track file"
            continue
        report.track_files += 1
        rows = adsb.split_flights(read.rows, max_gap=max_gap)
        rows, repeated = adsb.mark_repeated_positions(rows)
        notes["repeated_position"] += repeated
        report.per_file[name] = (len(rows), int(rows["track_id"].nunique()))
        frames.append(rows)
    table = pd.concat(frames, ignore_index=True)
    parsed, ground = _local_frames(table, dims)
    if airborne:
        parsed.track_code[ground] = -1
    steps = group_rows(parsed)
    # Rows on the ground were given no track on purpose: count them under their own reason.
    aside = steps.report.set_aside
    aside["on_ground"] = int(ground.sum()) if airborne else 0
    aside["no_track_id"] -= aside["on_ground"]  # they were given no track id above
    steps.report.set_aside = +aside
    notes["implausible_jump"] = _jumps(steps)
    steps.report.notes.update(notes)
    steps.report.notes = +steps.report.notes
    steps.report.check()
    report.rows = steps.report
    return steps, report


#: Horizontal speed (m/s, about 1170 kt) above which a move between two reports is implausible.
MAX_SPEED = 600.0


def _jumps(steps: TrackSteps) -> int:
    """Steps whose position lies further from the track's previous position than
    :data:`MAX_SPEED` allows (spoofing, time-stamp jumps): counted, left to the estimators."""
    position, time = steps.position[:, :2], steps.time
    seen = np.isfinite(position).all(axis=1)
    track = steps.track_of_step
    index = np.flatnonzero(seen)
    same = track[index][1:] == track[index][:-1]
    distance = np.linalg.norm(np.diff(position[index], axis=0), axis=1)
    elapsed = np.diff(time[index])
    return int((same & (distance > MAX_SPEED * np.maximum(elapsed, 1e-9))).sum())


def _short_name(path: Path) -> str:
    return f"{path.parent.name}/{path.name}"


def _local_frames(table: Any, dims: int) -> tuple[ParsedRows, np.ndarray]:
    """Rows in each track's east-north-up frame, and where the source says on the ground."""
    import pandas as pd

    df: pd.DataFrame = table
    codes, uniques = pd.factorize(df["track_id"], use_na_sentinel=True)
    codes = np.asarray(codes, dtype=np.int64)
    lat = df["latitude"].to_numpy(dtype=np.float64)
    lon = df["longitude"].to_numpy(dtype=np.float64)
    alt = df["altitude"].to_numpy(dtype=np.float64) * geodesy.FOOT
    has_position = np.isfinite(lat) & np.isfinite(lon)
    # Frame of each track: its median position; height 0 (altitude is barometric anyway).
    frame = pd.DataFrame(
        {
            "code": codes,
            "lat": np.where(has_position, lat, np.nan),
            "lon": np.where(has_position, lon, np.nan),
        }
    )
    centre = frame.groupby("code")[["lat", "lon"]].median()
    lat0 = centre["lat"].reindex(codes).to_numpy()
    lon0 = centre["lon"].reindex(codes).to_numpy()
    # The horizontal frame uses the altitude where known, else the track's median altitude.
    alt_median = pd.Series(alt).groupby(codes).transform("median").to_numpy()
    height = np.where(np.isfinite(alt), alt, np.where(np.isfinite(alt_median), alt_median, 0.0))
    with np.errstate(invalid="ignore"):
        enu = geodesy.geodetic_to_enu(
            lat, lon, height, np.nan_to_num(lat0), np.nan_to_num(lon0), 0.0
        )
    position = np.stack([enu[:, 0], enu[:, 1]] + ([alt] if dims == 3 else []), axis=1)
    position[~has_position, :2] = np.nan

    speed = df["groundspeed"].to_numpy(dtype=np.float64) * geodesy.KNOT
    heading = np.radians(df["track"].to_numpy(dtype=np.float64))
    climb = df["vertical_rate"].to_numpy(dtype=np.float64) * geodesy.FEET_PER_MINUTE
    local = np.stack([speed * np.sin(heading), speed * np.cos(heading), np.zeros_like(speed)], 1)
    with np.errstate(invalid="ignore"):
        velocity = geodesy.rotate_enu(
            local, np.nan_to_num(lat), np.nan_to_num(lon), np.nan_to_num(lat0), np.nan_to_num(lon0)
        )
    velocity[~(has_position & np.isfinite(speed) & np.isfinite(heading))] = np.nan
    extra = {
        "ve": velocity[:, 0],
        "vn": velocity[:, 1],
        "lat0": lat0,
        "lon0": lon0,
        # as reported, for tools that take them (ft, kt, deg, ft/min)
        "altitude_ft": df["altitude"].to_numpy(dtype=np.float64),
        "groundspeed_kt": df["groundspeed"].to_numpy(dtype=np.float64),
        "track_deg": df["track"].to_numpy(dtype=np.float64),
        "vertical_rate_fpm": df["vertical_rate"].to_numpy(dtype=np.float64),
    }
    if dims == 3:
        extra["vu"] = climb
    parsed = ParsedRows(
        track_code=codes,
        track_ids=[str(u) for u in uniques],
        time=df["time"].to_numpy(dtype=np.float64),
        position=position,
        extra=extra,
        non_numeric=np.zeros(len(df), dtype=bool),
    )
    return parsed, df["on_ground"].to_numpy(dtype=bool)
