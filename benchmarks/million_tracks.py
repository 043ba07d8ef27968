"""A million tracks through ``torchsvs track`` in bounded memory.

Writes a file of ``--tracks`` simulated nearly-constant-velocity tracks of ``--steps`` scans
(string ids, 1 s scans, 50 m noise, rows of each track together) in chunks, then runs
``torchsvs track`` on it in a child process and reports the child's peak resident memory (from
``getrusage``), wall time and throughput.

    python -m benchmarks.million_tracks [--tracks 1000000] [--steps 100] [--format csv]
"""

from __future__ import annotations

import argparse
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def write_tracks(
    path: Path,
    tracks: int,
    steps: int,
    chunk: int = 50_000,
    seed: int = 0,
    ragged: bool = False,
    missing: float = 0.0,
    first_id: int = 0,
) -> None:
    """Seeded tracks (rows of each track together, 1 s scans, 50 m noise); ``ragged``: each
    track keeps its first ``steps/2`` to ``steps`` scans; ``missing``: share of empty
    position values; ids ``track-<n>`` from ``first_id`` on."""
    import pyarrow as pa
    import pyarrow.csv as pcsv
    import pyarrow.parquet as pq

    gen = np.random.default_rng(seed)
    writer = None
    for first in range(0, tracks, chunk):
        count = min(chunk, tracks - first)
        v = gen.normal(0, 60, (count, 1, 2))
        start = gen.normal(0, 5e4, (count, 1, 2))
        accel = np.cumsum(gen.normal(0, 0.5, (count, steps, 2)), axis=1)
        t = np.arange(steps, dtype=float)
        pos = start + v * t[None, :, None] + np.cumsum(accel, axis=1)
        z = pos + gen.normal(0, 50, pos.shape)
        if missing > 0:
            z[gen.random(z.shape) < missing] = np.nan
        numbers = np.arange(first_id + first, first_id + first + count)
        ids = np.repeat(np.char.add("track-", numbers.astype(str)), steps)
        kept = np.ones((count, steps), dtype=bool)
        if ragged:
            lengths = gen.integers(steps // 2, steps + 1, count)
            kept = t[None, :] < lengths[:, None]
        rows = kept.ravel()
        table = pa.table(
            {
                "track_id": ids[rows],
                "time": np.tile(t, count)[rows],
                "x": pa.array(z[..., 0].ravel()[rows].round(2), from_pandas=True),
                "y": pa.array(z[..., 1].ravel()[rows].round(2), from_pandas=True),
            }
        )
        if writer is None:
            writer = (
                pq.ParquetWriter(path, table.schema)
                if path.suffix == ".parquet"
                else pcsv.CSVWriter(path, table.schema)
            )
        writer.write_table(table)
    assert writer is not None
    writer.close()


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tracks", type=int, default=1_000_000)
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--format", choices=["csv", "parquet"], default="csv")
    parser.add_argument("--estimator", default="ks")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as workdir:
        source = Path(workdir) / f"tracks.{args.format}"
        target = Path(workdir) / f"estimates.{args.format}"
        start = time.perf_counter()
        write_tracks(source, args.tracks, args.steps)
        written = time.perf_counter() - start
        command = [
            sys.executable,
            "-m",
            "torchsvs.cli",
            "track",
            str(source),
            "-o",
            str(target),
            "--estimator",
            args.estimator,
            "--meas-std",
            "50",
            "--stream",
        ]
        start = time.perf_counter()
        subprocess.run(command, check=True)
        seconds = time.perf_counter() - start
        peak_kib = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
        rows = args.tracks * args.steps
        size = source.stat().st_size / 1e9
        print(
            f"{args.tracks} tracks × {args.steps} steps ({rows} rows, {size:.2f} GB "
            f"{args.format}, written in {written:.0f} s): torchsvs track --estimator "
            f"{args.estimator} took {seconds:.0f} s ({1e6 * seconds / rows:.2f} µs per row, "
            f"reading and writing included), peak memory {peak_kib / 2**20:.2f} GiB; output "
            f"{target.stat().st_size / 1e9:.2f} GB"
        )


if __name__ == "__main__":
    main()
