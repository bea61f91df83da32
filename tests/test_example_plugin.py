"""The third-party example package, installed from examples/, is found and used by a skill."""

from __future__ import annotations

import csv
import json
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import ROOT, run_vistac

EXAMPLE = ROOT / "examples/vistac-example-plugin"


@pytest.fixture(scope="module")
def installed(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """pip-install the example into a private folder (the venv is left untouched)."""
    target = tmp_path_factory.mktemp("site")
    subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "install",
            "-q",
            "--no-deps",
            "--no-build-isolation",
            "--target",
            str(target),
            str(EXAMPLE),
        ],
        check=True,
        capture_output=True,
        timeout=300,
    )
    return target


def test_not_found_until_installed(installed: Path) -> None:
    absent = run_vistac("plugins", env={"VISTAC_DISABLE_PLUGIN_AUTOLOAD": "0"})
    assert "example.noisy_camera" not in absent.stdout
    present = run_vistac(
        "plugins", env={"PYTHONPATH": str(installed), "VISTAC_DISABLE_PLUGIN_AUTOLOAD": "0"}
    )
    assert "example.noisy_camera" in present.stdout and "[example]" in present.stdout


def test_skill_uses_the_example_camera_and_observer(installed: Path, tmp_path: Path) -> None:
    out = tmp_path / "out"
    result = run_vistac(
        "-q",
        "run",
        str(EXAMPLE / "noisy_camera.yaml"),
        "--out",
        str(out),
        env={"PYTHONPATH": str(installed), "VISTAC_DISABLE_PLUGIN_AUTOLOAD": "0"},
    )
    assert result.returncode == 0, result.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["status"] == "success" and len(summary["episodes"]) == 1
    with (out / "tactile.csv").open() as handle:
        rows = list(csv.DictReader(handle))
    steps = summary["episodes"][0]["steps"]
    assert len(rows) == 2 * steps  # one row per pad per observation
    assert max(abs(float(r["fx_n"])) + abs(float(r["fy_n"])) for r in rows) > 0.05  # it touched
    # The wrapper degraded the views: more dropouts than the raw 160x120 camera gives.
    import numpy as np

    depth = np.load(out / "views/0000.npz", allow_pickle=False)["depth_m"]
    assert np.isnan(depth).mean() > 0.04
