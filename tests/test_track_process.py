"""The ``torchsvs track`` program's process set-up (:func:`~torchsvs.track_command.
set_up_process`): memory a block frees is reused by the next without fresh zeroed pages, idle
helper threads sleep, and what the user set in the environment stays."""

from __future__ import annotations

import subprocess
import sys

import pytest

CHECK = """
import os, resource
import numpy as np
os.environ["OMP_WAIT_POLICY"] = "ACTIVE"  # (the user's own choice)
if {set_up}:
    from torchsvs.track_command import set_up_process
    set_up_process()

def faults_of_a_block():
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    block = np.ones(2 << 20)  # 16 MB, freed at once
    block += 1.0
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before

print(faults_of_a_block(), faults_of_a_block(), os.environ["OMP_WAIT_POLICY"],
      os.environ.get("ARROW_DEFAULT_MEMORY_POOL"), os.environ.get("OPENBLAS_NUM_THREADS"))
"""


def _run(set_up: bool) -> list[str]:
    done = subprocess.run(
        [sys.executable, "-c", CHECK.format(set_up=set_up)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, done.stderr
    return done.stdout.split()


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt")
def test_a_freed_block_is_reused_without_fresh_pages():
    """The second block of the same size takes the first's memory: next to no page faults
    (each fresh page is one, and the system zeroes it), where the default allocator maps it
    anew."""
    first, second, *_ = map(int, _run(True)[:2])
    assert first > 100 and second < first / 10, (first, second)
    plain_first, plain_second = map(int, _run(False)[:2])
    assert plain_second > plain_first / 2, "the default allocator reuses it too: nothing to test"


def test_the_users_environment_is_kept_and_the_rest_set():
    _, _, omp, pool, blas = _run(True)
    assert (omp, pool, blas) == ("ACTIVE", "system", "1")


RUN = """
import gc, sys
import numpy as np
from torchsvs.track_command import set_up_process
set_up_process()
assert not gc.isenabled(), "collecting during the imports"
t = np.arange(30.0)
rows = ["track_id,time,x,y"] + [f"a,{s},{3 * s},{-s}" for s in t]
rows += [f"b,{s},{s},{2 * s}" for s in t]
with open(sys.argv[1], "w") as f:
    f.write("\\n".join(rows) + "\\n")
from torchsvs.cli import main
main(["track", sys.argv[1], "-o", sys.argv[2], "--meas-std", "1", "--q", "1", "--quiet"])
print(gc.isenabled(), gc.get_freeze_count() > 1000)
"""


def test_the_program_collects_again_once_imported(tmp_path):
    """No garbage collection while the modules load (their objects, frozen, are never
    traversed again), and collection as usual after that."""
    done = subprocess.run(
        [sys.executable, "-c", RUN, str(tmp_path / "in.csv"), str(tmp_path / "out.csv")],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == ["True", "True"]
