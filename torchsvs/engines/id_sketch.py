"""Whether an engine's parts held each track whole: the parts' track ids in a HyperLogLog sketch
(Flajolet, Fusy, Gandouet & Meunier 2007), merged on the driver, beside the count of ids the
parts held each (:class:`IdSketch`). A track split between parts is estimated in pieces, each
at its own ends, and counted once per part: where the parts' counts add up to clearly more
than the distinct ids, the run warns (:func:`split_warning`). Its memory is fixed (16 kB a
part), whatever the number of tracks.

References:
    Flajolet, Fusy, Gandouet, Meunier, "HyperLogLog: the analysis of a near-optimal
    cardinality estimation algorithm", AofA 2007, DMTCS Proceedings AH, 127-146.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

#: The sketch's registers: 2^14 (a relative standard error of 0.8% on many ids, far less on
#: few: counted exactly in effect up to a few thousand).
BITS = 14
REGISTERS = 1 << BITS
#: Up to this many ids the hashes are kept too, and the distinct ids counted exactly.
EXACT_MOST = 1 << 16
#: The parts' ids must exceed the distinct ids by this many standard errors of the sketch ...
SPLIT_ERRORS = 4.0
#: ... and by at least this share of them (a few cut tracks among millions matter little).
SPLIT_SHARE = 1e-3


@dataclass
class IdSketch:
    """The distinct track ids of some parts (registers) and the ids the parts held, each
    counted once per part that held it (``counted``), and while they are few their hashes."""

    registers: np.ndarray = field(default_factory=lambda: np.zeros(REGISTERS, np.uint8))
    counted: int = 0
    #: the ids' hashes, each once, while there are at most :data:`EXACT_MOST` (else None)
    exact: np.ndarray | None = field(default_factory=lambda: np.zeros(0, np.uint64))

    @classmethod
    def of(cls, ids: Any) -> IdSketch:
        """The sketch of one part's ids (a pandas Series or an Arrow array; empty ones skipped)."""
        import pandas as pd

        values = ids.to_pandas() if hasattr(ids, "to_pandas") else pd.Series(ids)
        unique = pd.unique(values.dropna())
        sketch = cls(counted=len(unique))
        if len(unique):
            hashed = pd.util.hash_array(np.asarray(unique, dtype=object), categorize=False)
            sketch.add(hashed.astype(np.uint64))
        return sketch

    def add(self, hashed: np.ndarray) -> None:
        """Adds 64-bit hashes: each register keeps the most leading zeros (plus one) of the
        hashes' low bits that its top bits choose."""
        if self.exact is not None:
            joined = np.union1d(self.exact, hashed)
            self.exact = joined if len(joined) <= EXACT_MOST else None
        index = (hashed >> np.uint64(64 - BITS)).astype(np.int64)
        rest = hashed & np.uint64((1 << (64 - BITS)) - 1)
        width = 64 - BITS
        with np.errstate(divide="ignore"):
            top = np.floor(np.log2(rest.astype(np.float64)))
        rank = np.where(rest > 0, width - top, width + 1).astype(np.uint8)
        np.maximum.at(self.registers, index, rank)

    def merge(self, other: IdSketch) -> None:
        """Adds another part's sketch."""
        np.maximum(self.registers, other.registers, out=self.registers)
        self.counted += other.counted
        if self.exact is not None and other.exact is not None:
            joined = np.union1d(self.exact, other.exact)
            self.exact = joined if len(joined) <= EXACT_MOST else None
        else:
            self.exact = None

    def distinct(self) -> tuple[float, float]:
        """The distinct ids, estimated, and the estimate's standard error (linear counting
        while registers are empty, else HyperLogLog's 1.04 / √m); exact, of no error, while
        the hashes are kept."""
        if self.exact is not None:
            return float(len(self.exact)), 0.0
        m = float(REGISTERS)
        empty = int((self.registers == 0).sum())
        alpha = 0.7213 / (1.0 + 1.079 / m)
        raw = alpha * m * m / float(np.sum(np.ldexp(1.0, -self.registers.astype(np.int64))))
        if raw <= 2.5 * m and empty > 0:
            estimate = m * math.log(m / empty)
            t = estimate / m
            return estimate, math.sqrt(m * max(math.exp(t) - t - 1.0, 0.0))
        return raw, 1.04 / math.sqrt(m) * raw


def split_warning(sketch: IdSketch) -> str | None:
    """The run's warning where the parts held clearly more ids than there are distinct ones:
    tracks split between parts, each piece estimated alone."""
    distinct, error = sketch.distinct()
    excess = sketch.counted - distinct
    if excess < 0.5 or excess <= SPLIT_ERRORS * error or excess <= SPLIT_SHARE * distinct:
        return None
    return (
        f"tracks split between parts: the parts held {sketch.counted:,} track ids, about "
        f"{distinct:,.0f} distinct ones; a track split between parts is estimated in pieces, "
        "each worse at its ends (its error estimate too). Each track's rows must lie in one "
        "part: leave partitioned=False (the rows are then shuffled by track id), or write the "
        "dataset with each track in one file and read each file as one partition"
    )
