"""Recorded ADS-B flights from the samples of the ``traffic`` wheel, as one table of rows.

The wheel ``traffic==2.13`` ships recorded flights under ``traffic/data/samples/``. Install the
files alone with ``pip install --no-deps traffic==2.13``; this module finds them with
``importlib.util.find_spec`` and never imports ``traffic`` (its ``__init__`` needs packages that
torchsvs does not). This module needs pandas, which torchsvs itself does not require.

Formats read (told apart by extension and content, not by folder):

* ``*.json.gz`` (and any JSON in the same layout): a pandas ``to_json`` table, either a list of
  records or a dict of columns ``{column: {row_index: value}}`` (file order is the order of the
  row keys). ``timestamp`` is integer **milliseconds** since the epoch, ``altitude``
  barometric ft, ``groundspeed`` kt, ``track`` deg clockwise from north, ``vertical_rate``
  ft/min, ``onground`` a boolean where present. A table without latitude/longitude columns
  (``performance/fuelflow_a320``: flight-data-recorder parameters) is not a track.
* FlightRadar24 API dumps (``fr24/*.json``): ``result.response.data.flight.track`` lists points
  with ``timestamp`` (s), ``latitude``, ``longitude``, ``altitude.feet``, ``speed.kts``,
  ``verticalSpeed.fpm`` and ``heading`` (FR24's name for the ground track). FR24 has no
  on-ground flag (its altitude reads 0 ft on the ground), so ``on_ground`` stays False.
* readsb traces (``readsb/trace_full_*.json``): ``timestamp`` (s) plus ``trace`` rows
  ``[s after timestamp, lat, lon, altitude ft or "ground", groundspeed kt, track deg, flags,
  vertical rate ft/min, details, source, geometric altitude, geometric rate, ias, roll]``.
  Flag bit 8 marks a geometric altitude, read as missing (``altitude`` is barometric).
* rs1090 decoded Mode S (``*.jsonl``): one message a line with ``timestamp`` (s, float),
  ``icao24`` and whichever fields the message carries. A surface position message
  (``bds == "06"``) says the aircraft is on the ground; an airborne position whose altitude
  ``source`` is GNSS is geometric, read as missing.
* Not tracks (``rows`` is None, ``note`` says why): airspace polygons (``airspaces/``), raw
  Beast-format Mode S frames (``dump1090/*.bin``), tables without positions.

Rules shared by every track file (:func:`read_adsb_file`):

* one output row per record, trace point or message, in file order, with exactly the columns
  of :data:`COLUMNS`; numbers are float64, and anything that is not a finite JSON number (null,
  text, booleans, objects) reads as NaN rather than raising;
* ``track_id`` is ``"<file stem>/<id>"`` with ``id`` the row's non-empty ``flight_id``, else
  its ``icao24`` in lower case (FR24: the flight id; readsb: the ``icao``), so ids are unique
  across files; a row with neither id belongs to the track ``"<file stem>/"``;
* ``on_ground`` is True where the source says so (``onground``, an altitude of ``"ground"``,
  a surface position message) and False otherwise; a ground altitude reads as NaN.

Two clean-ups the raw rows need before filtering:

* one aircraft (one icao24) in a file may fly several flights hours apart:
  :func:`split_flights` cuts its track at gaps longer than ``max_gap``;
* receivers resample to 1 s (or 5 s) and repeat the last position between position messages:
  :func:`mark_repeated_positions` reads those repeats as missing, since they are not
  measurements.
"""

from __future__ import annotations

import gzip
import importlib.util
import json
import math
import zlib
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import pandas as pd

#: The columns of every track table, in order (see the module docstring for units).
COLUMNS = (
    "track_id",
    "time",
    "latitude",
    "longitude",
    "altitude",
    "groundspeed",
    "track",
    "vertical_rate",
    "on_ground",
)
#: The float64 columns of :data:`COLUMNS`.
NUMERIC_COLUMNS = COLUMNS[1:-1]

INSTALL_HINT = "the ADS-B samples come with the traffic wheel: pip install --no-deps traffic==2.13"

_GROUND_TEXTS = {"ground", "gnd"}
#: What a file that is not a track contains.
_NOT_A_TRACK = {
    "airspace": "airspace polygon, not a track",
    "beast": "raw Mode S frames (not decoded)",
    "no_position": "no latitude/longitude columns (aircraft parameters, not a track)",
}
# Errors that mean the content is not what the format promises, as opposed to a missing file.
_PARSE_ERRORS = (
    ValueError,
    KeyError,
    TypeError,
    IndexError,
    AttributeError,
    EOFError,
    gzip.BadGzipFile,
    zlib.error,
)


class AdsbFile(NamedTuple):
    """One sample file read: its track rows, or a note saying why it holds none."""

    path: Path
    rows: pd.DataFrame | None  #: [R rows] the columns of :data:`COLUMNS`, None if not a track
    note: str | None  #: why ``rows`` is None (None for a track file)


def samples_dir() -> Path:
    """The ``data/samples`` folder of the installed ``traffic`` package.

    Found with ``importlib.util.find_spec``, which locates the package without running its
    ``__init__``.

    Raises:
        ImportError: ``traffic`` is not installed, or its wheel has no samples.
    """
    spec = importlib.util.find_spec("traffic")
    locations = list(spec.submodule_search_locations or []) if spec is not None else []
    for location in locations:
        folder = Path(location) / "data" / "samples"
        if folder.is_dir():
            return folder
    raise ImportError(INSTALL_HINT)


def sample_files(root: str | Path | None = None) -> list[Path]:
    """Every data file under the samples folder, sorted by path.

    Args:
        root: the folder to list; :func:`samples_dir` by default.

    Returns:
        All files of every extension, without ``__init__.py`` and ``__pycache__``.
    """
    folder = samples_dir() if root is None else Path(root)
    return sorted(
        path
        for path in folder.rglob("*")
        if path.is_file()
        and path.name != "__init__.py"
        and "__pycache__" not in path.relative_to(folder).parts
    )


def read_adsb_file(path: str | Path) -> AdsbFile:
    """Read one sample file into the rows of its tracks (see the module docstring).

    Args:
        path: a ``.json.gz``, ``.json``, ``.jsonl`` or ``.bin`` sample file.

    Returns:
        ``AdsbFile(path, rows, note)``: ``rows`` has one row per record / trace point / message
        in file order, columns :data:`COLUMNS` (``track_id`` text, ``time`` s since the epoch,
        ``latitude``/``longitude`` deg, ``altitude`` barometric ft, ``groundspeed`` kt,
        ``track`` deg, ``vertical_rate`` ft/min, all float64 with NaN where missing;
        ``on_ground`` bool); or ``rows`` is None and ``note`` says why the file is not a track.

    Raises:
        ValueError: the file cannot be parsed, or its format is unknown (names the file).
        OSError: the file cannot be opened.
    """
    path = Path(path)
    stem = path.name.split(".")[0]
    try:
        if path.suffix == ".bin":
            with open(path, "rb") as handle:
                if handle.read(1) != b"\x1a":  # every Beast frame starts with an escape byte
                    raise ValueError("not a Beast binary stream")
            return AdsbFile(path, None, _NOT_A_TRACK["beast"])
        if path.suffix == ".jsonl":
            return AdsbFile(path, _mode_s_rows(stem, _json_lines(path)), None)
        if path.name.endswith((".json", ".json.gz")):
            return _read_json(path, stem)
    except _PARSE_ERRORS as err:
        raise ValueError(f"{path}: cannot be read as ADS-B data ({err})") from err
    raise ValueError(f"{path}: unknown format (expected .json, .json.gz, .jsonl or .bin)")


def split_flights(rows: pd.DataFrame, max_gap: float = 600.0) -> pd.DataFrame:
    """Cut tracks into flights where the time between consecutive rows exceeds ``max_gap``.

    A track with such a gap (in time order) has its ids suffixed ``"#1"``, ``"#2"``, ... in
    time order; a track without one keeps its id. Rows with no time sort last, so they join
    their track's last flight.

    Args:
        rows: [R rows] with at least ``track_id`` and ``time`` (s).
        max_gap: the longest gap (s) within one flight.

    Returns:
        A copy of ``rows`` in the same row order, with ``track_id`` replaced.
    """
    if not max_gap >= 0:
        raise ValueError(f"max_gap must be a non-negative number of seconds, got {max_gap}")
    codes, order, new_track = _time_order(rows)
    time = rows["time"].to_numpy(dtype=np.float64)[order]
    gap = np.zeros(len(order), dtype=bool)
    gap[1:] = np.diff(time) > max_gap
    gap &= ~new_track
    gaps_so_far = np.cumsum(gap)
    track_start = np.flatnonzero(new_track)
    # Flight number within its track: gaps since the track's first row, plus one.
    start_of_row = track_start[np.cumsum(new_track) - 1]
    flight = gaps_so_far - gaps_so_far[start_of_row] + 1
    flights_in_track = np.zeros(codes.max() + 1 if len(codes) else 0, dtype=np.int64)
    np.maximum.at(flights_in_track, codes[order], flight)

    flight_of_row = np.empty(len(order), dtype=np.int64)
    flight_of_row[order] = flight
    split = flights_in_track[codes] > 1
    ids = rows["track_id"]
    suffixed = ids.astype(str) + "#" + pd.Series(flight_of_row, index=rows.index).astype(str)
    return rows.assign(track_id=ids.where(~split, suffixed))


def mark_repeated_positions(rows: pd.DataFrame) -> tuple[pd.DataFrame, int]:
    """Read as missing each position that repeats the previous row's of its track.

    Receivers resample to a fixed rate and repeat the last position until a new position
    message arrives; a repeat is not a measurement. Within each track in time order (ties in
    row order), a row whose latitude and longitude both equal the previous row's is a repeat.
    Altitude is not compared: it legitimately stays put in level flight.

    Args:
        rows: [R rows] with ``track_id``, ``time`` (s), ``latitude`` and ``longitude`` (deg).

    Returns:
        ``(marked, count)``: a copy of ``rows`` in the same order with NaN latitude and
        longitude on the ``count`` repeated rows.
    """
    _, order, new_track = _time_order(rows)
    latitude = rows["latitude"].to_numpy(dtype=np.float64)
    longitude = rows["longitude"].to_numpy(dtype=np.float64)
    sorted_lat, sorted_lon = latitude[order], longitude[order]
    repeat_sorted = np.zeros(len(order), dtype=bool)
    repeat_sorted[1:] = (sorted_lat[1:] == sorted_lat[:-1]) & (sorted_lon[1:] == sorted_lon[:-1])
    repeat_sorted &= ~new_track
    repeat = np.empty(len(order), dtype=bool)
    repeat[order] = repeat_sorted
    marked = rows.assign(
        latitude=np.where(repeat, np.nan, latitude),
        longitude=np.where(repeat, np.nan, longitude),
    )
    return marked, int(repeat.sum())


def _time_order(rows: pd.DataFrame) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rows grouped by track and sorted by time within each (stable, NaN times last).

    Returns:
        ``(codes [R], order [R], new_track [R])``: each row's track number, the row indices in
        track-then-time order, and whether each sorted row starts a track.
    """
    codes = np.asarray(pd.factorize(rows["track_id"], use_na_sentinel=False)[0], dtype=np.int64)
    time = rows["time"].to_numpy(dtype=np.float64)
    order = np.lexsort((np.arange(len(time)), time, codes))  # equal times keep row order
    new_track = np.ones(len(order), dtype=bool)
    new_track[1:] = codes[order][1:] != codes[order][:-1]
    return codes, order, new_track


# --- reading -------------------------------------------------------------------------------

#: Columns read from a pandas-style table (others are ignored).
_TABLE_COLUMNS = (
    "timestamp",
    "flight_id",
    "icao24",
    "latitude",
    "longitude",
    "altitude",
    "groundspeed",
    "track",
    "vertical_rate",
    "onground",
)


def _read_json(path: Path, stem: str) -> AdsbFile:
    data = path.read_bytes()
    content = json.loads(gzip.decompress(data) if path.name.endswith(".gz") else data)
    if isinstance(content, dict) and "result" in content:
        return AdsbFile(path, _fr24_rows(stem, content), None)
    if isinstance(content, dict) and "trace" in content:
        return AdsbFile(path, _readsb_rows(stem, content), None)
    if isinstance(content, dict) and ("shapes" in content or "coordinates" in content):
        return AdsbFile(path, None, _NOT_A_TRACK["airspace"])
    table = _table(content)
    if "latitude" not in table or "longitude" not in table:
        return AdsbFile(path, None, _NOT_A_TRACK["no_position"])
    if "timestamp" not in table:
        raise ValueError("a table with positions but no timestamp column")
    flight_id, icao24 = _id_column(table, "flight_id"), _id_column(table, "icao24")
    ids = flight_id.where(flight_id != "", icao24.str.lower())
    time = _float_column(table, "timestamp") / 1000.0  # pandas to_json writes milliseconds
    return AdsbFile(path, _frame(stem, ids, time, table.rename(columns={"onground": "flag"})), None)


def _table(content: object) -> pd.DataFrame:
    """The columns of :data:`_TABLE_COLUMNS` present in a pandas ``to_json`` table, in file order.

    Built by pandas so that column types are inferred in C: the largest samples have 300k rows.
    """
    if isinstance(content, list):
        if not set(map(type, content)) <= {dict}:
            raise ValueError("a JSON list whose items are not all records")
        names = set().union(*content)
        present = [name for name in _TABLE_COLUMNS if name in names]
        return pd.DataFrame.from_records(content, columns=present)
    if isinstance(content, dict) and all(isinstance(col, dict) for col in content.values()):
        # Row keys in order of first appearance; a column without a key has a missing value.
        keys = list(dict.fromkeys(key for column in content.values() for key in column))
        return pd.DataFrame(
            {
                name: pd.Series([content[name].get(key) for key in keys], dtype=object)
                for name in _TABLE_COLUMNS
                if name in content
            },
            index=pd.RangeIndex(len(keys)),
        ).infer_objects()
    raise ValueError("neither a list of records nor a dict of columns")


def _fr24_rows(stem: str, content: Mapping[str, Any]) -> pd.DataFrame:
    flight = content["result"]["response"]["data"]["flight"]
    points = flight["track"]
    source = pd.DataFrame(
        {
            "latitude": [p.get("latitude") for p in points],
            "longitude": [p.get("longitude") for p in points],
            "altitude": [_dig(p, "altitude", "feet") for p in points],
            "groundspeed": [_dig(p, "speed", "kts") for p in points],
            "track": [p.get("heading") for p in points],  # FR24's "heading" is the ground track
            "vertical_rate": [_dig(p, "verticalSpeed", "fpm") for p in points],
        }
    )
    ids = pd.Series(_id_text(flight["identification"]["id"]), index=source.index, dtype=str)
    time = _as_float([p.get("timestamp") for p in points])
    return _frame(stem, ids, time, source)


def _readsb_rows(stem: str, content: Mapping[str, Any]) -> pd.DataFrame:
    points = content["trace"]
    start = _number(content.get("timestamp"))
    if math.isnan(start):
        raise ValueError("a readsb trace without a numeric timestamp")
    altitude = []
    for point in points:
        flags = _item(point, 6)
        geometric = isinstance(flags, int) and bool(flags & 8)
        altitude.append(None if geometric else _item(point, 3))
    source = pd.DataFrame(
        {
            "latitude": [_item(p, 1) for p in points],
            "longitude": [_item(p, 2) for p in points],
            "altitude": pd.Series(altitude, dtype=object),  # the "ground" texts stay text
            "groundspeed": [_item(p, 4) for p in points],
            "track": [_item(p, 5) for p in points],
            "vertical_rate": [_item(p, 7) for p in points],
        }
    )
    ids = pd.Series(_id_text(content.get("icao")).lower(), index=source.index, dtype=str)
    time = start + _as_float([_item(p, 0) for p in points])
    return _frame(stem, ids, time, source)


def _json_lines(path: Path) -> list[dict[str, Any]]:
    messages = []
    with open(path, encoding="utf-8") as handle:
        for number, line in enumerate(handle, start=1):
            if not line.strip():
                continue
            message = json.loads(line)
            if not isinstance(message, dict):
                raise ValueError(f"line {number} is not a JSON object")
            messages.append(message)
    return messages


def _mode_s_rows(stem: str, messages: Sequence[Mapping[str, Any]]) -> pd.DataFrame:
    def baro_altitude(message: Mapping[str, Any]) -> Any:
        geometric = message.get("bds") == "05" and str(message.get("source")).lower() == "gnss"
        return None if geometric else message.get("altitude")

    source = pd.DataFrame(
        {
            "latitude": [m.get("latitude") for m in messages],
            "longitude": [m.get("longitude") for m in messages],
            "altitude": [baro_altitude(m) for m in messages],
            "groundspeed": [m.get("groundspeed") for m in messages],
            "track": [m.get("track") for m in messages],
            "vertical_rate": [m.get("vertical_rate") for m in messages],
            # BDS 0,6 is the surface position message: only an aircraft on the ground sends it.
            "flag": [m.get("bds") == "06" for m in messages],
        }
    )
    ids = _id_column(pd.DataFrame({"icao24": [m.get("icao24") for m in messages]}), "icao24")
    time = _as_float([m.get("timestamp") for m in messages])
    return _frame(stem, ids.str.lower(), time, source)


def _frame(stem: str, ids: pd.Series, time: np.ndarray, source: pd.DataFrame) -> pd.DataFrame:
    """The canonical table of :data:`COLUMNS` from a reader's columns.

    Args:
        stem: the file's name without extensions, the prefix of every track id.
        ids: [R] text, the id of each row within its file ("" where none).
        time: [R] float64 s since the epoch.
        source: [R rows] whichever of ``latitude``, ``longitude``, ``altitude``,
            ``groundspeed``, ``track``, ``vertical_rate`` the file has, in the canonical units
            but any types, and ``flag``, the source's own on-ground flag.
    """
    altitude, ground_altitude = _altitude_column(source)
    table = {
        "track_id": (stem + "/" + ids.astype(str)).to_numpy(),
        "time": np.where(np.isfinite(time), time, np.nan),
        "latitude": _float_column(source, "latitude"),
        "longitude": _float_column(source, "longitude"),
        "altitude": altitude,
        "groundspeed": _float_column(source, "groundspeed"),
        "track": _float_column(source, "track"),
        "vertical_rate": _float_column(source, "vertical_rate"),
        "on_ground": _flag_column(source, "flag") | ground_altitude,
    }
    frame = pd.DataFrame(table, columns=list(COLUMNS))
    return frame.astype({"track_id": str})


def _float_column(table: pd.DataFrame, name: str) -> np.ndarray:
    """[R] float64 values of a column; NaN where absent, not a finite number, or no column."""
    if name not in table:
        return np.full(len(table), np.nan)
    column = table[name]
    if column.dtype.kind in "iuf":  # typed by pandas: no per-value work needed
        values = column.to_numpy(dtype=np.float64)
        return np.where(np.isfinite(values), values, np.nan)
    if column.dtype.kind == "b":
        return np.full(len(table), np.nan)  # booleans are not measurements
    return _as_float(column.tolist())


def _altitude_column(table: pd.DataFrame) -> tuple[np.ndarray, np.ndarray]:
    """([R] float64 altitude, NaN where ground-like text; [R] bool whether it was such text)."""
    altitude = _float_column(table, "altitude")
    if "altitude" not in table or table["altitude"].dtype.kind in "iufb":
        return altitude, np.zeros(len(table), dtype=bool)
    ground = [
        isinstance(value, str) and value.strip().lower() in _GROUND_TEXTS
        for value in table["altitude"].tolist()
    ]
    return altitude, np.asarray(ground, dtype=bool)


def _flag_column(table: pd.DataFrame, name: str) -> np.ndarray:
    """[R] bool: True where the column says true (True, 1 or the text "true")."""
    if name not in table:
        return np.zeros(len(table), dtype=bool)
    column = table[name]
    if column.dtype.kind == "b":
        return column.to_numpy(dtype=bool)
    return np.fromiter(map(_is_true, column.tolist()), dtype=bool, count=len(table))


def _id_column(table: pd.DataFrame, name: str) -> pd.Series:
    """[R] stripped id texts of a column; "" where absent (null, NaN, no column)."""
    if name not in table:
        return pd.Series("", index=table.index, dtype=str)
    column = table[name]
    if pd.api.types.is_string_dtype(column):
        return column.fillna("").astype(str).str.strip()
    return pd.Series([_id_text(v) for v in column.tolist()], index=table.index, dtype=str)


def _number(value: object) -> float:
    """A finite JSON number as float; NaN for anything else (null, text, booleans, objects)."""
    if type(value) is float:
        return value if math.isfinite(value) else math.nan
    if type(value) is int:
        try:
            return float(value)
        except OverflowError:  # an integer beyond float range is no measurement either
            return math.nan
    return math.nan


def _as_float(values: Sequence[object]) -> np.ndarray:
    """[R] float64 of :func:`_number` of each value."""
    if set(map(type, values)) <= {int, float, type(None)}:
        try:  # numbers and nulls only: numpy converts them in C, None to NaN
            numbers = np.array(values, dtype=np.float64)
            return np.where(np.isfinite(numbers), numbers, np.nan)
        except OverflowError:
            pass
    return np.fromiter(map(_number, values), dtype=np.float64, count=len(values))


def _is_true(value: object) -> bool:
    if isinstance(value, str):
        return value.strip().lower() == "true"
    return value is True or (type(value) in (int, float) and value == 1)


def _id_text(value: object) -> str:
    """An id as stripped text; empty for null, NaN, booleans and objects."""
    if isinstance(value, str):
        return value.strip()
    if type(value) is int:
        return str(value)
    return ""


def _dig(record: Mapping[str, Any], *keys: str) -> Any:
    """``record[k1][k2]...``, or None where a level is missing or not a dict."""
    value: Any = record
    for key in keys:
        if not isinstance(value, dict):
            return None
        value = value.get(key)
    return value


def _item(row: Sequence[Any], index: int) -> Any:
    """``row[index]``, or None past the end (older readsb traces have fewer fields)."""
    return row[index] if index < len(row) else None
