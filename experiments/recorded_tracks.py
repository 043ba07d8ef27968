"""Recorded tracks of several kinds: every estimator of ``torchsvs track``, run as a user would.

The sets (:mod:`experiments.recorded_sets`): airliners at their own report times and on 10 s
scans, 1 s scans, aircraft taxiing on the ground (slow targets, a stand-in for ships), other
aircraft at irregular report times, simulated hard turns; each measured with seeded Gaussian
noise σ from 10 to 100 m, written to a CSV ``track_id,time,x,y`` with the truth kept aside.

Every estimator the command offers (the choices of ``--estimator``, so ``auto`` is picked up
when it exists) runs in each mode of :data:`MODES`: with no options (the noise read off the
data), ``--fit``, ``--meas-std σ`` and ``--meas-std σ --fit``. A run is the command itself,
``torchsvs track IN -o OUT --estimator E ...``: by default ``torchsvs.cli.main`` in this process
(the same code, ``track_file`` underneath, without an interpreter start-up per run), with
``--via cli`` a ``python -m torchsvs.cli track`` subprocess. Each run is timed; its output is
scored against the truth: 2-D position RMSE (the root of the mean over rows of the squared
distance), rows without an estimate counted apart. A run the command refuses or that fails is
kept with its message. When ``track`` writes a summary beside its output
(``<output stem>.summary.json`` with ``estimated_position_rmse``), its truth-free estimate is
set beside the true RMSE and flagged where more than 15% off.

Writes ``experiments/results/recorded_tracks.md`` (+ ``.png``, ``_examples.png``, ``.json``;
another stem with ``--name``).

    python -m experiments.recorded_tracks [--kinds own,taxi] [--rows 5000] [--via cli]
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import math
import re
import resource
import subprocess
import sys
import tempfile
import time
import warnings
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import pandas as pd

from experiments.common import render
from experiments.recorded_sets import (
    CORRELATION_TIME,
    DEFAULT_KINDS,
    DEJITTER_WINDOW,
    HEAVY_DOF,
    KINDS,
    MIXED_RANGE,
    NOISE_KINDS,
    TURN_DT,
    BenchSet,
    build_sets,
    dejitter,
    describe,
)

RESULTS = Path(__file__).parent / "results"
ROOT = Path(__file__).resolve().parents[1]

#: Modes of a run: the options added to ``--estimator E`` for noise level σ.
MODES: dict[str, Callable[[float], list[str]]] = {
    "default": lambda sigma: [],
    "--fit": lambda sigma: ["--fit"],
    "--meas-std σ": lambda sigma: ["--meas-std", f"{sigma:g}"],
    "--meas-std σ --fit": lambda sigma: ["--meas-std", f"{sigma:g}", "--fit"],
    "--no-velocity": lambda sigma: ["--no-velocity"],
    "--no-velocity --fit": lambda sigma: ["--no-velocity", "--fit"],
    # each row's own noise, as the sensor states it (the sets of --noise other than white)
    "--noise-col sigma": lambda sigma: ["--noise-col", "sigma"],
}
#: Modes run by default (``--modes``): the others are asked for by name. ``--no-velocity`` is the
#: SVSF family's H⁺ mode (the papers' SVSS, no velocity pseudo-measurement), beside the variable
#: boundary layer that ``track`` runs by default.
DEFAULT_MODES = ("default", "--fit", "--meas-std σ", "--meas-std σ --fit")
#: A truth-free estimate further than this from the true RMSE (relative) is flagged.
ESTIMATE_TOLERANCE = 0.15
#: ``auto`` is compared with the best single estimator: this ratio or less is "within".
AUTO_TOLERANCE = 1.03


@dataclass
class Run:
    """One ``torchsvs track`` run on one set and what it gave."""

    set: str
    estimator: str
    mode: str
    argv: list[str]
    rmse: float = math.nan  #: 2-D position RMSE over the rows with an estimate (m)
    raw: float = math.nan  #: 2-D RMSE of the measurements (m)
    missing: int = 0  #: rows without an estimate
    rows: int = 0
    seconds: float = math.nan  #: wall time of the run
    cpu_seconds: float = math.nan  #: its CPU time (the wall time on an idle core)
    sigma_used: float = math.nan  #: the noise std the run used (read off its log; m per axis)
    estimated: float = math.nan  #: truth-free estimate of the position RMSE (summary file)
    measurement: float = math.nan  #: the summary's measurement RMSE
    chosen: str = ""  #: the estimator the summary says was run (``auto``)
    error: str = ""  #: why the run gave nothing (the command's message)
    warnings: list[str] = field(default_factory=list)
    code: str = ""  #: the commit the run ran on (``git log -1``)
    via: str = "inprocess"  #: in this process or through a subprocess

    @property
    def ratio(self) -> float:
        return self.rmse / self.raw

    @property
    def estimate_ratio(self) -> float:
        return self.estimated / self.rmse

    @property
    def ok(self) -> bool:
        return not self.error and math.isfinite(self.rmse)

    @property
    def below_raw(self) -> bool:
        return self.ok and self.missing == 0 and self.rmse < self.raw


# --- what the command offers -------------------------------------------------------------------


def estimator_choices(parser: argparse.ArgumentParser | None = None) -> tuple[list[str], str]:
    """The ``--estimator`` choices of ``torchsvs track`` (those of
    :data:`torchsvs.estimator_names.ESTIMATORS` first, in its order, then any other, such as ``auto``)
    and its default."""
    from torchsvs.estimator_names import ESTIMATORS
    from torchsvs.track_options import track_parser

    parser = parser or track_parser()
    action = next(a for a in parser._actions if "--estimator" in a.option_strings)
    choices = list(action.choices or ESTIMATORS)
    ordered = [c for c in ESTIMATORS if c in choices] + [c for c in choices if c not in ESTIMATORS]
    return ordered, str(action.default)


# --- one run -----------------------------------------------------------------------------------


def summary_path(target: Path) -> Path:
    """Where ``track`` writes its summary: ``<output stem>.summary.json`` beside the output."""
    return target.with_name(target.stem + ".summary.json")


class Command(NamedTuple):
    """What one ``torchsvs track`` command did."""

    seconds: float  #: wall time
    cpu_seconds: float  #: CPU time (its process or subprocess): the wall time on an idle core
    log: str  #: its standard error
    error: str  #: its message when it failed or refused ("" when it succeeded)
    warnings: list[str]  #: warnings (in-process: raised; in a subprocess: lines naming one)


def run_command(argv: list[str], via: str = "inprocess") -> Command:
    """``torchsvs track ARGV`` in this process (``torchsvs.cli.main``) or as a subprocess."""
    start = time.perf_counter()
    if via == "cli":
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        done = subprocess.run(
            [sys.executable, "-m", "torchsvs.cli", "track", *argv],
            capture_output=True,
            text=True,
            cwd=ROOT,
        )
        seconds = time.perf_counter() - start
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        cpu = after.ru_utime + after.ru_stime - before.ru_utime - before.ru_stime
        lines = [line for line in done.stderr.splitlines() if line.strip()]
        error = "" if done.returncode == 0 else (lines[-1] if lines else f"exit {done.returncode}")
        caught = [line.strip() for line in lines if "Warning" in line]
        return Command(seconds, cpu, done.stderr, error, caught)
    if via != "inprocess":
        raise ValueError(f"via: expected 'inprocess' or 'cli', got {via!r}")
    from torchsvs import cli

    stream = io.StringIO()
    error = ""
    cpu_start = time.process_time()
    with warnings.catch_warnings(record=True) as seen, contextlib.redirect_stderr(stream):
        warnings.simplefilter("always")  # every run shows its own warnings, not only the first
        try:
            cli.main(["track", *argv])
        except SystemExit as stop:
            if stop.code not in (None, 0):
                error = str(stop.code)
        except Exception as err:  # a crash is a result too: shown, not raised
            error = f"{type(err).__name__}: {err}"
    seconds, cpu = time.perf_counter() - start, time.process_time() - cpu_start
    messages = [f"{w.category.__name__}: {w.message}" for w in seen]
    return Command(seconds, cpu, stream.getvalue(), error, messages)


_MEAS_VAR = re.compile(r"^settings: .*?meas_var=\[([^\]]*)\]", re.MULTILINE)


def sigma_used(log: str) -> float:
    """The measurement noise std (m per axis, root of the mean variance) of the settings line a
    run printed (NaN when there is none)."""
    found = _MEAS_VAR.findall(log)
    if not found:
        return math.nan
    try:
        values = [float(v) for v in found[-1].split(",")]
    except ValueError:
        return math.nan
    return math.sqrt(sum(values) / len(values))


def read_summary(target: Path) -> dict[str, Any]:
    """The summary ``track`` wrote beside ``target``, or ``{}``."""
    path = summary_path(target)
    if not path.is_file():
        return {}
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return {}
    return data if isinstance(data, dict) else {}


def summary_number(summary: dict[str, Any], key: str) -> float:
    """A number of the summary: at its top level, else in its ``overall`` part."""
    for part in (summary, summary.get("overall")):
        if isinstance(part, dict) and isinstance(part.get(key), int | float):
            return float(part[key])
    return math.nan


def score(output: pd.DataFrame, truth: pd.DataFrame) -> tuple[float, int]:
    """2-D position RMSE of ``output``'s ``x, y`` against the truth over the rows with an
    estimate, and the number of truth rows without one (NaN, or no output row). Rows are
    matched in order when the ids and times agree row by row, else by ``(track_id, time)``
    (times to the microsecond)."""

    def keyed(table: pd.DataFrame) -> pd.DataFrame:
        return pd.DataFrame(
            {
                "track_id": table["track_id"].astype(str).to_numpy(),
                "time": table["time"].to_numpy(float).round(6),
            }
        )

    mine, theirs = keyed(truth), keyed(output)
    if len(output) == len(truth) and mine.equals(theirs):
        estimate = output[["x", "y"]].to_numpy(float)
    else:
        found = theirs.assign(x=output["x"].to_numpy(float), y=output["y"].to_numpy(float))
        found = found.drop_duplicates(["track_id", "time"])
        merged = mine.merge(found, on=["track_id", "time"], how="left")
        estimate = merged[["x", "y"]].to_numpy(float)
    error = estimate - truth[["x", "y"]].to_numpy(float)
    has = np.isfinite(error).all(axis=1)
    rmse = float(np.sqrt(np.mean((error[has] ** 2).sum(axis=1)))) if has.any() else math.nan
    return rmse, int((~has).sum())


@dataclass(frozen=True)
class Job:
    """What one run needs (picklable, for worker processes)."""

    set: str
    sigma: float
    raw: float
    source: str
    truth: str
    estimator: str
    mode: str
    target: str
    via: str
    code: str = ""  #: the commit it runs on


def run_job(job: Job) -> Run:
    """One ``torchsvs track`` run of a job, scored."""
    import torch

    torch.set_num_threads(1)
    target = Path(job.target)
    for old in (target, summary_path(target)):
        old.unlink(missing_ok=True)  # a fresh output: track may refuse to replace a file
    argv = [job.source, "-o", str(target), "--estimator", job.estimator]
    argv += MODES[job.mode](job.sigma)
    done = run_command(argv, job.via)
    error = done.error
    shown = ["torchsvs", "track", "IN", "-o", "OUT", *argv[3:]]
    result = Run(job.set, job.estimator, job.mode, shown, raw=job.raw, seconds=done.seconds)
    result.cpu_seconds = done.cpu_seconds
    result.code, result.via = job.code, job.via
    result.warnings = list(dict.fromkeys(done.warnings))
    result.sigma_used = sigma_used(done.log)
    truth = pd.read_csv(job.truth)
    result.rows = len(truth)
    if not error and not target.is_file():
        error = "no output file written"
    if error:
        result.error = " ".join(error.split())
        result.missing = len(truth)
        return result
    try:
        output = pd.read_csv(target)
        result.rmse, result.missing = score(output, truth)
    except (KeyError, ValueError) as err:
        result.error = f"output not readable: {err}"
        result.missing = len(truth)
    summary = read_summary(target)
    result.estimated = summary_number(summary, "estimated_position_rmse")
    result.measurement = summary_number(summary, "measurement_rmse")
    chosen = summary.get("estimator")
    result.chosen = chosen if isinstance(chosen, str) and chosen != job.estimator else ""
    told = summary.get("warnings")
    if isinstance(told, list):  # what the run warned about, as its summary says
        result.warnings = list(dict.fromkeys([*result.warnings, *map(str, told)]))
    return result


def run_all(
    sets: Sequence[BenchSet],
    estimators: Sequence[str],
    modes: Sequence[str],
    workdir: Path,
    via: str = "inprocess",
    jobs: int = 1,
    progress: bool = True,
) -> list[Run]:
    """Every estimator × mode on every set (``jobs`` worker processes; 1: in this one).

    Each result is appended to ``workdir/runs.jsonl`` as it comes; a run already there (same
    set, estimator, mode, code and way of running) is taken from it instead of run again, so an
    interrupted benchmark resumes where it stopped when given the same work folder."""
    from tqdm.auto import tqdm

    workdir.mkdir(parents=True, exist_ok=True)
    journal = workdir / "runs.jsonl"
    code = _git_head()
    done: dict[tuple[str, str, str], Run] = {}
    if journal.is_file():
        for line in journal.read_text().splitlines():
            try:
                run = Run(**json.loads(line))
            except (ValueError, TypeError):
                continue  # a line cut short by the interruption
            if run.code == code and run.via == via:
                done[(run.set, run.estimator, run.mode)] = run
    work: list[Job] = []
    for bench in sets:
        source, truth = bench.write(workdir / "sets")
        raw = describe(bench).raw_rmse
        for estimator in estimators:
            for mode in modes:
                if (bench.name, estimator, mode) in done:
                    continue
                slug = re.sub(r"[^a-z0-9]+", "_", f"{estimator} {mode}".lower()).strip("_")
                target = workdir / "out" / bench.slug / f"{slug}.csv"
                target.parent.mkdir(parents=True, exist_ok=True)
                work.append(
                    Job(
                        bench.name,
                        bench.sigma,
                        raw,
                        str(source),
                        str(truth),
                        estimator,
                        mode,
                        str(target),
                        via,
                        code,
                    )
                )
    bar = tqdm(total=len(work), desc="runs", unit="run", disable=not progress)
    with open(journal, "a") as log:

        def keep(result: Run) -> None:
            done[(result.set, result.estimator, result.mode)] = result
            log.write(json.dumps(asdict(result)) + "\n")
            log.flush()
            bar.update()

        if jobs <= 1:
            for job in work:
                bar.set_postfix_str(f"{job.set} {job.estimator} {job.mode}")
                keep(run_job(job))
        else:
            with ProcessPoolExecutor(max_workers=jobs) as pool:
                for result in pool.map(run_job, work):
                    keep(result)
    bar.close()
    return [
        done[(b.name, e, m)]
        for b in sets
        for e in estimators
        for m in modes
        if (b.name, e, m) in done
    ]


# --- the report --------------------------------------------------------------------------------


def _f(value: float, digits: int = 1) -> str:
    if not math.isfinite(value):
        return "—"
    return f"{value:,.{digits}f}"


def ratio_cell(run: Run | None) -> str:
    """A run's ratio to raw, bold when not below raw, ✗ when it gave nothing."""
    if run is None:
        return ""
    if not run.ok:
        return "✗"
    text = f"{run.ratio:.2f}"
    if run.missing:
        text += f" ({run.missing} no est.)"
    return text if run.below_raw else f"**{text}**"


def table(header: Sequence[str], rows: Sequence[Sequence[object]]) -> list[str]:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return lines


def sources_text(files: Sequence[str]) -> str:
    """Sample files (``folder/name``) in short: a folder's count when it gives several."""
    folders: dict[str, list[str]] = {}
    for name in files:
        folder, _, _ = name.rpartition("/")
        folders.setdefault(folder, []).append(name)
    return ", ".join(
        names[0] if len(names) == 1 else f"{folder}/ ({len(names)} files)"
        for folder, names in folders.items()
    )


def sets_section(sets: Sequence[BenchSet]) -> str:
    """The sets' table and how each kind's truth was made."""
    rows = []
    for bench in sets:
        d = describe(bench)
        rows.append(
            [
                bench.name,
                bench.kind.title,
                sources_text(bench.truth.sources),
                d.tracks,
                f"{d.rows:,}",
                " / ".join(f"{v:.3g}" for v in d.interval[:3]) + f" (≤ {d.interval[3]:.3g})",
                " / ".join(f"{v:.3g}" for v in d.speed),
                f"{bench.sigma:g}",
                _f(d.raw_rmse),
            ]
        )
    header = [
        "set",
        "kind",
        "sources",
        "tracks",
        "rows",
        "interval s",
        "speed m/s",
        "σ m",
        "raw RMSE m",
    ]
    truths = []
    seen = set()
    for bench in sets:
        kind = bench.kind
        if kind.name in seen:
            continue
        seen.add(kind.name)
        rough = bench.truth.roughness
        roughness = ""
        if rough and math.isfinite(rough.get("along", math.nan)):
            roughness = _text(
                "truth_roughness", along=f"{rough['along']:.1f}", across=f"{rough['across']:.1f}"
            )
        note = _text("truth_note", note=kind.note[0].upper() + kind.note[1:]) if kind.note else ""
        truths.append(
            _text(
                "truth",
                kind=kind.name,
                title=kind.title,
                builder=" ".join((getattr(kind.build, "func", kind.build).__doc__ or "").split()),
                note=note,
                counts=", ".join(f"{k} {v:,}" for k, v in bench.truth.counts.items()),
                roughness=roughness,
            )
        )
    noise = NOISE_TEXT[sets[0].noise if sets else "white"]
    return _text(
        "sets", noise=noise, table="\n".join(table(header, rows)), truths="\n".join(truths)
    )


#: What the report says of the measurements' noise, by kind (:data:`~experiments.
#: recorded_sets.NOISE_KINDS`).
NOISE_TEXT = {
    "white": "independent Gaussian noise σ",
    "mixed": (
        f"independent Gaussian noise, each track's own σ drawn from σ/{MIXED_RANGE:g} to "
        f"σ×{MIXED_RANGE:g} (log-uniform: sensors of different quality in one file)"
    ),
    "heavy": (
        f"independent noise of Student's t with {HEAVY_DOF:g} degrees of freedom, of standard "
        "deviation σ (a heavy-tailed sensor)"
    ),
    "correlated": (
        f"Gaussian noise σ correlated between a track's reports as exp(-Δt / "
        f"{CORRELATION_TIME:g} s) (a GPS's slowly wandering error, which positions alone "
        "cannot tell from motion)"
    ),
}


def truth_check(along: float = 25.0, seed: int = 0) -> dict[str, float]:
    """The re-timing (:func:`~experiments.recorded_sets.dejitter`) on simulated 1 s tracks
    (the turning kind's turns, 1 s scans) whose reports are moved along the track by a white
    error of ``along`` m: the truth's 2-D RMS error as recorded and after re-timing."""
    import torch

    from torchsvs.scenarios import ManeuverRanges, random_maneuvers

    ranges = ManeuverRanges(
        steps=600,
        dt=1.0,
        speed=(100.0, 250.0),
        segment_duration=(10.0, 60.0),
        turn_rate_deg=(3.0, 6.0),
        kind_weights=(0.35, 0.65, 0.0, 0.0),
    )
    batch = random_maneuvers(10, ranges, torch.Generator().manual_seed(seed)).truth.numpy()
    rng = np.random.default_rng(seed)
    before, after = [], []
    t = np.arange(1, ranges.steps + 1, dtype=float)
    for track in batch:
        position, velocity = track[:, [0, 2]], track[:, [1, 3]]
        unit = velocity / np.linalg.norm(velocity, axis=1, keepdims=True)
        recorded = position + rng.normal(0.0, along, (len(t), 1)) * unit
        moved, _ = dejitter(t, recorded)
        before.append(((recorded - position) ** 2).sum(1))
        after.append(((moved - position) ** 2).sum(1))
    return {
        "before": float(np.sqrt(np.mean(np.concatenate(before)))),
        "after": float(np.sqrt(np.mean(np.concatenate(after)))),
    }


def by_key(runs: Sequence[Run]) -> dict[tuple[str, str, str], Run]:
    return {(r.set, r.estimator, r.mode): r for r in runs}


def headline(
    runs: Sequence[Run], sets: Sequence[str], estimators: Sequence[str], modes: Sequence[str]
) -> list[str]:
    index = by_key(runs)
    rows = []
    for estimator in estimators:
        for mode in modes:
            rows.append(
                [f"{estimator}", mode] + [ratio_cell(index.get((s, estimator, mode))) for s in sets]
            )
    return table(["estimator", "mode", *sets], rows)


def below_raw_section(
    runs: Sequence[Run], sets: Sequence[str], estimators: Sequence[str], modes: Sequence[str]
) -> list[str]:
    index = by_key(runs)
    rows = []
    for estimator in estimators:
        cells: list[object] = [estimator]
        for mode in modes:
            mine = [index[(s, estimator, mode)] for s in sets if (s, estimator, mode) in index]
            if not mine:
                cells.append("")
                continue
            failed = [r for r in mine if not r.ok]
            if len(failed) == len(mine):
                cells.append("✗ (" + _short(failed[0].error, 40) + ")")
                continue
            below = sum(r.below_raw for r in mine)
            worst = max((r for r in mine if r.ok), key=lambda r: r.ratio)
            text = f"{below}/{len(mine)}; worst {worst.ratio:.2f} ({worst.set})"
            cells.append(text if below == len(mine) else f"**{text}**")
        rows.append(cells)
    return table(["estimator", *modes], rows)


def _short(text: str, size: int) -> str:
    text = " ".join(text.split())
    return text if len(text) <= size else text[: size - 1] + "…"


def best_run(
    index: dict[tuple[str, str, str], Run], s: str, estimators: Sequence[str], mode: str
) -> Run | None:
    """The run of the lowest RMSE among ``estimators`` on set ``s`` in ``mode`` (runs that
    failed or left rows without an estimate do not count), or None."""
    done = [index.get((s, e, mode)) for e in estimators]
    usable = [r for r in done if r is not None and r.ok and not r.missing]
    return min(usable, key=lambda r: r.rmse) if usable else None


def best_section(
    runs: Sequence[Run], sets: Sequence[str], estimators: Sequence[str], modes: Sequence[str]
) -> list[str]:
    """Per set and mode: the best single estimator (RMSE, × raw), and ``auto``'s ratio to it."""
    index = by_key(runs)
    singles = [e for e in estimators if e != "auto"]
    has_auto = "auto" in estimators
    rows = []
    for s in sets:
        cells: list[object] = [s]
        for mode in modes:
            best = best_run(index, s, singles, mode)
            if best is None:
                cells += ["—"] + (["—"] if has_auto else [])
                continue
            cells.append(f"{best.estimator} {_f(best.rmse)} ({best.ratio:.2f})")
            if not has_auto:
                continue
            auto = index.get((s, "auto", mode))
            if auto is None or not auto.ok:
                cells.append("✗" if auto is not None else "—")
                continue
            ratio = auto.rmse / best.rmse
            chosen = f" ({auto.chosen})" if auto.chosen else ""
            text = f"{ratio:.3f}{chosen}"
            cells.append(text if ratio <= AUTO_TOLERANCE and not auto.missing else f"**{text}**")
        rows.append(cells)
    header = ["set"]
    for mode in modes:
        header += [f"best: {mode}"] + ([f"auto / best: {mode}"] if has_auto else [])
    return table(header, rows)


#: The SVSF family (issue 29: its best at most 1.00x the Kalman smoother on every set and mode).
FAMILY = ("svsf", "svss", "svstps")


def family_section(runs: Sequence[Run], sets: Sequence[str], modes: Sequence[str]) -> str:
    """Per set and mode: the best of the SVSF family's RMSE over the Kalman smoother's (``ks``),
    bold above 1, and a line on all of them; empty where neither ran."""
    index = by_key(runs)
    rows, ratios = [], []
    for s in sets:
        cells: list[object] = [s]
        for mode in modes:
            ks, best = best_run(index, s, ["ks"], mode), best_run(index, s, FAMILY, mode)
            if ks is None or best is None:
                cells.append("—")
                continue
            ratio = round(best.rmse / ks.rmse, 4)  # (as printed: a twin's float noise is 1)
            ratios.append((ratio, s, mode))
            text = f"{ratio:.4f} ({best.estimator})"
            cells.append(f"**{text}**" if ratio > 1.0 else text)
        rows.append(cells)
    if not ratios:
        return ""
    worst = max(ratios)
    above = sum(r > 1.0 for r, _, _ in ratios)
    return _text(
        "family",
        table="\n".join(table(["set", *modes], rows)),
        above=above,
        count=len(ratios),
        worst=f"{worst[0]:.4f}",
        where=f"{worst[1]}, {worst[2]}",
        mean=f"{sum(r for r, _, _ in ratios) / len(ratios):.4f}",
    )


def estimate_section(runs: Sequence[Run]) -> str:
    """How many runs wrote a truth-free estimate, and those more than 15% off the true RMSE."""
    with_estimate = [r for r in runs if r.ok and math.isfinite(r.estimated)]
    if not with_estimate:
        return _text("estimate_none")
    off = [r for r in with_estimate if abs(r.estimate_ratio - 1) > ESTIMATE_TOLERANCE]
    counts = {"runs": len(with_estimate), "off": len(off), "tolerance": f"{ESTIMATE_TOLERANCE:.0%}"}
    if not off:
        return _text("estimate_all_near", **counts)
    rows = table(
        ["set", "estimator", "mode", "true RMSE m", "estimated m", "estimated / true", "warned"],
        [
            [
                r.set,
                r.estimator,
                r.mode,
                _f(r.rmse),
                _f(r.estimated),
                f"{r.estimate_ratio:.2f}",
                "yes" if warned_of_estimate(r) else "**no**",
            ]
            for r in sorted(off, key=lambda r: -abs(math.log(max(r.estimate_ratio, 1e-12))))
        ],
    )
    counts["warned"] = sum(warned_of_estimate(r) for r in off)
    from torchsvs.estimate_warnings import UNCERTAIN_REACH
    from torchsvs.fitting.outliers import GROSS_ERROR_SHARE

    counts["reach"] = f"{UNCERTAIN_REACH:g}"
    counts["gross"] = f"{GROSS_ERROR_SHARE:.1%}"
    return _text("estimate_some_off", table="\n".join(rows), **counts)


def warned_of_estimate(run: Run) -> bool:
    """Whether the run warned that its error estimate is uncertain
    (:func:`torchsvs.estimate_warnings.uncertain_estimate`), no estimate (below zero,
    :func:`~torchsvs.estimate_warnings.below_zero_estimate`) or may be off: the sensor erring grossly
    (:func:`~torchsvs.estimate_warnings.gross_errors`), one noise level not fitting every track, a
    noise given above what the data show."""
    signs = (
        "is uncertain",
        "counts white noise only",
        "below zero",
        "does not fit every track",
        "above what the data show",
    )
    return any(sign in w for w in run.warnings for sign in signs)


#: The rows of issue 28's table that a set of this benchmark matches: (what was run, kind, σ,
#: estimator, mode, the issue's raw RMSE and result; m, 2-D; the issue's simulated rows are
#: per axis, so they are scaled by √2 here).
ISSUE_ROWS: list[tuple[str, str, float, str, str, float, float]] = [
    (
        "`--estimator pf --meas-std 50`, recorded airliners, 10 s scans",
        "scan10",
        50,
        "pf",
        "--meas-std σ",
        70.7,
        5660,
    ),
    (
        "`--estimator pf`, simulated turning tracks, σ 50",
        "turning",
        50,
        "pf",
        "default",
        50.0 * 2**0.5,
        1742 * 2**0.5,
    ),
    (
        "`--estimator svss --meas-std 50`, recorded ships, ~9 s scans",
        "taxi",
        50,
        "svss",
        "--meas-std σ",
        70.4,
        556,
    ),
    (
        "`--estimator svss --meas-std 10`, recorded ships",
        "taxi",
        10,
        "svss",
        "--meas-std σ",
        14.2,
        86,
    ),
    (
        "`--estimator svss --meas-std 100`, recorded airliners",
        "scan10",
        100,
        "svss",
        "--meas-std σ",
        139.7,
        129,
    ),
    ("(same, KS)", "scan10", 100, "ks", "--meas-std σ", 139.7, 83),
    (
        "`--estimator svss --meas-std 10`, a drone's GPS at 1 s",
        "scan1",
        10,
        "svss",
        "--meas-std σ",
        14.4,
        12.7,
    ),
    ("(same, KS)", "scan1", 10, "ks", "--meas-std σ", 14.4, 5.1),
    (
        "`--estimator svss --meas-std 50`, simulated turning tracks",
        "turning",
        50,
        "svss",
        "--meas-std σ",
        50.0 * 2**0.5,
        59.4 * 2**0.5,
    ),
    (
        "`--estimator svsf`, simulated turning tracks",
        "turning",
        50,
        "svsf",
        "default",
        50.0 * 2**0.5,
        50.0 * 2**0.5,
    ),
    (
        "default (KS) without `--meas-std`, recorded ships σ 50",
        "taxi",
        50,
        "ks",
        "default",
        70.4,
        29.3,
    ),
    ("(same, `--fit`)", "taxi", 50, "ks", "--fit", 70.4, 21.6),
    (
        "default without `--meas-std`, simulated turning tracks σ 50",
        "turning",
        50,
        "ks",
        "default",
        50.0 * 2**0.5,
        43.7 * 2**0.5,
    ),
]


def issue_section(runs: Sequence[Run], sets: Sequence[BenchSet]) -> str:
    """Issue 28's rows beside the runs on the matching sets; empty where no set matches."""
    index = by_key(runs)
    names = {(b.kind.name, b.sigma): b.name for b in sets}
    rows = []
    for what, kind, sigma, estimator, mode, raw, result in ISSUE_ROWS:
        name = names.get((kind, sigma))
        run = index.get((name, estimator, mode)) if name else None
        if run is None:
            continue
        issue_ratio = result / raw
        if run.ok:
            ours = f"{_f(run.rmse)} of {_f(run.raw)} ({run.ratio:.2f})"
            agree = "yes" if (issue_ratio >= 1) == (not run.below_raw) else "no"
        else:
            ours, agree = "✗ " + _short(run.error, 50), "—"
        rows.append(
            [
                what,
                f"{run.set}, `{estimator}` {mode}",
                f"{_f(result)} of {_f(raw)} ({issue_ratio:.2f})",
                ours,
                agree,
            ]
        )
    if not rows:
        return ""
    lines = table(
        [
            "issue 28's row",
            "here",
            "issue: result of raw (ratio)",
            "here: result of raw (ratio)",
            "same side of raw",
        ],
        rows,
    )
    return _text("issue", table="\n".join(lines))


def detail_section(runs: Sequence[Run], bench: BenchSet) -> str:
    """Every run on one set: its scores, cost, truth-free estimate and messages."""
    mine = [r for r in runs if r.set == bench.name]
    raw = describe(bench).raw_rmse
    rows = []
    for r in mine:
        if r.ok:
            rmse = _f(r.rmse) if r.below_raw else f"**{_f(r.rmse)}**"
            ratio = f"{r.ratio:.2f}" if r.below_raw else f"**{r.ratio:.2f}**"
        else:
            rmse = ratio = "✗"
        estimate = _f(r.estimated)
        est_ratio = ""
        if r.ok and math.isfinite(r.estimated):
            est_ratio = f"{r.estimate_ratio:.2f}"
            if abs(r.estimate_ratio - 1) > ESTIMATE_TOLERANCE:
                est_ratio = f"**{est_ratio}** ⚠"
        note = []
        if r.chosen:
            note.append(f"ran {r.chosen}")
        if r.error:
            note.append(_short(r.error, 120))
        if r.warnings:
            note.append(f"{len(r.warnings)} warning(s): " + _short(r.warnings[0], 80))
        rows.append(
            [
                r.estimator,
                r.mode,
                rmse,
                ratio,
                r.missing,
                _f(r.sigma_used),
                estimate,
                est_ratio,
                _f(r.seconds),
                _f(r.cpu_seconds),
                "; ".join(note),
            ]
        )
    lines = table(
        [
            "estimator",
            "mode",
            "RMSE m",
            "× raw",
            "no est.",
            "σ used m",
            "est. RMSE m",
            "est. / true",
            "s",
            "CPU s",
            "note",
        ],
        rows,
    )
    return _text(
        "set_runs", set=bench.name, title=bench.kind.title, raw=_f(raw), table="\n".join(lines)
    )


def heat_map(
    runs: Sequence[Run],
    sets: Sequence[str],
    estimators: Sequence[str],
    modes: Sequence[str],
    path: Path,
) -> None:
    """Ratio to raw of every estimator × mode (rows) on every set (columns); log colour scale
    centred on 1, failures grey."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import TwoSlopeNorm

    index = by_key(runs)
    labels = [f"{e} · {m}" for e in estimators for m in modes]
    values = np.full((len(labels), len(sets)), np.nan)
    for i, (e, m) in enumerate((e, m) for e in estimators for m in modes):
        for j, s in enumerate(sets):
            run = index.get((s, e, m))
            if run is not None and run.ok:
                values[i, j] = math.log2(max(run.ratio, 1e-3))
    fig, ax = plt.subplots(figsize=(1.0 * len(sets) + 3.5, 0.24 * len(labels) + 1.8))
    norm = TwoSlopeNorm(vmin=-2.0, vcenter=0.0, vmax=2.0)
    cmap = plt.get_cmap("RdYlGn_r").with_extremes(bad="0.8")
    ax.imshow(np.clip(values, -2, 2), cmap=cmap, norm=norm, aspect="auto")
    for i in range(len(labels)):
        for j in range(len(sets)):
            v = values[i, j]
            text = "✗" if not math.isfinite(v) else f"{2**v:.2f}" if 2**v < 10 else f"{2**v:.0f}"
            worse = math.isfinite(v) and v >= 0
            ax.text(
                j,
                i,
                text,
                ha="center",
                va="center",
                fontsize=6,
                fontweight="bold" if worse else "normal",
                color="white" if math.isfinite(v) and abs(v) > 1.5 else "black",
            )
    ax.set_xticks(range(len(sets)), sets, rotation=45, ha="right", fontsize=7)
    ax.set_yticks(range(len(labels)), labels, fontsize=6)
    ax.set_title(
        "position RMSE / raw measurement RMSE (green < 1 < red, bold: not below raw; grey ✗: no result)",
        fontsize=8,
    )
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)


def _git_head() -> str:
    """The last commit that changed ``torchsvs/`` in this checkout (what the runs ran), with a
    mark when it has uncommitted changes there."""
    try:
        log = subprocess.run(
            ["git", "log", "-1", "--format=%h %s", "--", "torchsvs"],
            capture_output=True,
            text=True,
            cwd=ROOT,
        )
        status = subprocess.run(
            ["git", "status", "--porcelain", "--", "torchsvs"],
            capture_output=True,
            text=True,
            cwd=ROOT,
        )
    except OSError:
        return "unknown"
    if log.returncode != 0:
        return "unknown"
    head = _short(log.stdout.strip(), 70)
    return head + (" + uncommitted changes" if status.stdout.strip() else "")


def tracks_figure(sets: Sequence[BenchSet], path: Path) -> None:
    """One track of each kind: its truth and its measurements at the kind's lowest σ."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    first: dict[str, BenchSet] = {}
    for bench in sorted(sets, key=lambda b: b.sigma):
        first.setdefault(bench.kind.name, bench)
    columns = min(3, len(first))
    lines = math.ceil(len(first) / columns)
    fig, grid = plt.subplots(lines, columns, figsize=(3.4 * columns, 3.2 * lines), squeeze=False)
    axes = list(grid.ravel())
    for ax in axes[len(first) :]:
        ax.set_axis_off()
    for ax, bench in zip(axes, first.values(), strict=False):
        truth, measured = bench.truth.rows, bench.measurements
        lengths = truth.groupby("track_id", sort=False).size()
        track = lengths.idxmax()
        mine = (truth["track_id"] == track).to_numpy()
        ax.plot(measured["x"][mine], measured["y"][mine], ".", ms=2, color="0.6", label="measured")
        ax.plot(truth["x"][mine], truth["y"][mine], "-", lw=1, color="C3", label="truth")
        ax.set_title(f"{bench.name}\n{_short(str(track), 34)}", fontsize=7)
        ax.set_aspect("equal", adjustable="datalim")
        ax.tick_params(labelsize=6)
    axes[0].legend(fontsize=6)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def report(
    sets: Sequence[BenchSet],
    runs: Sequence[Run],
    estimators: Sequence[str],
    modes: Sequence[str],
    default: str,
    options: dict[str, Any],
    timing: str,
    figure: str,
    check: dict[str, float],
) -> str:
    """The report of ``runs`` on ``sets`` (``check``: :func:`truth_check`'s numbers), its prose
    from ``templates/recorded_tracks.md``."""
    offered, _ = estimator_choices()
    failures = [r for r in runs if not r.ok]
    total_run = sum(r.seconds for r in runs if math.isfinite(r.seconds))
    total_cpu = sum(r.cpu_seconds for r in runs if math.isfinite(r.cpu_seconds))
    cost: dict[str, float] = {}
    for r in runs:
        if math.isfinite(r.cpu_seconds):
            key = f"`{r.estimator}` {r.mode}"
            cost[key] = cost.get(key, 0.0) + r.cpu_seconds
    costliest = sorted(cost.items(), key=lambda kv: -kv[1])[:4]
    details = [detail_section(runs, bench) for bench in sets]
    if failures:
        reasons: dict[str, int] = {}
        for r in failures:
            reasons[_short(r.error, 160)] = reasons.get(_short(r.error, 160), 0) + 1
        messages = "\n".join(f"- {count} × {reason}" for reason, count in reasons.items())
        details.append(_text("failures", messages=messages))
    text = _text(
        "report",
        codes=", ".join(f"`{c}`" for c in dict.fromkeys(r.code or "unknown" for r in runs)),
        options=", ".join(f"{k} {v}" for k, v in options.items()),
        runs=len(runs),
        sets=len(sets),
        estimators=len(estimators),
        modes=len(modes),
        run_minutes=f"{total_run / 60:.1f}",
        cpu_minutes=f"{total_cpu / 60:.1f}",
        timing=timing,
        costliest=", ".join(f"{k} {v / 60:.1f}" for k, v in costliest),
        mode_list=", ".join(
            _text("mode" if MODES[m](1.0) else "mode_default", mode=m) for m in modes
        ),
        sigma_note=_text("sigma_note") if any("σ" in m for m in modes) else "",
        default=default,
        auto_offered=_text("auto_offered" if "auto" in offered else "auto_not_offered"),
        figure=figure,
        headline="\n".join(headline(runs, [b.name for b in sets], estimators, modes)),
        below_raw="\n".join(below_raw_section(runs, [b.name for b in sets], estimators, modes)),
        best_auto=(
            _text("best_auto", tolerance=f"{AUTO_TOLERANCE:.2f}")
            if "auto" in estimators
            else _text("best_no_auto")
        ),
        best="\n".join(best_section(runs, [b.name for b in sets], estimators, modes)),
        family=family_section(runs, [b.name for b in sets], modes),
        estimate=estimate_section(runs),
        issue=issue_section(runs, sets),
        sets_section=sets_section(sets),
        examples=Path(figure).stem + "_examples.png",
        check_before=f"{check['before']:.1f}",
        check_after=f"{check['after']:.1f}",
        window=f"{DEJITTER_WINDOW:g}",
        turn_dt=f"{TURN_DT:g}",
        details="\n\n".join(details),
    )
    return text.rstrip() + "\n"


def _text(section: str, **fields: object) -> str:
    """Section ``section`` of ``templates/recorded_tracks.md``, filled."""
    return render("recorded_tracks", section, **fields)


def save_runs(path: Path, options: dict[str, Any], runs: Sequence[Run]) -> None:
    """The runs as JSON, one run a line (``--merge`` and ``--report-only`` read it back)."""
    lines = ",\n".join(json.dumps(asdict(r), ensure_ascii=False) for r in runs)
    head = json.dumps(options, ensure_ascii=False)
    path.write_text(f'{{"options": {head},\n"runs": [\n{lines}\n]}}\n')


def merged_sets(
    to_run: list[BenchSet],
    kept: list[Run],
    rows: int,
    seed: int,
    faults: bool,
    noise: str = "white",
) -> list[BenchSet]:
    """The sets of a report: those run now and, rebuilt (each seeded by its kind and σ alone),
    those of the saved runs kept beside them (``--merge``, ``--report-only``: a kind at other
    noise levels than this command's keeps its own), in the kinds' order, then σ's."""
    found = {b.name: b for b in to_run}
    levels: dict[str, set[float]] = {}
    for r in kept:
        kind, level = r.set.split(" σ")
        levels.setdefault(kind, set()).add(float(level.split()[0]))
    for kind, sigmas in levels.items():
        for b in build_sets([kind], rows, seed, sorted(sigmas), faults=faults, noise=noise):
            found.setdefault(b.name, b)
    order = {k: i for i, k in enumerate(KINDS)}
    return sorted(found.values(), key=lambda b: (order[b.kind.name], b.sigma))


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--kinds", default=",".join(DEFAULT_KINDS), help="kinds of track (comma-separated)"
    )
    parser.add_argument(
        "--sigmas", default=None, help="noise levels for every kind (default: each kind's own)"
    )
    parser.add_argument("--rows", type=int, default=5000, help="rows per set (about)")
    parser.add_argument("--seed", type=int, default=0, help="of the sets' samples and noise")
    parser.add_argument(
        "--estimators", default=None, help="estimators (default: every choice of --estimator)"
    )
    parser.add_argument(
        "--modes",
        default=",".join(DEFAULT_MODES),
        help=f"modes (comma-separated; default {','.join(DEFAULT_MODES)}; also: "
        f"{', '.join(m for m in MODES if m not in DEFAULT_MODES)})",
    )
    parser.add_argument(
        "--via",
        choices=("inprocess", "cli"),
        default="inprocess",
        help="torchsvs.cli.main in this process, or a `python -m torchsvs.cli` subprocess",
    )
    parser.add_argument("--jobs", type=int, default=1, help="worker processes (default 1)")
    parser.add_argument("--out", default=str(RESULTS), help="folder of the report")
    parser.add_argument(
        "--name",
        default=None,
        help="stem of the report's files (NAME.md, ...; default recorded_tracks)",
    )
    parser.add_argument("--workdir", default=None, help="keep the sets and outputs here")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    parser.add_argument(
        "--faults",
        action="store_true",
        help="measure with faults (recorded_sets.add_faults: outliers, dropouts, time jitter, "
        "a bias that comes and goes); the report is NAME (default recorded_faults)",
    )
    parser.add_argument(
        "--noise",
        default="white",
        choices=NOISE_KINDS,
        help="the measurements' noise (recorded_sets.NOISE_KINDS: white Gaussian, each track's "
        "own σ, Student's t, correlated in time); the report is NAME (default recorded_NOISE)",
    )
    parser.add_argument(
        "--merge",
        action="store_true",
        help="keep the runs saved in OUT/NAME.json and replace those run now (e.g. "
        "one kind or estimator after a fix)",
    )
    parser.add_argument(
        "--report-only",
        action="store_true",
        help="run nothing: the report of the runs saved in OUT/NAME.json",
    )
    args = parser.parse_args(argv)
    default_name = "recorded_faults" if args.faults else "recorded_tracks"
    args.name = args.name or (default_name if args.noise == "white" else f"recorded_{args.noise}")
    import torch

    torch.set_num_threads(1)
    start = time.perf_counter()
    kinds = [k for k in args.kinds.split(",") if k]
    sigmas = [float(s) for s in args.sigmas.split(",")] if args.sigmas else None
    choices, default = estimator_choices()
    estimators = args.estimators.split(",") if args.estimators else choices
    unknown = [e for e in estimators if e not in choices]
    if unknown:
        raise SystemExit(f"estimators: expected names among {choices}, got {unknown}")
    modes = [m for m in MODES if m in args.modes.split(",")]
    if not modes:
        raise SystemExit(f"modes: expected names among {list(MODES)}, got {args.modes!r}")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    saved = out / f"{args.name}.json"
    options: dict[str, Any] = {
        "rows": f"~{args.rows:,} per set",
        "seed": args.seed,
        "via": args.via,
        "jobs": args.jobs,
    }
    kept: list[Run] = []
    if args.merge or args.report_only:
        record = json.loads(saved.read_text())
        if isinstance(record, list):  # the first runs wrote the runs alone
            record = {"options": options, "runs": record}
        kept = [Run(**r) for r in record["runs"]]
        options = record.get("options", options)
    run_kinds = [] if args.report_only else kinds
    seed, rows = args.seed, args.rows
    if kept:  # the saved runs' sets are rebuilt as they were drawn
        seed = int(options.get("seed", seed))
        rows = int(re.sub(r"\D", "", str(options.get("rows", rows))) or rows)
        if run_kinds and (seed, rows) != (args.seed, args.rows):
            raise SystemExit(
                f"merge: the saved runs are of --seed {seed} --rows {rows}; run the new ones so"
            )
    to_run = build_sets(
        run_kinds, rows, seed, sigmas, not args.quiet, faults=args.faults, noise=args.noise
    )
    sets = merged_sets(to_run, kept, rows, seed, args.faults, args.noise)
    with contextlib.ExitStack() as stack:
        if args.workdir:
            workdir = Path(args.workdir)
        else:
            folder = tempfile.TemporaryDirectory(prefix="recorded_")
            workdir = Path(stack.enter_context(folder))
        new = run_all(to_run, estimators, modes, workdir, args.via, args.jobs, not args.quiet)
    done = {(r.set, r.estimator, r.mode) for r in new}
    runs = [r for r in kept if (r.set, r.estimator, r.mode) not in done] + new
    # in the order of the sets, the command's estimators and the modes
    set_order = {b.name: i for i, b in enumerate(sets)}
    est_order = {e: i for i, e in enumerate(choices)}
    mode_order = {m: i for i, m in enumerate(MODES)}
    lost = [r for r in runs if not (r.set in set_order and r.estimator in est_order)]
    lost += [r for r in runs if r.mode not in mode_order]
    if lost:  # (never written without them: the saved file is the only copy of its runs)
        raise SystemExit(
            f"merge: {len(lost)} saved runs have no set or estimator here, e.g. {lost[0]}"
        )
    runs.sort(key=lambda r: (set_order[r.set], est_order[r.estimator], mode_order[r.mode]))
    if new:
        save_runs(saved, options, runs)
    seconds = time.perf_counter() - start
    if new:
        timing = _text(
            "timing_run",
            minutes=f"{seconds / 60:.1f}",
            sets=len(sets),
            runs=len(new),
            merged=_text("timing_merged") if kept else "",
        )
    else:
        timing = _text("timing_saved")
    shown_estimators = [e for e in choices if any(r.estimator == e for r in runs)]
    shown_modes = [m for m in MODES if any(r.mode == m for r in runs)]
    figure = out / f"{args.name}.png"
    heat_map(runs, [b.name for b in sets], shown_estimators, shown_modes, figure)
    tracks_figure(sets, out / f"{args.name}_examples.png")
    check = truth_check()
    text = report(
        sets, runs, shown_estimators, shown_modes, default, options, timing, figure.name, check
    )
    (out / f"{args.name}.md").write_text(text)
    print(text)
    print(f"\n(total {time.perf_counter() - start:.0f} s)")


if __name__ == "__main__":
    main()
