"""``torchsvs track``: checks its paths and columns, then runs :func:`~torchsvs.tracking.
track_file` in this process, or :func:`~torchsvs.training.predict.predict_file` in
``--processes N`` of them (:class:`OtherRanks` starts the others)."""

from __future__ import annotations

import argparse
import gc
import os
import socket
import subprocess
import sys
import threading
from pathlib import Path
from typing import Any

from torchsvs.track_options import track_parser


def track(argv: list[str]) -> None:
    """``torchsvs track``: see :func:`track_parser`."""
    parser = track_parser()
    args = parser.parse_args(argv)
    if args.lag == 0 and args.estimator != "imm":
        parser.error(
            f"argument --lag: expected an integer >= 1 (0 only for --estimator imm: its "
            f"filter), got 0 with --estimator {args.estimator}"
        )
    if args.noise_col is not None and args.meas_std is not None:
        parser.error(
            "argument --noise-col: each row's noise is given by the column, and --meas-std "
            "gives one for all; give one of them"
        )
    if args.processes > 1 and Path(args.input).is_dir():
        parser.error(
            f"argument --processes: rank 0 reads one file whole, and {args.input!r} is a "
            "directory (a Parquet dataset); run it in one process (streamed file by file) or "
            "on Spark or Dask (torchsvs.engines)"
        )
    if args.threads is None:
        args.threads = default_threads(args.processes)
    reader = None
    if os.environ.get("LOCAL_RANK", "0") == "0":  # ranks 1..N-1 of --processes read no file
        try:
            check_paths(args)
            if args.processes > 1:  # (rank 0 reads the file whole, once the others run)
                args.columns = described_columns(args, input_description(args))
            else:  # the input read from now on, beside torch's import
                reader = start_reading(args)
        except (ValueError, TypeError, FileNotFoundError) as err:
            raise SystemExit(f"torchsvs track: {err}") from err
    if args.processes > 1 and not args.stream and "LOCAL_RANK" not in os.environ:
        with OtherRanks(argv, args.processes, args.threads):
            _track(args)
    else:
        _track(args, reader)


#: glibc's ``mallopt`` parameters (malloc.h) set by :func:`set_up_process`.
M_TRIM_THRESHOLD, M_TOP_PAD, M_MMAP_THRESHOLD, M_ARENA_MAX = -1, -2, -3, -8
#: The largest threshold glibc takes (64-bit): larger arrays are mapped, and zeroed, anew.
MMAP_THRESHOLD_MAX = 32 << 20


#: Set by :func:`set_up_process`: the program collects no garbage until its imports are done.
_COLLECT_AFTER_IMPORTS = False


def set_up_process() -> None:
    """The ``torchsvs track`` program's process, set up before any thread starts or library
    loads (in the program alone: a process that calls :func:`track` keeps its own set-up).
    Measured on 10 M rows, each paired against the process without it (n = 8):

    * the allocators keep the memory a block frees for the next block's arrays, instead of
      handing it back to the system, which hands it out again as fresh pages it zeroes (12% of
      the run's CPU): glibc's one arena (a thread's own arena maps every large array anew),
      freed memory kept (trim threshold, top pad), arrays up to 32 MB from it, and Arrow
      allocating from it too (its mimalloc pool zeroed new pages of its own): system time
      1.41 -> 1.05 s, wall 0.95x; Arrow's pool alone then 1.22 -> 0.76 s, wall 0.93x;
    * idle OpenMP threads (torch's) and OpenBLAS threads (numpy's) sleep instead of spinning
      for the next parallel region, on cores the reading, writing and groups' threads need:
      CPU 0.93x, wall 0.95x;
    * no garbage collection while the modules are imported, whose objects are then frozen out
      of it (``gc.freeze``, :func:`_track`): the collector's time 0.33 -> 0.01 s.

    All of it: system time 1.53 -> 0.76 s, CPU 0.85x, wall 0.87x, peak memory 1.02 -> 0.87 GB
    (n = 10), the same bytes out. Environment variables the user set are kept."""
    global _COLLECT_AFTER_IMPORTS
    for name, value in (
        ("ARROW_DEFAULT_MEMORY_POOL", "system"),
        ("OMP_WAIT_POLICY", "PASSIVE"),
        ("OPENBLAS_NUM_THREADS", "1"),
    ):
        os.environ.setdefault(name, value)
    gc.disable()
    _COLLECT_AFTER_IMPORTS = True
    if not sys.platform.startswith("linux"):
        return
    import ctypes

    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):  # (not glibc: musl has no mallopt)
        return
    for option, size in (
        (M_ARENA_MAX, 1),
        (M_MMAP_THRESHOLD, MMAP_THRESHOLD_MAX),
        (M_TRIM_THRESHOLD, 1 << 30),
        (M_TOP_PAD, 256 << 20),
    ):
        mallopt(option, size)


def _columns(args: argparse.Namespace) -> Any:
    from torchsvs.datasets import Columns

    pos = tuple(args.pos_cols.split(",")) if args.pos_cols else None
    extra = () if args.noise_col is None else (args.noise_col,)
    return Columns(
        args.id_col, args.time_col, pos, extra, time_unit=args.time_unit, frame=args.frame
    )


def check_paths(args: argparse.Namespace) -> None:
    """Checks the paths of ``torchsvs track`` before anything runs: the input readable, the
    output and ``--save`` never an input, an existing file only with ``--force``."""
    from torchsvs.datasets.paths import check_input, check_output
    from torchsvs.datasets.rows import file_format

    check_input(args.input, "input")
    check_output(args.output, "output", inputs=(args.input, args.checkpoint), force=args.force)
    if not Path(args.input).is_dir():  # a directory's output is a directory of Parquet files
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


def input_description(args: argparse.Namespace) -> Any:
    """The input's description (:func:`~torchsvs.datasets.describe.describe_input`)."""
    from torchsvs.datasets.describe import describe_input

    return describe_input(args.input, _columns(args), block_rows=args.block_rows, name="input")


def start_reading(args: argparse.Namespace) -> Any:
    """The input's description, then its blocks, read in a thread from now on
    (:class:`~torchsvs.datasets.reading.ReadAhead`): torch's import and the plan run beside
    it."""
    from torchsvs.datasets.reading import ReadAhead

    return ReadAhead(
        args.input,
        _columns(args),
        block_rows=args.block_rows,
        whole=_whole(args),
        describe=True,
        name="input",
    )


def _whole(args: argparse.Namespace) -> bool | None:
    """The input read whole (``--in-memory``), streamed (``--stream``), or as its size says."""
    return True if args.in_memory else False if args.stream else None


def described_columns(args: argparse.Namespace, described: Any) -> Any:
    """Checks what the input's first block holds (:func:`input_description`: the frame, the
    time unit), prints what was found (unless ``--quiet``) and any warning.

    Returns:
        The resolved :class:`~torchsvs.datasets.Columns`.
    """
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


def default_threads(processes: int = 1) -> int:
    """``--threads`` by default: the cores this process may run on, shared by ``processes``.
    The compiled passes split a group's tracks over them and reading and writing run beside
    the estimating; the tensor step loops of small batches take one thread whatever this
    says (:func:`~torchsvs.estimator.threads_for`)."""
    try:
        cores = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # (not on every platform)
        cores = os.cpu_count() or 1
    return max(1, cores // max(processes, 1))


def _track(args: argparse.Namespace, reader: Any = None) -> None:
    """The run, with ``reader`` the input's :func:`start_reading` (one process), if begun."""
    import torch

    from torchsvs.recipes import Settings
    from torchsvs.tracking import track_file

    if _COLLECT_AFTER_IMPORTS:  # (the modules' objects stay: none to collect among them)
        gc.freeze()
        gc.enable()
    torch.set_num_threads(args.threads)
    try:
        if reader is not None:  # (read while the lines above imported)
            args.columns = described_columns(args, reader.description())
        columns = getattr(args, "columns", None) or _columns(args)
        # (with a --save file as --checkpoint, its own settings: track_plan.checkpoint_settings)
        settings = Settings(
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
            step_q=not args.no_step_q,
            outliers=not args.keep_outliers,
            noise_column=args.noise_col,
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
            "precision": args.precision,
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
                whole=_whole(args),
                progress=not args.quiet,
                blocks=reader,
                **common,
            )
    except (ValueError, TypeError, FileNotFoundError) as err:
        raise SystemExit(f"torchsvs track: {err}") from err
    finally:
        if reader is not None:  # (an error before the run: the reading stops)
            reader.close()
    if run is not None and not args.quiet:  # None: a process launched by rank 0
        print(run.summary(), file=sys.stderr)
