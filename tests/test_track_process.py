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
      os.environ.get("MIMALLOC_PURGE_DELAY"), os.environ.get("OPENBLAS_NUM_THREADS"))
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
    _, _, omp, purge, blas = _run(True)
    assert (omp, purge, blas) == ("ACTIVE", "-1", "1")
