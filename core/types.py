"""Core data types shared by every plugin.

SI units everywhere (m, kg, s, N, rad). World frame: z up, table top at z = 0, robot base at
the origin, +y away from the robot. Arrays are numpy arrays whose shapes are documented per
field; every type validates shapes and finiteness on construction so that a bad sensor
reading fails where it is produced, not three plugins later.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray
from vistac.errors import DataError

FloatArray = NDArray[np.float64]


def _as_float_array(name: str, value: object, shape: tuple[int | None, ...]) -> FloatArray:
    """Convert ``value`` to a float64 array and check its shape (None = any size)."""
    array = np.asarray(value, dtype=np.float64)
    if array.ndim != len(shape) or any(
        want is not None and got != want for got, want in zip(array.shape, shape, strict=True)
    ):
        raise DataError(f"{name}: expected shape {shape}, got {array.shape}")
    return array


def _require_finite(name: str, array: FloatArray) -> None:
    if not np.all(np.isfinite(array)):
        raise DataError(f"{name}: contains NaN or inf values")


@dataclass(frozen=True)
class PixelWindow:
    """A rectangle of an image: columns ``u0 .. u0 + width - 1``, rows ``v0 .. v0 + height - 1``
    (pixels)."""

    u0: int
    v0: int
    width: int
    height: int

    def check(self, image_width: int, image_height: int) -> tuple[int, int, int, int]:
        """(u0, v0, width, height), or DataError unless the window lies inside the image."""
        if (
            self.width <= 0 or self.height <= 0 or self.u0 < 0 or self.v0 < 0
            or self.u0 + self.width > image_width or self.v0 + self.height > image_height
        ):  # fmt: skip
            raise DataError(
                f"pixel window {self.width}x{self.height} at ({self.u0}, {self.v0}) is not "
                f"inside the {image_width}x{image_height} image"
            )
        return self.u0, self.v0, self.width, self.height


@dataclass(frozen=True)
class CameraIntrinsics:
    """Pinhole intrinsics of a depth camera (pixels)."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    def __post_init__(self) -> None:
        if self.width <= 0 or self.height <= 0:
            raise DataError(f"camera size must be positive, got {self.width}x{self.height}")
        if self.fx <= 0 or self.fy <= 0:
            raise DataError(f"focal lengths must be positive, got fx={self.fx}, fy={self.fy}")

    @classmethod
    def from_fov(cls, width: int, height: int, vertical_fov_rad: float) -> CameraIntrinsics:
        """Square pixels, principal point at the image centre."""
        focal = 0.5 * height / np.tan(0.5 * vertical_fov_rad)
        return cls(width, height, focal, focal, (width - 1) / 2.0, (height - 1) / 2.0)

    def scaled(self, width: int, height: int) -> CameraIntrinsics:
        """The same camera resampled to ``width x height`` pixels."""
        sx, sy = width / self.width, height / self.height
        return CameraIntrinsics(
            width,
            height,
            self.fx * sx,
            self.fy * sy,
            (self.cx + 0.5) * sx - 0.5,
            (self.cy + 0.5) * sy - 0.5,
        )

    def cropped(self, window: PixelWindow) -> CameraIntrinsics:
        """The camera seen through ``window`` (a region of interest of this image)."""
        u0, v0, width, height = window.check(self.width, self.height)
        return CameraIntrinsics(width, height, self.fx, self.fy, self.cx - u0, self.cy - v0)

    def project(self, world_from_camera: FloatArray, points_m: FloatArray) -> FloatArray:
        """Pixel coordinates (u, v) [N, 2] of world points [N, 3]; NaN behind the camera."""
        rotation, translation = world_from_camera[:3, :3], world_from_camera[:3, 3]
        camera = (np.asarray(points_m, dtype=np.float64) - translation) @ rotation
        z = np.where(camera[:, 2] > 1e-6, camera[:, 2], np.nan)
        return np.column_stack(
            [self.fx * camera[:, 0] / z + self.cx, self.fy * camera[:, 1] / z + self.cy]
        )

    def window_of(self, world_from_camera: FloatArray, points_m: FloatArray) -> PixelWindow | None:
        """The smallest pixel window that holds the projections of ``points_m`` [N, 3] (world),
        clipped to the image; None when none of them is in view."""
        uv = self.project(world_from_camera, points_m)
        uv = uv[np.isfinite(uv).all(axis=1)]
        size = np.array([self.width, self.height])
        if len(uv) == 0 or np.any(uv.max(axis=0) < -0.5) or np.any(uv.min(axis=0) > size):
            return None  # nothing in front of the camera, or all beside the image
        lo = np.clip(np.floor(uv.min(axis=0) + 0.5), 0, size - 1)
        hi = np.clip(np.floor(uv.max(axis=0) + 0.5), 0, size - 1)
        u0, v0 = int(lo[0]), int(lo[1])
        return PixelWindow(u0, v0, int(hi[0]) - u0 + 1, int(hi[1]) - v0 + 1)

    def pixel_rays(self) -> FloatArray:
        """Unit-depth ray per pixel in the camera frame (x right, y down, z forward).

        Returns: [H, W, 3] with z = 1.
        """
        u = np.arange(self.width, dtype=np.float64)
        v = np.arange(self.height, dtype=np.float64)
        uu, vv = np.meshgrid(u, v)
        return np.stack(
            [(uu - self.cx) / self.fx, (vv - self.cy) / self.fy, np.ones_like(uu)], axis=-1
        )


@dataclass(frozen=True)
class PointCloud:
    """A set of 3D points in the world frame.

    points_m: [N, 3]; normals: [N, 3] unit vectors or None.
    """

    points_m: FloatArray
    normals: FloatArray | None = None

    def __post_init__(self) -> None:
        points = _as_float_array("PointCloud.points_m", self.points_m, (None, 3))
        _require_finite("PointCloud.points_m", points)
        object.__setattr__(self, "points_m", points)
        if self.normals is not None:
            normals = _as_float_array("PointCloud.normals", self.normals, (len(points), 3))
            _require_finite("PointCloud.normals", normals)
            object.__setattr__(self, "normals", normals)

    def __len__(self) -> int:
        return len(self.points_m)

    @staticmethod
    def merge(clouds: list[PointCloud]) -> PointCloud:
        """Concatenate clouds (normals kept only when every cloud has them)."""
        if not clouds:
            return PointCloud(np.zeros((0, 3)))
        points = np.concatenate([c.points_m for c in clouds])
        if all(c.normals is not None for c in clouds):
            normals = np.concatenate([c.normals for c in clouds if c.normals is not None])
            return PointCloud(points, normals)
        return PointCloud(points)


@dataclass(frozen=True)
class RGBD:
    """One depth (and optionally colour) image with its camera.

    depth_m: [H, W], NaN where the sensor returned nothing; rgb: [H, W, 3] uint8 or None;
    world_from_camera: [4, 4] homogeneous pose of the optical frame (x right, y down, z forward).
    """

    depth_m: FloatArray
    intrinsics: CameraIntrinsics
    world_from_camera: FloatArray
    timestamp_s: float
    rgb: NDArray[np.uint8] | None = None

    def __post_init__(self) -> None:
        shape = (self.intrinsics.height, self.intrinsics.width)
        depth = _as_float_array("RGBD.depth_m", self.depth_m, shape)
        pose = _as_float_array("RGBD.world_from_camera", self.world_from_camera, (4, 4))
        _require_finite("RGBD.world_from_camera", pose)
        object.__setattr__(self, "depth_m", depth)
        object.__setattr__(self, "world_from_camera", pose)

    def point_cloud(self) -> PointCloud:
        """Back-project the valid depth pixels into the world frame. Returns N <= H*W points."""
        rays = self.intrinsics.pixel_rays()
        valid = np.isfinite(self.depth_m) & (self.depth_m > 0)
        points_camera = rays[valid] * self.depth_m[valid][:, None]
        rotation, translation = self.world_from_camera[:3, :3], self.world_from_camera[:3, 3]
        return PointCloud(points_camera @ rotation.T + translation)


@dataclass(frozen=True)
class TactileReading:
    """2D (x, y, world frame) contact force per tactile pad.

    force_n: [P, 2] for P pads (2 for the two fingers of a parallel gripper).
    """

    force_n: FloatArray
    timestamp_s: float

    def __post_init__(self) -> None:
        force = _as_float_array("TactileReading.force_n", self.force_n, (None, 2))
        _require_finite("TactileReading.force_n", force)
        object.__setattr__(self, "force_n", force)


@dataclass(frozen=True)
class ArmState:
    """Cartesian state of the tool centre point.

    pose: [4] = (x_m, y_m, z_m, yaw_rad); twist: [4] = (vx, vy, vz in m/s, wz in rad/s).
    protective_stop: the controller refuses motion for safety (a protective, safeguard or
    emergency stop, a safety fault or violation); a person must clear it.
    """

    pose: FloatArray
    twist: FloatArray
    timestamp_s: float
    protective_stop: bool = False

    def __post_init__(self) -> None:
        for name in ("pose", "twist"):
            array = _as_float_array(f"ArmState.{name}", getattr(self, name), (4,))
            _require_finite(f"ArmState.{name}", array)
            object.__setattr__(self, name, array)


@dataclass(frozen=True)
class GripperState:
    """Opening of a two-finger gripper."""

    width_m: float
    object_detected: bool
    moving: bool
    timestamp_s: float


@dataclass(frozen=True)
class Viewpoint:
    """A camera placement: optical centre ``eye_m`` [3] looking at ``target_m`` [3]."""

    eye_m: FloatArray
    target_m: FloatArray

    def __post_init__(self) -> None:
        for name in ("eye_m", "target_m"):
            array = _as_float_array(f"Viewpoint.{name}", getattr(self, name), (3,))
            _require_finite(f"Viewpoint.{name}", array)
            object.__setattr__(self, name, array)

    @classmethod
    def on_hemisphere(
        cls, target_m: FloatArray, radius_m: float, azimuth_rad: float, elevation_rad: float
    ) -> Viewpoint:
        """A view on the hemisphere of ``radius_m`` around ``target_m`` (azimuth from +x)."""
        direction = np.array(
            [
                np.cos(elevation_rad) * np.cos(azimuth_rad),
                np.cos(elevation_rad) * np.sin(azimuth_rad),
                np.sin(elevation_rad),
            ]
        )
        target = np.asarray(target_m, dtype=np.float64)
        return cls(target + radius_m * direction, target)


@dataclass(frozen=True)
class Push:
    """Non-prehensile push (paper 1, III-A).

    cp_m: [2] contact point on the object outline (world x, y); pd_rad: push direction (angle
    of the pushing motion about z); speed_mps: pusher speed u; link: index of the pushed link.
    """

    cp_m: FloatArray
    pd_rad: float
    speed_mps: float
    duration_s: float = 5.0
    link: int = 0
    kind: Literal["push"] = field(default="push", init=False)

    def __post_init__(self) -> None:
        _check_action(self)


@dataclass(frozen=True)
class Pull:
    """Prehensile pull: grasp at ``gp_m`` [2], then move along ``pd_rad`` at ``speed_mps``.

    grasp_axis_rad: direction in which the fingers close (perpendicular to the link's
    surface normal at the grasp point).
    """

    gp_m: FloatArray
    pd_rad: float
    speed_mps: float
    grasp_axis_rad: float
    duration_s: float = 5.0
    link: int = 0
    kind: Literal["pull"] = field(default="pull", init=False)

    def __post_init__(self) -> None:
        _check_action(self)


Action = Push | Pull


def _check_action(action: Push | Pull) -> None:
    point_name = "cp_m" if isinstance(action, Push) else "gp_m"
    point = _as_float_array(f"{action.kind}.{point_name}", getattr(action, point_name), (2,))
    _require_finite(f"{action.kind}.{point_name}", point)
    object.__setattr__(action, point_name, point)
    if not np.isfinite(action.pd_rad):
        raise DataError(f"{action.kind}.pd_rad must be finite")
    if not action.speed_mps > 0 or not action.duration_s > 0:
        raise DataError(f"{action.kind}: speed_mps and duration_s must be > 0")


def action_point(action: Action) -> FloatArray:
    """Contact point of a push or grasp point of a pull: [2]."""
    return action.cp_m if isinstance(action, Push) else action.gp_m


def action_to_dict(action: Action) -> dict[str, object]:
    """JSON-ready description of an action."""
    result: dict[str, object] = {
        "kind": action.kind,
        "point_m": action_point(action).tolist(),
        "pd_rad": float(action.pd_rad),
        "speed_mps": float(action.speed_mps),
        "duration_s": float(action.duration_s),
        "link": int(action.link),
    }
    if isinstance(action, Pull):
        result["grasp_axis_rad"] = float(action.grasp_axis_rad)
    return result


def action_from_dict(fields: dict[str, Any]) -> Action:
    """The action ``action_to_dict`` wrote (an episode's meta.json)."""
    point = np.asarray(fields["point_m"], dtype=np.float64)
    pd_rad, speed_mps = float(fields["pd_rad"]), float(fields["speed_mps"])
    duration_s, link = float(fields["duration_s"]), int(fields.get("link", 0))
    if fields["kind"] == "pull":
        grasp_axis_rad = float(fields["grasp_axis_rad"])
        return Pull(point, pd_rad, speed_mps, grasp_axis_rad, duration_s, link)
    if fields["kind"] == "push":
        return Push(point, pd_rad, speed_mps, duration_s, link)
    raise DataError(f"unknown action kind {fields['kind']!r}; expected 'push' or 'pull'")


@dataclass(frozen=True)
class Superquadric:
    """A (tapered) superquadric in its own frame, placed by ``world_from_sq`` [4, 4].

    scale_m: [3] semi-axes a1..a3; exponents: [2] = (eps1, eps2); taper: [2] = (kappa1,
    kappa2) or [3] = (kappa1, kappa2, shear): the tapering of paper 1 eq. 2 and a shear
    x += shear * y after it (an extension that fits right triangles); zeros for none.
    """

    scale_m: FloatArray
    exponents: FloatArray
    world_from_sq: FloatArray
    taper: FloatArray = field(default_factory=lambda: np.zeros(2))


@dataclass(frozen=True)
class ShapeEstimate:
    """Result of shape perception.

    links: one superquadric per link; initial_poses: [L, 3] = (x_m, y_m, theta_rad) per link;
    uncertainty: [L, K] per-link parameter standard deviations (K estimator-specific);
    cloud: the segmented object point cloud the estimate was fitted to; covariance: [L, K, K]
    per-link parameter covariance (diagonal = uncertainty**2), or None where the estimator
    gives standard deviations only.
    """

    links: tuple[Superquadric, ...]
    initial_poses: FloatArray
    uncertainty: FloatArray
    cloud: PointCloud
    covariance: FloatArray | None = None


@dataclass(frozen=True)
class GaussianBelief:
    """Gaussian belief over a named state vector.

    mean: [n]; cov: [n, n] symmetric positive semi-definite; names: n entry names such as
    ``"m_0"``, ``"f_0"``, ``"com_x_1"``, ``"f_j_0"``.
    """

    mean: FloatArray
    cov: FloatArray
    names: tuple[str, ...]

    def __post_init__(self) -> None:
        n = len(self.names)
        mean = _as_float_array("GaussianBelief.mean", self.mean, (n,))
        cov = _as_float_array("GaussianBelief.cov", self.cov, (n, n))
        _require_finite("GaussianBelief.mean", mean)
        _require_finite("GaussianBelief.cov", cov)
        object.__setattr__(self, "mean", mean)
        object.__setattr__(self, "cov", cov)

    def index(self, name: str) -> int:
        try:
            return self.names.index(name)
        except ValueError:
            entries = ", ".join(self.names)
            raise KeyError(f"belief has no entry {name!r}; entries: {entries}") from None

    @property
    def std(self) -> FloatArray:
        """Marginal standard deviations: [n]."""
        return np.sqrt(np.clip(np.diag(self.cov), 0.0, None))

    def as_dict(self) -> dict[str, dict[str, float]]:
        return {
            name: {"mean": float(m), "std": float(s)}
            for name, m, s in zip(self.names, self.mean, self.std, strict=True)
        }

    @staticmethod
    def link_count(entries: Mapping[str, object]) -> int:
        """The links of a belief in ``as_dict`` form (one ``m_l`` entry per link)."""
        return sum(1 for name in entries if name.startswith("m_"))

    @staticmethod
    def link_poses(entries: Mapping[str, Mapping[str, float]], links: Sequence[int]) -> FloatArray:
        """The pose means of ``links`` of a belief in ``as_dict`` form: [len(links), 3] =
        (x m, y m, theta rad)."""
        return np.array(
            [[entries[f"{key}_{link}"]["mean"] for key in ("x", "y", "theta")] for link in links],
            dtype=np.float64,
        ).reshape(len(links), 3)

    def correlation_dict(self, decimals: int = 4) -> dict[str, object]:
        """``{"names": [n], "matrix": [n][n]}``: the correlation of the entries (0 between an
        entry of std 0 and the others), rounded; with ``as_dict`` it gives back the
        covariance."""
        std = self.std
        scale = np.where(std > 0, std, 1.0)
        correlation = self.cov / np.outer(scale, scale)
        np.fill_diagonal(correlation, 1.0)
        matrix = np.round(np.clip(correlation, -1.0, 1.0), decimals)
        return {"names": list(self.names), "matrix": matrix.tolist()}
