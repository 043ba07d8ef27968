"""``torchsvs track`` in two processes against one (``--processes 2``: Lightning's
``Trainer.predict`` with ``strategy="ddp"``, gloo, one intra-op thread per process).

Writes a seeded file of ragged tracks with empty values (:func:`benchmarks.million_tracks.
write_tracks`), then runs the command in fresh processes, start-up, reading and writing
included: one process with the command's default of one thread, one process with two threads,
and two processes, taking turns for ``--rounds`` rounds after a warm-up; the best of each counts.
The two-process output must be the same bytes as the one-process output. The phases are the
command's own timings (``TrackRun.phases``; rank 0's in two processes) from its best run.
Writes ``benchmarks/ddp_predict.md``.

    python -m benchmarks.ddp_predict [--tracks 4000] [--steps 300] [--rounds 2]
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import tempfile
import time
from functools import partial
from pathlib import Path

from benchmarks.million_tracks import write_tracks
from benchmarks.timing import alternating_best

ROOT = Path(__file__).resolve().parents[1]
#: name: (options, share of --tracks); the particle filter is far costlier per row.
CASES = {
    "ks (default)": (["--estimator", "ks"], 1.0),
    "svss": (["--estimator", "svss"], 1.0),
    "pf, 100 particles": (["--estimator", "pf", "--particles", "100"], 0.2),
}
#: The runs compared; the output of each must be the same bytes (same --max-cells, so the same
#: groups of tracks), but the first's: the command's defaults, to show what the groups cost.
RUNS = {
    "1 process, defaults": [],
    "1 process, 1 thread": ["--threads", "1"],
    "1 process, 2 threads": ["--threads", "2"],
    "2 processes × 1 thread": ["--threads", "1", "--processes", "2"],
}
#: Interpreter start, imports and exit: what one process of each path pays before and after.
IMPORTS = {
    "python -c 'import torchsvs.tracking' (one process)": "import torchsvs.cli, torchsvs.tracking",
    "python -c 'import torchsvs.training.predict' (each DDP process)": (
        "import torchsvs.cli, torchsvs.training.predict"
    ),
}


def track(source: Path, target: Path, options: list[str], record: list) -> None:
    """One ``torchsvs track`` run in a fresh interpreter; appends (wall seconds, phases)."""
    command = [sys.executable, "-m", "torchsvs.cli", "track", str(source), "-o", str(target)]
    command += ["--force"]  # the rounds write the same files
    command += ["--meas-std", "50", *options]
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    start = time.perf_counter()
    done = subprocess.run(command, env=env, capture_output=True, text=True)
    if done.returncode:  # say why, not only that it failed
        raise RuntimeError(f"{' '.join(command)} exited {done.returncode}:\n{done.stderr[-3000:]}")
    wall = time.perf_counter() - start
    line = next(t for t in done.stderr.splitlines() if t.startswith("phases: "))
    phases = {k: float(v) for k, v in re.findall(r"([\w -]+?) ([\d.]+) s", line[8:])}
    phases = {k.strip(", "): v for k, v in phases.items()}
    inside = float(re.search(r"([\d.]+) s in all", done.stderr).group(1))  # type: ignore[union-attr]
    phases["interpreter and imports"] = wall - inside
    phases["estimating CPU"] = float(re.search(r"([\d.]+) s CPU", done.stderr).group(1))  # type: ignore[union-attr]
    record.append((wall, phases))


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tracks", type=int, default=4000)
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument(
        "--max-cells",
        type=int,
        default=1 << 15,
        help="padded steps per group of tracks (several groups per process)",
    )
    keys = {case.split()[0].rstrip(","): case for case in CASES}  # ks, svss, pf
    parser.add_argument(
        "--cases",
        default=",".join(keys),
        help="comma-separated estimators of the table (ks, svss, pf; default: all), e.g. pf"
        " alone with more --tracks for a run where estimating dominates",
    )
    parser.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "ddp_predict.md")
    args = parser.parse_args(argv)
    chosen = [keys.get(c.strip(), c.strip()) for c in args.cases.split(",")]
    unknown = [c for c in chosen if c not in CASES]
    if unknown:
        parser.error(f"--cases: unknown {unknown}; expected some of {list(keys)}")
    results = {}
    with tempfile.TemporaryDirectory() as workdir:
        folder = Path(workdir)
        for case, (options, share) in CASES.items():
            if case not in chosen:
                continue
            tracks = max(2, round(share * args.tracks))
            source = folder / f"tracks_{tracks}.csv"
            if not source.exists():
                write_tracks(source, tracks, args.steps, seed=0, ragged=True, missing=0.02)
            rows = sum(1 for _ in source.open()) - 1
            records: dict[str, list] = {run: [] for run in RUNS}
            outputs = {run: folder / f"estimates_{i}.csv" for i, run in enumerate(RUNS)}
            grouped = ["--max-cells", str(args.max_cells)]
            calls = {
                run: partial(
                    track,
                    source,
                    outputs[run],
                    options + RUNS[run] + (grouped if RUNS[run] else []),
                    records[run],
                )
                for run in RUNS
            }
            best = alternating_best(calls, args.rounds, progress=case)
            compared = [out.read_bytes() for run, out in outputs.items() if RUNS[run]]
            same = all(out == compared[0] for out in compared)
            phases = {run: min(records[run], key=lambda r: r[0])[1] for run in RUNS}
            results[case] = (tracks, rows, best, phases, same)
            print(case, {k: round(v, 2) for k, v in best.items()}, "identical:", same)
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    imports = alternating_best(
        {
            name: partial(subprocess.run, [sys.executable, "-c", code], env=env, check=True)
            for name, code in IMPORTS.items()
        },
        args.rounds,
    )
    write_report(args, results, imports)


def write_report(args: argparse.Namespace, results: dict, imports: dict[str, float]) -> None:
    lines = [
        "# torchsvs track in two processes",
        "",
        f"Generated by `python -m benchmarks.ddp_predict --tracks {args.tracks} --steps "
        f"{args.steps} --rounds {args.rounds} --max-cells {args.max_cells}"
        + ("" if args.cases == "ks,svss,pf" else f" --cases {args.cases}")
        + "` on "
        f"{os.cpu_count()} cores (shared with other work; load average "
        f"{os.getloadavg()[0]:.1f} at the end). Seeded CSV "
        "of ragged tracks (each keeps its first steps/2 to steps scans), 2% empty values, "
        "`--meas-std 50`; wall time of the whole command in a fresh interpreter (start-up, "
        "reading, settings, estimating, writing), best of the rounds, runs taking turns. "
        "Two processes: `--processes 2` (Lightning `Trainer.predict`, DDP on gloo, one "
        "intra-op thread per process); the command's default is one process, one thread. "
        f"All runs but the first give `--max-cells {args.max_cells}` (padded steps per "
        "estimator call), so there are several groups of tracks per process; the first runs "
        "the command's defaults (2^19), to show what smaller groups cost one process. "
        "`same bytes`: the outputs of the runs with the same groups are identical.",
        "",
        "| estimator | tracks | rows | " + " | ".join(RUNS) + " | 1 process (best) ÷ 2 "
        "processes | same bytes |",
        "|---|---|---|" + "---|" * len(RUNS) + "---|---|",
    ]
    two = list(RUNS)[-1]
    for case, (tracks, rows, best, _, same) in results.items():
        baseline = min(v for k, v in best.items() if k != two)
        times = " | ".join(f"{best[run]:.1f} s" for run in RUNS)
        lines.append(
            f"| {case} | {tracks} | {rows:,} | {times} | {baseline / best[two]:.2f}× | "
            f"{'yes' if same else 'NO'} |"
        )
    lines += ["", "| start-up of one process | wall |", "|---|---|"]
    lines += [f"| {name} | {seconds:.1f} s |" for name, seconds in imports.items()]
    lines += [
        "",
        "Where the time goes (seconds, from the best run of each; two processes: rank 0's "
        "phases; `start-up` is rank 0's time from the call to every process having joined the "
        "process group: the trainer and what is left of rank 1's interpreter and imports; "
        "`reading`: rank 0's wait for its reading thread after the start-up, and the transfer "
        "of the tracks' steps to rank 1; `settings` includes rank 1 waiting for rank 0's "
        "broadcast; `estimating CPU`: the "
        "CPU time of the process while estimating, where `estimating` is its wall time):",
        "",
    ]
    names = ["interpreter and imports", "start-up", "reading", "settings", "estimating"]
    names += ["estimating CPU", "gathering", "writing", "other"]
    lines.append("| estimator | run | " + " | ".join(names) + " |")
    lines.append("|---|---|" + "---|" * len(names))
    for case, (_, _, _, phases, _) in results.items():
        for run, timed in phases.items():
            cells = [f"{timed[n]:.1f}" if n in timed else "" for n in names]
            lines.append(f"| {case} | {run} | " + " | ".join(cells) + " |")
    lines += ["", "## Reading the numbers", ""]
    lines += [reading(case, result) for case, result in results.items()]
    lines += ["", WHY]
    args.out.write_text("\n".join(lines) + "\n")
    print(f"wrote {args.out}")


def reading(case: str, result: tuple) -> str:
    """What bounds the speed-up of a case, from its own measurements."""
    _, _, best, phases, _ = result
    one, two = list(RUNS)[1], list(RUNS)[-1]
    single, double = phases[one], phases[two]
    total, estimating = best[one], single["estimating"]
    bound = total / (total - estimating / 2)
    ratio = min(v for k, v in best.items() if k != two) / best[two]
    verdict = "reaches" if ratio >= 1.6 else "misses"
    return (
        f"- **{case}** {verdict} the 1.6× target ({ratio:.2f}×). In one process (1 thread) "
        f"estimating takes {estimating:.1f} s of {total:.1f} s "
        f"({100 * estimating / total:.0f}%; {single['estimating CPU']:.1f} s of CPU): halving "
        f"only that would give at most {bound:.2f}×. Rank 0's half took "
        f"{double['estimating CPU']:.1f} s of CPU in {double['estimating']:.1f} s. Two "
        f"processes took {best[two]:.1f} s: on rank 0, interpreter, imports "
        f"and exit {double['interpreter and imports']:.1f} s (one process: "
        f"{single['interpreter and imports']:.1f} s), start-up of the run "
        f"{double['start-up']:.1f} s, reading {double['reading']:.1f} s (one process: "
        f"{single['reading']:.1f} s), settings {double['settings']:.1f} s, gathering "
        f"{double['gathering']:.1f} s, writing {double['writing']:.1f} s."
    )


WHY = """Where two processes lose time, in the order of the table's columns: every process
imports Lightning (one process does not need it; the start-up table above, with the
interpreter's teardown at exit, which the command skips). The command starts rank 1 before its
own imports, as `torchrun` does (Lightning joins processes created outside it), so rank 1's
interpreter and imports run beside rank 0's (`start-up`: what is left of rank 0's wait for rank
1 to join the process group). Rank 0 reads the file in a thread during that wait, and `reading`
is what is left of it after the start-up plus sending the tracks' steps to rank 1 (which reads
nothing). On a machine loaded by other work two processes get less than two cores (compare the
CPU and wall times of estimating); the settings (noise read off the data, or a fit) and the
output are computed and written once, on rank 0, while rank 1 waits or has finished. Only the
estimating phase is shared. So two processes can pay off only where estimating dominates a run
by far (long runs of the particle filters, or files much larger than here) on otherwise idle
cores; a 1.6× speed-up on the Kalman smoother or the SVSS would need more than a second
process and writing per process."""

if __name__ == "__main__":
    main()
