"""The real-hardware skills: they validate without devices, and ``vistac run`` completes a
push against the emulators (UR controller, Robotiq pty, PapillArray pty, camera frames
recorded from the simulator) and records it."""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import SKILLS
from emulators.loopback import next_loopback
from emulators.papillarray import PapillArrayPty
from emulators.robotiq import GripperSim, RobotiqPty
from emulators.ur_controller import URControllerProcess
from vistac.pluginmanager import Plugins
from vistac.plugins.hardware.camera.recorded import record_frames
from vistac.testing import build_components

CliRunner = Callable[..., tuple[int, str, str]]
PARK_TCP = [0.0, 0.25, 0.12, np.pi, 0.0, 0.0]
PUSH_ONCE = "{sequence: [look, choose_action, execute_action, stop]}"


def test_real_skills_validate_without_devices(cli: CliRunner) -> None:
    for name in ("explore_push.yaml", "explore_pull.yaml"):
        code, out, err = cli("validate", str(SKILLS / "real" / name))
        assert code == 0, err
        assert "ok" in out


def record_sim_view(plugins: Plugins, tmp_path: Path) -> Path:
    sim = {
        "world": {"plugin": "sim.mujoco", "with": {"object": str(SKILLS / "objects/rect2.yaml")}},
        "camera": {"plugin": "sim.depth_camera", "with": {"width": 320, "height": 240}},
    }
    ctx = build_components(sim, tmp_path / "sim", plugins=plugins)
    folder = tmp_path / "recording"
    record_frames(ctx.component("camera"), folder, 1)
    ctx.close_all()
    return folder


def run_real_push(
    cli: CliRunner,
    plugins: Plugins,
    tmp_path: Path,
    tree: str,
    speed_mps: float,
    inject: Callable[[URControllerProcess, PapillArrayPty], None] | None = None,
) -> tuple[int, str, dict[str, Any]]:
    """Run skills/real/explore_push.yaml against the emulators; ``inject`` runs in a thread
    once the arm has been streamed 20 velocities. Returns (exit code, stderr, UR state)."""
    recording = record_sim_view(plugins, tmp_path)
    out = tmp_path / "out"
    with (
        URControllerProcess(next_loopback(), PARK_TCP) as ur,
        RobotiqPty(GripperSim()) as gripper,
        PapillArrayPty(rate_hz=100.0) as pads,
    ):
        injector = threading.Thread(target=_when_moving, args=(ur, pads, inject), daemon=True)
        if inject is not None:
            injector.start()
        code, _, err = cli(
            "run",
            str(SKILLS / "real" / "explore_push.yaml"),
            "--out",
            str(out),
            "--set",
            f"components.arm.with.host={ur.host}",
            "--set",
            f"components.arm.with.max_speed_mps={speed_mps}",
            "--set",
            f"components.gripper.with.port={gripper.path}",
            "--set",
            f"components.tactile.with.port={pads.path}",
            "--set",
            f"components.camera={{plugin: camera.recorded, with: {{directory: {recording}}}}}",
            "--set",
            f"components.affordances.with.speed_mps={min(speed_mps, 0.05)}",
            "--set",
            "components.affordances.with.duration_s=1.0",
            "--set",
            f"tree={tree}",
        )
        if inject is not None:
            injector.join(5.0)
        time.sleep(0.2)
        state = ur.state()
    assert 10 in state["commands"]  # the arm was driven by speedL through the real client
    return code, err, state


def _when_moving(
    ur: URControllerProcess,
    pads: PapillArrayPty,
    inject: Callable[[URControllerProcess, PapillArrayPty], None] | None,
) -> None:
    deadline = time.monotonic() + 60.0
    while ur.state()["commands"].count(10) < 20 and time.monotonic() < deadline:
        time.sleep(0.05)
    if inject is not None:
        inject(ur, pads)


def check_recorded_push(out: Path) -> None:
    episode = out / "episodes" / "0000"
    assert (episode / "data.npz").is_file()
    meta = json.loads((episode / "meta.json").read_text())
    assert meta["action"]["kind"] == "push"
    with np.load(episode / "data.npz", allow_pickle=False) as data:
        assert len(data["tactile_force_n"]) >= 10  # 1 s at 15 Hz, observed


def test_real_push_runs_against_the_emulators(
    cli: CliRunner, plugins: Plugins, tmp_path: Path
) -> None:
    # One push at 0.25 m/s approach speed (the cap's upper bound) to keep the test short;
    # without update_belief, since no object moves in front of the emulators.
    code, err, _ = run_real_push(cli, plugins, tmp_path, PUSH_ONCE, speed_mps=0.25)
    assert code == 0, err
    check_recorded_push(tmp_path / "out")


@pytest.mark.slow
def test_real_push_skill_with_belief_update(
    cli: CliRunner, plugins: Plugins, tmp_path: Path
) -> None:
    tree = "{sequence: [look, choose_action, execute_action, update_belief, stop]}"
    code, err, _ = run_real_push(cli, plugins, tmp_path, tree, speed_mps=0.025)
    assert code == 0, err
    check_recorded_push(tmp_path / "out")


def protective_stop(ur: URControllerProcess, pads: PapillArrayPty) -> None:
    ur.protective_stop()


def tactile_goes_silent(ur: URControllerProcess, pads: PapillArrayPty) -> None:
    pads.silent = True


@pytest.mark.parametrize(
    ("inject", "message"),
    [(protective_stop, "protective stop: motion refused"), (tactile_goes_silent, "stale tactile")],
)
def test_faults_during_a_real_push_stop_the_arm(
    cli: CliRunner,
    plugins: Plugins,
    tmp_path: Path,
    inject: Callable[[URControllerProcess, PapillArrayPty], None],
    message: str,
) -> None:
    code, err, state = run_real_push(cli, plugins, tmp_path, PUSH_ONCE, 0.25, inject)
    assert code != 0
    assert message in err
    assert np.allclose(state["speed"], 0.0)  # the arm was stopped (or never resumed)
    assert "unlock protective stop" not in state["dashboard"]
