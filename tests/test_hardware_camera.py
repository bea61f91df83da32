"""``camera.recorded`` replaying frames recorded from the simulator, and ``camera.rgbd`` on
an OpenCV image sequence (the live backends need a device)."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from conftest import SKILLS
from vistac.errors import ConfigError, DataError, HardwareError
from vistac.pluginmanager import Plugins
from vistac.plugins.hardware.camera.recorded import record_frames
from vistac.testing import build_components, check_component
from vistac.types import PixelWindow, Viewpoint

SIM = {
    "world": {"plugin": "sim.mujoco", "with": {"object": str(SKILLS / "objects/rect1.yaml")}},
    "camera": {"plugin": "sim.depth_camera", "with": {"width": 80, "height": 60}},
}


def record_sim(plugins: Plugins, tmp_path: Path, count: int) -> tuple[Path, list[Any]]:
    ctx = build_components(SIM, tmp_path / "sim", plugins=plugins)
    camera = ctx.component("camera")
    folder = tmp_path / "recording"
    record_frames(camera, folder, count)
    frames = [np.load(p, allow_pickle=False) for p in sorted(folder.glob("*.npz"))]
    ctx.close_all()
    return folder, frames


def recorded(plugins: Plugins, tmp_path: Path, **options: Any) -> Any:
    components = {"camera": {"plugin": "camera.recorded", "with": options}}
    return build_components(components, tmp_path, plugins=plugins).component("camera")


def test_replays_sim_frames_in_order_and_loops(plugins: Plugins, tmp_path: Path) -> None:
    folder, frames = record_sim(plugins, tmp_path, 2)
    camera = recorded(plugins, tmp_path, directory=str(folder))
    assert not camera.movable
    first, second, third = camera.capture(), camera.capture(), camera.capture()
    assert np.array_equal(first.depth_m, frames[0]["depth_m"], equal_nan=True)
    assert np.array_equal(second.depth_m, frames[1]["depth_m"], equal_nan=True)
    assert np.array_equal(third.depth_m, first.depth_m, equal_nan=True)  # looped
    assert np.allclose(first.world_from_camera, frames[0]["world_from_camera"])
    assert first.intrinsics.fx == pytest.approx(frames[0]["intrinsics"][0, 0])
    assert len(first.point_cloud()) > 1000  # the table and the object are in view
    small = camera.capture(32, 24)
    assert small.depth_m.shape == (24, 32) and small.intrinsics.width == 32
    assert abs(small.timestamp_s - time.monotonic()) < 1.0  # replayed now, on the run clock
    with pytest.raises(HardwareError, match="fixed camera"):
        camera.move_to(Viewpoint(np.zeros(3), np.ones(3)))


def test_recorded_validation_errors(plugins: Plugins, tmp_path: Path) -> None:
    with pytest.raises(DataError, match="does not exist"):
        recorded(plugins, tmp_path, directory=str(tmp_path / "missing"))
    (tmp_path / "empty").mkdir()
    with pytest.raises(DataError, match=r"no \.npz frames"):
        recorded(plugins, tmp_path, directory=str(tmp_path / "empty"))
    bad = tmp_path / "bad"
    bad.mkdir()
    np.savez(
        bad / "frame_000000.npz",
        depth_m=np.zeros((4, 4)),
        intrinsics=np.eye(2),
        world_from_camera=np.eye(4),
    )
    with pytest.raises(DataError, match=r"intrinsics \[3, 3\]"):
        recorded(plugins, tmp_path, directory=str(bad))
    np.savez(bad / "frame_000000.npz", depth_m=np.zeros((4, 4)))
    with pytest.raises(DataError, match="missing arrays"):
        recorded(plugins, tmp_path, directory=str(bad))


def test_recorded_camera_conforms(plugins: Plugins, tmp_path: Path) -> None:
    folder, _ = record_sim(plugins, tmp_path, 1)
    check_component(recorded(plugins, tmp_path, directory=str(folder)), advance=time.sleep)


def write_depth_images(folder: Path, count: int) -> str:
    folder.mkdir()
    for i in range(count):
        depth_units = np.full((30, 40), 50 + i, dtype=np.uint8)  # 50 cm + i cm at 1 cm/unit
        depth_units[:5] = 0  # no return
        cv2.imwrite(str(folder / f"depth_{i:03d}.png"), depth_units)
    return str(folder / "depth_%03d.png")


def test_rgbd_camera_on_an_image_sequence(plugins: Plugins, tmp_path: Path) -> None:
    pattern = write_depth_images(tmp_path / "seq", 4)
    options = {
        "backend": "images",
        "device": pattern,
        "width": 40,
        "height": 30,
        "fx": 50.0,
        "fy": 50.0,
        "cx": 19.5,
        "cy": 14.5,
        "depth_scale_m": 0.01,
    }
    ctx = build_components(
        {"camera": {"plugin": "camera.rgbd", "with": options}}, tmp_path, plugins=plugins
    )
    camera = ctx.component("camera")
    frame = camera.capture()
    assert np.all(np.isnan(frame.depth_m[:5]))
    assert np.allclose(frame.depth_m[5:], 0.5)
    assert np.allclose(camera.capture().depth_m[5:], 0.51)
    assert camera.capture(20, 15).depth_m.shape == (15, 20)
    crop = camera.capture(window=PixelWindow(10, 0, 20, 10))  # the 4th frame, rows 0-4 dropped
    assert crop.intrinsics.cx == pytest.approx(9.5) and np.isnan(crop.depth_m[:5]).all()
    with pytest.raises(HardwareError, match="no more frames"):
        camera.capture()
    camera.close()


def test_rgbd_camera_missing_device_is_a_clear_error(plugins: Plugins, tmp_path: Path) -> None:
    options = {"backend": "images", "device": str(tmp_path / "none_%03d.png")}
    with pytest.raises(HardwareError, match="cannot open images device"):
        build_components(
            {"camera": {"plugin": "camera.rgbd", "with": options}}, tmp_path, plugins=plugins
        )


def test_rgbd_camera_conforms(plugins: Plugins, tmp_path: Path) -> None:
    options: dict[str, Any] = {"backend": "images", "width": 40, "height": 30, "cx": 19.5}
    options |= {"device": write_depth_images(tmp_path / "seq", 5), "cy": 14.5}
    components = {"camera": {"plugin": "camera.rgbd", "with": options}}
    camera = build_components(components, tmp_path, plugins=plugins).component("camera")
    check_component(camera, advance=time.sleep)
    camera.close()


def test_rgbd_camera_refuses_a_mirrored_pose(plugins: Plugins, tmp_path: Path) -> None:
    mirror = [[1, 0, 0, 0], [0, 1, 0, 0.45], [0, 0, -1, 0.8], [0, 0, 0, 1]]  # orthonormal, det -1
    options = {"backend": "images", "world_from_camera": mirror}
    with pytest.raises(ConfigError, match=r"with\.world_from_camera: Value error, "):
        build_components(
            {"camera": {"plugin": "camera.rgbd", "with": options}}, tmp_path, plugins=plugins
        )


class FakeLiveCapture:
    """A live OpenCV capture that records the API it was opened with and the flags asked."""

    opened: list[tuple[int, int]] = []
    retrieved: list[int] = []

    def __init__(self, index: int, api: int) -> None:
        FakeLiveCapture.opened.append((index, api))

    def isOpened(self) -> bool:  # noqa: N802 (OpenCV's name)
        return True

    def grab(self) -> bool:
        return True

    def retrieve(self, flag: int) -> tuple[bool, np.ndarray]:
        """Depth (500 mm) first, then a BGR image."""
        FakeLiveCapture.retrieved.append(flag)
        if len(FakeLiveCapture.retrieved) == 1:
            return True, np.full((30, 40), 500, dtype=np.uint16)
        return True, np.zeros((30, 40, 3), dtype=np.uint8)

    def release(self) -> None:
        pass


@pytest.mark.parametrize(
    ("backend", "api", "flags"),
    [
        ("openni2", cv2.CAP_OPENNI2, [cv2.CAP_OPENNI_DEPTH_MAP, cv2.CAP_OPENNI_BGR_IMAGE]),
        ("realsense", cv2.CAP_INTELPERC, [cv2.CAP_INTELPERC_DEPTH_MAP, cv2.CAP_INTELPERC_IMAGE]),
    ],
)
def test_rgbd_camera_retrieves_with_its_backends_flags(
    plugins: Plugins, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, backend: str, api: int,
    flags: list[int],
) -> None:  # fmt: skip
    monkeypatch.setattr(cv2, "VideoCapture", FakeLiveCapture)
    monkeypatch.setattr(FakeLiveCapture, "opened", [])
    monkeypatch.setattr(FakeLiveCapture, "retrieved", [])
    options = {"backend": backend, "device": "2", "width": 40, "height": 30}
    components = {"camera": {"plugin": "camera.rgbd", "with": options}}
    camera = build_components(components, tmp_path, plugins=plugins).component("camera")
    assert np.allclose(camera.capture().depth_m, 0.5)
    assert FakeLiveCapture.opened == [(2, api)]
    assert FakeLiveCapture.retrieved == flags
    assert cv2.CAP_INTELPERC_IMAGE != cv2.CAP_OPENNI_BGR_IMAGE  # 3 and 5: the flag matters
