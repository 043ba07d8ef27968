"""The ``torchsvs`` command line.

    torchsvs demo [--epochs 4] [--runs 500]           learn ψ, γ; track Chen et al. 2020's scenarios
    torchsvs reproduce svss [--runs 500] [--seed 0]   Tables 1-3, A2 and Figs 4-9 of that paper
    torchsvs reproduce spvsf [--runs 100]             Tables 1, 2, 4, 5, Figs 5-9 of Gadsden 2012
    torchsvs reproduce road [--runs 100]              Figs 2-10 of Zhang & Zhou 2022 (road targets)
                                                      (reports in ./torchsvs-results/ or --out)
    torchsvs fit --config CONFIG.yaml                 train an estimator (LightningCLI)
    torchsvs track INPUT -o OUTPUT [--estimator svss] [--fit] [--processes 2] ...
                                                      estimate every track of a CSV/Parquet file

The experiments are scripts of the source checkout (``experiments/``), not of the installed
library: the command runs them from the clone that ``pip install -e .`` installed.
"""

from __future__ import annotations

import argparse
import atexit
import importlib
import math
import os
import socket
import subprocess
import sys
import threading
from collections.abc import Callable
from pathlib import Path
from types import ModuleType
from typing import Any

COMMANDS = {
    "demo": ("experiments.demo", "learn ψ, γ, then track the scenarios of Chen et al. 2020"),
    "reproduce svss": ("experiments.svss_paper", "Chen et al. 2020: Tables 1-3, A2, Figs 4-9"),
    "reproduce spvsf": (
        "experiments.spvsf_paper",
        "Gadsden et al. 2012: Tables 1, 2, 4, 5, Figs 5-9",
    ),
    "reproduce road": (
        "experiments.road_tracking",
        "Zhang & Zhou 2022: the SM road tracker, Figs 2-10",
    ),
}


def _import_experiment(module: str) -> ModuleType:
    root = Path(__file__).resolve().parents[1]
    if not (root / "experiments" / "__init__.py").is_file():
        raise SystemExit(
            "torchsvs: the experiments are part of the source checkout (experiments/); "
            "install torchsvs from a clone with `pip install -e .` to run them"
        )
    if str(root) not in sys.path:
        sys.path.insert(0, str(root))
    return importlib.import_module(module)


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
    """``auto``, a unit of :data:`~torchsvs.datasets.rows.TIME_UNITS` or seconds per unit."""
    from torchsvs.datasets.rows import TIME_UNITS

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
    from torchsvs.recipes import ESTIMATORS

    parser = argparse.ArgumentParser(
        prog="torchsvs track",
        description=(
            "Estimate every track of a CSV or Parquet file (rows: track id, time, position) and "
            "write one row per input row with the estimated position and velocity."
        ),
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="estimators:\n" + "\n".join(f"  {k:<8} {v}" for k, v in ESTIMATORS.items()),
    )
    parser.add_argument(
        "input",
        help="a .csv (.csv.gz, .tsv, .txt; separator , ; tab or | read from the header) or "
        ".parquet file of track rows",
    )
    parser.add_argument(
        "-o",
        "--output",
        required=True,
        help="the .csv or .parquet to write (never the input; an existing file only with "
        "--force); written under a temporary name beside it and renamed when complete",
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
        help="measurement noise standard deviation, one value or one per axis, in metres (also "
        "for latitude, longitude: --frame) (default: read off the data; with --fit, learned)",
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
        "the smoothers svss and svstps); with --no-velocity the "
        "width in measurement noise standard deviations (default 5)",
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
        "--fit-tracks", type=_at_least_one, default=2000, help="tracks the fit uses (default 2000)"
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
        help="read the whole file at once: any row order (the default for files under 256 MiB)",
    )
    reading.add_argument(
        "--stream",
        action="store_true",
        help="stream the file track by track in bounded memory (the default for files of "
        "256 MiB or more): each track's rows must be contiguous (any order within a track); a "
        "track found again after other tracks stops the run with its id: sort the file by "
        "track id or pass --in-memory",
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
        "--stream), reads the settings off it (and fits) once, sends the others their tracks' "
        "steps and the settings, gathers the estimates and writes the same file as one "
        "process; only the estimating is shared, so it pays only where that dominates, see "
        "benchmarks/ddp_predict.md; default 1",
    )
    parser.add_argument(
        "--double", action="store_true", help="compute in float64 (default float32)"
    )
    parser.add_argument(
        "--threads", type=_at_least_one, default=1, help="torch threads (default 1)"
    )
    parser.add_argument("--quiet", action="store_true", help="no progress bar or summary")
    return parser


def track(argv: list[str]) -> None:
    """``torchsvs track``: see :func:`track_parser`."""
    parser = track_parser()
    args = parser.parse_args(argv)
    if args.lag == 0 and args.estimator != "imm":
        parser.error(
            f"argument --lag: expected an integer >= 1 (0 only for --estimator imm: its "
            f"filter), got 0 with --estimator {args.estimator}"
        )
    if os.environ.get("LOCAL_RANK", "0") == "0":  # ranks 1..N-1 of --processes read no file
        try:
            args.columns = checked_columns(args)
        except (ValueError, TypeError, FileNotFoundError) as err:
            raise SystemExit(f"torchsvs track: {err}") from err
    if args.processes > 1 and not args.stream and "LOCAL_RANK" not in os.environ:
        with OtherRanks(argv, args.processes, args.threads):
            _track(args)
    else:
        _track(args)


def _columns(args: argparse.Namespace) -> Any:
    from torchsvs.datasets import Columns

    pos = tuple(args.pos_cols.split(",")) if args.pos_cols else None
    return Columns(args.id_col, args.time_col, pos, time_unit=args.time_unit, frame=args.frame)


def checked_columns(args: argparse.Namespace) -> Any:
    """Checks the paths of ``torchsvs track`` before anything runs (the input readable, the
    output and ``--save`` never an input, an existing file only with ``--force``), settles the
    input's columns on its first block (:func:`~torchsvs.datasets.describe.describe_input`: the
    frame, the time unit) and prints what was found (unless ``--quiet``) and any warning.

    Returns:
        The resolved :class:`~torchsvs.datasets.Columns`.
    """
    from torchsvs.datasets.describe import describe_input
    from torchsvs.datasets.paths import check_input, check_output
    from torchsvs.datasets.rows import file_format

    check_input(args.input, "input")
    check_output(args.output, "output", inputs=(args.input, args.checkpoint), force=args.force)
    try:
        file_format(args.output)
    except ValueError:
        raise ValueError(
            f"output: expected a .csv or .parquet file name, got {args.output!r}"
        ) from None
    if args.save is not None:
        if Path(args.save).resolve() == Path(args.output).resolve():
            raise ValueError(f"save: {args.save!r} is the output file; name another file")
        check_output(args.save, "save", inputs=(args.input,), force=args.force)
    if args.checkpoint is not None and not Path(args.checkpoint).is_file():
        raise FileNotFoundError(f"checkpoint: {args.checkpoint!r}: no such file")
    described = describe_input(args.input, _columns(args), block_rows=args.block_rows, name="input")
    if described.constant and args.checkpoint is None and None in (args.meas_std, args.q):
        raise ValueError(
            f"position: {described.constant} do not change within any track of the first "
            f"{described.rows} rows: no noise can be read off them; give --meas-std (one value "
            "per axis) and --q, or leave such a column out with --pos-cols"
        )
    if not args.quiet:
        for line in described.lines:
            print(f"reading {args.input}: {line}", file=sys.stderr)
    for text in described.warnings:
        print(f"torchsvs track: warning: {text}", file=sys.stderr)
    return described.columns


class OtherRanks:
    """Starts ranks ``1..N-1`` of ``torchsvs track --processes N`` at once, as ``torchrun``
    does, and sets this process up as rank 0 of that group (Lightning then joins the processes
    instead of launching them). Lightning's own launcher starts them only when rank 0 reaches
    ``Trainer.predict``, after its imports: their interpreters and imports (seconds) then run
    after rank 0's instead of beside them. A rank that fails ends the others, as Lightning's
    launcher does; on leaving, rank 0 waits for the others and restores its environment."""

    VARIABLES = ("MASTER_ADDR", "MASTER_PORT", "NODE_RANK", "WORLD_SIZE", "LOCAL_RANK")

    def __init__(self, argv: list[str], processes: int, threads: int) -> None:
        self.command = [sys.executable, "-m", "torchsvs.cli", "track", *argv]
        self.processes, self.threads = processes, threads
        self.saved = {k: os.environ.get(k) for k in (*self.VARIABLES, "OMP_NUM_THREADS")}
        self.children: list[subprocess.Popen[bytes]] = []
        self.done = threading.Event()

    def __enter__(self) -> OtherRanks:
        with socket.socket() as probe:  # a free port for the process group
            probe.bind(("127.0.0.1", 0))
            port = probe.getsockname()[1]
        os.environ.update(
            MASTER_ADDR="127.0.0.1",
            MASTER_PORT=str(port),
            NODE_RANK="0",
            WORLD_SIZE=str(self.processes),
            OMP_NUM_THREADS=str(self.threads),
        )
        for rank in range(1, self.processes):
            env = dict(os.environ, LOCAL_RANK=str(rank))
            self.children.append(subprocess.Popen(self.command, env=env))
        os.environ["LOCAL_RANK"] = "0"
        threading.Thread(target=self._watch, daemon=True, name="other-ranks").start()
        return self

    def _watch(self) -> None:
        """Ends this process if another rank fails (rank 0 would wait for it forever)."""
        while not self.done.wait(0.5):
            codes = [child.poll() for child in self.children]
            if all(code == 0 for code in codes):
                return
            failed = [(c.pid, code) for c, code in zip(self.children, codes, strict=True) if code]
            if failed:
                print(f"torchsvs track: a process ended with {failed}; ending", file=sys.stderr)
                self._end_children()
                os._exit(1)

    def _end_children(self) -> None:
        for child in self.children:
            if child.poll() is None:
                child.kill()

    def __exit__(self, kind: object, error: object, trace: object) -> None:
        try:
            if kind is not None:  # rank 0 failed: the others would wait for it
                self._end_children()
            for child in self.children:
                child.wait()
        finally:
            self.done.set()  # stops the watch
            for key, value in self.saved.items():
                if value is None:
                    os.environ.pop(key, None)
                else:
                    os.environ[key] = value


def _track(args: argparse.Namespace) -> None:
    import torch

    from torchsvs.recipes import Settings
    from torchsvs.tracking import saved_settings, track_file

    torch.set_num_threads(args.threads)
    columns = getattr(args, "columns", None) or _columns(args)
    try:
        if args.checkpoint is not None and Path(args.checkpoint).is_file():
            try:
                base = saved_settings(args.checkpoint)
            except ValueError:
                base = None
        else:
            base = None
        settings = base or Settings(
            estimator=args.estimator,
            meas_var=None if args.meas_std is None else [s * s for s in args.meas_std],
            q=args.q,
            psi=args.psi,
            gamma=args.gamma,
            lag=args.lag,
            velocity=not args.no_velocity,
            particles=args.particles,
            turn_q=args.turn_q,
            turn_rate_q=args.turn_rate_q,
            turn_rate_std=args.turn_rate_std,
            switch_prob=args.switch_prob,
            track_q=not args.shared_q,
            outliers=not args.keep_outliers,
        )
        fit_options: dict[str, object] = {
            "tracks": args.fit_tracks,
            # Given, or read off the data robustly (estimate_noise): SURE fits in its units. The
            # innovation likelihood's noise (self_tune's first stage) counts turns as noise: on
            # recorded tracks at irregular times it made the KS worse than the measurements.
            "known_noise": True,
        }
        if args.fit_steps is not None:
            fit_options["steps"] = args.fit_steps
        common: dict[str, Any] = {
            "columns": columns,
            "fit": args.fit,
            "fit_options": fit_options,
            "checkpoint": args.checkpoint,
            "save": args.save,
            "covariance": args.covariance,
            "block_rows": args.block_rows,
            "max_cells": args.max_cells,
            "dtype": torch.float64 if args.double else torch.float32,
            "log": None if args.quiet else lambda text: print(text, file=sys.stderr),
        }
        if args.processes > 1:
            if args.stream:
                raise ValueError(
                    "processes: more than one process reads the whole file; drop --stream"
                )
            from torchsvs.training.predict import predict_file

            run = predict_file(
                args.input,
                args.output,
                settings,
                processes=args.processes,
                threads=args.threads,
                **common,
            )
        else:
            run = track_file(
                args.input,
                args.output,
                settings,
                whole=True if args.in_memory else False if args.stream else None,
                progress=not args.quiet,
                **common,
            )
    except (ValueError, TypeError, FileNotFoundError) as err:
        raise SystemExit(f"torchsvs track: {err}") from err
    if run is not None and not args.quiet:  # None: a process launched by rank 0
        print(run.summary(), file=sys.stderr)


#: Where ``torchsvs reproduce`` writes its reports unless ``--out`` says otherwise (the
#: checkout's tracked ``experiments/results/`` is for ``make reproduce``).
REPRODUCE_OUT = Path("torchsvs-results")


def usage() -> str:
    lines = [f"  torchsvs {k:<16} {v[1]}" for k, v in COMMANDS.items()]
    lines.append("  torchsvs fit --config CONFIG.yaml   train an estimator (LightningCLI)")
    lines.append("  torchsvs track INPUT -o OUTPUT      estimate every track of a file")
    return (
        "usage: torchsvs COMMAND [options]\n\ncommands:\n"
        + "\n".join(lines)
        + "\n\n`torchsvs COMMAND --help` lists a command's options."
    )


def reproduce_usage() -> str:
    """What ``torchsvs reproduce`` (alone or with ``--help``) prints: the reproductions."""
    lines = [
        f"  torchsvs {k:<16} {v[1]}" for k, v in COMMANDS.items() if k.startswith("reproduce ")
    ]
    return (
        "usage: torchsvs reproduce NAME [options]\n\nreproductions (reports in "
        f"./{REPRODUCE_OUT}/NAME unless --out says otherwise):\n"
        + "\n".join(lines)
        + "\n\n`torchsvs reproduce NAME --help` lists its options."
    )


def main(argv: list[str] | None = None) -> None:
    """Dispatches ``torchsvs COMMAND [options]`` to the experiment's own ``main``."""
    args = list(sys.argv[1:] if argv is None else argv)
    if not args:
        print(usage(), file=sys.stderr)
        raise SystemExit(2)
    if args[:1] in (["-h"], ["--help"], ["help"]):
        print(usage())  # asked for: standard output, success
        return
    if args[:1] == ["fit"]:
        from torchsvs.training.cli import main as fit

        fit(args[1:])
        return
    if args[:1] == ["track"]:
        track(args[1:])
        return
    if args[:1] == ["reproduce"] and args[1:2] in ([], ["-h"], ["--help"], ["help"]):
        print(reproduce_usage())  # what there is to reproduce: standard output, success
        return
    for words in sorted(COMMANDS, key=len, reverse=True):
        size = len(words.split())
        if args[:size] == words.split():
            run = _import_experiment(COMMANDS[words][0]).main
            if words.startswith("reproduce"):
                out = REPRODUCE_OUT / words.split()[1]
                run(args[size:], prog=f"torchsvs {words}", out=out)
            else:
                run(args[size:], prog=f"torchsvs {words}")
            return
    if args[:1] == ["reproduce"]:
        print(f"torchsvs: unknown reproduction {args[1]!r}\n\n{reproduce_usage()}", file=sys.stderr)
        raise SystemExit(2)
    print(f"torchsvs: unknown command {' '.join(args[:2])!r}\n\n{usage()}", file=sys.stderr)
    raise SystemExit(2)


def command() -> None:
    """The ``torchsvs`` program: :func:`main`, then an exit that skips tearing down the
    interpreter's modules (torch, Lightning: about a second, paid by every process of a run)
    once the exit handlers have run and the output is flushed."""
    try:
        main()
        code = 0
    except SystemExit as stop:
        if stop.code is not None and not isinstance(stop.code, int):
            print(stop.code, file=sys.stderr)
        code = stop.code if isinstance(stop.code, int) else 0 if stop.code is None else 1
    atexit._run_exitfuncs()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


if __name__ == "__main__":
    command()
