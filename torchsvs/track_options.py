"""The options of ``torchsvs track`` (:func:`track_parser`) and the argument types that check
them as they are read (a bad value stops the command with its option named)."""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable

from torchsvs.datasets.tables import SAMPLE_TRACKS


def _floats(text: str) -> list[float]:
    try:
        return [float(v) for v in text.split(",")]
    except ValueError as err:
        raise argparse.ArgumentTypeError(
            f"expected numbers separated by commas, got {text!r}"
        ) from err


def _positive_floats(text: str) -> list[float]:
    """Numbers separated by commas, each finite and > 0 (noise levels, widths)."""
    values = _floats(text)
    if not all(math.isfinite(v) and v > 0 for v in values):
        raise argparse.ArgumentTypeError(f"expected finite numbers > 0, got {text!r}")
    return values


def _positive(text: str) -> float:
    """One finite number > 0."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"expected a finite number > 0, got {text!r}")
    return value


def _fraction(text: str) -> float:
    """A number in [0, 1)."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not 0.0 <= value < 1.0:
        raise argparse.ArgumentTypeError(f"expected a number in [0, 1), got {text!r}")
    return value


def _integer_at_least(least: int) -> Callable[[str], int]:
    """An argparse type: an integer of at least ``least``."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            value = least - 1
        if value < least:
            raise argparse.ArgumentTypeError(f"expected an integer >= {least}, got {text!r}")
        return value

    return parse


_at_least_one = _integer_at_least(1)
_at_least_zero = _integer_at_least(0)


def _time_unit(text: str) -> float | str:
    """``auto``, a unit of :data:`~torchsvs.datasets.times.TIME_UNITS` or seconds per unit."""
    from torchsvs.datasets.times import TIME_UNITS

    if text == "auto" or text in TIME_UNITS:
        return text
    try:
        return _positive(text)
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(
            f"expected auto, {', '.join(TIME_UNITS)} or seconds per unit (a number > 0), "
            f"got {text!r}"
        ) from None


def track_parser() -> argparse.ArgumentParser:
    from torchsvs.estimator_names import ESTIMATORS

    parser = argparse.ArgumentParser(
        prog="torchsvs track",
        description=(
            "Estimate every track of a CSV or Parquet file, or of a directory of Parquet files "
            "(rows: track id, time, position), and write one row per input row with the "
            "estimated position and velocity."
        ),
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="estimators:\n" + "\n".join(f"  {k:<8} {v}" for k, v in ESTIMATORS.items()),
    )
    parser.add_argument(
        "input",
        help="a .csv (.csv.gz, .tsv, .txt; separator , ; tab or | read from the header) or "
        ".parquet file of track rows, or a directory of .parquet files (a dataset, e.g. written "
        "by Spark or pyarrow.dataset, hive partitions such as part=3/ included; names starting "
        "with . or _ skipped): read file by file, a track's rows all in one file",
    )
    parser.add_argument(
        "-o",
        "--output",
        required=True,
        help="the .csv or .parquet to write (never the input; an existing file only with "
        "--force): one row per input row, its id and time as read, the estimated positions and "
        "velocities (the input's other columns are not copied); written under a temporary name "
        "beside it and renamed when complete. For a "
        "directory input, the directory to write: one .parquet file per input file under the "
        "same relative name, written in a temporary directory beside it and renamed when "
        "complete (an existing one is replaced as a whole, only with --force)",
    )
    parser.add_argument(
        "--force", action="store_true", help="replace an existing output (or --save) file"
    )
    parser.add_argument(
        "--estimator",
        default="auto",
        choices=sorted(ESTIMATORS),
        help="default auto: ks, svss and, on small files, imm, "
        "each tuned on the file without truth, the one of the lowest estimated error kept (its "
        "table is printed)",
    )
    parser.add_argument("--id-col", default="track_id", help="track id column (default track_id)")
    parser.add_argument("--time-col", default="time", help="time column (default time)")
    parser.add_argument(
        "--pos-cols",
        default=None,
        help="position columns, e.g. x,y or x,y,z, or lat,lon[,alt] (default: x, y[, z], or "
        "without them latitude/lat, longitude/lon/lng[, altitude/alt/height/elevation])",
    )
    parser.add_argument(
        "--frame",
        default="auto",
        choices=("auto", "metric", "wgs84"),
        help="what the positions are: metric (metres, estimated as read) or wgs84 (latitude, "
        "longitude in degrees[, altitude in metres]: estimated in metres east, north[, up] of "
        "each track's first position, written back as degrees, with velocities v_east, "
        "v_north[, v_up] in m/s and covariances in metres); default auto: wgs84 when the "
        "position columns are named as latitude and longitude (any case)",
    )
    parser.add_argument(
        "--time-unit",
        type=_time_unit,
        default="auto",
        help="unit of a numeric time: s, ms, us, ns or seconds per unit (0.001 = ms); default "
        "auto: seconds, or ms/us/ns since 1970 when the values are that large (from 1e11, "
        "1e14, 1e17); date-time texts (ISO 8601) and timestamps need none",
    )
    parser.add_argument(
        "--meas-std",
        type=_positive_floats,
        default=None,
        help="measurement noise standard deviation, one value or one per axis, in the positions' "
        "units (metres for latitude, longitude: --frame; the run's messages say m for them) "
        "(default: read off the data; with --fit, learned)",
    )
    parser.add_argument(
        "--noise-col",
        default=None,
        help="a column of each row's measurement noise standard deviation (in the positions' "
        "units: metres, also for latitude, longitude), where the rows come from sensors of "
        "different quality (ADS-B's accuracy category, a GPS's reported accuracy): each "
        "track runs at the median of its rows' (not with --meas-std)",
    )
    parser.add_argument(
        "--q",
        type=_positive,
        default=None,
        help="process noise of the CV model (imm: of its CV mode; default: read off the data, "
        "for imm 0.03 of it)",
    )
    parser.add_argument(
        "--shared-q",
        action="store_true",
        help="one q for every track (default: each track its own, picked by its SURE and "
        "shrunk toward the file's; not for imm, nor where --q is given)",
    )
    parser.add_argument(
        "--no-step-q",
        action="store_true",
        help="ks: each track one q (default: where SURE finds it better on the sample, each "
        "step a blend of the smoother's passes at several q, weighted by their SURE over a "
        "window of steps around it)",
    )
    parser.add_argument(
        "--keep-outliers",
        action="store_true",
        help="use every position (default: a position far off the path its neighbours agree "
        "on, at a chance below one in a million for the noise, is set aside as missing and "
        "flagged in the output's outlier column)",
    )
    parser.add_argument(
        "--psi",
        type=_positive_floats,
        default=None,
        help="SVSF family's boundary layer, one value or one per axis: the variable boundary "
        "layer's limit in innovation standard deviations (default 2 for svsf and spvsf, 4 for "
        "the smoothers svss and svstps, kept where the sample shows it surely helps, else "
        "the run goes as the Kalman twin); with --no-velocity the width in measurement noise "
        "standard deviations (default 5)",
    )
    parser.add_argument(
        "--gamma", type=_fraction, default=0.1, help="SVSF memory in [0, 1) (default 0.1)"
    )
    parser.add_argument(
        "--lag",
        type=_at_least_zero,
        default=None,
        help="smoother lag (default: ks, svss and svstps the full interval, imm 5; svss "
        "--no-velocity 1; imm --lag 0: the IMM filter; refused for the filters)",
    )
    parser.add_argument(
        "--no-velocity",
        action="store_true",
        help="SVSF family in the paper's H⁺ mode (velocity never corrected) instead of "
        "finite-difference velocities",
    )
    parser.add_argument(
        "--particles", type=_at_least_one, default=350, help="particles of pf and spvsf"
    )
    parser.add_argument(
        "--turn-q",
        type=float,
        default=None,
        help="imm: white acceleration variance of the turn mode (m²/s⁴; default q/T of the data)",
    )
    parser.add_argument(
        "--turn-rate-q",
        type=float,
        default=None,
        help="imm: turn-rate noise of the turn mode (rad²/s⁴; default from the data's q, "
        "interval and speed)",
    )
    parser.add_argument(
        "--turn-rate-std",
        type=float,
        default=None,
        help="imm: prior standard deviation of the turn rate (rad/s; default from the data)",
    )
    parser.add_argument(
        "--switch-prob",
        type=float,
        default=0.05,
        help="imm: probability of a switch between the CV and turn modes per step (default 0.05)",
    )
    parser.add_argument(
        "--fit", action="store_true", help="tune the estimator on the input itself (no truth)"
    )
    parser.add_argument(
        "--fit-tracks",
        type=_at_least_one,
        default=SAMPLE_TRACKS,
        help=f"tracks the fit uses (default {SAMPLE_TRACKS})",
    )
    parser.add_argument(
        "--fit-steps", type=_at_least_one, default=None, help="optimiser steps of the fit"
    )
    parser.add_argument(
        "--checkpoint",
        default=None,
        help="load parameters (a --save file or a Lightning checkpoint)",
    )
    parser.add_argument(
        "--save",
        default=None,
        help="save the settings and parameters used (never over the input or the output; an "
        "existing file only with --force)",
    )
    parser.add_argument("--covariance", action="store_true", help="also write the covariances")
    reading = parser.add_mutually_exclusive_group()
    reading.add_argument(
        "--in-memory",
        action="store_true",
        help="read the whole file (each file of a directory) at once: any row order (the "
        "default for files of up to 2^22 rows, a CSV's counted at 40 bytes a row)",
    )
    reading.add_argument(
        "--stream",
        action="store_true",
        help="stream the file track by track in bounded memory (the default for files of "
        "more than 2^22 rows): each track's rows must be contiguous (any order within a "
        "track); a track found again after other tracks, or in two files of a directory, "
        "stops the run with its id: sort the file by track id or pass --in-memory",
    )
    parser.add_argument(
        "--block-rows", type=_at_least_one, default=1 << 18, help="rows per streamed block"
    )
    parser.add_argument(
        "--max-cells",
        type=_at_least_one,
        default=1 << 19,
        help="padded steps (tracks × steps) per estimator call: bounds memory (default 2^19)",
    )
    parser.add_argument(
        "--processes",
        type=_at_least_one,
        default=1,
        help="processes sharing the tracks (Lightning DDP on CPU, gloo; each runs --threads "
        "threads): rank 0 alone reads the whole file (into memory, any row order; not with "
        "--stream, nor a directory), reads the settings off it (and fits) once, sends the "
        "others their tracks' steps and the settings, gathers the estimates and writes the "
        "same file as one process; only the estimating is shared, so it pays only where that "
        "dominates, see benchmarks/ddp_predict.md; default 1",
    )
    parser.add_argument(
        "--double", action="store_true", help="compute in float64 (default float32)"
    )
    parser.add_argument(
        "--precision",
        choices=("auto", "float32", "float64"),
        default="auto",
        help="of the estimates written (default auto: float32 where it keeps every position "
        "to a hundredth of the measurement noise, as metres near an origin; float64 for large "
        "map coordinates and for latitude, longitude in degrees)",
    )
    parser.add_argument(
        "--threads",
        type=_at_least_one,
        default=None,
        help="threads of each process (default: the cores this process may use, divided by "
        "--processes): torch's intra-op threads, and the groups of tracks estimated at once "
        "(each on one thread)",
    )
    parser.add_argument("--quiet", action="store_true", help="no progress bar or summary")
    return parser
