"""``torchsvs track --processes N`` (``Trainer.predict``, DDP on CPU): the same output file as one
process, byte for byte; clear errors.

Lightning's DDP launcher runs the launching command again per process, so the multi-process runs
start ``python -m torchsvs.cli`` in a subprocess.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.test_track_cli import _simulated_csv
from torchsvs.cli import main
from torchsvs.datasets import Columns, track_blocks
from torchsvs.recipes import Settings
from torchsvs.track_run import summary_path
from torchsvs.training.predict import predict_file

# Lightning 2.6 on torch 2.13, at every run of a Trainer in this process.
pytestmark = pytest.mark.filterwarnings("ignore:.*LeafSpec.*:FutureWarning")
ROOT = Path(__file__).resolve().parents[1]
COLUMNS = ["--id-col", "id", "--time-col", "t"]
#: Unequal lengths, so the groups differ in width; with MAX_CELLS their count is odd.
LENGTHS = [40, 7, 25, 60, 13, 33, 52, 20, 9]
MAX_CELLS = 120


def _source(tmp_path: Path) -> Path:
    source = tmp_path / "in.csv"
    _simulated_csv(source, tracks=len(LENGTHS), steps=LENGTHS)
    block = next(track_blocks(source, Columns("id", "t"), whole=True))
    groups = len(list(block.steps.batches(MAX_CELLS)))
    assert groups % 2 == 1 and groups > 2  # two ranks: the sampler must not even them out
    return source


def _track(source: Path, target: Path, *args: str, processes: int = 1) -> None:
    argv = ["track", str(source), "-o", str(target), *COLUMNS, "--max-cells", str(MAX_CELLS)]
    argv += [*args, "--quiet"]
    if processes == 1:
        main(argv)
        return
    # A fresh interpreter per process; PYTHONPATH: this checkout's torchsvs in every one.
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    command = [sys.executable, "-m", "torchsvs.cli", *argv, "--processes", str(processes)]
    subprocess.run(command, check=True, cwd=source.parent, env=env, timeout=600)


@pytest.mark.parametrize("estimator", ["ks", "svss", "pf", "imm"])
def test_lightning_predict_in_one_process_writes_what_track_writes(tmp_path, estimator):
    """The Lightning path with one device, in this process, against today's loop; the particle
    filter's draws are seeded per group, so they do not depend on the groups before."""
    source = _source(tmp_path)
    today, lightning = tmp_path / "today.csv", tmp_path / "lightning.csv"
    _track(source, today, "--estimator", estimator, "--particles", "40", "--covariance")
    settings = Settings(estimator=estimator, particles=40)
    run = predict_file(
        source,
        lightning,
        settings,
        processes=1,
        columns=Columns("id", "t"),
        max_cells=MAX_CELLS,
        covariance=True,
    )
    assert run is not None and run.report.total > 0
    assert lightning.read_bytes() == today.read_bytes()
    # the summary counts the same per-track q as the loop's
    ours = json.loads(summary_path(today).read_text())
    assert run.summary_json().get("q_per_track") == ours.get("q_per_track")


def test_two_processes_write_the_same_file_as_one(tmp_path):
    """Two gloo processes through the command line: every row, in order, the same bytes."""
    source = _source(tmp_path)
    one, two = tmp_path / "one.csv", tmp_path / "two.csv"
    args = ["--estimator", "svss", "--covariance"]
    _track(source, one, *args)
    _track(source, two, *args, processes=2)
    assert two.read_bytes() == one.read_bytes()


@pytest.mark.slow
@pytest.mark.parametrize(
    "args",
    [
        [],
        ["--estimator", "pf", "--particles", "40"],
        ["--fit", "--fit-steps", "3", "--double"],
        ["--max-cells", str(1 << 19)],
    ],
    ids=["default", "pf", "fit", "one-group"],
)
def test_two_processes_write_the_same_file_as_one_for_each_setting(tmp_path, args):
    """The default estimator, random draws, a fit (once, on rank 0, then broadcast), and fewer
    groups than processes (the last ``--max-cells`` counts)."""
    source = _source(tmp_path)
    one, two = tmp_path / "one.parquet", tmp_path / "two.parquet"
    _track(source, one, *args)
    _track(source, two, *args, processes=2)
    assert two.read_bytes() == one.read_bytes()


@pytest.mark.parametrize(
    "args, message",
    [
        (["--processes", "0"], "argument --processes: expected an integer >= 1, got '0'"),
        (["--processes", "two"], "argument --processes: expected an integer >= 1, got 'two'"),
        (["--max-cells", "-5"], "argument --max-cells: expected an integer >= 1, got '-5'"),
        (["--processes", "2", "--stream"], "processes: more than one process reads the whole"),
    ],
)
def test_bad_process_arguments_name_what_is_wrong(tmp_path, capsys, args, message):
    source = tmp_path / "in.csv"
    _simulated_csv(source, tracks=2, steps=10)
    with pytest.raises(SystemExit) as exit_info:
        main(["track", str(source), "-o", str(tmp_path / "o.csv"), *COLUMNS, *args, "--quiet"])
    assert exit_info.value.code != 0
    assert message in str(exit_info.value.code) + capsys.readouterr().err


@pytest.mark.parametrize("processes", [0, -1, 1.5, True])
def test_predict_file_refuses_bad_process_counts(tmp_path, processes):
    with pytest.raises(ValueError, match=r"^processes: expected an integer >= 1, got "):
        predict_file(tmp_path / "in.csv", tmp_path / "o.csv", Settings(), processes=processes)


def test_the_reading_thread_hands_its_error_to_setup(tmp_path):
    """A file that cannot be read fails in ``setup`` (the caller's thread), with the reader's
    own error; without the thread, ``setup`` reads the file itself."""
    from torchsvs.training.predict import TrackFileDataModule

    missing = TrackFileDataModule(tmp_path / "missing.csv", Columns("id", "t"))
    missing.start_reading()
    with pytest.raises((FileNotFoundError, OSError)):
        missing.setup("predict")
    source = _source(tmp_path)
    threaded, direct = (
        TrackFileDataModule(source, Columns("id", "t"), max_cells=MAX_CELLS) for _ in range(2)
    )
    threaded.start_reading()
    threaded.setup("predict")
    direct.setup("predict")
    assert threaded.steps.ids == direct.steps.ids
    assert [g.tolist() for g in threaded.groups] == [g.tolist() for g in direct.groups]


def test_rank_zero_ends_when_another_rank_fails(tmp_path):
    """The command starts ranks 1..N-1 itself (before Lightning); one that fails (here: no such
    file) must end rank 0, which would otherwise wait for it in a collective forever."""
    script = (
        "import time\n"
        "from torchsvs.track_command import OtherRanks\n"
        "with OtherRanks(['missing.csv', '-o', 'out.csv'], 2, 1):\n"
        "    time.sleep(120)\n"
    )
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    env.pop("LOCAL_RANK", None)
    done = subprocess.run(
        [sys.executable, "-c", script],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=100,
    )
    assert done.returncode == 1
    assert "No such file or directory: 'missing.csv'" in done.stderr  # rank 1's own error
    assert "a process ended with" in done.stderr
