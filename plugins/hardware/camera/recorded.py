"""``camera.recorded``: replays recorded RGB-D frames, so the shape pipeline runs on real
recordings, and ``write_frame`` / ``record_frames`` to make such recordings.

A recording is a directory of ``.npz`` files, one per frame, replayed in name order
(``frame_000000.npz`` ...), loaded with ``allow_pickle=False``:

- ``depth_m``: [H, W] float, metres along the optical axis, NaN where nothing was measured;
- ``intrinsics``: [3, 3] pinhole matrix K;
- ``world_from_camera``: [4, 4] pose of the optical frame (x right, y down, z forward);
- ``rgb`` (optional): [H, W, 3] uint8.

The camera is fixed (``movable = False``): ``move_to`` raises; skills take one view.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import Field
from vistac.component import Component, ComponentConfig, ComponentContext, SkillPath
from vistac.errors import DataError, HardwareError
from vistac.plugins.hardware.camera.image import resample
from vistac.types import RGBD, CameraIntrinsics, PixelWindow, Viewpoint


def write_frame(directory: Path, index: int, frame: RGBD) -> Path:
    """Save ``frame`` as ``directory/frame_{index:06d}.npz`` (the format above)."""
    directory.mkdir(parents=True, exist_ok=True)
    k = frame.intrinsics
    arrays: dict[str, Any] = {
        "depth_m": frame.depth_m,
        "intrinsics": np.array([[k.fx, 0.0, k.cx], [0.0, k.fy, k.cy], [0.0, 0.0, 1.0]]),
        "world_from_camera": frame.world_from_camera,
    }
    if frame.rgb is not None:
        arrays["rgb"] = frame.rgb
    path = directory / f"frame_{index:06d}.npz"
    np.savez_compressed(path, **arrays)
    return path


def record_frames(camera: Any, directory: Path, count: int) -> list[Path]:
    """Capture ``count`` frames from any ``Camera`` into ``directory``."""
    return [write_frame(directory, i, camera.capture()) for i in range(count)]


def load_frame(path: Path) -> RGBD:
    """Read one recorded frame; DataError naming the file and the problem."""
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {name: data[name] for name in data.files}
    except (OSError, ValueError) as exc:
        raise DataError(f"{path}: not a readable .npz frame ({exc})") from exc
    missing = {"depth_m", "intrinsics", "world_from_camera"} - set(arrays)
    if missing:
        raise DataError(f"{path}: missing arrays {sorted(missing)}")
    depth = np.asarray(arrays["depth_m"], dtype=np.float64)
    k = np.asarray(arrays["intrinsics"], dtype=np.float64)
    if depth.ndim != 2 or k.shape != (3, 3):
        raise DataError(
            f"{path}: depth_m must be [H, W] and intrinsics [3, 3], got {depth.shape} and {k.shape}"
        )
    rgb = arrays.get("rgb")
    if rgb is not None and (rgb.shape != (*depth.shape, 3) or rgb.dtype != np.uint8):
        raise DataError(f"{path}: rgb must be uint8 [{depth.shape[0]}, {depth.shape[1]}, 3]")
    intrinsics = CameraIntrinsics(
        depth.shape[1], depth.shape[0], k[0, 0], k[1, 1], k[0, 2], k[1, 2]
    )
    return RGBD(depth, intrinsics, arrays["world_from_camera"], time.monotonic(), rgb)


class RecordedCamera(Component):
    """Implements the ``Camera`` protocol by replaying a recording (fixed camera)."""

    kind = "camera"
    movable = False

    class Config(ComponentConfig):
        directory: SkillPath = Path("recording")
        """Folder of ``.npz`` frames (relative to the skill file)."""
        at_end: Literal["loop", "hold"] = "loop"
        """After the last frame: start again, or keep returning the last one."""
        max_frames: int = Field(default=10_000, gt=0)

    def __init__(self, config: Config, ctx: ComponentContext) -> None:
        super().__init__(config, ctx)
        directory = Path(config.directory)
        if not directory.is_dir():
            raise DataError(
                f"camera.recorded: recording folder {directory} does not exist; set "
                "components.camera.with.directory"
            )
        self.paths = sorted(directory.glob("*.npz"))[: config.max_frames]
        if not self.paths:
            raise DataError(f"camera.recorded: no .npz frames in {directory}")
        self.frames = [load_frame(path) for path in self.paths]
        self.index = 0

    def move_to(self, view: Viewpoint) -> None:
        raise HardwareError(
            "camera.recorded is a fixed camera and cannot move; use one view (max_views: 1)"
        )

    def capture(
        self, width: int | None = None, height: int | None = None, window: PixelWindow | None = None
    ) -> RGBD:
        """The next recorded frame, stamped now, optionally resampled."""
        frame = self.frames[self.index]
        if self.index + 1 < len(self.frames):
            self.index += 1
        elif self.config.at_end == "loop":
            self.index = 0
        stamped = RGBD(
            frame.depth_m, frame.intrinsics, frame.world_from_camera, time.monotonic(), frame.rgb
        )
        return resample(stamped, width, height, window)
