"""Simulated depth camera: the table plane in closed form, ``mj_multiRay`` for the rest.

The camera is a free-floating optical frame (the Panda arm's role in the paper): ``move_to``
places it anywhere. Rays hit every geom, the gripper included (occlusion). Depth is the
z coordinate in the optical frame (x right, y down, z forward), with Gaussian noise, random
dropouts and out-of-range pixels set to NaN.

Only the pixels inside the projected bounding box of a geom other than the table are ray cast
(one batched ``mj_multiRay`` call); every other pixel can only see the table plane, which is
intersected in closed form as MuJoCo's ``ray_plane`` does, so the image is the same.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import mujoco
import numpy as np
from numpy.typing import NDArray
from pydantic import Field
from vistac.component import Component, ComponentConfig, ComponentContext
from vistac.errors import DataError
from vistac.plugins.hardware.sim.arm import find_world
from vistac.types import RGBD, CameraIntrinsics, FloatArray, PixelWindow, Viewpoint

_WORLD_UP = np.array([0.0, 0.0, 1.0])
_MIN_RAYS_PER_THREAD = 4096
"""Fewer rays are cast by the caller; more go to the pool (while the caller draws the noise)."""
_CACHED_VIEWS = 8
"""Image geometries and camera poses whose rays and table depth are kept."""
_TABLE_GEOM = "table"
"""The plane at z = 0, axis-aligned and centred at the origin (see :mod:`.mjcf`)."""
_MJ_MINVAL = 1e-15
"""MuJoCo's ``mjMINVAL``: a ray whose world z is above minus this misses a plane."""
_TABLE_EDGE_MARGIN_M = 1e-9
"""Image corners this close to the table's edge send the whole image through the edge test."""
_BOX_MARGIN_PX = 1
"""Pixels ray cast beyond each geom's projected bounding box (for rounding)."""
_MIN_BOX_DEPTH_M = 1e-6
"""A bounding box reaching closer to the image plane than this may be seen anywhere."""
_BOX_SIGNS = np.array(list(itertools.product((-1.0, 1.0), repeat=3)))
"""The eight corners of a unit box: [8, 3]."""

IntArray = NDArray[np.intp]


@dataclass(frozen=True)
class _View:
    """One image geometry seen from one camera pose: the pixels' world rays and the table.

    The world ray of pixel (u, v), scaled to unit depth, is ``along_v[:, v] + along_u[:, u]``
    (``along_u`` [3, W], ``along_v`` [3, H]); ``table_depth_m`` [H, W] (read-only) is the
    depth of the table, NaN where a ray misses it; ``cutoff_m`` is ``mj_multiRay``'s cutoff.
    """

    along_u: FloatArray
    along_v: FloatArray
    table_depth_m: FloatArray
    cutoff_m: float


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
        self._views: dict[tuple[CameraIntrinsics, bytes], _View] = {}
        model = self.world.model
        table = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, _TABLE_GEOM)
        self._table_half_size_m = model.geom_size[table, :2].copy()
        self._geoms = np.flatnonzero(np.arange(model.ngeom) != table)
        """The geoms other than the table: [G]."""
        aabb = model.geom_aabb[self._geoms]
        self._box_corners_m = aabb[:, None, :3] + _BOX_SIGNS * aabb[:, None, 3:]
        """Bounding box corners [G, 8, 3] in each geom's frame."""
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

    def _view(self, intrinsics: CameraIntrinsics) -> _View:
        """The rays and the table of ``intrinsics`` from the current pose, cached (the table
        does not move)."""
        key = (intrinsics, self.world_from_camera.tobytes())
        if key not in self._views:
            if len(self._views) >= _CACHED_VIEWS:
                self._views.clear()
            self._views[key] = self._new_view(intrinsics)
        return self._views[key]

    def _new_view(self, intrinsics: CameraIntrinsics) -> _View:
        """The rays and the table of ``intrinsics`` from the current pose."""
        pixel_u = np.arange(intrinsics.width, dtype=np.float64)
        pixel_v = np.arange(intrinsics.height, dtype=np.float64)
        x_per_z = (pixel_u - intrinsics.cx) / intrinsics.fx  # as CameraIntrinsics.pixel_rays
        y_per_z = (pixel_v - intrinsics.cy) / intrinsics.fy
        rotation, origin = self.world_from_camera[:3, :3], self.world_from_camera[:3, 3]
        along_u = rotation[:, :1] * x_per_z
        along_v = rotation[:, 1:2] * y_per_z + rotation[:, 2:]
        table_depth_m = self._table_depth(origin, along_u, along_v)
        table_depth_m.flags.writeable = False
        # mj_multiRay cuts off at a straight-line distance: far enough for the longest ray
        # to reach the depth range (``_corrupt`` applies the range to the depth itself)
        longest = math.sqrt(np.max(x_per_z**2) + np.max(y_per_z**2) + 1.0)
        return _View(along_u, along_v, table_depth_m, self.config.max_range_m * longest)

    def capture(
        self, width: int | None = None, height: int | None = None, window: PixelWindow | None = None
    ) -> RGBD:
        """One frame; ``window`` crops the full image before the resampling to
        ``width x height``. Only the returned pixels are ray cast, so a small window resampled
        to more pixels than it has is sharper than the full image, not interpolated."""
        intrinsics = self.intrinsics if window is None else self.intrinsics.cropped(window)
        if width is not None or height is not None:
            intrinsics = intrinsics.scaled(width or intrinsics.width, height or intrinsics.height)
        finish_depth = self._start_ray_depth(intrinsics)
        noise_m, dropped = self._draw_corruption(intrinsics)  # while the rays are cast
        return RGBD(
            depth_m=self._corrupt(finish_depth(), noise_m, dropped),
            intrinsics=intrinsics,
            world_from_camera=self.world_from_camera.copy(),
            timestamp_s=self.world.time_s,
        )

    def _start_ray_depth(self, intrinsics: CameraIntrinsics) -> Callable[[], FloatArray]:
        """Start the ray casting; the function returned waits for it and returns the
        noise-free optical-frame depth per pixel: [H, W], NaN where nothing is hit.

        The rays have unit z in the camera frame, and ``mj_multiRay`` measures distance in
        multiples of the ray vector's length, so the distance is the depth.
        """
        view = self._view(intrinsics)
        depth_m = view.table_depth_m.copy()
        rows, columns = self._pixels_near_geoms(intrinsics)
        rays_world = (view.along_v[:, rows] + view.along_u[:, columns]).T.copy()  # [M, 3]
        finish_cast = self._start_cast(self.world_from_camera[:3, 3], rays_world, view.cutoff_m)

        def finish() -> FloatArray:
            depth_m[rows, columns] = finish_cast()
            return depth_m

        return finish

    def _table_depth(
        self, origin: FloatArray, along_u: FloatArray, along_v: FloatArray
    ) -> FloatArray:
        """Depth [H, W] of the table plane, NaN where a ray misses it, computed as MuJoCo's
        ``ray_plane`` does (rays as in :class:`_View`; ``origin`` [3]: the camera centre)."""
        ray_z = np.add.outer(along_v[2], along_u[2])
        if origin[2] >= 0 and self._sees_only_table(origin, along_u, along_v):
            return np.divide(-origin[2], ray_z, out=ray_z)
        depth_m = np.full_like(ray_z, np.nan)
        if origin[2] < 0:  # the plane faces up (and mj_multiRay's cutoff never drops it)
            return depth_m
        np.divide(-origin[2], ray_z, out=depth_m, where=ray_z < -_MJ_MINVAL)
        for axis in range(2):
            hit_m = np.add.outer(along_v[axis], along_u[axis])
            hit_m *= depth_m
            hit_m += origin[axis]
            depth_m[~(np.abs(hit_m) <= self._table_half_size_m[axis])] = np.nan
        return depth_m

    def _sees_only_table(
        self, origin: FloatArray, along_u: FloatArray, along_v: FloatArray
    ) -> bool:
        """Whether every pixel's ray meets the table inside its edges: true when the four
        image corners' rays do (the image of the table is convex)."""
        x_m, y_m, z_m = origin.tolist()
        half_x_m, half_y_m = (self._table_half_size_m - _TABLE_EDGE_MARGIN_M).tolist()
        for ray_u in along_u[:, [0, -1]].T.tolist():
            for ray_v in along_v[:, [0, -1]].T.tolist():
                ray_x, ray_y, ray_z = (a + b for a, b in zip(ray_v, ray_u, strict=True))
                if ray_z >= -_MJ_MINVAL:
                    return False
                depth = -z_m / ray_z
                if abs(x_m + depth * ray_x) > half_x_m or abs(y_m + depth * ray_y) > half_y_m:
                    return False
        return True

    def _pixels_near_geoms(self, intrinsics: CameraIntrinsics) -> tuple[IntArray, IntArray]:
        """(rows [M], columns [M]) of the pixels whose rays may meet a geom other than the
        table: those in a geom's projected bounding box (every pixel when a box reaches
        behind the image plane)."""
        data, geoms = self.world.data, self._geoms
        rotation, origin = self.world_from_camera[:3, :3], self.world_from_camera[:3, 3]
        camera_from_geoms = data.geom_xmat[geoms].reshape(-1, 3, 3).transpose(0, 2, 1) @ rotation
        offsets_m = (data.geom_xpos[geoms] - origin) @ rotation  # [G, 3]
        corners = self._box_corners_m @ camera_from_geoms + offsets_m[:, None]  # [G, 8, 3]
        corners = corners[corners[..., 2].max(axis=1) >= 0]  # not behind the camera
        width, height = intrinsics.width, intrinsics.height
        near = np.zeros((height, width), dtype=bool)
        if corners.size and corners[..., 2].min() < _MIN_BOX_DEPTH_M:
            near[:] = True
        else:
            uv = corners[..., :2] / corners[..., 2:] * (intrinsics.fx, intrinsics.fy)
            uv += (intrinsics.cx, intrinsics.cy)  # [G', 8, 2]
            bounds = np.concatenate([uv.min(axis=1), uv.max(axis=1)], axis=1)  # [G', 4]
            for u_low, v_low, u_high, v_high in bounds.tolist():
                near[_pixel_span(v_low, v_high, height), _pixel_span(u_low, u_high, width)] = True
        rows, columns = np.nonzero(near)
        return rows, columns

    def _start_cast(
        self, origin: FloatArray, rays_world: FloatArray, cutoff: float
    ) -> Callable[[], FloatArray]:
        """Start ``mj_multiRay`` on ``rays_world`` [M, 3]: in up to ``ray_threads`` pool threads
        for many rays, in the calling thread for few; the function returned waits for it and
        returns the depth [M], NaN where nothing is hit."""
        count = len(rays_world)
        geom_id = np.empty(count, dtype=np.int32)
        depth_m = np.empty(count)

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

        threads = min(self.config.ray_threads, count // _MIN_RAYS_PER_THREAD)
        if threads == 0:
            cast(slice(0, count))
        bounds = np.linspace(0, count, threads + 1).astype(int).tolist() if threads else []
        # mj_multiRay releases the GIL: the chunks run in parallel, and with the caller
        casts = [self._pool.submit(cast, slice(a, b)) for a, b in itertools.pairwise(bounds)]

        def finish() -> FloatArray:
            for done in casts:
                done.result()
            depth_m[geom_id < 0] = np.nan
            return depth_m

        return finish

    def _draw_corruption(
        self, intrinsics: CameraIntrinsics
    ) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
        """The random part of a frame's corruption: (depth noise [H, W] in m, dropped
        pixels [H, W])."""
        shape = (intrinsics.height, intrinsics.width)
        noise_m = self._rng.standard_normal(shape, dtype=np.float32)
        noise_m *= self.config.depth_noise_m
        return noise_m, self._rng.random(shape) < self.config.dropout_prob

    def _corrupt(
        self, depth_m: FloatArray, noise_m: NDArray[np.float32], dropped: NDArray[np.bool_]
    ) -> FloatArray:
        """Add the noise, drop pixels and apply the range limits, in place: [H, W]."""
        depth_m += noise_m
        invalid = dropped
        invalid |= depth_m < self.config.min_range_m
        invalid |= depth_m > self.config.max_range_m
        depth_m[invalid] = np.nan
        return depth_m


def _pixel_span(low: float, high: float, size: int) -> slice:
    """The pixels of an image axis of ``size`` covering the coordinates ``low..high``, with
    a margin (empty when they are beside the image)."""
    start = max(math.floor(low) - _BOX_MARGIN_PX, 0)
    return slice(start, max(min(math.ceil(high) + _BOX_MARGIN_PX + 1, size), start))
