"""``camera.rgbd``: a live RGB-D camera through OpenCV's ``VideoCapture``.

Backends: ``openni2`` and ``realsense`` (OpenCV's CAP_OPENNI2 / CAP_INTELPERC: the depth map
and the colour image of one grab), or ``images`` (an image sequence such as
``depth_%04d.png`` whose first channel is depth in ``depth_scale_m`` units; for recorded
streams and tests). Intrinsics and the fixed ``world_from_camera`` pose come from the config
(calibrate them once). The camera is fixed (``movable = False``): ``move_to`` raises and
skills take one view (``max_views: 1``). Every grab has a deadline.
"""

from __future__ import annotations

import logging
import time
from typing import Any, Literal

import numpy as np
from pydantic import Field, field_validator
from vistac.component import Component, ComponentConfig, ComponentContext
from vistac.errors import HardwareError
from vistac.plugins.hardware.camera.image import resample
from vistac.plugins.hardware.deadline import call_with_deadline
from vistac.types import RGBD, CameraIntrinsics, FloatArray, PixelWindow, Viewpoint

log = logging.getLogger(__name__)

Pose = tuple[
    tuple[float, float, float, float],
    tuple[float, float, float, float],
    tuple[float, float, float, float],
    tuple[float, float, float, float],
]
_LOOKING_DOWN: Pose = (
    (1.0, 0.0, 0.0, 0.0),
    (0.0, -1.0, 0.0, 0.45),
    (0.0, 0.0, -1.0, 0.8),
    (0.0, 0.0, 0.0, 1.0),
)
_LIVE_FLAGS = {  # backend: OpenCV API, depth map and BGR colour retrieve flags (cv2 names)
    "openni2": ("CAP_OPENNI2", "CAP_OPENNI_DEPTH_MAP", "CAP_OPENNI_BGR_IMAGE"),
    "realsense": ("CAP_INTELPERC", "CAP_INTELPERC_DEPTH_MAP", "CAP_INTELPERC_IMAGE"),
}


class RGBDCamera(Component):
    """Implements the ``Camera`` protocol on a fixed live RGB-D camera."""

    kind = "camera"
    movable = False

    class Config(ComponentConfig):
        backend: Literal["openni2", "realsense", "images"] = "openni2"
        device: str = "0"
        """Device index for openni2/realsense, or a path pattern for ``images``."""
        width: int = Field(default=640, gt=0)
        height: int = Field(default=480, gt=0)
        fx: float = Field(default=525.0, gt=0.0)
        fy: float = Field(default=525.0, gt=0.0)
        cx: float = 319.5
        cy: float = 239.5
        depth_scale_m: float = Field(default=0.001, gt=0.0)
        """Metres per depth unit (1 mm for OpenNI / RealSense)."""
        min_range_m: float = Field(default=0.1, ge=0.0)
        max_range_m: float = Field(default=3.0, gt=0.0)
        world_from_camera: Pose = _LOOKING_DOWN
        """Fixed extrinsic: pose of the optical frame in the world (robot base) frame."""
        grab_timeout_s: float = Field(default=1.0, gt=0.0)

        @field_validator("world_from_camera")
        @classmethod
        def _rigid(cls, value: Pose) -> Pose:
            pose = np.asarray(value)
            rotation = pose[:3, :3]
            orthonormal = np.allclose(rotation @ rotation.T, np.eye(3), atol=1e-6)
            proper = np.isclose(np.linalg.det(rotation), 1.0, atol=1e-6)  # -1: a mirror
            if not (orthonormal and proper and np.allclose(pose[3], [0, 0, 0, 1])):
                raise ValueError(
                    "world_from_camera must be a rigid transform (a rotation with det +1, "
                    "not a mirror, and a translation; last row 0 0 0 1)"
                )
            return value

    def __init__(self, config: Config, ctx: ComponentContext) -> None:
        super().__init__(config, ctx)
        import cv2

        self.cv2 = cv2
        self.intrinsics = CameraIntrinsics(
            config.width, config.height, config.fx, config.fy, config.cx, config.cy
        )
        self.world_from_camera = np.asarray(config.world_from_camera, dtype=np.float64)
        self.depth_flag = self.colour_flag = 0
        self.capture_device = self._open()

    def _open(self) -> Any:
        cv2, config = self.cv2, self.config
        if config.backend == "images":
            device = cv2.VideoCapture(config.device, cv2.CAP_IMAGES)
        else:
            api, self.depth_flag, self.colour_flag = (
                getattr(cv2, name) for name in _LIVE_FLAGS[config.backend]
            )
            device = cv2.VideoCapture(int(config.device), api)
        if not device.isOpened():
            raise HardwareError(
                f"camera.rgbd: cannot open {config.backend} device {config.device!r}; check the "
                "cable, the device index and that OpenCV was built with this backend"
            )
        return device

    def move_to(self, view: Viewpoint) -> None:
        raise HardwareError("camera.rgbd is a fixed camera and cannot move; use max_views: 1")

    def _grab(self) -> tuple[FloatArray, np.ndarray | None]:
        """Depth in sensor units [H, W] and BGR colour or None."""
        device = self.capture_device
        if self.config.backend == "images":
            ok, image = device.read()
            if not ok:
                raise HardwareError("camera.rgbd: the image sequence has no more frames")
            return np.asarray(image[..., 0] if image.ndim == 3 else image, np.float64), None
        if not device.grab():
            raise HardwareError("camera.rgbd: grab failed (camera unplugged?)")
        depth_ok, depth = device.retrieve(flag=self.depth_flag)
        colour_ok, colour = device.retrieve(flag=self.colour_flag)
        if not depth_ok:
            raise HardwareError("camera.rgbd: no depth map in the grabbed frame")
        return np.asarray(depth, np.float64), colour if colour_ok else None

    def capture(
        self, width: int | None = None, height: int | None = None, window: PixelWindow | None = None
    ) -> RGBD:
        raw, colour = call_with_deadline(self._grab, self.config.grab_timeout_s, "camera grab")
        if raw.shape != (self.config.height, self.config.width):
            raise HardwareError(
                f"camera.rgbd: frame is {raw.shape[1]}x{raw.shape[0]}, config says "
                f"{self.config.width}x{self.config.height}; fix width/height"
            )
        depth_m = raw * self.config.depth_scale_m
        depth_m[(depth_m < self.config.min_range_m) | (depth_m > self.config.max_range_m)] = np.nan
        rgb = None
        if colour is not None and colour.shape[:2] == raw.shape:
            rgb = np.ascontiguousarray(colour[..., ::-1], dtype=np.uint8)
        frame = RGBD(depth_m, self.intrinsics, self.world_from_camera, time.monotonic(), rgb)
        return resample(frame, width, height, window)

    def close(self) -> None:
        self.capture_device.release()
