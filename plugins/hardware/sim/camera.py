"""Simulated depth camera: one batched ``mj_multiRay`` call for all pixels.

The camera is a free-floating optical frame (the Panda arm's role in the paper): ``move_to``
places it anywhere. Rays hit every geom, the gripper included (occlusion). Depth is the
z coordinate in the optical frame (x right, y down, z forward), with Gaussian noise, random
dropouts and out-of-range pixels set to NaN.
"""

from __future__ import annotations

import itertools
import math
from concurrent.futures import ThreadPoolExecutor

import mujoco
import numpy as np
from pydantic import Field
from vistac.component import Component, ComponentConfig, ComponentContext
from vistac.errors import DataError
from vistac.plugins.hardware.sim.arm import find_world
from vistac.types import RGBD, CameraIntrinsics, FloatArray, PixelWindow, Viewpoint

_WORLD_UP = np.array([0.0, 0.0, 1.0])
_MIN_RAYS_PER_THREAD = 8192
_CACHED_GEOMETRIES = 8


def look_at(view: Viewpoint) -> FloatArray:
    """World-from-optical-frame pose [4, 4] of a camera at ``view.eye_m`` facing the target.

    Image right is horizontal; for a camera looking straight down, image up is world +y.
    """
    forward = view.target_m - view.eye_m
    norm = np.linalg.norm(forward)
    if norm < 1e-9:
        raise DataError("viewpoint eye and target coincide")
    forward = forward / norm
    right = np.cross(forward, _WORLD_UP)
    if np.linalg.norm(right) < 1e-6:
        right = np.cross(forward, np.array([0.0, 1.0, 0.0]))
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    pose = np.eye(4)
    pose[:3, :3] = np.column_stack([right, down, forward])
    pose[:3, 3] = view.eye_m
    return pose


class SimDepthCamera(Component):
    """Implements the ``Camera`` protocol (movable) by ray casting the MuJoCo scene."""

    kind = "camera"
    movable = True

    class Config(ComponentConfig):
        width: int = Field(default=320, gt=0, le=1280)
        height: int = Field(default=240, gt=0, le=960)
        vertical_fov_deg: float = Field(default=58.0, gt=1.0, lt=170.0)
        depth_noise_m: float = Field(default=0.002, ge=0.0)
        dropout_prob: float = Field(default=0.01, ge=0.0, le=1.0)
        min_range_m: float = Field(default=0.1, ge=0.0)
        max_range_m: float = Field(default=3.0, gt=0.0)
        azimuth_deg: float = -90.0
        """Initial view around the object centre; azimuth from +x (-90: from the robot side)."""
        elevation_deg: float = Field(default=60.0, gt=0.0, le=90.0)
        radius_m: float = Field(default=0.5, gt=0.0)
        ray_threads: int = Field(default=2, ge=1, le=64)
        """Threads sharing the ray casting of one capture (large images only)."""

    def __init__(self, config: Config, ctx: ComponentContext) -> None:
        super().__init__(config, ctx)
        self.world = find_world(ctx, "sim.depth_camera")
        self.intrinsics = CameraIntrinsics.from_fov(
            config.width, config.height, math.radians(config.vertical_fov_deg)
        )
        self._rng = ctx.rng("camera")
        self._rays: dict[CameraIntrinsics, FloatArray] = {}
        self._pool = ThreadPoolExecutor(config.ray_threads, thread_name_prefix="raycast")
        self.move_to(
            Viewpoint.on_hemisphere(
                self.world.object_center_m(),
                config.radius_m,
                math.radians(config.azimuth_deg),
                math.radians(config.elevation_deg),
            )
        )

    def close(self) -> None:
        self._pool.shutdown(wait=False)

    def move_to(self, view: Viewpoint) -> None:
        self.world_from_camera = look_at(view)

    def _pixel_rays(self, intrinsics: CameraIntrinsics) -> FloatArray:
        """Unit-depth rays [H*W, 3] in the camera frame, cached per image geometry."""
        if intrinsics not in self._rays:
            if len(self._rays) >= _CACHED_GEOMETRIES:
                self._rays.clear()
            self._rays[intrinsics] = np.ascontiguousarray(intrinsics.pixel_rays().reshape(-1, 3))
        return self._rays[intrinsics]

    def capture(
        self, width: int | None = None, height: int | None = None, window: PixelWindow | None = None
    ) -> RGBD:
        """One frame; ``window`` crops the full image before the resampling to
        ``width x height``. Only the returned pixels are ray cast, so a small window resampled
        to more pixels than it has is sharper than the full image, not interpolated."""
        intrinsics = self.intrinsics if window is None else self.intrinsics.cropped(window)
        if width is not None or height is not None:
            intrinsics = intrinsics.scaled(width or intrinsics.width, height or intrinsics.height)
        depth_m = self._ray_depth(intrinsics).reshape(intrinsics.height, intrinsics.width)
        return RGBD(
            depth_m=self._corrupt(depth_m),
            intrinsics=intrinsics,
            world_from_camera=self.world_from_camera.copy(),
            timestamp_s=self.world.time_s,
        )

    def _ray_depth(self, intrinsics: CameraIntrinsics) -> FloatArray:
        """Noise-free optical-frame depth per pixel: [H*W], NaN where nothing is hit.

        The rays have unit z in the camera frame, and ``mj_multiRay`` measures distance in
        multiples of the ray vector's length, so the distance is the depth.
        """
        rays_camera = self._pixel_rays(intrinsics)
        count = len(rays_camera)
        rays_world = np.ascontiguousarray(rays_camera @ self.world_from_camera[:3, :3].T)
        geom_id = np.empty(count, dtype=np.int32)
        depth_m = np.empty(count)
        origin = np.ascontiguousarray(self.world_from_camera[:3, 3])
        # mj_multiRay cuts off at a straight-line distance: far enough for the longest ray
        # to reach the depth range (``_corrupt`` applies the range to the depth itself)
        cutoff = self.config.max_range_m * float(np.linalg.norm(rays_camera, axis=1).max())

        def cast(chunk: slice) -> None:
            mujoco.mj_multiRay(
                self.world.model,
                self.world.data,
                origin,
                rays_world[chunk].ravel(),
                None,
                1,
                -1,
                geom_id[chunk],
                depth_m[chunk],
                None,
                chunk.stop - chunk.start,
                cutoff,
            )

        bounds = np.linspace(0, count, self.config.ray_threads + 1).astype(int)
        chunks = [slice(int(a), int(b)) for a, b in itertools.pairwise(bounds)]
        if len(chunks) == 1 or count < _MIN_RAYS_PER_THREAD * len(chunks):
            cast(slice(0, count))
        else:  # mj_multiRay releases the GIL: the chunks run in parallel
            list(self._pool.map(cast, chunks))
        depth_m[geom_id < 0] = np.nan
        return depth_m

    def _corrupt(self, depth_m: FloatArray) -> FloatArray:
        """Add Gaussian noise, drop pixels and apply the range limits: [H, W] -> [H, W]."""
        noise = self._rng.standard_normal(depth_m.shape, dtype=np.float32)
        noisy = depth_m + self.config.depth_noise_m * noise
        dropped = self._rng.random(depth_m.shape) < self.config.dropout_prob
        outside = (noisy < self.config.min_range_m) | (noisy > self.config.max_range_m)
        noisy[dropped | outside] = np.nan
        return noisy
