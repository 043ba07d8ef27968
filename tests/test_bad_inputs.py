"""The bad-input catalogue of ``torchsvs track`` and the track-file API: every case a new user
meets gets a named error (the option, column or file, and what was expected) or a documented
handling that the run prints or counts; none is silent. ``tests/test_bad_input.py`` holds the
estimators' own argument checks."""

from __future__ import annotations

import math
import os
import re
import shlex
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.csv as pcsv
import pyarrow.parquet as pq
import pytest
import torch

from torchsvs.cli import main
from torchsvs.datasets import (
    Columns,
    EstimateWriter,
    geodesy,
    noise_lags,
    read_tracks,
    write_estimates,
)
from torchsvs.datasets.describe import describe_input
from torchsvs.datasets.rows import InputWarning
from torchsvs.track_options import track_parser

ROOT = Path(__file__).resolve().parents[1]
SIGMA = 30.0


def _tracks(tracks: int = 3, steps: int = 40, seed: int = 0, dt: float = 5.0):
    """Straight tracks ``(ids [R], t [R], truth [R, 2], z [R, 2])`` in metres, 30 m noise."""
    gen = np.random.default_rng(seed)
    ids, times, truth = [], [], []
    for k in range(tracks):
        t = np.arange(steps) * dt
        v = gen.normal(0, 100, 2)
        ids += [f"t{k}"] * steps
        times.append(t)
        truth.append(gen.normal(0, 1e3, 2) + t[:, None] * v)
    true = np.concatenate(truth)
    return np.array(ids), np.concatenate(times), true, true + gen.normal(0, SIGMA, true.shape)


def _csv(path: Path, header: str, rows) -> Path:
    path.write_text(header + "\n" + "\n".join(",".join(map(str, r)) for r in rows) + "\n")
    return path


def _metric_file(path: Path, **kwargs) -> Path:
    ids, t, _, z = _tracks(**kwargs)
    rows = [
        (i, f"{ti:.1f}", f"{x:.3f}", f"{y:.3f}") for i, ti, (x, y) in zip(ids, t, z, strict=True)
    ]
    return _csv(path, "track_id,time,x,y", rows)


def _track(capsys, *args: str) -> tuple[int, str]:
    """``torchsvs track ARGS``: the exit code and what it printed on standard error. The
    estimator is the KS unless ARGS name one (these cases are about reading, not choosing)."""
    words = [str(a) for a in args]
    if "--estimator" not in words:
        words += ["--estimator", "ks"]
    try:
        main(["track", *words])
        code = 0
    except SystemExit as stop:
        code = stop.code if isinstance(stop.code, int) else 1
        if not isinstance(stop.code, int) and stop.code is not None:
            print(stop.code, file=__import__("sys").stderr)
    return code, capsys.readouterr().err


def _refused(capsys, pattern: str, *args: str) -> str:
    code, err = _track(capsys, *args)
    assert code != 0, err
    assert re.search(pattern, err), err
    return err


def _column(path: Path, name: str) -> np.ndarray:
    return pcsv.read_csv(path).column(name).to_numpy()


# --- 1. The output never replaces an input -------------------------------------------------


@pytest.mark.parametrize("spelling", ["same", "dot", "absolute", "symlink", "hardlink"])
def test_output_naming_the_input_is_refused(tmp_path, capsys, monkeypatch, spelling):
    source = _metric_file(tmp_path / "a.csv")
    before = source.read_bytes()
    monkeypatch.chdir(tmp_path)
    if spelling == "symlink":
        (tmp_path / "link.csv").symlink_to(source)
    if spelling == "hardlink":
        os.link(source, tmp_path / "link.csv")
    target = {
        "same": "a.csv",
        "dot": "./a.csv",
        "absolute": str(source),
        "symlink": "link.csv",
        "hardlink": "link.csv",
    }[spelling]
    _refused(
        capsys,
        r"output: .* is the input file .*never replaces an input",
        "a.csv",
        "-o",
        target,
        "--force",
    )
    assert source.read_bytes() == before


def test_existing_output_needs_force(tmp_path, capsys):
    source = _metric_file(tmp_path / "a.csv")
    target = tmp_path / "out.csv"
    target.write_text("keep me\n")
    _refused(capsys, r"output: '.*out\.csv' exists; pass --force", source, "-o", target)
    assert target.read_text() == "keep me\n"
    code, err = _track(capsys, source, "-o", target, "--force", "--quiet")
    assert code == 0, err
    assert len(target.read_text().splitlines()) == 3 * 40 + 1


def test_save_never_replaces_the_input_or_the_output(tmp_path, capsys):
    source = _metric_file(tmp_path / "a.csv")
    target, saved = tmp_path / "out.csv", tmp_path / "s.pt"
    _refused(
        capsys, r"save: .* is the input file", source, "-o", target, "--save", source, "--force"
    )
    _refused(capsys, r"save: .* is the output file", source, "-o", target, "--save", target)
    saved.write_text("old")
    _refused(capsys, r"save: .*s\.pt' exists; pass --force", source, "-o", target, "--save", saved)
    assert saved.read_text() == "old" and not target.exists()


def test_a_failed_run_leaves_the_old_output_and_no_partial_file(tmp_path, capsys):
    """Streaming stops at a track found again after other tracks, after blocks were written:
    the earlier output stays as it was and no temporary file is left."""
    ids, t, _, z = _tracks(tracks=4, steps=30)
    rows = [(i, ti, x, y) for i, ti, (x, y) in zip(ids, t, z, strict=True)]
    rows.append(("t0", 1000.0, 0.0, 0.0))  # t0 again, after the other tracks
    source = _csv(tmp_path / "a.csv", "track_id,time,x,y", rows)
    target = tmp_path / "out.csv"
    target.write_text("the previous run\n")
    _refused(
        capsys,
        r"track 't0': its rows are not contiguous.*--in-memory",
        source,
        "-o",
        target,
        "--force",
        "--stream",
        "--block-rows",
        "20",
        "--quiet",
    )
    assert target.read_text() == "the previous run\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.csv", "out.csv"]


def test_estimate_writer_renames_only_a_complete_file(tmp_path):
    target = tmp_path / "out.csv"
    target.write_text("old\n")
    table = pa.table({"a": [1.0, 2.0]})
    with pytest.raises(RuntimeError), EstimateWriter(target) as writer:
        writer.write(table)
        raise RuntimeError("midway")
    assert target.read_text() == "old\n" and len(list(tmp_path.iterdir())) == 1
    with EstimateWriter(target) as writer:
        writer.write(table)
    assert target.read_text().splitlines() == ['"a"', "1", "2"]
    fresh = tmp_path / "fresh.csv"
    with EstimateWriter(fresh) as writer:
        writer.write(table)
    plain = tmp_path / "plain.csv"
    plain.write_text("")
    assert fresh.stat().st_mode == plain.stat().st_mode  # not mkstemp's private mode


def test_python_api_never_writes_over_the_file_it_read(tmp_path):
    from torchsvs.recipes import Settings
    from torchsvs.tracking import track_file

    source = _metric_file(tmp_path / "a.csv")
    before = source.read_bytes()
    tracks, _ = read_tracks(source, meas_std=SIGMA)
    with pytest.raises(ValueError, match="^path: .* is the input file"):
        write_estimates(tracks, torch.zeros(*tracks.z.shape[:2], 4, dtype=tracks.z.dtype), source)
    with pytest.raises(ValueError, match="^target: .* is the input file"):
        track_file(source, tmp_path / "." / "a.csv", Settings(), progress=False)
    assert source.read_bytes() == before


# --- 2. Latitude and longitude ---------------------------------------------------------------


def test_local_frame_round_trip_is_exact():
    """Tangent plane and back, to 1e-9 degrees (0.1 mm), for points up to 60° away."""
    gen = np.random.default_rng(0)
    lat0, lon0 = gen.uniform(-85, 85, 2000), gen.uniform(-180, 180, 2000)
    for spread in (0.01, 1.0, 60.0):
        lat = np.clip(lat0 + gen.uniform(-spread, spread, 2000), -89.9, 89.9)
        lon = lon0 + gen.uniform(-spread, spread, 2000)
        back_lat, back_lon = geodesy.from_local(geodesy.to_local(lat, lon, lat0, lon0), lat0, lon0)
        assert np.abs(back_lat - lat).max() < 1e-9
        assert np.abs((back_lon - lon + 180) % 360 - 180).max() < 1e-9


def test_local_axes_map_a_local_velocity_into_the_frame():
    """``J v`` is the derivative of the plane coordinates when the point moves with velocity
    ``v`` (east, north at the point): a central difference of :func:`to_local` over ±0.5 s."""
    lat0, lon0 = 52.0, 4.0
    for lat, lon in ((52.5, 4.2), (55.0, 12.0), (40.0, -10.0)):
        v = np.array([120.0, -80.0])
        ends = []
        for sign in (-0.5, 0.5):
            step = np.array([v[0] * sign, v[1] * sign, 0.0])
            la, lo, _ = geodesy.enu_to_geodetic(step, lat, lon, 0.0)
            ends.append(geodesy.to_local(la, lo, lat0, lon0))
        numeric = ends[1] - ends[0]
        exact = geodesy.local_axes(lat, lon, lat0, lon0) @ v
        assert np.abs(numeric - exact).max() < 1e-4 * np.linalg.norm(v)


def _geodetic_rows(
    lat0=47.0, lon0=8.0, names=("latitude", "longitude"), altitude=False, tracks=3, steps=40
):
    """The metric tracks of :func:`_tracks` placed at (lat0, lon0), in degrees."""
    ids, t, truth, z = _tracks(tracks=tracks, steps=steps)
    lat, lon = geodesy.from_local(z, lat0, lon0)
    header = ",".join(["track_id", "time", *names] + (["altitude"] if altitude else []))
    rows = []
    for r in range(len(ids)):
        row = [ids[r], f"{t[r]:.1f}", f"{lat[r]:.10f}", f"{lon[r]:.10f}"]
        rows.append(row + ([f"{1000 + z[r, 0] / 10:.3f}"] if altitude else []))
    return header, rows, (ids, t, z, lat, lon)


def test_latitude_longitude_round_trip_through_the_command(tmp_path, capsys):
    """With a huge q and a tiny noise the smoother's estimate is the measurement: the degrees
    written back equal those read to 1e-9."""
    header, rows, (_, _, _, lat, lon) = _geodetic_rows(altitude=True)
    source = _csv(tmp_path / "a.csv", header, rows)
    target = tmp_path / "out.csv"
    code, err = _track(capsys, source, "-o", target, "--meas-std", "1e-3", "--q", "1e9", "--double")
    assert code == 0, err
    assert "WGS 84 latitude, longitude (degrees), altitude (m)" in err
    out = pcsv.read_csv(target)
    assert out.column_names[:8] == [
        "track_id",
        "time",
        "latitude",
        "longitude",
        "altitude",
        "v_east",
        "v_north",
        "v_up",
    ]
    read = np.array([[float(r[2]), float(r[3])] for r in rows])
    assert np.abs(out.column("latitude").to_numpy() - read[:, 0]).max() < 1e-9
    assert np.abs(out.column("longitude").to_numpy() - read[:, 1]).max() < 1e-9


def test_latitude_longitude_are_estimated_in_metres(tmp_path, capsys):
    """The same tracks in degrees and in metres: the noise read off the data is the same (in
    metres, not degrees), and so are the velocities (m/s) and position covariances (m²)."""
    header, rows, (ids, t, z, _, _) = _geodetic_rows(names=("Lat", "LON"))
    degrees = _csv(tmp_path / "deg.csv", header, rows)
    metres = _csv(
        tmp_path / "m.csv",
        "track_id,time,x,y",
        [(i, f"{ti:.1f}", f"{x:.6f}", f"{y:.6f}") for i, ti, (x, y) in zip(ids, t, z, strict=True)],
    )
    noise = []
    for source in (degrees, metres):
        code, err = _track(
            capsys, source, "-o", source.with_suffix(".out.csv"), "--double", "--covariance"
        )
        assert code == 0, err
        noise.append([float(v) for v in re.search(r"noise std \[([^\]]+)\]", err)[1].split(",")])
    assert SIGMA / 2 < noise[1][0] < 2 * SIGMA
    assert np.allclose(noise[0], noise[1], rtol=1e-3), noise
    geo, flat = (
        pcsv.read_csv(degrees.with_suffix(".out.csv")),
        pcsv.read_csv(metres.with_suffix(".out.csv")),
    )
    # The metric file's plane is tangent at (47°, 8°); the east and north at an estimate
    # 30 km away turn by 0.3° against it (meridian convergence): turned, the m/s agree.
    lat, lon = geo.column("Lat").to_numpy(), geo.column("LON").to_numpy()
    plane = np.stack([flat.column("vx").to_numpy(), flat.column("vy").to_numpy()], -1)
    local = np.linalg.solve(geodesy.local_axes(lat, lon, 47.0, 8.0), plane[..., None])[..., 0]
    assert np.abs(local - plane).max() > 0.05  # the turn matters
    velocity = np.stack([geo.column("v_east").to_numpy(), geo.column("v_north").to_numpy()], -1)
    assert np.allclose(velocity, local, rtol=1e-3, atol=1e-3)
    assert np.allclose(
        geo.column("cov_east_east").to_numpy(), flat.column("cov_x_x").to_numpy(), rtol=1e-3
    )


def test_latitude_longitude_streamed_equal_read_whole(tmp_path, capsys):
    """Each track's frame is its own first position, whichever block its rows arrive in."""
    header, rows, _ = _geodetic_rows(altitude=True)
    source = _csv(tmp_path / "a.csv", header, rows)
    outputs = []
    for name, mode in (("w.csv", ["--in-memory"]), ("s.csv", ["--stream", "--block-rows", "7"])):
        code, err = _track(
            capsys,
            source,
            "-o",
            tmp_path / name,
            "--meas-std",
            "30",
            "--q",
            "1",
            "--covariance",
            *mode,
        )
        assert code == 0, err
        outputs.append((tmp_path / name).read_bytes())
    assert outputs[0] == outputs[1]


@pytest.mark.parametrize(
    "names", [("lat", "lon"), ("Latitude", "Longitude"), ("LAT", "lng"), ("lon", "lat")]
)
def test_latitude_longitude_names_are_recognised(tmp_path, capsys, names):
    header, rows, _ = _geodetic_rows(names=names)
    source = _csv(tmp_path / "a.csv", header, rows)
    code, err = _track(
        capsys, source, "-o", tmp_path / "o.csv", "--pos-cols", ",".join(names), "--meas-std", "30"
    )
    assert code == 0, err
    assert "WGS 84 latitude, longitude (degrees)" in err and "v_east, v_north" in err
    assert "v_east" in pcsv.read_csv(tmp_path / "o.csv").column_names


def test_degrees_under_other_names_are_warned_about(tmp_path, capsys):
    header, rows, _ = _geodetic_rows(names=("a", "b"))
    source = _csv(tmp_path / "a.csv", header, rows)
    code, err = _track(
        capsys, source, "-o", tmp_path / "o.csv", "--pos-cols", "a,b", "--meas-std", "30", "--quiet"
    )
    assert code == 0, err
    assert re.search(r"warning: position: .*if they are latitude and longitude.*--frame wgs84", err)
    with pytest.warns(InputWarning, match="--frame wgs84"):
        read_tracks(source, Columns(position=("a", "b")), meas_std=1.0)
    code, err = _track(
        capsys,
        source,
        "-o",
        tmp_path / "w.csv",
        "--pos-cols",
        "a,b",
        "--frame",
        "wgs84",
        "--meas-std",
        "30",
    )
    assert code == 0 and "WGS 84" in err and "warning" not in err


@pytest.mark.parametrize(
    "altitudes, feet",
    [
        ((3000.0, 100.0), "25"),  # ADS-B's barometric altitude: 25 ft steps
        ((38000.0, 1.7), "reaches"),  # cruise in feet: above any aircraft in metres
        ((3000.0, 1.7), None),  # metres, as GNSS gives them
    ],
)
def test_an_altitude_in_feet_is_warned_about(tmp_path, capsys, altitudes, feet):
    """Latitude, longitude and an ``altitude`` in feet were read as metres without a word:
    the altitude's noise and estimates in feet, and the 3-D error estimate a mix."""
    gen = np.random.default_rng(2)
    base, climb = altitudes
    rows = []
    for k in range(4):
        for i in range(40):
            alt = base + climb * i + gen.normal(0, 20)
            alt = round(alt / 25) * 25 if feet == "25" else round(alt, 1)
            lat, lon = 48.0 + 0.001 * i + 1e-3 * k, 2.0 + 0.002 * i
            rows.append((f"t{k}", 5.0 * i, *(gen.normal([lat, lon], 1e-4)), alt))
    source = _csv(tmp_path / "a.csv", "track_id,time,lat,lon,altitude", rows)
    code, err = _track(capsys, source, "-o", tmp_path / "o.csv", "--quiet")
    assert code == 0, err
    said = re.search(r"warning: altitude: column 'altitude' (.*)", err)
    if feet is None:
        assert said is None, err
    else:
        assert said is not None and feet in said.group(1), err
        assert "x 0.3048" in said.group(1)


def test_metres_in_a_latitude_column_name_the_frame_flag(tmp_path, capsys):
    source = _metric_file(tmp_path / "a.csv")
    source.write_text(source.read_text().replace("x,y", "lat,lon", 1))
    _refused(
        capsys,
        r"position: column 'lat' holds mostly no latitude in degrees.*--frame metric",
        source,
        "-o",
        tmp_path / "o.csv",
    )
    code, err = _track(capsys, source, "-o", tmp_path / "o.csv", "--frame", "metric")
    assert code == 0, err
    assert "position 'lat', 'lon': metres" in err
    assert "vlat" in pcsv.read_csv(tmp_path / "o.csv").column_names


def test_wgs84_asked_of_metres_and_noise_free_positions_say_so(tmp_path, capsys):
    """``--frame wgs84`` on a file of x, y says it reads latitude and longitude (it said the
    file had no x, y columns, listing them); positions without noise say that, not that there
    are too few of them."""
    source = _metric_file(tmp_path / "a.csv")
    _refused(
        capsys,
        r"position: the frame is WGS 84 .* reads latitude and longitude columns .* the file has "
        r"none \(its columns: \['track_id', 'time', 'x', 'y'\]\).* --pos-cols LAT,LON",
        source,
        "-o",
        tmp_path / "o.csv",
        "--frame",
        "wgs84",
    )
    ids, t, truth, _ = _tracks(steps=80)
    points = zip(ids, t, truth.tolist(), strict=True)
    rows = [(i, f"{s:.1f}", f"{x!r}", f"{y!r}") for i, s, (x, y) in points]
    clean = _csv(tmp_path / "clean.csv", "track_id,time,x,y", rows)
    _refused(
        capsys,
        r"meas_std: the positions carry no measurement noise to read: most lie exactly on smooth "
        r"paths .*\(--meas-std\)",
        clean,
        "-o",
        tmp_path / "o.csv",
    )


def test_longitudes_come_back_in_the_convention_they_were_read_in(tmp_path, capsys):
    """A track across the antimeridian read in 0-360° (179.5-180.5°) came back in
    -180..180° (180.5° written as -179.5°); each row's estimate is now in its own convention,
    and a track read in ±180° stays there."""
    gen = np.random.default_rng(4)
    steps = 60
    lat = 45.0 + 0.001 * np.arange(steps) + gen.normal(0, 2e-4, steps)
    lon = 179.5 + 0.02 * np.arange(steps) + gen.normal(0, 2e-4, steps)  # to 180.68°
    for name, values in (("east", lon), ("signed", (lon + 180.0) % 360.0 - 180.0)):
        rows = [
            ("a", i * 5, f"{la:.6f}", f"{lo:.6f}")
            for i, (la, lo) in enumerate(zip(lat, values, strict=True))
        ]
        source = _csv(tmp_path / f"{name}.csv", "track_id,time,lat,lon", rows)
        code, err = _track(capsys, source, "-o", tmp_path / f"{name}.out.csv", "--meas-std", "20")
        assert code == 0, err
        out = _column(tmp_path / f"{name}.out.csv", "lon")
        assert np.abs((out - values + 180.0) % 360.0 - 180.0).max() < 0.005  # (the noise)
        assert (out >= 0).all() if name == "east" else (np.abs(out) <= 180.0).all()


def test_a_lone_stray_report_beyond_the_frame_is_read_as_missing(tmp_path, capsys):
    """A (0, 0) report (GPS's null island) or a longitude off by 180° among a track's near
    reports is a glitch: read as missing and counted, the run goes on (it refused the whole
    file, telling the user to split the track), the row estimated from its neighbours."""
    gen = np.random.default_rng(2)
    steps = 60
    lat = 45.0 + 0.001 * np.arange(steps) + gen.normal(0, 2e-4, steps)
    lon = 179.5 + 0.002 * np.arange(steps) + gen.normal(0, 2e-4, steps)
    lat[20], lon[20] = 0.0, 0.0
    lon[40] -= 180.0
    points = enumerate(zip(lat, lon, strict=True))
    rows = [("a", i * 5, f"{la:.6f}", f"{lo:.6f}") for i, (la, lo) in points]
    source = _csv(tmp_path / "a.csv", "track_id,time,lat,lon", rows)
    code, err = _track(capsys, source, "-o", tmp_path / "o.csv", "--meas-std", "20")
    assert code == 0, err
    assert "invalid_coordinate: 2 " in err
    out = pcsv.read_csv(tmp_path / "o.csv")
    for k in (20, 40):  # estimated on the track, within a few hundred metres of its neighbours
        near = np.array([k - 1, k + 1])
        assert abs(_column(tmp_path / "o.csv", "lat")[k] - lat[near].mean()) < 0.005
        assert abs(_column(tmp_path / "o.csv", "lon")[k] - (lon[near].mean() % 360)) < 0.005
    assert out.num_rows == steps


def test_a_track_around_the_globe_is_refused(tmp_path, capsys):
    rows = [("a", i, 0.0, lon) for i, lon in enumerate((0.0, 40.0, 85.0, 120.0))]
    source = _csv(tmp_path / "a.csv", "track_id,time,lat,lon", rows)
    _refused(
        capsys,
        r"track 'a': reaches more than 80° of arc .* from the row at time 2\.0 s on",
        source,
        "-o",
        tmp_path / "o.csv",
        "--meas-std",
        "30",
        "--q",
        "1",
    )


def test_coordinates_out_of_range_are_counted_as_missing(tmp_path, capsys):
    header, rows, _ = _geodetic_rows()
    rows[5][2] = "95.0"  # a latitude past the pole
    source = _csv(tmp_path / "a.csv", header, rows)
    code, err = _track(capsys, source, "-o", tmp_path / "o.csv", "--meas-std", "30")
    assert code == 0, err
    assert "note, invalid_coordinate: 1" in err and "1 prediction-only" in err


# --- 3. Time units --------------------------------------------------------------------------


def _velocity_with_times(tmp_path, capsys, times: list[str], *args: str) -> tuple[np.ndarray, str]:
    ids, _, _, z = _tracks(tracks=1, steps=len(times))
    rows = [(i, ts, f"{x:.3f}", f"{y:.3f}") for i, ts, (x, y) in zip(ids, times, z, strict=True)]
    source = _csv(tmp_path / "a.csv", "track_id,time,x,y", rows)
    target = tmp_path / "o.csv"
    target.unlink(missing_ok=True)
    code, err = _track(capsys, source, "-o", target, "--meas-std", "30", "--q", "1", *args)
    assert code == 0, err
    return _column(target, "vx"), err


@pytest.mark.parametrize(
    "unit, scale, found",
    [
        ("s", 1.0, "numbers, read as seconds"),
        ("ms", 1e3, "milliseconds since 1970 (detected"),
        ("us", 1e6, "microseconds since 1970 (detected"),
        ("ns", 1e9, "nanoseconds since 1970 (detected"),
    ],
)
def test_epoch_times_in_any_unit_are_detected(tmp_path, capsys, unit, scale, found):
    seconds = 1.7e9 + np.arange(40) * 5.0
    reference, _ = _velocity_with_times(tmp_path, capsys, [f"{s:.0f}" for s in seconds])
    velocity, err = _velocity_with_times(tmp_path, capsys, [f"{s * scale:.0f}" for s in seconds])
    assert found in err
    assert np.allclose(velocity, reference, rtol=1e-9)
    if unit != "s":  # given outright, and the old number of seconds per unit
        given, err = _velocity_with_times(
            tmp_path, capsys, [f"{s * scale:.0f}" for s in seconds], "--time-unit", unit
        )
        assert np.allclose(given, reference, rtol=1e-9) and "as given" in err
        number, _ = _velocity_with_times(
            tmp_path, capsys, [f"{s * scale:.0f}" for s in seconds], "--time-unit", str(1 / scale)
        )
        assert np.allclose(number, reference, rtol=1e-6)


def test_iso_times_and_parquet_timestamps_are_read_as_dates(tmp_path, capsys):
    seconds = 1.7e9 + np.arange(40) * 5.0
    reference, _ = _velocity_with_times(tmp_path, capsys, [f"{s:.0f}" for s in seconds])
    iso = [np.datetime_as_string(np.datetime64(int(s), "s")) + "Z" for s in seconds]
    velocity, err = _velocity_with_times(tmp_path, capsys, iso)
    assert "date-time texts (ISO 8601" in err
    assert np.allclose(velocity, reference, rtol=1e-9)
    ids, _, _, z = _tracks(tracks=1, steps=40)
    z = np.round(z, 3)  # as the CSV holds them
    table = pa.table(
        {
            "track_id": ids,
            "time": pa.array((seconds * 1e3).astype("int64"), pa.timestamp("ms")),
            "x": z[:, 0],
            "y": z[:, 1],
        }
    )
    pq.write_table(table, tmp_path / "a.parquet")
    code, err = _track(
        capsys, tmp_path / "a.parquet", "-o", tmp_path / "p.csv", "--meas-std", "30", "--q", "1"
    )
    assert code == 0 and "timestamps (timestamp[ms])" in err
    assert np.allclose(_column(tmp_path / "p.csv", "vx"), reference, rtol=1e-9)


def test_small_millisecond_times_are_warned_about(tmp_path, capsys):
    """Milliseconds from 0 look like seconds; an interval of thousands of seconds is named."""
    milliseconds = [str(i * 5000) for i in range(40)]
    _, err = _velocity_with_times(tmp_path, capsys, milliseconds)
    assert re.search(r"warning: time: the typical interval .* is 5000 s; .*--time-unit ms", err)
    given, err = _velocity_with_times(tmp_path, capsys, milliseconds, "--time-unit", "ms")
    assert "warning" not in err
    seconds, _ = _velocity_with_times(tmp_path, capsys, [str(i * 5) for i in range(40)])
    assert np.allclose(given, seconds, rtol=1e-9)


def test_unusable_and_negative_times(tmp_path, capsys):
    """NaN, inf and empty times set the row aside (counted; its output row keeps its id and
    time with empty estimates); negative times are times like any other."""
    times = [f"{-100 + 5.0 * i}" for i in range(40)]
    times[3], times[7], times[11] = "nan", "inf", ""
    _, err = _velocity_with_times(tmp_path, capsys, times)
    assert "set aside, no_time: 3" in err
    out = pcsv.read_csv(
        tmp_path / "o.csv", convert_options=pcsv.ConvertOptions(column_types={"time": pa.string()})
    )
    assert out.num_rows == 40 and np.isnan(out.column("x").to_numpy()[[3, 7, 11]]).all()
    shifted = [str(float(v) + 1e3) if v not in ("nan", "inf", "") else v for v in times]
    later, _ = _velocity_with_times(tmp_path, capsys, shifted)
    earlier, _ = _velocity_with_times(tmp_path, capsys, times)
    assert np.allclose(later, earlier, rtol=1e-6, equal_nan=True)


def test_a_date_among_a_tracks_seconds_is_set_aside_where_it_cannot_be_placed(tmp_path, capsys):
    """A track's times in seconds from 0 with one ISO date among them: read as seconds since
    1970 the date went 54 years on, its row's estimate the raw measurement, noted only as out
    of order. It is set aside, named; a date that agrees with the numbers (epoch seconds) is
    kept, and the other rows come out as without the date."""
    times = [f"{5.0 * i}" for i in range(40)]
    clean, _ = _velocity_with_times(tmp_path, capsys, times)
    times[12] = "2024-05-01T12:00:00Z"  # decades from the track's other times
    times[20] = "1970-01-01T00:01:40Z"  # 100 s since 1970: the number it stands for
    velocity, err = _velocity_with_times(tmp_path, capsys, times)
    assert "set aside, time_unlike_its_track: 1" in err and "out_of_order" not in err
    assert np.isnan(velocity[12]) and np.isfinite(np.delete(velocity, 12)).all()
    times[12] = ""
    without, _ = _velocity_with_times(tmp_path, capsys, times)
    assert np.allclose(velocity, without, equal_nan=True) and np.isfinite(clean).all()
    # most of the track's times dates: a number among them is the odd one out
    dates = [np.datetime_as_string(np.datetime64(1_700_000_000 + 5 * i, "s")) for i in range(40)]
    dates[5] = "25"
    velocity, err = _velocity_with_times(tmp_path, capsys, dates)
    assert "set aside, time_unlike_its_track: 1" in err and np.isnan(velocity[5])


def test_times_too_coarse_as_short_floats_are_named(tmp_path, capsys):
    """Epoch seconds stored as 32-bit floats are 128 s apart near 1.7e9: rows a second apart
    shared times and were merged, and the estimates came out 200 times the measurements' error
    without a word. The run names the column, its resolution and what to store instead; the
    same times as 64-bit floats, or 32-bit floats from 0, read without it."""
    ids, _, _, z = _tracks(tracks=2, steps=60)
    seconds = np.tile(np.arange(60.0) * 10.0, 2)  # (10 s apart: 13 times of 128 s left)
    for name, times, named in (
        ("epoch32", pa.array(1.7e9 + seconds, pa.float32()), True),
        ("epoch64", pa.array(1.7e9 + seconds, pa.float64()), False),
        ("small32", pa.array(seconds, pa.float32()), False),
    ):
        table = pa.table({"track_id": ids, "time": times, "x": z[:, 0], "y": z[:, 1]})
        pq.write_table(table, tmp_path / f"{name}.parquet")
        code, err = _track(
            capsys, tmp_path / f"{name}.parquet", "-o", tmp_path / f"{name}.csv", "--meas-std", "30"
        )
        assert code == 0
        found = re.search(
            r"time: column 'time' holds 32-bit floats: near 1\.7e\+09 they are 128 s", err
        )
        assert bool(found) == named, err


def test_tracks_too_short_to_read_the_noise_off_are_named(tmp_path, capsys):
    """Thousands of tracks of 2 rows: the noise is read off differences within a track, and
    the refusal said "too few observed positions" of a file of 40,000; it names the tracks'
    length."""
    rows = [(f"t{k}", t, 10.0 * k + t, 5.0 * t) for k in range(300) for t in (0.0, 1.0)]
    source = _csv(tmp_path / "a.csv", "track_id,time,x,y", rows)
    _refused(
        capsys,
        r"too few observed positions within a track .* the longest track read has 2\)",
        source,
        "-o",
        tmp_path / "o.csv",
    )


def test_tracks_too_short_to_smooth_at_a_given_noise_get_advice_that_fits(tmp_path, capsys):
    """The same tracks of 2 rows with ``--meas-std`` run (each passes through both positions)
    and are not below the measurements: ``auto``'s warning advised ``--meas-std``, which the
    user had given; it names the tracks' length instead."""
    rng = np.random.default_rng(0)
    rows = [
        (f"t{k}", t, 10.0 * k + t + rng.normal(0, 3), 5.0 * t + rng.normal(0, 3))
        for k in range(300)
        for t in (0.0, 1.0)
    ]
    source = _csv(tmp_path / "a.csv", "track_id,time,x,y", rows)
    code, err = _track(
        capsys, source, "-o", tmp_path / "o.csv", "--meas-std", "3", "--estimator", "auto"
    )
    assert code == 0, err
    said = re.search(r"warning: ks: .* is not clearly below the measurements'.*", err)
    assert said is not None, err
    assert "--meas-std" not in said.group(0)
    assert "2 positions per track" in said.group(0)


def test_an_svsf_run_as_its_kalman_filter_gets_the_kalman_filters_advice(
    tmp_path, capsys, monkeypatch
):
    """Targets jerking far more between reports than the sensor errs: no filter gets clearly
    below the measurements. The SVSF ran as its Kalman filter twin (its limit not earning its
    place) advised ``--meas-std``, as if ``auto`` had chosen it, where the Kalman filter itself
    advised a smoother; both now advise the smoother. (The noise read off these positions is
    the jerks, and the second differences two reports apart say so: the run then makes no
    point estimate to advise on, ``test_noise_lags.py``; that check is off here.)"""
    rng = np.random.default_rng(1)
    rows = []
    for k in range(60):
        v, p = np.zeros(2), np.zeros(2)
        for t in range(60):
            v += rng.normal(0, 30, 2)
            p += v
            z = p + rng.normal(0, 1, 2)
            rows.append((f"t{k}", t, z[0], z[1]))
    source = _csv(tmp_path / "a.csv", "track_id,time,x,y", rows)
    monkeypatch.setattr(noise_lags, "LAG_SHARE", -math.inf)
    for estimator in ("kf", "svsf"):
        code, err = _track(
            capsys, source, "-o", tmp_path / "o.csv", "--estimator", estimator, "--force"
        )
        assert code == 0, err
        said = re.search(r"warning: kf: .* is not clearly below the measurements'.*", err)
        assert said is not None, (estimator, err)
        assert "try --estimator auto" in said.group(0), (estimator, said.group(0))


def test_a_file_without_any_usable_time_is_refused(tmp_path, capsys):
    source = _csv(tmp_path / "a.csv", "track_id,time,x,y", [("a", "soon", 1, 2), ("a", "", 3, 4)])
    _refused(
        capsys,
        r"input: no row of the first 2 rows can be placed(.|\n)*no_time: 2",
        source,
        "-o",
        tmp_path / "o.csv",
    )


# --- 4. Settings refused by the parser, naming the option -----------------------------------


@pytest.mark.parametrize(
    "option, value",
    [
        ("--meas-std", "-5"),
        ("--meas-std", "0"),
        ("--meas-std", "nan"),
        ("--meas-std", "inf"),
        ("--meas-std", "30,-1"),
        ("--q", "0"),
        ("--q", "-1"),
        ("--q", "nan"),
        ("--psi", "0"),
        ("--psi", "100,-5"),
        ("--gamma", "1"),
        ("--gamma", "-0.1"),
        ("--gamma", "nan"),
        ("--particles", "0"),
        ("--lag", "0"),
        ("--lag", "-2"),
        ("--time-unit", "hours"),
        ("--time-unit", "0"),
        ("--frame", "utm"),
    ],
)
def test_bad_settings_are_refused_naming_the_option(tmp_path, capsys, option, value):
    source = _metric_file(tmp_path / "a.csv")
    with pytest.raises(SystemExit) as stop:
        main(["track", str(source), "-o", str(tmp_path / "o.csv"), option, value])
    assert stop.value.code == 2
    assert f"argument {option}: " in capsys.readouterr().err
    assert not (tmp_path / "o.csv").exists()


# --- 5. Files that cannot be read or written --------------------------------------------------


@pytest.mark.parametrize(
    "name, content, pattern",
    [
        ("h.csv", "track_id,time,x,y\n", r"input: '.*h\.csv' has a header but no rows"),
        ("e.csv", "", r"input: '.*e\.csv' is empty \(no header, no rows\)"),
        ("a.xlsx", "track_id,time,x,y\n", r"input: expected a \.csv or \.parquet file .*a\.xlsx"),
        ("n.csv", None, r"input: '.*n\.csv': no such file"),
        (
            "id.csv",
            "id,time,x,y\na,0,1,1\n",
            r"columns: \['track_id'\] not in the file \(its columns: \['id', 'time', 'x', 'y'\]\); "
            r"name yours with --id-col",
        ),
        ("t.csv", "track_id,t,x,y\na,0,1,1\n", r"columns: \['time'\] .*--time-col"),
        (
            "p.csv",
            "track_id,time,east,north\na,0,1,1\n",
            r"position: the file has no x, y columns and no latitude, longitude columns \(its "
            r"columns: .*--pos-cols",
        ),
        (
            "x.csv",
            "track_id,time,x,y\na,0,abc,1\na,1,def,2\n",
            r"position: column 'x' holds no numbers in the first 2 rows "
            r"\(e\.g\. \['abc', 'def'\]\)",
        ),
        ("c.csv", 'track_id,time,x,y\na,0,"1,5",1\na,1,"2,5",2\n', r"decimal commas are not read"),
        (
            "z.csv",
            "track_id,time,x,y,z\na,0,1,1,\na,1,2,2,\n",
            r"position: column 'z' holds no numbers in the first 2 rows \(each empty or a text",
        ),
        (  # (texts read as missing: it said "empty")
            "na.csv",
            "track_id,time,x,y\na,0,n/a,1\na,1,NA,2\n",
            r"position: column 'x' holds no numbers .* read as missing: NA, n/a",
        ),
        (  # (one of x, y: it said the file had no x, y columns)
            "y.csv",
            "track_id,time,x\na,0,1\na,1,2\n",
            r"position: the file has no column 'y' beside the other and no latitude",
        ),
        (
            "r.csv",
            "track_id,time,x,y\na,0,1,1\na,1,2,2,7\n",
            r"path: '.*r\.csv': CSV parse error: Expected 4 columns, got 5: a,1,2,2,7",
        ),
    ],
)
def test_unreadable_inputs_get_a_clear_message(tmp_path, capsys, name, content, pattern):
    if content is not None:
        (tmp_path / name).write_text(content)
    _refused(capsys, pattern, tmp_path / name, "-o", tmp_path / "o.csv")
    assert not (tmp_path / "o.csv").exists()


def test_header_only_parquet_and_directory_inputs(tmp_path, capsys):
    empty = pa.table(
        {
            "track_id": pa.array([], pa.string()),
            "time": pa.array([], pa.float64()),
            "x": pa.array([], pa.float64()),
            "y": pa.array([], pa.float64()),
        }
    )
    pq.write_table(empty, tmp_path / "a.parquet")
    _refused(
        capsys,
        r"input: .* has a header but no rows",
        tmp_path / "a.parquet",
        "-o",
        tmp_path / "o.csv",
    )
    _refused(  # a directory is a dataset: its first file with rows is described
        capsys,
        r"input: .*a\.parquet' has a header but no rows",
        tmp_path,
        "-o",
        tmp_path.parent / f"{tmp_path.name}_out",
    )
    _refused(
        capsys,
        r"output: .* and the input directory .* lie one inside the other",
        tmp_path,
        "-o",
        tmp_path / "o.csv",
    )


def test_a_setting_given_against_a_saved_checkpoint_is_refused(tmp_path, capsys):
    """``--checkpoint`` of a ``--save`` file runs with the saved settings: a ``--meas-std``
    given beside it was dropped without a word."""
    source = _metric_file(tmp_path / "a.csv")
    saved = tmp_path / "saved.pt"
    code, err = _track(capsys, source, "-o", tmp_path / "s.csv", "--save", saved)
    assert code == 0, err
    _refused(  # (the saved settings are the run's: a different noise was dropped unsaid)
        capsys,
        r"settings: meas_var \(--meas-std\) = \[2500.0\] given, and the checkpoint .* holds "
        "its own",
        source,
        "-o",
        tmp_path / "o.csv",
        "--checkpoint",
        saved,
        "--meas-std",
        "50",
    )


def test_unwritable_outputs_get_a_clear_message(tmp_path, capsys):
    source = _metric_file(tmp_path / "a.csv")
    _refused(
        capsys,
        r"output: the directory '.*missing' does not exist",
        source,
        "-o",
        tmp_path / "missing" / "o.csv",
    )
    _refused(
        capsys, r"output: the directory '.*a\.csv' does not exist", source, "-o", source / "o.csv"
    )
    _refused(capsys, r"output: .* is a directory", source, "-o", tmp_path, "--force")
    _refused(
        capsys,
        r"output: expected a \.csv or \.parquet file name",
        source,
        "-o",
        tmp_path / "o.xlsx",
    )
    _refused(
        capsys,
        r"checkpoint: .*: no such file",
        source,
        "-o",
        tmp_path / "o.csv",
        "--checkpoint",
        tmp_path / "none.pt",
    )
    locked = tmp_path / "locked"
    locked.mkdir(mode=0o500)
    if os.access(locked, os.W_OK):  # root writes anywhere
        pytest.skip("running as a user who can write into a read-only directory")
    _refused(
        capsys, r"output: the directory .*locked' cannot be written", source, "-o", locked / "o.csv"
    )


# --- 6. Help and README say what the code does ------------------------------------------------


def test_the_checkout_commands_are_not_commands_of_the_installed_cli(capsys):
    """The demo and the reproductions are scripts of the clone (make demo, make reproduce): the
    installed ``torchsvs`` refuses them as unknown and says where they run."""
    for argv in (["demo"], ["reproduce", "svss"], ["reproduce", "--help"]):
        with pytest.raises(SystemExit) as stop:
            main(argv)
        assert stop.value.code == 2
        err = capsys.readouterr().err
        assert f"unknown command {argv[0]!r}" in err and "make demo, make reproduce" in err


TRACK_GUIDE = ROOT / "docs" / "guide" / "track_files.md"


def _readme_track_commands() -> list[list[str]]:
    text = (ROOT / "README.md").read_text() + TRACK_GUIDE.read_text(encoding="utf-8")
    return [
        shlex.split(line.split("#")[0])
        for block in re.findall(r"```bash\n(.*?)```", text, flags=re.S)
        for line in block.splitlines()
        if line.startswith("torchsvs track ") and "--help" not in line
    ]


def test_readme_track_examples_parse():
    """Every ``torchsvs track`` example of the README and the track-file guide parses with the
    command's own parser."""
    commands = _readme_track_commands()
    assert len(commands) >= 10
    parser = track_parser()
    for words in commands:
        parser.parse_args(words[2:])  # exits on an unknown option or a bad value


def _option_help(name: str) -> str:
    action = next(a for a in track_parser()._actions if name in a.option_strings)
    return " ".join(str(action.help).split())


def test_readme_and_help_say_who_reads_the_file_and_in_what_order(tmp_path):
    """``--processes``: rank 0 alone reads the file (torchsvs.training.predict reads it on rank
    0 and broadcasts the steps); streaming (files of more than 2^22 rows) needs contiguous tracks,
    and the help of both reading modes and the track-file guide say so."""
    import torchsvs.training.predict as predict
    from torchsvs.datasets.reading import WHOLE_ROWS, ReadAhead

    readme = " ".join(TRACK_GUIDE.read_text(encoding="utf-8").split())
    assert "rank 0 alone reads the whole file" in _option_help("--processes")
    assert "rank 0 alone reads the whole file" in readme
    assert "Only rank 0 reads the file" in predict.TrackFileDataModule.__doc__
    # track_file's reading: whole where the file is small enough (whole=None), so a small
    # file's tracks need not be contiguous; streamed, they must be
    scattered = tmp_path / "scattered.csv"
    scattered.write_text("track_id,time,x,y\na,1,0,0\nb,1,5,5\na,2,1,1\nb,2,6,6\na,3,2,2\n")
    with ReadAhead(scattered, Columns(time_unit="s"), whole=None) as reader:
        (block,) = list(reader)
    assert block.steps.ids == ["a", "b"] and list(block.steps.length) == [3, 2]
    with (
        ReadAhead(scattered, Columns(time_unit="s"), whole=False) as reader,
        pytest.raises(ValueError, match="'a': its rows are not contiguous"),
    ):
        list(reader)
    assert WHOLE_ROWS == 1 << 22
    for text in (_option_help("--stream"), readme):
        assert "2^22 rows" in text and "contiguous" in text and "--in-memory" in text
    # "any row order" only where the file is read whole
    for claim in re.finditer("any row order", readme):
        before = readme[max(0, claim.start() - 200) : claim.start()]
        assert "whole" in before or "in memory" in before, before


def test_readme_names_every_input_option():
    """The track-file guide's account of input handling names the options that change it."""
    readme = TRACK_GUIDE.read_text(encoding="utf-8")
    for option in ("--frame", "--time-unit", "--force", "--in-memory", "--pos-cols"):
        assert option in readme
        assert any(option in a.option_strings for a in track_parser()._actions)


# --- 7. Python API dtypes -----------------------------------------------------------------------


def test_prior_of_another_dtype_than_z_is_refused():
    import torchsvs as ts

    kf = ts.KalmanFilter(ts.models.ConstantVelocity(q=1.0, r=1.0))
    z = torch.zeros(2, 5, 2)
    x0, P0 = torch.zeros(4), torch.eye(4)
    with pytest.raises(TypeError, match=r"^P0: dtype torch\.float64 .* z's dtype torch\.float32"):
        kf(z, x0, P0.double())
    with pytest.raises(TypeError, match=r"^x0: dtype torch\.float64 .* z's dtype torch\.float32"):
        kf(z, x0.double(), P0)
    with pytest.raises(TypeError, match=r"^x0: dtype torch\.float32 .* z's dtype torch\.float64"):
        kf(z.double(), x0, P0.double())
    model = ts.models.ConstantVelocity(q=1.0, r=1.0, dt=1.0)
    with pytest.raises(TypeError, match=r"^dt: dtype torch\.float64 .* z's dtype torch\.float32"):
        ts.KalmanFilter(model)(z, x0, P0, dt=torch.ones(2, 5, dtype=torch.float64))
    with pytest.raises(TypeError, match=r"^P0: dtype torch\.float64 differs from x0's dtype"):
        kf.init(x0, P0.double())
    kf(z, x0, P0)  # matching dtypes, and plain numbers, run
    kf(z.double(), [0.0] * 4, np.eye(4))
    ts.KalmanFilter(model)(z, x0, P0, dt=np.ones((2, 5)))


# --- 8. More of what a new user meets -------------------------------------------------------


def test_duplicated_ids_in_separate_places(tmp_path, capsys):
    """Read whole (the default up to 2^22 rows), a track's rows may be anywhere in the file;
    streamed, a track found again after other tracks stops the run naming it and the flag."""
    ids, t, _, z = _tracks(tracks=2, steps=20)
    rows = [(i, ti, x, y) for i, ti, (x, y) in zip(ids, t, z, strict=True)]
    rows = rows[:10] + rows[20:] + rows[10:20]  # t0, t1, then t0 again
    source = _csv(tmp_path / "a.csv", "track_id,time,x,y", rows)
    code, err = _track(capsys, source, "-o", tmp_path / "o.csv", "--meas-std", "30")
    assert code == 0 and "40 rows in 2 tracks" in err
    _refused(
        capsys,
        r"track 't0': its rows are not contiguous.*sort it by track id.*--in-memory",
        source,
        "-o",
        tmp_path / "s.csv",
        "--stream",
        "--meas-std",
        "30",
    )


def test_single_row_and_still_tracks(tmp_path, capsys):
    """A track of one row gets its measurement and velocity 0 (counted); a track whose rows
    all sit at one position is estimated there; a file where every track stands still has no
    noise to read off and names the options to give."""
    ids, t, _, z = _tracks(tracks=2, steps=30)
    rows = [(i, ti, x, y) for i, ti, (x, y) in zip(ids, t, z, strict=True)]
    rows += [("one", 3.0, 10.0, 20.0)] + [("still", float(i), 5.0, 7.0) for i in range(10)]
    source = _csv(tmp_path / "a.csv", "track_id,time,x,y", rows)
    code, err = _track(capsys, source, "-o", tmp_path / "o.csv")
    assert code == 0, err
    assert "note, tracks_single_point_axis: 1" in err
    out = pcsv.read_csv(tmp_path / "o.csv").to_pandas().set_index("track_id")
    assert tuple(out.loc["one", ["x", "vx", "y", "vy"]]) == (10.0, 0.0, 20.0, 0.0)
    still = out.loc["still"]
    assert np.allclose(still["x"], 5.0, atol=1e-3) and np.allclose(still["vx"], 0.0, atol=1e-3)
    parked = _csv(
        tmp_path / "p.csv",
        "track_id,time,x,y",
        [(k, float(i), 5.0 * k, 7.0) for k in range(3) for i in range(10)],
    )
    _refused(
        capsys,
        r"position: \['x', 'y'\] do not change within any track .*--meas-std .*--q",
        parked,
        "-o",
        tmp_path / "p_out.csv",
    )
    code, err = _track(
        capsys, parked, "-o", tmp_path / "p_out.csv", "--meas-std", "1", "--q", "0.01"
    )
    assert code == 0, err
    assert np.allclose(_column(tmp_path / "p_out.csv", "y"), 7.0, atol=1e-3)


@pytest.mark.parametrize("separator", [";", "\t", "|"])
def test_other_separators_and_a_byte_order_mark(tmp_path, capsys, separator):
    source = _metric_file(tmp_path / "a.csv")
    comma = pcsv.read_csv(source)
    text = source.read_text().replace(",", separator)
    other = tmp_path / "b.csv"
    other.write_text(text, encoding="utf-8-sig")
    code, err = _track(capsys, other, "-o", tmp_path / "o.csv", "--meas-std", "30")
    assert code == 0, err
    assert f"separator {separator!r} (read from the header)" in err
    code, _ = _track(capsys, source, "-o", tmp_path / "c.csv", "--meas-std", "30")
    assert np.array_equal(_column(tmp_path / "o.csv", "x"), _column(tmp_path / "c.csv", "x"))
    assert comma.num_rows == pcsv.read_csv(tmp_path / "o.csv").num_rows


def test_unsorted_and_repeated_times_within_a_track(tmp_path, capsys):
    """Rows out of time order are sorted into place, rows sharing a time merged: both counted,
    and the estimates are those of the sorted file."""
    ids, t, _, z = _tracks(tracks=2, steps=30)
    rows = [(i, ti, x, y) for i, ti, (x, y) in zip(ids, t, z, strict=True)]
    sorted_file = _csv(tmp_path / "s.csv", "track_id,time,x,y", rows)
    gen = np.random.default_rng(1)
    shuffled = [rows[i] for i in gen.permutation(len(rows))]
    mixed = _csv(tmp_path / "m.csv", "track_id,time,x,y", shuffled + [rows[4]])
    code, err = _track(capsys, mixed, "-o", tmp_path / "mo.csv", "--meas-std", "30")
    assert code == 0 and "note, out_of_order:" in err and "note, duplicate_time: 1" in err
    code, _ = _track(capsys, sorted_file, "-o", tmp_path / "so.csv", "--meas-std", "30")
    merged = pcsv.read_csv(tmp_path / "mo.csv").to_pandas().iloc[:-1]
    merged = merged.sort_values(["track_id", "time"]).reset_index(drop=True)
    plain = pcsv.read_csv(tmp_path / "so.csv").to_pandas()
    assert np.allclose(merged["x"], plain["x"], rtol=1e-6)


def test_rows_without_id_or_position(tmp_path, capsys):
    ids, t, _, z = _tracks(tracks=1, steps=20)
    rows = [(i, ti, x, y) for i, ti, (x, y) in zip(ids, t, z, strict=True)]
    rows += [("", 3.0, 1.0, 1.0), ("ghost", 1.0, "", ""), ("t0", 200.0, "abc", "")]
    source = _csv(tmp_path / "a.csv", "track_id,time,x,y", rows)
    code, err = _track(capsys, source, "-o", tmp_path / "o.csv", "--meas-std", "30")
    assert code == 0, err
    for text in (
        "set aside, no_track_id: 1",
        "set aside, track_without_position: 1",
        "note, non_numeric_value: 1",
        "1 prediction-only",
    ):
        assert text in err
    assert pcsv.read_csv(tmp_path / "o.csv").num_rows == len(rows)


def test_ids_that_read_as_missing_elsewhere_are_ids(tmp_path, capsys):
    """A track id "NA", "null" or "N/A" is an id: its rows keep it and are estimated (Arrow's
    default null texts made them rows without an id); the same texts in a position are missing
    values, not text to count."""
    ids, t, _, z = _tracks(tracks=3, steps=20)
    names = {"t0": "NA", "t1": "null", "t2": "N/A"}
    rows = [(names[i], ti, x, y) for i, ti, (x, y) in zip(ids, t, z, strict=True)]
    rows[5] = (rows[5][0], rows[5][1], "NA", "nan")
    source = _csv(tmp_path / "a.csv", "track_id,time,x,y", rows)
    code, err = _track(capsys, source, "-o", tmp_path / "o.csv", "--meas-std", "30")
    assert code == 0, err
    assert "60 rows in 3 tracks" in err and "1 prediction-only" in err
    assert "no_track_id" not in err and "non_numeric_value" not in err
    lines = (tmp_path / "o.csv").read_text().splitlines()[1:]
    assert [line.split(",")[0].strip('"') for line in lines] == [r[0] for r in rows]
    assert all(line.split(",")[2] for line in lines)  # every row estimated


def test_describe_input_settles_frame_and_time_unit(tmp_path):
    header, rows, _ = _geodetic_rows(altitude=True)
    rows = [[r[0], str(int(float(r[1]) * 1e3 + 1.7e12)), *r[2:]] for r in rows]
    source = _csv(tmp_path / "a.csv", header, rows)
    found = describe_input(source)
    assert found.columns.frame == "wgs84"
    assert found.columns.position == ("latitude", "longitude", "altitude")
    assert math.isclose(found.columns.seconds_per_unit, 1e-3)
    assert not found.warnings


@pytest.mark.parametrize(
    "options",
    [("--pos-cols", "x,time"), ("--id-col", "time"), ("--time-col", "x"), ("--id-col", "y")],
)
def test_a_column_named_for_two_roles_is_refused_by_name(tmp_path, capsys, options):
    """A column named as the id, the time or a position twice over is refused with the roles
    named (it ended in pyarrow's "field exists 2 times" traceback)."""
    path = _metric_file(tmp_path / "in.csv")
    err = _refused(
        capsys, r"columns: each column serves one role", path, "-o", tmp_path / "o.csv", *options
    )
    assert "Traceback" not in err and "--pos-cols" in err
