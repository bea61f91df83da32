"""Observation model of the dual filter (paper 1, III-F "Update Step", eq. 27-30).

The observation is ``z = [depth (H*W), force (2)]``: the 64x64 depth image of the camera's
last viewpoint, flattened row-major, followed by the total contact force on the fingers
(world x, y, N), 4098 values by default. The expected observation of a sigma point renders the
initial segmented object cloud moved rigidly with each link to the sigma point's planar link
poses (projective transformation, eq. 27) and appends the process model's predicted force
(eq. 28). ``R = diag(sigma_v^2 x H*W, sigma_t^2 x 2)`` comes from ``ObsNoiseNet`` (eq. 29-30).

Conventions:

- depth is the z coordinate in the optical frame (x right, y down, z forward), as
  ``SimDepthCamera`` returns it; pixel (row v, column u) has its centre at ``(u, v)`` in
  ``CameraIntrinsics`` coordinates;
- background: a pixel that no object point covers shows the table plane z = 0 along that
  pixel's ray, or ``max_range_m`` where the ray misses the table or meets it beyond the range;
- no return: non-finite observed depth pixels (NaN, the sensor's "nothing") are replaced by the
  same background value, so they carry no innovation;
- splat: each object point covers the ``splat_px x splat_px`` pixels whose centres are nearest
  to its projection (1: the nearest pixel only), which fills the holes a sparse cloud leaves.

All tensors are float64 (``DTYPE``) on the CPU.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Any

import torch
from numpy.typing import NDArray
from torch import Tensor, nn
from vistac.plugins.filters.state import DTYPE, StateLayout
from vistac.types import CameraIntrinsics

logger = logging.getLogger(__name__)

TensorLike = Tensor | NDArray[Any]
N_FORCE = 2
"""Tactile values at the end of the observation: total contact force (world x, y, N)."""


def _rotation_z(theta_rad: Tensor) -> Tensor:
    """[...] -> [..., 2, 2] planar rotation matrices."""
    cos, sin = theta_rad.cos(), theta_rad.sin()
    return torch.stack([torch.stack([cos, -sin], -1), torch.stack([sin, cos], -1)], -2)


def _check_shape(name: str, tensor: Tensor, shape: tuple[int, ...]) -> None:
    """Raise ValueError unless the trailing dimensions of ``tensor`` equal ``shape``."""
    if tensor.dim() < len(shape) or tuple(tensor.shape[tensor.dim() - len(shape) :]) != shape:
        expected = ", ".join(map(str, shape))
        raise ValueError(f"{name}: expected shape [..., {expected}], got {list(tensor.shape)}")


_SCRATCH_SIZES = 4
"""Render sizes (image counts) whose scratch tensors a projector keeps; more are dropped."""
RENDER_DTYPE = torch.float32
"""The z-buffer's working type: float32 pixel coordinates are exact to 1e-5 px and depths to
3e-8 m at 0.5 m, and half the bytes of float64 take a render of 100 images of 2,000 points
through the cache (the filter step's largest cost). Rendered images are float64 again."""


@dataclass(frozen=True)
class _RenderScratch:
    """Working tensors of a render of N images of P points, kept between calls: fresh
    multi-megabyte tensors on every call cost more in page faults than the arithmetic."""

    pixel: Tensor
    """[3, N, P] homogeneous pixel coordinates (u z, v z, z) in the padded image
    (``RENDER_DTYPE``, as every working tensor of the z-buffer but the flat indices)."""
    depth: Tensor
    """[N, P] depth clamped into the range, then the value each point scatters (used only
    when some point is out of range)."""
    dropped: Tensor
    """[N, P] bool: outside the depth range."""
    flat: Tensor
    """[N, P] flat index of each footprint's first pixel (float64, exact integers)."""
    index: Tensor
    """[N, P] the same as int64."""
    padded: Tensor
    """[N, H + 2 pad, W + 2 pad] the z-buffer."""
    image_start: Tensor
    """[N, 1] flat index of each image's first padded pixel (float64)."""

    @classmethod
    def allocate(cls, n_images: int, n_points: int, padded_hw: tuple[int, int]) -> _RenderScratch:
        padded_size = padded_hw[0] * padded_hw[1]
        image_start = torch.arange(n_images, dtype=DTYPE)[:, None] * padded_size
        return cls(
            pixel=torch.empty(3, n_images, n_points, dtype=RENDER_DTYPE),
            depth=torch.empty(n_images, n_points, dtype=RENDER_DTYPE),
            dropped=torch.empty(n_images, n_points, dtype=torch.bool),
            flat=torch.empty(n_images, n_points, dtype=DTYPE),
            index=torch.empty(n_images, n_points, dtype=torch.int64),
            padded=torch.empty(n_images, *padded_hw, dtype=RENDER_DTYPE),
            image_start=image_start,
        )


class DepthProjector:
    """Renders the initial segmented object cloud at planar link poses (eq. 27).

    Each point moves rigidly with its link: for the initial link pose ``(x0, y0, theta0)`` and a
    new pose ``(x, y, theta)``, the point rotates about z by ``theta - theta0`` around the
    link's origin and translates by ``(x - x0, y - y0)``; its height is unchanged. The moved
    points are projected with the pinhole model and z-buffered with a scatter-min over the
    flattened (batch, pixel) index: no Python loop over points or sigma points. The rigid
    motion, the camera pose and the intrinsics are one linear map per image, applied to all
    points by a single matrix product. The working tensors are kept between calls (per image
    count), so one projector must not render from two threads at once.

    Not differentiable with respect to the poses: the pixel a point lands in is piecewise
    constant, so ``render`` runs without autograd and returns values only (the filter's
    likelihood weights need no gradient through the image).
    """

    def __init__(
        self,
        points_m: TensorLike,
        link_index: TensorLike,
        initial_poses: TensorLike,
        intrinsics: CameraIntrinsics,
        world_from_camera: TensorLike,
        *,
        width_px: int = 64,
        height_px: int = 64,
        splat_px: int = 1,
        min_range_m: float = 0.1,
        max_range_m: float = 3.0,
    ) -> None:
        """Args:
        points_m: [P, 3] segmented object cloud at t0, world frame.
        link_index: [P] int, the link each point belongs to.
        initial_poses: [L, 3] link poses at t0 (x_m, y_m, theta_rad).
        intrinsics: the camera's intrinsics at any resolution; resampled to
            ``width_px x height_px``.
        world_from_camera: [4, 4] pose of the optical frame (x right, y down, z forward).
        splat_px: side of the square footprint of each point in pixels (>= 1).
        min_range_m, max_range_m: points outside this depth range are dropped (the sensor
            returns nothing there); ``max_range_m`` is also the background where a pixel's
            ray misses the table.
        """
        points = torch.as_tensor(points_m, dtype=DTYPE)
        links = torch.as_tensor(link_index, dtype=torch.int64)
        poses0 = torch.as_tensor(initial_poses, dtype=DTYPE)
        pose_wc = torch.as_tensor(world_from_camera, dtype=DTYPE)
        self._validate(points, links, poses0, pose_wc, splat_px, min_range_m, max_range_m)
        self.n_links = poses0.shape[0]
        self.splat_px = splat_px
        self.min_range_m = min_range_m
        self.max_range_m = max_range_m
        self.intrinsics = intrinsics.scaled(width_px, height_px)
        rotation_wc, translation_wc = pose_wc[:3, :3], pose_wc[:3, 3]
        pixel_from_world = self._padded_pixel_from_camera() @ rotation_wc.T
        self._pose_to_map = self._pose_coefficients(pixel_from_world, translation_wc)
        depth_m = (points - translation_wc) @ rotation_wc[:, 2]  # at the initial poses
        self._local, self._link_points = self._link_coordinates(points, links, poses0, depth_m)
        self._footprint = self._footprint_offsets(splat_px, self.intrinsics.width + 2 * splat_px)
        rays = torch.as_tensor(self.intrinsics.pixel_rays(), dtype=DTYPE)  # unit depth
        # [3, H W]: each pixel's ray, axis by axis (ops with 3 entries innermost are slow)
        self._rays_world = (rays @ rotation_wc.T).reshape(-1, 3).T.contiguous()
        self._camera_origin_m = translation_wc
        self.object_top_m = float(points[:, 2].max()) if points.numel() else 0.0
        """Height of the highest cloud point above the table plane (m)."""
        table_m = self._table_depth(translation_wc).to(RENDER_DTYPE)
        self.background_m = table_m.to(DTYPE)  # what the z-buffer holds, exactly
        self._padded_background = torch.nn.functional.pad(table_m, (splat_px,) * 4, value=math.inf)
        self._scratch: dict[int, _RenderScratch] = {}
        logger.debug(
            "DepthProjector: %d points, %d links, %dx%d px, splat %d, %.0f%% background rays "
            "miss the table",
            points.shape[0], self.n_links, width_px, height_px, splat_px,
            100.0 * float((self.background_m == max_range_m).to(DTYPE).mean()),
        )

    @staticmethod
    def _validate(
        points: Tensor, links: Tensor, poses0: Tensor, pose_wc: Tensor, splat_px: int,
        min_range_m: float, max_range_m: float,
    ) -> None:
        if points.dim() != 2 or points.shape[1] != 3 or not bool(points.isfinite().all()):
            raise ValueError(f"points_m: expected finite [P, 3], got {list(points.shape)}")
        if links.shape != points.shape[:1]:
            raise ValueError(f"link_index: expected [{points.shape[0]}], got {list(links.shape)}")
        if poses0.dim() != 2 or poses0.shape[1] != 3 or poses0.shape[0] < 1:
            raise ValueError(f"initial_poses: expected [L, 3], got {list(poses0.shape)}")
        if links.numel() and (int(links.min()) < 0 or int(links.max()) >= poses0.shape[0]):
            raise ValueError(f"link_index: values must lie in [0, {poses0.shape[0]})")
        if pose_wc.shape != (4, 4):
            raise ValueError(f"world_from_camera: expected [4, 4], got {list(pose_wc.shape)}")
        if splat_px < 1:
            raise ValueError(f"splat_px must be >= 1, got {splat_px}")
        if not 0.0 < min_range_m < max_range_m:
            raise ValueError(f"need 0 < min_range_m < max_range_m, got {min_range_m}, "
                             f"{max_range_m}")

    @staticmethod
    def _link_coordinates(
        points: Tensor, links: Tensor, poses0: Tensor, depth_m: Tensor
    ) -> tuple[list[Tensor], list[slice]]:
        """Per link, the coordinates its points' images are linear in: [4, P_l] rows
        (x, y, 1, height), x and y in the link's frame, ``Rz(-theta0) (p_xy - origin0)``; and
        each link's columns of the point order.

        The points are sorted by link, then by their initial depth ``depth_m`` [P], nearest
        first: the z-buffer's minimum then rarely changes after a pixel's first point, which
        halves the scatter-min's time (fewer mispredicted branches); its result does not
        depend on the order.
        """
        by_depth = torch.argsort(depth_m)
        order = by_depth[torch.argsort(links[by_depth], stable=True)]
        points, links = points[order], links[order]
        local_xy = torch.einsum(
            "pji,pj->pi", _rotation_z(poses0[links, 2]), points[:, :2] - poses0[links, :2]
        )
        local = torch.stack(
            [local_xy[:, 0], local_xy[:, 1], torch.ones_like(points[:, 2]), points[:, 2]]
        )
        ends = torch.bincount(links, minlength=poses0.shape[0]).cumsum(0).tolist()
        columns = [slice(start, end) for start, end in zip([0, *ends[:-1]], ends, strict=True)]
        return [local[:, c].to(RENDER_DTYPE) for c in columns], columns

    @staticmethod
    def _pose_coefficients(pixel_from_world: Tensor, translation_wc: Tensor) -> Tensor:
        """[5, 12]: the map of a link's points, ``(u z, v z, z) = A (x, y, 1, height)`` with A
        [3, 4] flattened row-major, is linear in the link pose features (cos theta, sin theta,
        x, y, 1); this is that linear map.

        ``A = [Pxy Rz(theta) | Pxy (x, y) + c | Pz]`` with ``Pxy``, ``Pz`` the pixel images of
        the world x, y and z axes and ``c = -P t_wc`` the camera offset.
        """
        axis_x, axis_y, axis_z = pixel_from_world.T
        offset = -pixel_from_world @ translation_wc
        zero = torch.zeros(3, dtype=DTYPE)
        columns = [  # per feature: the columns (x, y, 1, height) of A
            [axis_x, axis_y, zero, zero],  # cos theta
            [axis_y, -axis_x, zero, zero],  # sin theta
            [zero, zero, axis_x, zero],  # x
            [zero, zero, axis_y, zero],  # y
            [zero, zero, offset, axis_z],  # 1
        ]
        return torch.stack([torch.stack(c, -1).reshape(12) for c in columns])

    def _padded_pixel_from_camera(self) -> Tensor:
        """[3, 3] intrinsic matrix whose homogeneous result ``(u z, v z, z)`` has ``floor(u)``,
        ``floor(v)`` = the column and row of a point's footprint's first pixel in the image
        padded by ``splat_px`` pixels on each side.

        The footprint's first pixel is the one whose corner is nearest to the projection
        shifted by ``-(splat_px - 1) / 2``: ``floor(fx x / z + cx - (splat_px - 1) / 2 + 0.5)``.
        """
        k = self.intrinsics
        offset = self.splat_px - 0.5 * (self.splat_px - 1) + 0.5
        return torch.tensor(
            [[k.fx, 0.0, k.cx + offset], [0.0, k.fy, k.cy + offset], [0.0, 0.0, 1.0]],
            dtype=DTYPE,
        )

    @staticmethod
    def _footprint_offsets(splat_px: int, row_stride: int) -> Tensor:
        """Flat index offsets of a point's footprint from its first pixel: [splat_px^2] int64."""
        steps = torch.arange(splat_px)
        return (steps[:, None] * row_stride + steps[None, :]).reshape(-1)

    def _table_depth(self, translation_wc: Tensor) -> Tensor:
        """Depth of the plane z = 0 along each pixel's ray, ``max_range_m`` where the ray
        misses it or meets it beyond the range: [H, W]."""
        rise_m = self._rays_world[2]  # world z change per metre of depth
        depth_m = (-translation_wc[2] / rise_m).reshape(self.height_px, self.width_px)
        hits = depth_m.isfinite() & (depth_m > 0.0) & (depth_m <= self.max_range_m)
        return torch.where(hits, depth_m, torch.full_like(depth_m, self.max_range_m))

    def world_points(self, depth_m: Tensor) -> Tensor:
        """The world points the pixels of flattened depth images [..., H*W] (m) see:
        [..., H*W, 3]."""
        return torch.stack(self._world_coordinates(depth_m), -1)

    def _world_coordinates(self, depth_m: Tensor) -> tuple[Tensor, ...]:
        """x, y and z (m) [..., H*W] of ``world_points``."""
        return tuple(
            origin + depth_m * ray
            for origin, ray in zip(self._camera_origin_m, self._rays_world, strict=True)
        )

    def robot_pixels(
        self, depth_m: Tensor, tcp_xy_m: Tensor, radius_m: float, margin_m: float
    ) -> Tensor:
        """Pixels of flattened depth images [..., H*W] that may see the robot, given its TCP
        position tcp_xy_m [..., 2]: bool [..., H*W]. The robot is whatever is higher than
        the object's top (``object_top_m``) by more than ``margin_m`` (the arm, the palm), or
        within ``radius_m`` of the TCP in the table plane (the fingers)."""
        x_m, y_m, z_m = self._world_coordinates(depth_m)
        above = z_m > self.object_top_m + margin_m
        dx_m = x_m - tcp_xy_m[..., :1]
        dy_m = y_m - tcp_xy_m[..., 1:]
        return above | (dx_m * dx_m + dy_m * dy_m < radius_m**2)

    @property
    def height_px(self) -> int:
        return self.intrinsics.height

    @property
    def width_px(self) -> int:
        return self.intrinsics.width

    def _pixel_maps(self, link_poses: Tensor) -> Tensor:
        """Per link, the linear map from its ``_local`` coordinates to the homogeneous pixel
        coordinates of each image: link_poses [N, L, 3] (x_m, y_m, theta_rad) ->
        [L, 3 N, 4], rows ordered (u, v, z) then image."""
        theta = link_poses[..., 2]
        x_m, y_m, ones = link_poses[..., 0], link_poses[..., 1], torch.ones_like(theta)
        features = torch.stack([theta.cos(), theta.sin(), x_m, y_m, ones], -1)
        maps = (features @ self._pose_to_map).unflatten(-1, (3, 4))  # [N, L, 3, 4]
        return maps.permute(1, 2, 0, 3).reshape(self.n_links, -1, 4)

    def render(self, link_poses: Tensor) -> Tensor:
        """Expected depth images: [..., C, L, 3] (x_m, y_m, theta_rad) -> [..., C, H, W] (m).

        Any leading shape works; [..., L, 3] -> [..., H, W]. Values only (no autograd).
        """
        poses = torch.as_tensor(link_poses, dtype=DTYPE)
        _check_shape("link_poses", poses, (self.n_links, 3))
        depth_m = torch.empty((*poses.shape[:-2], self.height_px, self.width_px), dtype=DTYPE)
        self.render_into(poses.reshape(-1, self.n_links, 3), depth_m.view(-1, *depth_m.shape[-2:]))
        return depth_m

    def render_into(self, link_poses: Tensor, out: Tensor) -> None:
        """``render`` of link_poses [N, L, 3] written into out [N, H, W] (any strides, e.g. a
        view of the depth part of observation vectors). Values only (no autograd)."""
        n_images = link_poses.shape[0]
        scratch = self._scratch.get(n_images)
        if scratch is None:
            if len(self._scratch) >= _SCRATCH_SIZES:
                del self._scratch[next(iter(self._scratch))]
            padded_h, padded_w = self._padded_background.shape
            n_points = self._link_points[-1].stop
            scratch = _RenderScratch.allocate(n_images, n_points, (padded_h, padded_w))
            self._scratch[n_images] = scratch
        with torch.no_grad():
            pixel = scratch.pixel.view(3 * n_images, -1)
            maps = self._pixel_maps(link_poses.detach()).to(RENDER_DTYPE)
            for link_map, local, columns in zip(maps, self._local, self._link_points, strict=True):
                torch.mm(link_map, local, out=pixel[:, columns])
            out.copy_(self._zbuffer(scratch))

    def _zbuffer(self, scratch: _RenderScratch) -> Tensor:
        """Scatter-min of the points' depth (``scratch.pixel``) into their footprints:
        -> [N, H, W], a view of ``scratch.padded``.

        The image is padded by ``splat_px`` pixels on each side and the footprints' first
        pixels are clamped into the padding, so that no bounds test is needed: what lands in
        the padding is cropped. Dropped points scatter +inf, which ``amin`` ignores.
        """
        k, pad = self.intrinsics, self.splat_px
        padded_w = k.width + 2 * pad
        u_z, v_z, z_m = scratch.pixel
        depth_m, dropped = self._depth_in_range(z_m, scratch)
        col0 = u_z.div_(depth_m).clamp_(0.0, k.width + pad).floor_()
        row0 = v_z.div_(depth_m).clamp_(0.0, k.height + pad).floor_()
        first = torch.add(col0, row0, alpha=padded_w, out=scratch.flat).add_(scratch.image_start)
        index = scratch.index.copy_(first)
        values = depth_m if dropped is None else depth_m.masked_fill_(dropped, math.inf)
        if self.splat_px > 1:
            index = index[..., None] + self._footprint
            values = values[..., None].expand(index.shape)
        padded = scratch.padded
        padded.copy_(self._padded_background.expand_as(padded))
        padded.view(-1).scatter_reduce_(
            0, index.reshape(-1), values.reshape(-1), reduce="amin", include_self=True
        )
        return padded[:, pad : pad + k.height, pad : pad + k.width]

    def _depth_in_range(self, z_m: Tensor, scratch: _RenderScratch) -> tuple[Tensor, Tensor | None]:
        """The points' depth z_m [N, P] clamped into the range (a safe divisor) and the mask
        of the points outside it; ``(z_m, None)`` when every point is in range (the usual
        case, checked in one pass)."""
        nearest_m, farthest_m = torch.aminmax(z_m)
        if self.min_range_m <= nearest_m and farthest_m <= self.max_range_m:
            return z_m, None
        depth_m = torch.clamp(z_m, self.min_range_m, self.max_range_m, out=scratch.depth)
        return depth_m, torch.ne(z_m, depth_m, out=scratch.dropped)


def observation_vector(depth_m: Tensor, force_n: Tensor, background_m: Tensor) -> Tensor:
    """Flatten a depth image and append the tactile values.

    depth_m: [..., H, W], non-finite where the sensor returned nothing; force_n: [..., 2];
    background_m: [H, W] the renderer's background (``DepthProjector.background_m``), which
    replaces the non-finite pixels so that they carry no innovation. Returns [..., H*W + 2].
    """
    depth = torch.as_tensor(depth_m, dtype=DTYPE)
    force = torch.as_tensor(force_n, dtype=DTYPE)
    _check_shape("depth_m", depth, tuple(background_m.shape))
    _check_shape("force_n", force, (N_FORCE,))
    depth = torch.where(depth.isfinite(), depth, background_m)
    return torch.cat([depth.flatten(-2), force], -1)


def split_observation(observation: Tensor, height_px: int, width_px: int) -> tuple[Tensor, Tensor]:
    """Inverse of ``observation_vector``: [..., H*W + 2] -> ([..., H, W], [..., 2])."""
    _check_shape("observation", observation, (height_px * width_px + N_FORCE,))
    depth = observation[..., : height_px * width_px]
    return depth.unflatten(-1, (height_px, width_px)), observation[..., height_px * width_px :]


class ObsNoiseNet(nn.Module):
    """Heteroscedastic observation noise (eq. 29-30).

    A 3-layer CNN on the normalised depth image gives the visual log-variance (one scalar per
    image); a 2-layer MLP on the normalised tactile values gives the tactile log-variance. Each
    log-variance is ``log(std_init^2) + bound * tanh(raw / bound)``: the variances stay
    positive and finite, within a factor ``exp(bound)`` of the initial ones, and start at
    ``visual_std_m^2`` and ``tactile_std_n^2`` (the output layers start near zero).
    """

    log_var_init: Tensor
    """Buffer [2]: initial log-variances (visual, tactile)."""
    evidence_steps: Tensor
    """Buffer []: the integrated autocorrelation time (steps) of the process model's force
    error, measured by ``vistac train``; the filter counts that many steps of an interaction
    as one independent observation (1 until trained)."""

    def __init__(
        self,
        *,
        height_px: int = 64,
        width_px: int = 64,
        visual_std_m: float = 0.005,
        tactile_std_n: float = 0.2,
        log_var_bound: float = math.log(100.0),
        depth_offset_m: float = 0.5,
        depth_scale_m: float = 0.25,
        force_scale_n: float = 5.0,
    ) -> None:
        """Depth is normalised as ``(depth - depth_offset_m) / depth_scale_m`` and force as
        ``force / force_scale_n`` before the networks."""
        super().__init__()
        if min(visual_std_m, tactile_std_n, log_var_bound, depth_scale_m, force_scale_n) <= 0:
            raise ValueError("ObsNoiseNet: stds, bound and scales must be positive")
        self.height_px, self.width_px = height_px, width_px
        self.log_var_bound = log_var_bound
        self.depth_offset_m, self.depth_scale_m = depth_offset_m, depth_scale_m
        self.force_scale_n = force_scale_n
        visual_head, tactile_head = nn.Linear(16, 1), nn.Linear(16, 1)
        with torch.no_grad():  # start near raw = 0, i.e. at the initial variances
            for head in (visual_head, tactile_head):
                head.weight.mul_(0.01)
                head.bias.zero_()
        self.visual = nn.Sequential(
            nn.Conv2d(1, 8, 5, stride=2, padding=2),
            nn.ReLU(),
            nn.Conv2d(8, 16, 3, stride=2, padding=1),
            nn.ReLU(),
            nn.Conv2d(16, 16, 3, stride=2, padding=1),
            nn.ReLU(),
            nn.AdaptiveAvgPool2d(1),
            nn.Flatten(),
            visual_head,
        )
        self.tactile = nn.Sequential(nn.Linear(N_FORCE, 16), nn.ReLU(), tactile_head)
        log_var_init = 2.0 * torch.tensor([math.log(visual_std_m), math.log(tactile_std_n)])
        self.register_buffer("log_var_init", log_var_init)
        self.register_buffer("evidence_steps", torch.tensor(1.0))
        self.to(DTYPE)

    def forward(self, observation: Tensor) -> Tensor:
        """Log-variances (visual, tactile): [..., H*W + 2] -> [..., 2]."""
        depth, force = split_observation(observation, self.height_px, self.width_px)
        batch = depth.shape[:-2]
        image = (depth - self.depth_offset_m) / self.depth_scale_m
        visual = self.visual(image.reshape(-1, 1, self.height_px, self.width_px))
        tactile = self.tactile(force.reshape(-1, N_FORCE) / self.force_scale_n)
        raw = torch.cat([visual, tactile], -1).reshape(*batch, 2)
        bound = self.log_var_bound
        return self.log_var_init + bound * torch.tanh(raw / bound)

    def noise_var(self, observation: Tensor) -> Tensor:
        """Diagonal of R: [..., H*W + 2] -> [..., H*W + 2] = (sigma_v^2 x H*W, sigma_t^2 x 2)."""
        var = self(observation).exp()
        batch = var.shape[:-1]
        visual = var[..., :1].expand(*batch, self.height_px * self.width_px)
        return torch.cat([visual, var[..., 1:].expand(*batch, N_FORCE)], -1)


def unexplained_entries(
    observation: Tensor,
    expected: Tensor,
    n_depth: int,
    margin_m: float | None,
    candidates: Tensor | None = None,
) -> Tensor:
    """Depth entries (the first ``n_depth``) of observation [..., k] nearer than the nearest
    of the expected observations [..., C, k] by more than ``margin_m``, and among
    ``candidates`` (bool [..., n_depth]; None: any): bool [..., k]; all False for
    ``margin_m`` None."""
    mask = torch.zeros(observation.shape, dtype=torch.bool, device=observation.device)
    if margin_m is None:
        return mask
    if candidates is None:
        nearest = expected[..., :n_depth].amin(-2)
        mask[..., :n_depth] = observation[..., :n_depth] < nearest - margin_m
        return mask
    # Only the candidates' columns: the minimum over the points of every column of a
    # [C, 4096] image stack took longer than the rest of this test together.
    columns = candidates.reshape(-1, n_depth).any(0).nonzero()[:, 0]
    nearest = expected.index_select(-1, columns).amin(-2)
    nearer = observation.index_select(-1, columns) < nearest - margin_m
    mask[..., columns] = nearer & candidates.index_select(-1, columns)
    return mask


class ProjectionObservationModel:
    """The filter's observation model: expected observations of sigma points and R."""

    def __init__(
        self,
        layout: StateLayout,
        projector: DepthProjector,
        noise_net: ObsNoiseNet,
        occlusion_margin_m: float | None = 0.01,
        robot_radius_m: float | None = 0.06,
        tactile_std: tuple[float, float] | None = None,
        contact_force_n: float | None = None,
    ) -> None:
        """occlusion_margin_m, robot_radius_m: see ``unexplained``; a margin of None keeps
        every pixel, a radius of None lets any pixel be an occluder. tactile_std: (a in N,
        b) for a tactile std of ``a + b |measured force|`` in place of the noise net's (see
        ``noise_var``); None keeps the noise net's."""
        if projector.n_links != layout.n_links:
            raise ValueError(
                f"projector has {projector.n_links} links, layout {layout.n_links}"
            )
        if (noise_net.height_px, noise_net.width_px) != (projector.height_px, projector.width_px):
            raise ValueError("noise_net and projector image sizes differ")
        self.layout = layout
        self.projector = projector
        self.noise_net = noise_net
        self.occlusion_margin_m = occlusion_margin_m
        self.robot_radius_m = robot_radius_m
        if tactile_std is not None and (tactile_std[0] <= 0 or tactile_std[1] < 0):
            raise ValueError(f"tactile_std: expected (a > 0 N, b >= 0), got {tactile_std}")
        self.tactile_std = tactile_std
        if contact_force_n is not None and contact_force_n < 0:
            raise ValueError(f"contact_force_n: expected >= 0 N, got {contact_force_n}")
        self.contact_force_n = contact_force_n

    @property
    def size(self) -> int:
        """Observation size H*W + 2 (4098 for 64x64)."""
        return self.projector.height_px * self.projector.width_px + N_FORCE

    def expected(self, states: Tensor, force_n: Tensor) -> Tensor:
        """Expected observation per sigma point (eq. 27-28).

        states: [..., C, n]; force_n: [..., C, 2] predicted contact force (process model).
        Returns [..., C, H*W + 2]. Gradients flow to ``force_n`` but not to the states: the
        rendered depth is values only.
        """
        _check_shape("states", states, (self.layout.size,))
        link_poses = self.layout.link_pose(states)[..., :3]  # (x, y, theta) per link
        n_depth = self.size - N_FORCE
        expected = torch.empty((*states.shape[:-1], self.size), dtype=DTYPE)
        flat = expected.view(-1, self.size)
        depth_m = flat[:, :n_depth].unflatten(-1, (self.projector.height_px, -1))
        # the render has no missing pixels: nothing for observation_vector to replace
        self.projector.render_into(link_poses.reshape(-1, self.layout.n_links, 3), depth_m)
        expected[..., n_depth:] = force_n
        return expected

    def observation(self, depth_m: Tensor, force_n: Tensor) -> Tensor:
        """A measured observation: depth [..., H, W] (NaN = no return), force [..., 2] ->
        [..., H*W + 2], no-return pixels set to the renderer's background."""
        return observation_vector(depth_m, force_n, self.projector.background_m)

    def noise_var(self, observation: Tensor) -> Tensor:
        """Diagonal of R: [..., H*W + 2] -> [..., H*W + 2]. With ``tactile_std`` (a, b) the
        two force entries get the variance ``(a + b |f|)^2`` of the measured force f [..., 2]:
        a force model's error that grows with the force, where the noise net's is learned."""
        var = self.noise_net.noise_var(observation)
        if self.tactile_std is None:
            return var
        floor_n, fraction = self.tactile_std
        force_n = observation[..., -N_FORCE:]
        std_n = floor_n + fraction * force_n.norm(dim=-1, keepdim=True)
        return torch.cat([var[..., :-N_FORCE], std_n.square().expand_as(force_n)], -1)

    def unexplained(
        self, observation: Tensor, expected: Tensor, tcp_xy_m: Tensor | None = None
    ) -> Tensor:
        """Depth pixels nearer to the camera than every sigma point's rendering, by more than
        ``occlusion_margin_m``, that may see the robot (``DepthProjector.robot_pixels`` with
        ``robot_radius_m`` about the TCP tcp_xy_m [..., 2]): the gripper or the arm hides the
        object or table there. The robot test keeps a belief that has lost the object: the
        object's own pixels, nearer than every rendering then, still pull it back. Without
        a TCP or a radius any nearer pixel is an occluder. observation [..., k], expected
        [..., C, k] -> bool [..., k].

        With ``contact_force_n``, both tactile entries are unexplained while the measured
        force is weaker than that: without contact the force is zero whatever the parameters,
        so what the points' forces disagree on then is the model's contact onset, not them."""
        n_depth = self.projector.height_px * self.projector.width_px
        candidates = None
        if tcp_xy_m is not None and self.robot_radius_m is not None and self.occlusion_margin_m:
            candidates = self.projector.robot_pixels(
                observation[..., :n_depth], tcp_xy_m, self.robot_radius_m, self.occlusion_margin_m
            )
        mask = unexplained_entries(
            observation, expected, n_depth, self.occlusion_margin_m, candidates
        )
        if self.contact_force_n is not None:
            force_n = observation[..., n_depth:]
            free = force_n.norm(dim=-1, keepdim=True) < self.contact_force_n
            mask[..., n_depth:] = free.expand_as(force_n)
        return mask
