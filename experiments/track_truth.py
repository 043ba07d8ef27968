"""A benchmark kind's truth: pieces of track (times and true positions) and the rows they make.
Shared by the recorded kinds (:mod:`experiments.recorded_sets`) and the simulated vehicles
(:mod:`experiments.vehicle_sets`)."""

from __future__ import annotations

from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import pandas as pd


@dataclass
class Piece:
    """A stretch of one recorded track: report times and truth positions (local frame, m)."""

    track_id: str
    time: np.ndarray  #: [n] s
    position: np.ndarray  #: [n, 2] east, north (m)
    groundspeed_kt: np.ndarray  #: [n] reported ground speed (kt), NaN where not reported
    origin: str = ""  #: the recorded track it is cut from (default: ``track_id``)
    source: str = ""  #: the sample file or folder it comes from (sampling is stratified by it)

    def __post_init__(self) -> None:
        self.origin = self.origin or self.track_id

    def __len__(self) -> int:
        return len(self.time)

    def take(self, index: np.ndarray, suffix: str = "") -> Piece:
        return Piece(
            self.track_id + suffix,
            self.time[index],
            self.position[index],
            self.groundspeed_kt[index],
            self.origin,
            self.source,
        )


@dataclass
class Truth:
    """The truth of one kind: rows ``track_id, time, x, y`` and how it was made."""

    kind: str
    rows: pd.DataFrame  #: track_id, time, x, y; sorted by track then time
    sources: list[str]  #: files (folder/name) or "simulation"
    counts: Counter[str] = field(default_factory=Counter)  #: what the cleaning did
    roughness: dict[str, float] = field(default_factory=dict)  #: :func:`roughness` as recorded


def truth_rows(pieces: Sequence[Piece]) -> pd.DataFrame:
    """Rows ``track_id, time, x, y`` of pieces (in order)."""
    if not pieces:
        return pd.DataFrame({"track_id": [], "time": [], "x": [], "y": []})
    return pd.DataFrame(
        {
            "track_id": np.concatenate([[p.track_id] * len(p) for p in pieces]),
            "time": np.concatenate([p.time for p in pieces]),
            "x": np.concatenate([p.position[:, 0] for p in pieces]),
            "y": np.concatenate([p.position[:, 1] for p in pieces]),
        }
    )
