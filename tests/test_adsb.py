"""ADS-B samples of the traffic wheel read into track rows; skipped when the wheel is absent.

Install the files with ``pip install --no-deps traffic==2.13``.
"""

from __future__ import annotations

import gzip
import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from torchsvs.datasets.adsb import (
    COLUMNS,
    NUMERIC_COLUMNS,
    AdsbFile,
    mark_repeated_positions,
    read_adsb_file,
    sample_files,
    samples_dir,
    split_flights,
)

try:
    SAMPLES = samples_dir()
except ImportError as err:
    pytest.skip(str(err), allow_module_level=True)

# Epoch seconds of 2005-01-01 and 2030-01-01: a time in milliseconds, or in seconds after an
# offset went missing, falls outside.
YEAR_2005, YEAR_2030 = 1104537600.0, 1893456000.0


@pytest.fixture(scope="module")
def read_all() -> dict[str, AdsbFile]:
    """Every sample file read once (about 10 s, most of it json.loads of the collections)."""
    return {path.relative_to(SAMPLES).as_posix(): read_adsb_file(path) for path in sample_files()}


def _frame(**columns) -> pd.DataFrame:
    return pd.DataFrame(columns)


def test_sample_files_lists_data_files_only() -> None:
    files = sample_files()
    assert files == sorted(files)
    names = {path.relative_to(SAMPLES).as_posix() for path in files}
    assert "__init__.py" not in {path.name for path in files}
    assert not any("__pycache__" in name for name in names)
    assert {"dump1090/sample_dump1090.bin", "rs1090/full_flight_short.jsonl"} <= names


def test_every_file_is_tracks_or_has_a_note(read_all: dict[str, AdsbFile]) -> None:
    for name, result in read_all.items():
        assert (result.rows is None) != (result.note is None), name
        if result.rows is None:
            assert result.note, name
            continue
        rows = result.rows
        assert list(rows.columns) == list(COLUMNS), name
        assert pd.api.types.is_string_dtype(rows["track_id"]), name
        assert all(rows[column].dtype == np.float64 for column in NUMERIC_COLUMNS), name
        assert rows["on_ground"].dtype == bool, name
        assert rows["track_id"].str.startswith(Path(name).name.split(".")[0] + "/").all(), name
        times = rows["time"].dropna()
        assert len(times) == len(rows), name
        assert times.between(YEAR_2005, YEAR_2030).all(), name
        lat, lon = rows["latitude"].dropna(), rows["longitude"].dropna()
        assert len(lat) > 0 and lat.abs().le(90).all() and lon.abs().le(180).all(), name


def test_track_files_and_notes(read_all: dict[str, AdsbFile]) -> None:
    tracks = [name for name, result in read_all.items() if result.rows is not None]
    assert len(tracks) >= 75
    notes = {name: result.note for name, result in read_all.items() if result.rows is None}
    assert set(notes) == {
        "airspaces/LFBOTMA.json",
        "dump1090/sample_dump1090.bin",
        "performance/fuelflow_a320.json.gz",
    }
    assert "airspace" in notes["airspaces/LFBOTMA.json"]
    assert "not decoded" in notes["dump1090/sample_dump1090.bin"]


def test_ajaccio_one_track_every_5_s(read_all: dict[str, AdsbFile]) -> None:
    rows = read_all["calibration/ajaccio.json.gz"].rows
    assert rows is not None and len(rows) == 2629
    assert rows["track_id"].unique().tolist() == ["ajaccio/39b415"]
    np.testing.assert_array_equal(np.diff(rows["time"].to_numpy()), 5.0)
    assert rows["time"].iloc[0] == 1515748470.0  # the first record's timestamp, 1515748470000 ms


def test_rows_follow_records_in_file_order(read_all: dict[str, AdsbFile]) -> None:
    # noisy_ground is stored as a dict of columns, kiwi as records with a flight_id
    for name, prefix in [
        ("noisy/noisy_ground.json.gz", "noisy_ground/"),
        ("featured/kiwi.json.gz", "kiwi/"),
    ]:
        raw = pd.DataFrame(json.loads(gzip.decompress((SAMPLES / name).read_bytes())))
        rows = read_all[name].rows
        assert rows is not None and len(rows) == len(raw)
        np.testing.assert_array_equal(rows["time"].to_numpy(), raw["timestamp"].to_numpy() / 1000)
        np.testing.assert_array_equal(rows["latitude"].to_numpy(), raw["latitude"].to_numpy())
        ids = raw["flight_id"] if "flight_id" in raw else raw["icao24"]
        assert rows["track_id"].tolist() == (prefix + ids.astype(str)).tolist()
        if "onground" in raw:
            np.testing.assert_array_equal(rows["on_ground"], raw["onground"].astype(bool))


def test_rs1090_times_are_seconds(read_all: dict[str, AdsbFile]) -> None:
    path = SAMPLES / "rs1090/full_flight_short.jsonl"
    lines = path.read_text().splitlines()
    rows = read_all["rs1090/full_flight_short.jsonl"].rows
    assert rows is not None and len(rows) == len(lines)
    assert rows["time"].iloc[0] == json.loads(lines[0])["timestamp"]
    assert rows["time"].iloc[-1] == json.loads(lines[-1])["timestamp"]
    span_h = (rows["time"].max() - rows["time"].min()) / 3600
    assert 1.0 < span_h < 2.0  # a short flight, not 1000 times longer or shorter
    assert rows["track_id"].unique().tolist() == ["full_flight_short/393322"]
    # the surface position messages (BDS 0,6) say the aircraft is on the ground
    surface = [json.loads(line).get("bds") == "06" for line in lines]
    np.testing.assert_array_equal(rows["on_ground"].to_numpy(), surface)


def test_fr24_points(read_all: dict[str, AdsbFile]) -> None:
    for path in sorted((SAMPLES / "fr24").glob("*.json")):
        flight = json.loads(path.read_text())["result"]["response"]["data"]["flight"]
        rows = read_all[f"fr24/{path.name}"].rows
        assert rows is not None and len(rows) == len(flight["track"])
        assert rows["track_id"].unique().tolist() == [
            f"{path.stem}/{flight['identification']['id']}"
        ]
        assert rows[["latitude", "longitude"]].notna().all().all()
        assert (
            rows["latitude"].between(-90, 90).all() and rows["longitude"].between(-180, 180).all()
        )
        first, last = flight["track"][0], flight["track"][-1]
        assert rows["time"].iloc[0] == first["timestamp"]
        assert rows["altitude"].iloc[-1] == last["altitude"]["feet"]
        assert rows["groundspeed"].iloc[-1] == last["speed"]["kts"]
        assert rows["vertical_rate"].iloc[-1] == last["verticalSpeed"]["fpm"]
        assert rows["track"].iloc[-1] == last["heading"]
        assert 0 < rows["altitude"].max() < 50000


def test_readsb_trace(read_all: dict[str, AdsbFile]) -> None:
    trace = json.loads((SAMPLES / "readsb/trace_full_ac671b.json").read_text())
    rows = read_all["readsb/trace_full_ac671b.json"].rows
    assert rows is not None and len(rows) == len(trace["trace"])
    assert rows["track_id"].unique().tolist() == ["trace_full_ac671b/ac671b"]
    # Belize to Denver and legs around the US: North American latitudes and longitudes
    assert rows["latitude"].between(10, 50).all() and rows["longitude"].between(-125, -80).all()
    assert rows["time"].iloc[-1] == trace["timestamp"] + trace["trace"][-1][0]
    ground = np.array([point[3] == "ground" for point in trace["trace"]])
    assert ground.sum() > 0
    np.testing.assert_array_equal(rows["on_ground"].to_numpy(), ground)
    assert rows["altitude"][ground].isna().all() and rows["altitude"][~ground].notna().all()


def test_bad_values_read_as_missing(tmp_path: Path) -> None:
    records = [
        {"timestamp": 1000, "icao24": "ABC123", "latitude": 1.5, "longitude": 2.0, "altitude": 300},
        {"timestamp": 2000, "icao24": "abc123", "latitude": "n/a", "longitude": {"x": 1},
         "altitude": "ground", "groundspeed": True, "track": None, "onground": None},
        {"timestamp": "late", "flight_id": "F1", "icao24": "abc123", "latitude": 1e400,
         "longitude": 2.0, "altitude": "GND", "vertical_rate": 10**400, "onground": True},
    ]  # fmt: skip
    path = tmp_path / "odd.json.gz"
    path.write_bytes(gzip.compress(json.dumps(records).encode()))  # 1e400 is written Infinity
    rows = read_adsb_file(path).rows
    assert rows is not None
    assert rows["track_id"].tolist() == ["odd/abc123", "odd/abc123", "odd/F1"]
    np.testing.assert_array_equal(rows["time"], [1.0, 2.0, np.nan])
    np.testing.assert_array_equal(rows["latitude"], [1.5, np.nan, np.nan])
    np.testing.assert_array_equal(rows["longitude"], [2.0, np.nan, 2.0])
    np.testing.assert_array_equal(rows["altitude"], [300.0, np.nan, np.nan])
    assert rows[["groundspeed", "track", "vertical_rate"]].isna().all().all()
    assert rows["on_ground"].tolist() == [False, True, True]


def test_dict_of_columns_keeps_file_order(tmp_path: Path) -> None:
    columns = {
        "timestamp": {"10": 3000, "9": 1000, "11": 2000},
        "icao24": {"10": "aa", "9": "aa", "11": "bb"},
        "latitude": {"10": 3.0, "9": 1.0, "11": 2.0},
        "longitude": {"10": 0.0, "9": 0.0, "11": 0.0},
    }
    path = tmp_path / "cols.json"
    path.write_text(json.dumps(columns))
    rows = read_adsb_file(path).rows
    assert rows is not None
    assert rows["latitude"].tolist() == [3.0, 1.0, 2.0]
    assert rows["track_id"].tolist() == ["cols/aa", "cols/aa", "cols/bb"]
    assert rows["altitude"].isna().all() and not rows["on_ground"].any()


@pytest.mark.parametrize(
    ("name", "content"),
    [
        ("broken.json.gz", b"not gzip at all"),
        ("broken.json", b'[{"timestamp": 1, "latitude": '),
        ("broken.jsonl", b'{"timestamp": 1, "icao24": "aa"}\n[1, 2]\n'),
        ("nested.json", b'{"result": {"response": {}}}'),
        ("notime.json", b'[{"latitude": 1.0, "longitude": 2.0}]'),
        ("unknown.csv", b"timestamp,latitude\n1,2\n"),
        ("frames.bin", b"*8d4840d6202cc371c32ce0576098;\n"),  # AVR text, not Beast
    ],
)
def test_unparseable_files_raise_naming_the_file(tmp_path: Path, name: str, content: bytes) -> None:
    path = tmp_path / name
    path.write_bytes(content)
    with pytest.raises(ValueError, match=name):
        read_adsb_file(path)


def test_split_flights_cuts_only_tracks_with_long_gaps() -> None:
    # track "a": 0, 10, 20 s then 3620, 3630 s (a 1 h gap), rows shuffled and interleaved
    rows = _frame(
        track_id=["a", "b", "a", "a", "b", "a", "c", "a"],
        time=[3620.0, 0.0, 10.0, 0.0, 500.0, 3630.0, 7.0, 20.0],
        latitude=np.arange(8.0),
    )
    split = split_flights(rows)
    assert split["track_id"].tolist() == ["a#2", "b", "a#1", "a#1", "b", "a#2", "c", "a#1"]
    assert split["latitude"].tolist() == rows["latitude"].tolist()  # row order kept
    assert rows["track_id"].tolist()[0] == "a"  # the input is not modified
    assert split_flights(rows, max_gap=4000.0)["track_id"].tolist() == rows["track_id"].tolist()
    ids = split_flights(rows, max_gap=400.0)["track_id"]
    assert ids[[1, 4, 6]].tolist() == ["b#1", "b#2", "c"]


def test_mark_repeated_positions_counts_repeats_in_time_order() -> None:
    # In time order, track "a" reads P, P, Q, P, P, NaN, NaN and track "b" reads P, P, P.
    p, q = (45.0, 7.0), (45.1, 7.0)
    track = [
        ("a", 2.0, *q),  # a at t=2: Q after P at t=1, new
        ("b", 1.0, *p),  # b at t=1: P after P at t=0, a repeat (tracks are separate)
        ("a", 0.0, *p),  # a at t=0: first of a
        ("a", 1.0, *p),  # a at t=1: repeat
        ("b", 0.0, *p),  # b at t=0: first of b, though "a" reported P just before in the file
        ("a", 4.0, *p),  # a at t=4: repeat of t=3
        ("a", 3.0, *p),  # a at t=3: P after Q, new
        ("b", 2.0, *p),  # b at t=2: repeat
        ("a", 5.0, np.nan, np.nan),  # missing, not a repeat
        ("a", 6.0, np.nan, np.nan),  # NaN never equals NaN: not a repeat
        ("a", 7.0, 45.0, 7.1),  # same latitude, new longitude: new
    ]
    rows = pd.DataFrame(track, columns=["track_id", "time", "latitude", "longitude"])
    rows["altitude"] = 1000.0
    marked, count = mark_repeated_positions(rows)
    repeats = [False, True, False, True, False, True, False, True, False, False, False]
    assert count == sum(repeats)
    np.testing.assert_array_equal(
        marked["latitude"].isna(), np.array(repeats) | rows["latitude"].isna()
    )
    assert marked["longitude"].isna().tolist() == marked["latitude"].isna().tolist()
    assert marked["time"].tolist() == rows["time"].tolist()  # row order kept
    assert (marked["altitude"] == 1000.0).all()
    assert rows["latitude"].notna().sum() == 9  # the input is not modified
