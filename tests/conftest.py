"""Shared fixtures. Tests load vistac's own plugins plus the test doubles in
``fixtures_plugin.py``; third-party autoload is disabled for a sealed, reproducible set."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

os.environ["VISTAC_DISABLE_PLUGIN_AUTOLOAD"] = "1"

from vistac.cli import main
from vistac.pluginmanager import Plugins, load_plugins

ROOT = Path(__file__).resolve().parents[1]
SKILLS = ROOT / "skills"


@pytest.fixture
def single_thread() -> Iterator[None]:
    """Torch on one thread: the networks' matrices are tiny, and a second thread only adds
    OpenMP spin-waits on a shared 2-core machine."""
    import torch

    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)


@pytest.fixture(scope="session")
def plugins() -> Plugins:
    return load_plugins(["fixtures_plugin"])


@pytest.fixture
def cli(capsys: pytest.CaptureFixture[str]) -> Callable[..., tuple[int, str, str]]:
    """Run ``vistac ARGS`` in-process: returns (exit code, stdout, stderr)."""

    def run(*args: str) -> tuple[int, str, str]:
        code = main(["-p", "fixtures_plugin", *args])
        out, err = capsys.readouterr()
        return code, out, err

    return run


def run_vistac(
    *args: str, env: dict[str, str] | None = None, timeout_s: float = 300
) -> subprocess.CompletedProcess[str]:
    """Run the ``vistac`` CLI in a fresh interpreter."""
    full_env = {**os.environ, **(env or {})}
    return subprocess.run(
        [sys.executable, "-m", "vistac.cli", *args],
        capture_output=True,
        text=True,
        env=full_env,
        timeout=timeout_s,
        cwd=ROOT,
    )


def write(path: Path, text: str) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return path


def fake_run(monkeypatch: pytest.MonkeyPatch, code: int) -> list[list[str]]:
    """``vistac run`` (``vistac.cli.main``) replaced by one that writes a summary and exits
    ``code``; returns the list its calls' arguments are appended to."""
    import vistac.cli

    calls: list[list[str]] = []

    def run(args: list[str]) -> int:
        run_dir = Path(args[args.index("--out") + 1])
        run_dir.mkdir(parents=True, exist_ok=True)
        (run_dir / "summary.json").write_text(json.dumps({"exit_code": code}))
        calls.append(args)
        return code

    monkeypatch.setattr(vistac.cli, "main", run)
    return calls


def wait_for(predicate: Callable[[], bool], timeout_s: float = 2.0) -> bool:
    """Poll ``predicate`` every 10 ms until it holds (True) or ``timeout_s`` passes (False)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.01)
    return False
