"""Times of a track file's rows: their unit, their reading as seconds, and a track's times
written in two ways that cannot both be right."""

from __future__ import annotations

import warnings
from typing import Any

import numpy as np

from torchsvs.datasets.arrow_numpy import to_float, to_numpy

#: Seconds per unit of the names ``Columns.time_unit`` (and ``--time-unit``) takes.
TIME_UNITS = {"s": 1.0, "ms": 1e-3, "us": 1e-6, "ns": 1e-9}
#: Smallest typical size of epoch times in each unit (1e11 s is the year 5138; 1e11 ms is 1973).
EPOCH_SIZE = {"ns": 1e17, "us": 1e14, "ms": 1e11}


def to_seconds(column: Any, unit: float) -> tuple[np.ndarray, np.ndarray]:
    """A time column as float64 seconds (NaN where unusable): numbers times ``unit``, date-time
    texts and timestamps as seconds since 1970-01-01 UTC (texts without a zone read as UTC);
    and where a text was read as a date-time (``[R]`` bool)."""
    import pyarrow as pa
    import pyarrow.compute as pc

    if pa.types.is_timestamp(column.type) or pa.types.is_date(column.type):
        ns = pc.cast(pc.cast(column, pa.timestamp("ns")), pa.int64())
        seconds = np.asarray(to_numpy(ns, np.nan), dtype=np.float64) * 1e-9
        return seconds, np.zeros(len(seconds), dtype=bool)
    values, bad = to_float(column)
    if unit != 1.0:
        values = values * unit
    if bad.any():  # texts that are not numbers may be dates
        import pandas as pd

        texts = column.filter(pa.array(bad)).to_pandas()
        with warnings.catch_warnings():  # a best-effort parse of every date-time format is meant
            warnings.simplefilter("ignore", UserWarning)
            parsed = pd.to_datetime(texts, errors="coerce", utc=True, format="mixed")
        ns = parsed.to_numpy(dtype="datetime64[ns]").astype(np.int64).astype(np.float64)
        ns[parsed.isna().to_numpy()] = np.nan
        values[bad] = ns * 1e-9
    return values, bad & np.isfinite(values)


def detect_time_unit(column: Any) -> tuple[float, str]:
    """Seconds per unit of a time column's numbers, and what was found (for a person).

    Timestamps and date-time texts carry their unit. Numbers are seconds unless their median
    size is that of times since 1970 in a finer unit (:data:`EPOCH_SIZE`: from 1e11 milli-,
    1e14 micro-, 1e17 nanoseconds; 1e11 s would be the year 5138). Small numbers in a finer
    unit (milliseconds from 0) cannot be told from seconds by their size: give the unit.
    """
    import pyarrow as pa

    if pa.types.is_timestamp(column.type) or pa.types.is_date(column.type):
        return 1.0, f"timestamps ({column.type})"
    values, text = to_float(column)
    numbers = values[np.isfinite(values)]
    if len(numbers) < text.sum():
        return 1.0, "date-time texts (ISO 8601 and the like; UTC unless a zone is given)"
    if len(numbers) == 0:
        return 1.0, "no usable times"
    size = float(np.median(np.abs(numbers)))
    for name, threshold in EPOCH_SIZE.items():
        if size >= threshold:
            long = {"ms": "milliseconds", "us": "microseconds", "ns": "nanoseconds"}[name]
            return TIME_UNITS[name], (
                f"numbers around {size:.3g}: {long} since 1970 (detected; --time-unit s "
                "reads them as seconds)"
            )
    return 1.0, "numbers, read as seconds (--time-unit ms, us, ns for other units)"


#: A time written as a date-time among a track's numbers (or the other way round) is set
#: aside where it lies this far from the median of the track's others: read as seconds since
#: 1970 beside seconds from 0 it is decades on (a date among epoch numbers agrees with them).
UNLIKE_APART = 365.25 * 86400.0


def unlike_their_track(time: np.ndarray, dated: np.ndarray, codes: np.ndarray) -> np.ndarray | None:
    """``[R]`` bool the rows whose time is written unlike most of their track's (a date-time
    text among numbers, or a number among date-times) and lies :data:`UNLIKE_APART` or more
    from the median of the track's others: no reading places it among them. None where no
    track writes its times both ways (``dated``: :func:`to_seconds`'s)."""
    known = np.isfinite(time) & (codes >= 0)
    if not (dated & known).any() or not (~dated & known).any():
        return None
    size = int(codes.max()) + 1
    dates = np.bincount(codes[known & dated], minlength=size)
    numbers = np.bincount(codes[known & ~dated], minlength=size)
    unlike = np.zeros(len(time), dtype=bool)
    for code in np.flatnonzero((dates > 0) & (numbers > 0)):
        rows = known & (codes == code)
        if dates[code] == numbers[code]:  # (no majority: neither way is the track's)
            continue
        odd = rows & (dated if dates[code] < numbers[code] else ~dated)
        centre = np.median(time[rows & ~odd])
        unlike |= odd & (np.abs(time - centre) >= UNLIKE_APART)
    return unlike if unlike.any() else None
