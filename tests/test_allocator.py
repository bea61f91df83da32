"""keep_freed_memory: blocks of a few MB are reused instead of page-faulting every time.

Each case runs in its own interpreter: the allocator settings are global to a process."""

from __future__ import annotations

import os
import platform
import subprocess
import sys

import pytest

pytestmark = pytest.mark.skipif(
    platform.system() != "Linux" or platform.libc_ver()[0] != "glibc", reason="glibc only"
)

# Allocates and fills four 3.2 MB arrays (a filter step's size), frees them, 40 times, and prints
# the minor page faults of the last 20 rounds. glibc's adaptive thresholds keep one such block
# on the heap but trim four freed together (more than twice the largest block).
FAULTS = """
import resource, sys
import numpy as np
from vistac.allocator import keep_freed_memory
changed = keep_freed_memory() if sys.argv[1] == "keep" else None
def rounds(count):
    for _ in range(count):
        blocks = [np.empty(400_000) for _ in range(4)]
        for block in blocks:
            block.fill(1.0)
        del blocks, block
rounds(20)
start = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
rounds(20)
print(changed, (resource.getrusage(resource.RUSAGE_SELF).ru_minflt - start) / 20)
"""


def _faults_per_round(mode: str, env: dict[str, str] | None = None) -> tuple[str, float]:
    out = subprocess.run(
        [sys.executable, "-c", FAULTS, mode],
        capture_output=True, text=True, check=True, env=env,
    ).stdout.split()  # fmt: skip
    return out[0], float(out[1])


def test_freed_blocks_are_reused_without_page_faults() -> None:
    changed, faults = _faults_per_round("keep")
    assert changed == "True"
    assert faults < 10.0  # four fresh 3.2 MB blocks are about 3,100 pages
    _, faults_default = _faults_per_round("default")
    assert faults_default > 100.0, "glibc now reuses such blocks by default: the module is moot"


def test_thresholds_set_in_the_environment_are_left_alone() -> None:
    env = dict(os.environ, MALLOC_TRIM_THRESHOLD_="131072")
    changed, _ = _faults_per_round("keep", env)
    assert changed == "False"
