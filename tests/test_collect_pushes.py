"""End to end: `vistac run skills/collect_pushes.yaml` writes the dataset the models train on."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from conftest import SKILLS, run_vistac
from vistac.types import CameraIntrinsics


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("collect") / "out"
    result = run_vistac(
        "run",
        str(SKILLS / "collect_pushes.yaml"),
        "--out",
        str(out),
        "--set",
        "tree.sequence.0.repeat.max=3",
        "--seed",
        "1",
    )
    assert result.returncode == 0, result.stderr
    assert (
        "looked from" in result.stdout and str(out) in result.stdout
    )  # what it did, where data is
    return out


def test_run_files(run_dir: Path) -> None:
    run = json.loads((run_dir / "run.json").read_text())
    assert run["status"] == "success" and run["seed"] == 1
    assert {"mujoco", "numpy", "vistac"} <= set(run["versions"])
    summary = json.loads((run_dir / "summary.json").read_text())
    assert len(summary["episodes"]) == 3 and summary["views"] == 12
    assert summary["ground_truth"]["parameters"]["m_0"] == pytest.approx(0.8)


def test_episodes_hold_the_stream_at_15_hz(run_dir: Path) -> None:
    episodes = sorted((run_dir / "episodes").iterdir())
    assert [e.name for e in episodes] == ["0000", "0001", "0002"]
    for folder in episodes:
        data = np.load(folder / "data.npz", allow_pickle=False)
        meta = json.loads((folder / "meta.json").read_text())
        steps = meta["steps"]
        assert steps == 75  # 5 s at 15 Hz
        # 15 Hz, each period rounded to whole 2 ms physics steps.
        assert np.allclose(np.diff(data["time_s"]), 1 / 15, atol=0.0021)
        assert np.mean(np.diff(data["time_s"])) == pytest.approx(1 / 15, abs=1e-4)
        assert data["tactile_force_n"].shape == (steps, 2, 2)
        assert data["arm_pose"].shape == (steps, 4)
        assert data["depth_m"].shape == (steps, 64, 64)
        assert data["object_pose"].shape == (steps, 1, 3)
        assert meta["action"]["kind"] in ("push", "pull")
        assert meta["ground_truth"]["parameters"]["f_0"] == pytest.approx(0.3)
        # The object moved during the interaction and the pads felt it.
        assert (
            np.linalg.norm(data["object_pose"][-1, 0, :2] - data["object_pose"][0, 0, :2]) > 0.005
        )
        assert np.abs(data["tactile_force_n"]).max() > 0.5


def test_views_are_recorded(run_dir: Path) -> None:
    view = np.load(run_dir / "views/0000.npz", allow_pickle=False)
    assert view["depth_m"].shape == (240, 320)
    assert view["world_from_camera"].shape == (4, 4)
    assert np.load(run_dir / "views/cloud.npz", allow_pickle=False)["points_m"].shape[1] == 3


def test_depth_images_are_cropped_to_the_object(run_dir: Path) -> None:
    """The per-step depth image covers the object and where the action moves it, at more
    pixels per metre than the whole 320x240 frame resampled to 64x64 would give."""
    whole = CameraIntrinsics.from_fov(320, 240, np.radians(58.0)).scaled(64, 64)
    for folder in sorted((run_dir / "episodes").iterdir()):
        data = np.load(folder / "data.npz", allow_pickle=False)
        fx, fy, cx, cy = data["depth_intrinsics"][0]
        assert fx > 1.5 * whole.fx and fy > whole.fy
        k = CameraIntrinsics(64, 64, fx, fy, cx, cy)
        for pose, camera in zip(data["object_pose"], data["camera_pose"], strict=True):
            centre = np.array([[pose[0, 0], pose[0, 1], 0.02]])
            u, v = k.project(camera, centre)[0]
            assert 0 <= u < 64 and 0 <= v < 64, "the object stays in the image"
