"""The third-party example package, installed from examples/, is found and used by a skill."""

from __future__ import annotations

import csv
import json
import os
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
    assert "example.rigid_push" in present.stdout


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


CHECK_MODEL = """
import tempfile
from pathlib import Path
from vistac.testing import build_components, check_component
ctx = build_components({"model": {"plugin": "example.rigid_push"}}, Path(tempfile.mkdtemp()))
check_component(ctx.component("model"))
print("conforms")
"""


def test_the_example_process_model_conforms(installed: Path) -> None:
    """A process model written outside vistac passes the process-model check as installed."""
    env = {**os.environ, "PYTHONPATH": str(installed), "VISTAC_DISABLE_PLUGIN_AUTOLOAD": "0"}
    result = subprocess.run(
        [sys.executable, "-c", CHECK_MODEL], capture_output=True, text=True, env=env, timeout=120
    )
    assert result.returncode == 0 and "conforms" in result.stdout, result.stderr


def test_the_dual_filter_runs_the_example_process_model(installed: Path, tmp_path: Path) -> None:
    """rigid_push.yaml: two pushes, each after a look; the dual filter updates the belief
    through the example's model; its finger force shows the friction load, so the std of m
    and f shrink from the prior's."""
    out = tmp_path / "out"
    result = run_vistac(
        "-q", "run", str(EXAMPLE / "rigid_push.yaml"), "--out", str(out),
        env={"PYTHONPATH": str(installed), "VISTAC_DISABLE_PLUGIN_AUTOLOAD": "0"},
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["status"] == "success" and len(summary["episodes"]) == 2
    assert "blocked_actions" not in summary  # each push chosen after a fresh look
    for name in ("m_0", "f_0"):
        assert summary["belief"][name]["std"] < 0.7 * summary["prior"][name]["std"], name
