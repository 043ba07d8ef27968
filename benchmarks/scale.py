"""Track datasets at scale: one process, ``--processes 2``, Spark ``local[2]`` and Dask on one
Parquet dataset, beside the floor of reading and writing it with pyarrow.

Writes a dataset of ``--rows`` rows (tracks of ``--steps`` 1 s scans, a directory of
``--files`` Parquet files, each track in one file), then runs, each in a child process timed
by ``/usr/bin/time`` (wall time and peak resident memory):

* the floor: ``pyarrow.parquet`` reads every file and writes the output's columns (id, time and
  four float32 estimates), nothing else;
* ``torchsvs track DIR -o OUT --estimator E --meas-std 50`` (one process, streaming), and with
  ``--shared-q --keep-outliers`` (one Kalman pass per track and the error estimate's);
* ``torchsvs track FILE --processes 2`` (rank 0 reads the dataset whole: the smaller sizes);
* Spark ``local[2]`` and a Dask ``LocalCluster`` of 2 workers (:mod:`torchsvs.engines`).

Each engine also runs on a dataset of ``--small`` rows: the difference gives its cost per row
and the small run its start-up, the constants of the projection ``T(R, N) = s + R c / N``
(``R`` rows, ``N`` executors of 2 cores like these). Results: ``benchmarks/scale.md``.

    python -m benchmarks.scale [--rows 10000000] [--small 200000] [--engines ...]
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

from benchmarks.million_tracks import write_tracks

HERE = Path(__file__).resolve().parent
ENGINES = ("floor", "one", "one-lean", "processes", "spark", "dask")
#: Rows above which ``--processes 2`` is not run (rank 0 holds the dataset whole).
PROCESSES_MAX_ROWS = 20_000_000
#: Rows per executor and year of a projection's example: 10 billion rows.
PROJECTED_ROWS = 10_000_000_000


@dataclass
class Measured:
    """One engine's run on one dataset."""

    engine: str
    rows: int
    seconds: float  #: wall time of the child process
    peak_gib: float  #: its peak resident memory (children of Spark's JVM not included)
    phases: dict[str, float] = field(default_factory=dict)  #: what the run itself reports


def write_dataset(folder: Path, rows: int, files: int, steps: int = 100, seed: int = 0) -> None:
    """``rows`` rows of tracks of ``steps`` scans in ``files`` Parquet files (each track in one
    file, its rows together), seeded."""
    folder.mkdir(parents=True, exist_ok=True)
    tracks = max(1, rows // steps)
    per_file = -(-tracks // files)
    for k in range(files):
        count = min(per_file, tracks - k * per_file)
        if count <= 0:
            break
        write_tracks(
            folder / f"part-{k:05d}.parquet",
            count,
            steps,
            seed=seed + k,
            first_id=k * per_file,
        )


def timed_child(command: list[str], env: dict[str, str] | None = None) -> tuple[float, float]:
    """Runs ``command`` under ``/usr/bin/time``: its wall seconds and peak memory (GiB)."""
    with tempfile.NamedTemporaryFile("r", suffix=".time") as report:
        start = time.perf_counter()
        subprocess.run(
            ["/usr/bin/time", "-f", "%M", "-o", report.name, *command],
            check=True,
            env={**os.environ, **(env or {})},
            stdout=subprocess.DEVNULL,
        )
        seconds = time.perf_counter() - start
        peak_kib = float(report.read().strip().splitlines()[-1])
    return seconds, peak_kib / 2**20


def floor(source: Path, target: Path) -> dict[str, float]:
    """pyarrow alone: read every file of ``source``, write id, time and four float32 columns
    per file to ``target`` (the output ``torchsvs track`` writes), nothing in between."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    target.mkdir(parents=True, exist_ok=True)
    reading = writing = 0.0
    for path in sorted(source.glob("*.parquet")):
        tick = time.perf_counter()
        table = pq.read_table(path)
        reading += time.perf_counter() - tick
        x = table.column("x").cast(pa.float32())
        y = table.column("y").cast(pa.float32())
        out = pa.table(
            {
                "track_id": table.column("track_id"),
                "time": table.column("time"),
                "x": x,
                "vx": x,
                "y": y,
                "vy": y,
            }
        )
        tick = time.perf_counter()
        pq.write_table(out, target / path.name)
        writing += time.perf_counter() - tick
    return {"reading": reading, "writing": writing}


def run_engine(engine: str, source: Path, target: Path, estimator: str) -> dict[str, float]:
    """One engine on ``source`` (in this process: the child :func:`measure` starts)."""
    if engine == "floor":  # pyarrow alone (no torch imported)
        return floor(source, target)
    import torch

    torch.set_num_threads(1)
    from torchsvs.recipes import Settings

    settings = Settings(estimator=estimator, meas_var=[2500.0, 2500.0])
    if engine == "spark":
        return _spark(source, target, settings)
    if engine == "dask":
        return _dask(source, target, settings)
    raise ValueError(f"engine: expected one of {ENGINES}, got {engine!r}")


def _spark(source: Path, target: Path, settings: object) -> dict[str, float]:
    """Spark ``local[2]``: plan on 2,000 whole tracks sampled by id, then read, shuffle by id,
    estimate and write in one action (:func:`torchsvs.engines.spark.parquet_to_parquet`)."""
    from pyspark.sql import SparkSession

    from torchsvs.engines.spark import parquet_to_parquet, plan_spark

    os.environ.setdefault("PYSPARK_PYTHON", sys.executable)
    os.environ.setdefault("SPARK_LOCAL_IP", "127.0.0.1")
    tick = time.perf_counter()
    spark = (
        SparkSession.builder.master("local[2]")
        .config("spark.driver.memory", "4g")
        .config("spark.sql.shuffle.partitions", "8")
        .config("spark.ui.enabled", "false")
        .config("spark.ui.showConsoleProgress", "false")
        .getOrCreate()
    )
    spark.sparkContext.setLogLevel("ERROR")
    started = time.perf_counter() - tick
    try:
        tick = time.perf_counter()
        plan = plan_spark(spark.read.parquet(str(source)), settings)
        planned = time.perf_counter() - tick
        _, seconds = parquet_to_parquet(spark, str(source), str(target), plan)
    finally:
        spark.stop()
    return {"start-up": started, "settings": planned, **seconds}


def _dask(source: Path, target: Path, settings: object) -> dict[str, float]:
    """Dask on a ``LocalCluster`` of 2 single-threaded worker processes: plan on the first
    file's tracks, then read, shuffle by id, estimate and write in one compute
    (:func:`torchsvs.engines.dask.parquet_to_parquet`)."""
    import logging

    import pandas as pd
    from distributed import Client, LocalCluster

    from torchsvs.engines.dask import parquet_to_parquet
    from torchsvs.track_plan import plan_tracks

    logging.getLogger("distributed").setLevel(logging.ERROR)
    tick = time.perf_counter()
    cluster = LocalCluster(
        n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0"
    )
    client = Client(cluster)
    started = time.perf_counter() - tick
    try:
        tick = time.perf_counter()
        first = sorted(source.glob("*.parquet"))[0]
        plan = plan_tracks(pd.read_parquet(first), settings)
        planned = time.perf_counter() - tick
        _, seconds = parquet_to_parquet(str(source), str(target), plan)
    finally:
        client.close()
        cluster.close()
    return {"start-up": started, "settings": planned, **seconds}


@functools.cache
def installed_bytecode() -> None:
    """Compiles torchsvs's modules to bytecode once, as installing a wheel does (pip compiles
    what it installs): a checkout installed in place (``pip install -e``) where
    ``PYTHONDONTWRITEBYTECODE`` is set, as on these machines, compiles every module at every
    start, 0.2 s of each ``torchsvs track`` that a user's installed copy does not spend."""
    import compileall

    import torchsvs

    compileall.compile_dir(Path(torchsvs.__file__).parent, quiet=1)


def measure(engine: str, source: Path, rows: int, work: Path, estimator: str) -> Measured:
    """``engine`` on the dataset ``source`` in a child process (torchsvs's modules compiled
    first, :func:`installed_bytecode`)."""
    installed_bytecode()
    target = work / f"out-{engine}"
    shutil.rmtree(target, ignore_errors=True)
    phases: dict[str, float] = {}
    if engine in ("one", "one-lean", "processes"):
        data = source if engine != "processes" else work / "whole.parquet"
        out = target if engine != "processes" else work / "out-processes.parquet"
        command = [sys.executable, "-m", "torchsvs.cli", "track", str(data), "-o", str(out)]
        command += ["--estimator", estimator, "--meas-std", "50", "--quiet", "--force"]
        if engine == "one-lean":
            command += ["--shared-q", "--keep-outliers"]
        if engine == "processes":
            command += ["--processes", "2"]
        seconds, peak = timed_child(command)
        from torchsvs.track_run import summary_path  # (not at the top: the floor's child
        # imports this module, and torch would add a second to its wall time)

        summary = json.loads(summary_path(out).read_text())
        phases = {k: float(v) for k, v in summary["phases"].items()}
    else:
        report = work / f"{engine}.json"
        command = [sys.executable, "-m", "benchmarks.scale", "--run-engine", engine]
        command += [str(source), str(target), estimator, str(report)]
        seconds, peak = timed_child(command)
        phases = json.loads(report.read_text())
    return Measured(engine, rows, seconds, peak, phases)


def whole_file(source: Path, target: Path) -> None:
    """The dataset as one Parquet file (for ``--processes``, which reads a file whole)."""
    import pyarrow.parquet as pq

    writer = None
    for path in sorted(source.glob("*.parquet")):
        table = pq.read_table(path)
        writer = writer or pq.ParquetWriter(target, table.schema)
        writer.write_table(table)
    assert writer is not None
    writer.close()


def working(found: Measured) -> float:
    """The seconds a run spent on its rows (reading, shuffling, estimating, writing): an
    engine's action (``run``), or the phases ``torchsvs track`` reports (where reading and
    writing run beside the estimating, its ``waiting`` for them in their place); else its wall
    time."""
    if "run" in found.phases:
        return found.phases["run"]
    names = ("reading", "estimating", "gathering", "writing")
    if "waiting" in found.phases:
        names = ("estimating", "gathering", "waiting")
    spent = [found.phases[k] for k in names if k in found.phases]
    return sum(spent) if spent else found.seconds


def projection(big: Measured, small: Measured) -> tuple[float, float]:
    """The start-up ``s`` (seconds) and cost per row ``c`` (seconds) of ``T = s + R c``: ``c``
    from the two runs' working seconds (:func:`working`), ``s`` the rest of the small run."""
    c = (working(big) - working(small)) / max(big.rows - small.rows, 1)
    return max(small.seconds - small.rows * c, 0.0), c


def report(runs: list[Measured], options: str, path: Path) -> str:
    """The markdown report."""
    big = max(r.rows for r in runs)
    small = min(r.rows for r in runs)
    at = {(r.engine, r.rows): r for r in runs}
    floor_big = at.get(("floor", big))
    lines = [
        f"# Track datasets at scale: {big:,} rows",
        "",
        f"Generated by `python -m benchmarks.scale {options}`. Each run is a child process "
        "timed with `/usr/bin/time` (wall, peak resident memory of that process: Spark's JVM "
        "and Dask's worker processes are separate and not included). × floor (wall): over the "
        "pyarrow child's wall time (its interpreter and imports included, as every child's); "
        "× floor (read + write): over the seconds pyarrow spends reading and writing alone. "
        "`torchsvs track` reads the next file and writes the last one beside the estimating "
        "(its phases overlap; `waiting`: the seconds the estimating waited for them). "
        "Machine: 2 cores, shared.",
        "",
        "| engine | rows | wall s | × floor (wall) | × floor (read + write) | µs per row "
        "| peak GiB | phases (s) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in sorted(runs, key=lambda r: (-r.rows, ENGINES.index(r.engine))):
        base = at.get(("floor", r.rows))
        ratio = f"{r.seconds / base.seconds:.2f}" if base else "—"
        io = sum(base.phases.get(k, 0.0) for k in ("reading", "writing")) if base else 0.0
        io_ratio = f"{r.seconds / io:.2f}" if io > 0 else "—"
        phases = ", ".join(f"{k} {v:.1f}" for k, v in r.phases.items() if isinstance(v, float))
        lines.append(
            f"| {r.engine} | {r.rows:,} | {r.seconds:.1f} | {ratio} | {io_ratio} | "
            f"{1e6 * r.seconds / r.rows:.2f} | {r.peak_gib:.2f} | {phases} |"
        )
    lines += ["", "## Cost model", ""]
    lines.append(
        "T(R, N) = s + R·c / N: cost per row `c` from the difference between the working "
        f"seconds (reading, shuffling, estimating, writing) of the {big:,}-row and "
        f"{small:,}-row runs, start-up `s` the rest of the small run's wall time (the "
        "interpreter, imports, a JVM or cluster, the plan); `N` executors of 2 cores like "
        "these, each streaming its share. Projected: 10 billion rows."
    )
    lines += ["", "| engine | s (s) | c (µs/row) | 10 G rows, N = 1 | N = 10 | N = 100 |"]
    lines.append("|---|---|---|---|---|---|")
    for engine in ENGINES:
        if (engine, big) in at and (engine, small) in at and big != small:
            s, c = projection(at[(engine, big)], at[(engine, small)])
            hours = [(s + PROJECTED_ROWS * c / n) / 3600 for n in (1, 10, 100)]
            lines.append(
                f"| {engine} | {s:.1f} | {1e6 * c:.2f} | "
                + " | ".join(f"{h:.2f} h" for h in hours)
                + " |"
            )
    if floor_big is not None:
        lines += ["", f"Floor at {big:,} rows: {floor_big.seconds:.1f} s wall."]
    text = "\n".join(lines) + "\n"
    path.write_text(text)
    return text


def main(argv: list[str] | None = None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["--run-engine"]:  # the child of measure()
        engine, source, target, estimator, out = argv[1:6]
        phases = run_engine(engine, Path(source), Path(target), estimator)
        Path(out).write_text(json.dumps(phases))
        return
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rows", type=int, default=10_000_000)
    parser.add_argument("--small", type=int, default=200_000)
    parser.add_argument("--files", type=int, default=10)
    parser.add_argument("--estimator", default="ks")
    parser.add_argument("--engines", default=",".join(ENGINES))
    parser.add_argument("--workdir", default=None, help="keep the datasets here")
    parser.add_argument("--out", default=str(HERE / "scale.md"))
    args = parser.parse_args(argv)
    engines = args.engines.split(",")
    unknown = [e for e in engines if e not in ENGINES]
    if unknown:
        parser.error(f"--engines: expected names among {ENGINES}, got {unknown}")
    work = Path(args.workdir or tempfile.mkdtemp(prefix="scale-"))
    runs = []
    for rows in sorted({args.small, args.rows}):
        source = work / f"tracks-{rows}"
        if not source.exists():
            tick = time.perf_counter()
            write_dataset(source, rows, args.files if rows == args.rows else 2)
            print(f"{rows:,} rows written in {time.perf_counter() - tick:.0f} s", flush=True)
        runs_dir = work / f"runs-{rows}"
        runs_dir.mkdir(parents=True, exist_ok=True)
        if "processes" in engines and rows <= PROCESSES_MAX_ROWS:
            whole_file(source, runs_dir / "whole.parquet")
        for engine in engines:
            if engine == "processes" and rows > PROCESSES_MAX_ROWS:
                continue
            found = measure(engine, source, rows, runs_dir, args.estimator)
            runs.append(found)
            print(
                f"{engine} on {rows:,} rows: {found.seconds:.1f} s, {found.peak_gib:.2f} GiB",
                flush=True,
            )
    options = " ".join(argv)
    print(report(runs, options, Path(args.out)))
    if args.workdir is None:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
