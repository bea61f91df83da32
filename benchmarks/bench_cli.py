"""`vistac plugins` start-up time (target < 1 s); peer: a bare `python -c pass`."""

from __future__ import annotations

import subprocess
import sys

from common import Row, median_time_s


def _run(*args: str) -> None:
    subprocess.run([sys.executable, *args], check=True, capture_output=True)


def run(repeats: int) -> list[Row]:
    plugins_s = median_time_s(lambda: _run("-m", "vistac.cli", "plugins"), repeats)
    bare_s = median_time_s(lambda: _run("-c", "pass"), repeats)
    return [
        Row(
            "`vistac plugins` wall time",
            plugins_s,
            "s",
            "< 1 s",
            plugins_s < 1.0,
            "bare `python -c pass`",
            bare_s,
            "imports no torch/open3d/mujoco/ur_rtde",
        )
    ]
