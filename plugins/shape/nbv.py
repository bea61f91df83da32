"""View planners that use the shape estimate: ``shape.entropy_nbv`` and ``shape.random_views``.

``shape.entropy_nbv`` is the next-best view of paper 1, III-B4 (eq. 10-14). Points are sampled
on every fitted superquadric; each gets an entropy; candidate cameras on a hemisphere around the
object look at it (eq. 12-13); the entropy of the points each camera would see is summed (eq. 14)
and the camera with the most is chosen.

Point entropy. Each sampled point j gets a Gaussian positional spread, covariance [3, 3]

    Sigma_j = sum_kl D_jk R_kl D_jl^T + u_j^2 I,

where D_jk [3] is the normal part of the point's displacement when parameter k of its
superquadric moves by one standard deviation (central finite differences,
``ShapeEstimate.uncertainty`` in the ``PARAMETER_NAMES`` order of ``shape.ems``; a slide along
the surface does not change the shape), R the parameters' correlation matrix
(``ShapeEstimate.covariance``; the identity without one), and u_j is the unseen spread of
eq. 10-11: the nearest-neighbour distance to the observed cloud beyond ``seen_distance_m``,
capped at ``unseen_spread_m`` (points below the table clearance are compared as if at it,
since the cloud has none there). The entropy is that of the spread above the sensor noise sigma_n,

    H_j = h(N(0, Sigma_j + sigma_n^2 I)) - h(N(0, sigma_n^2 I))
        = 0.5 log det(I + Sigma_j / sigma_n^2),

in nats: zero for a certain, observed point and at most 1.5 log(1 + (unseen_spread_m /
sigma_n)^2) for an unseen one. (Eq. 10's ``-p log p`` is not monotone in the distance; this is.)

View entropy (eq. 14): the sum of H_j over the points a camera sees (in the image, in front,
facing it, not occluded), divided by the number of sampled points, i.e. the mean entropy per
surface point that the view would observe. Planning stops when the best view's value is below
``entropy_threshold``.

``shape.random_views`` is the baseline: views at random azimuth and elevation.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from pydantic import Field, model_validator
from scipy.spatial import cKDTree
from vistac.component import Component, ComponentConfig, ComponentContext
from vistac.errors import DataError
from vistac.plugins.shape.ems import PARAMETER_NAMES, rotation_zyx
from vistac.plugins.shape.superquadric import (
    log_inside_outside,
    radial_surface_points,
    remove_taper,
    sample_surface,
    to_superquadric_frame,
)
from vistac.plugins.shape.views import object_centroid, uniform_view
from vistac.types import (
    CameraIntrinsics,
    FloatArray,
    PointCloud,
    ShapeEstimate,
    Superquadric,
    Viewpoint,
)

logger = logging.getLogger(__name__)

_WORLD_UP = np.array([0.0, 0.0, 1.0])
_GOLDEN_ANGLE_RAD = np.pi * (3.0 - np.sqrt(5.0))
_NORMAL_STEP = 1e-4
"""Finite-difference step for normals, as a fraction of the smallest semi-axis."""
_SCALE_NAMES = ("a1_m", "a2_m", "a3_m")
_EXPONENT_NAMES = ("eps1", "eps2")
_TAPER_NAMES = tuple(name for name in ("kappa1", "kappa2", "shear") if name in PARAMETER_NAMES)
"""Taper parameters in ``Superquadric.taper`` order (the shear only where EMS fits it)."""
_POSITION_NAMES = ("x_m", "y_m", "z_m")
_ANGLE_NAMES = ("yaw_rad", "pitch_rad", "roll_rad")
_PARAMETER_RANGES: dict[tuple[str, ...], tuple[float, float]] = {
    _SCALE_NAMES: (1e-4, np.inf),
    _EXPONENT_NAMES: (0.05, 2.5),
    ("kappa1",): (-1.0, 1.0),
    ("kappa2",): (0.0, 1.0),
}
"""Where perturbed parameters are clipped to keep the superquadric valid."""
_NEAR_M = 1e-3
"""Points closer to a camera than this (along its optical axis) are not seen."""


class _ElevationRange(ComponentConfig):
    """Shared check: ``min_elevation_deg <= max_elevation_deg``."""

    min_elevation_deg: float
    max_elevation_deg: float

    @model_validator(mode="after")
    def _check_range(self) -> _ElevationRange:
        if self.min_elevation_deg > self.max_elevation_deg:
            raise ValueError(
                f"min_elevation_deg ({self.min_elevation_deg}) must not exceed "
                f"max_elevation_deg ({self.max_elevation_deg})"
            )
        return self


class RandomViews(Component):
    """``views`` viewpoints at random azimuth (uniform in [0, 2 pi)) and elevation (uniform in
    [min_elevation_deg, max_elevation_deg]), drawn from ``ctx.rng("views")``."""

    kind = "view_planner"

    class Config(_ElevationRange):
        views: int = Field(4, gt=0, description="Number of views before returning None.")
        radius_m: float = Field(0.5, gt=0, description="Camera distance from the target.")
        min_elevation_deg: float = Field(30.0, ge=0, le=90, description="Lowest elevation.")
        max_elevation_deg: float = Field(70.0, ge=0, le=90, description="Highest elevation.")
        target_m: tuple[float, float, float] = Field(
            (0.0, 0.45, 0.03), description="Where to look before any cloud is available."
        )
        table_clearance_m: float = Field(
            0.008, ge=0, description="Cloud points below this height are table, not object."
        )

    def __init__(self, config: Config, ctx: ComponentContext) -> None:
        super().__init__(config, ctx)
        self.config: RandomViews.Config = config
        self._rng = ctx.rng("views")

    def next_view(
        self, cloud: PointCloud | None, shape: ShapeEstimate | None, views_taken: int
    ) -> Viewpoint | None:
        if views_taken >= self.config.views:
            return None
        target = object_centroid(
            cloud, np.array(self.config.target_m), self.config.table_clearance_m
        )
        azimuth = self._rng.uniform(0.0, 2 * np.pi)
        elevation = np.radians(
            self._rng.uniform(self.config.min_elevation_deg, self.config.max_elevation_deg)
        )
        return Viewpoint.on_hemisphere(target, self.config.radius_m, azimuth, elevation)


class EntropyNBV(Component):
    """Next-best view by view entropy (paper 1, III-B4, eq. 10-14); see the module docstring.

    Without a shape estimate (the first view, or when fitting failed) the views are those of
    ``shape.uniform_views``: ``start_azimuth_deg`` at ``elevation_deg``, then evenly spaced.
    """

    kind = "view_planner"

    class Config(_ElevationRange):
        max_views: int = Field(6, gt=0, description="Views taken before returning None.")
        radius_m: float = Field(0.5, gt=0, description="Camera distance from the target.")
        elevation_deg: float = Field(
            50.0, gt=0, le=90, description="Elevation of the views taken without a shape."
        )
        start_azimuth_deg: float = Field(
            -90.0, description="Azimuth (from +x) of the first view; -90 is the robot side."
        )
        target_m: tuple[float, float, float] = Field(
            (0.0, 0.45, 0.03), description="Where to look before any cloud is available."
        )
        table_clearance_m: float = Field(
            0.008, ge=0, description="Cloud points below this height are table, not object."
        )
        candidates: int = Field(64, gt=0, le=4096, description="Candidate views P.")
        min_elevation_deg: float = Field(
            15.0, ge=0, lt=90, description="Lowest elevation of the candidate views."
        )
        max_elevation_deg: float = Field(
            80.0, ge=0, lt=90, description="Highest elevation of the candidate views."
        )
        points_per_link: int = Field(
            1000, gt=0, le=100_000, description="Surface points M sampled per link."
        )
        seen_distance_m: float = Field(
            0.005, ge=0, description="Surface points this close to the cloud count as seen."
        )
        unseen_spread_m: float = Field(
            0.02, gt=0, description="Positional spread of an unseen point (the cap of u_j)."
        )
        sensor_noise_m: float = Field(
            0.002, gt=0, description="Spread sigma_n that counts as certain (zero entropy)."
        )
        entropy_threshold: float = Field(
            0.05,
            ge=0,
            description="Stop when the best view's entropy per sampled point (nats) is below.",
        )
        min_view_separation_deg: float = Field(
            15.0,
            ge=0,
            le=180,
            description="Candidates closer than this (angle at the target) to a view this "
            "planner returned before are skipped.",
        )
        width: int = Field(320, gt=0, le=1280, description="Image width of the camera model.")
        height: int = Field(240, gt=0, le=960, description="Image height of the camera model.")
        vertical_fov_deg: float = Field(
            58.0, gt=1, lt=170, description="Vertical field of view of the camera model."
        )
        zbuffer_bin_px: int = Field(
            4, gt=0, le=64, description="Side of the z-buffer cells used for occlusion (pixels)."
        )
        occlusion_tolerance_m: float = Field(
            0.01,
            ge=0,
            description="A point is hidden when it lies this much behind the nearest point of "
            "its z-buffer cell.",
        )

    def __init__(self, config: Config, ctx: ComponentContext) -> None:
        super().__init__(config, ctx)
        self.config: EntropyNBV.Config = config
        self.intrinsics = CameraIntrinsics.from_fov(
            config.width, config.height, np.radians(config.vertical_fov_deg)
        )
        self._rng = ctx.rng("nbv")
        self._taken_directions: list[FloatArray] = []

    def next_view(
        self, cloud: PointCloud | None, shape: ShapeEstimate | None, views_taken: int
    ) -> Viewpoint | None:
        if views_taken >= self.config.max_views:
            return None
        if shape is None or not shape.links:
            view: Viewpoint | None = self._fallback_view(cloud, views_taken)
        else:
            view = self._best_view(cloud, shape)
        if view is not None:
            direction = view.eye_m - view.target_m
            self._taken_directions.append(direction / np.linalg.norm(direction))
        return view

    def _fallback_view(self, cloud: PointCloud | None, views_taken: int) -> Viewpoint:
        """The view of ``shape.uniform_views`` number ``views_taken`` (of ``max_views``)."""
        return uniform_view(cloud, views_taken, self.config.max_views, self.config)

    def _best_view(self, cloud: PointCloud | None, shape: ShapeEstimate) -> Viewpoint | None:
        """The candidate with the largest view entropy, or None when it is below threshold."""
        cfg = self.config
        observed = cloud if cloud is not None and len(cloud) else shape.cloud
        points_m, normals, entropy = surface_entropy(
            shape, observed.points_m, cfg.points_per_link, self._rng, self._entropy_settings()
        )
        target = points_m.mean(axis=0)
        directions = hemisphere_directions(
            cfg.candidates, np.radians(cfg.min_elevation_deg), np.radians(cfg.max_elevation_deg)
        )
        eyes_m = target + cfg.radius_m * directions
        visible = visible_points(
            points_m, normals, look_at(eyes_m, target), self.intrinsics,
            cfg.zbuffer_bin_px, cfg.occlusion_tolerance_m,
        )  # fmt: skip
        view_entropy = visible @ entropy / len(entropy)
        view_entropy[self._near_taken(directions)] = -np.inf
        best = int(np.argmax(view_entropy))
        logger.info(
            "entropy NBV: best view entropy %.3f nats/point (threshold %.3f), eye %s",
            view_entropy[best], cfg.entropy_threshold, np.round(eyes_m[best], 3),
        )  # fmt: skip
        if not view_entropy[best] >= cfg.entropy_threshold:
            return None
        return Viewpoint(eyes_m[best], target)

    def _entropy_settings(self) -> EntropySettings:
        cfg = self.config
        return EntropySettings(
            cfg.seen_distance_m, cfg.unseen_spread_m, cfg.sensor_noise_m, cfg.table_clearance_m
        )

    def _near_taken(self, directions: FloatArray) -> FloatArray:
        """Mask [P] of candidate directions [P, 3] too close to a view returned before."""
        if not self._taken_directions:
            return np.zeros(len(directions), dtype=bool)
        cosine = directions @ np.array(self._taken_directions).T
        min_cosine = np.cos(np.radians(self.config.min_view_separation_deg))
        return np.asarray(np.any(cosine > min_cosine, axis=1))


@dataclass(frozen=True)
class EntropySettings:
    """Spreads that turn distances and parameter std into point entropy (see ``EntropyNBV``)."""

    seen_distance_m: float
    unseen_spread_m: float
    sensor_noise_m: float
    table_clearance_m: float = 0.0
    """The cloud has no points below this height: a surface point lower down is compared with
    the cloud as if it were at this height."""


def surface_entropy(
    shape: ShapeEstimate,
    observed_m: FloatArray,
    points_per_link: int,
    rng: np.random.Generator,
    settings: EntropySettings,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Sample every link's surface and give each point its entropy (module docstring).

    observed_m: [N, 3] observed cloud (N may be 0). Returns points_m [L*M, 3], outward unit
    normals [L*M, 3] and entropy [L*M] in nats (M = ``points_per_link``).
    """
    std = _parameter_std(shape)
    roots = _correlation_roots(shape, std)
    points, normals, displacements = [], [], []
    for sq, link_std, root in zip(shape.links, std, roots, strict=True):
        world_m = sample_surface(sq, points_per_link, rng)
        local_m = to_superquadric_frame(sq, world_m)
        normal = surface_normals(sq, local_m)
        points.append(world_m)
        normals.append(normal)
        moved = normal_displacements(parameter_displacements(sq, local_m, link_std), normal)
        displacements.append(np.einsum("kl,kmi->lmi", root, moved))
    points_m = np.concatenate(points)
    unseen_m = _unseen_spread_m(points_m, observed_m, settings)
    entropy = gaussian_entropy(np.concatenate(displacements, axis=1), unseen_m, settings)
    return points_m, np.concatenate(normals), entropy


def _parameter_std(shape: ShapeEstimate) -> FloatArray:
    """Per-link parameter std [L, K]; zeros (no shape term) when the layout is not EMS's."""
    std = np.asarray(shape.uncertainty, dtype=np.float64)
    if std.shape != (len(shape.links), len(PARAMETER_NAMES)):
        logger.warning(
            "entropy NBV: uncertainty of shape %s is not [links, %d] (PARAMETER_NAMES); "
            "using the unseen term only", std.shape, len(PARAMETER_NAMES),
        )  # fmt: skip
        return np.zeros((len(shape.links), len(PARAMETER_NAMES)))
    if not np.all(np.isfinite(std)):
        raise DataError("ShapeEstimate.uncertainty contains NaN or inf values")
    return std


def _correlation_roots(shape: ShapeEstimate, std: FloatArray) -> FloatArray:
    """Per link a square root S [K, K] of the parameters' correlation matrix (S S^T = R), so
    that displacements mixed by S add up to D R D^T: parameters that trade off against each
    other (yaw and shear of an ellipse) do not count twice. Identity without a covariance.
    Returns [L, K, K]."""
    count = std.shape[1]
    cov = shape.covariance
    if cov is None or np.shape(cov) != (len(shape.links), count, count):
        return np.broadcast_to(np.eye(count), (len(shape.links), count, count))
    scale = np.where(std > 0, std, 1.0)
    correlation = np.asarray(cov) / (scale[:, :, None] * scale[:, None, :])
    values, vectors = np.linalg.eigh(0.5 * (correlation + np.swapaxes(correlation, 1, 2)))
    return np.asarray(vectors * np.sqrt(np.clip(values, 0.0, None))[:, None, :])


def _unseen_spread_m(
    points_m: FloatArray, observed_m: FloatArray, settings: EntropySettings
) -> FloatArray:
    """u_j [M]: nearest-neighbour distance beyond ``seen_distance_m``, capped (eq. 11); points
    [M, 3] below the table clearance are raised to it first (the cloud cannot show them)."""
    if len(observed_m) == 0:
        return np.full(len(points_m), settings.unseen_spread_m)
    raised_m = points_m.copy()
    raised_m[:, 2] = np.maximum(raised_m[:, 2], settings.table_clearance_m)
    distance_m, _ = cKDTree(observed_m).query(raised_m)
    return np.clip(distance_m - settings.seen_distance_m, 0.0, settings.unseen_spread_m)


def gaussian_entropy(
    displacements_m: FloatArray, unseen_m: FloatArray, settings: EntropySettings
) -> FloatArray:
    """H_j = 0.5 log det(I + Sigma_j / sigma_n^2) with Sigma_j = D_j^T D_j + u_j^2 I.

    displacements_m: [K, M, 3] per-parameter displacements; unseen_m: [M]. Returns [M] nats.
    """
    covariance = np.einsum("kmi,kmj->mij", displacements_m, displacements_m)
    covariance += unseen_m[:, None, None] ** 2 * np.eye(3)
    _, log_det = np.linalg.slogdet(np.eye(3) + covariance / settings.sensor_noise_m**2)
    return np.asarray(0.5 * log_det)


def parameter_displacements(sq: Superquadric, local_m: FloatArray, std: FloatArray) -> FloatArray:
    """Displacement [K, M, 3] (world frame) of surface points when each parameter moves by
    its standard deviation: (p(theta + std_k e_k) - p(theta - std_k e_k)) / 2.

    local_m: [M, 3] points in the superquadric's frame; std: [K] in ``PARAMETER_NAMES`` order.
    A point keeps its radial direction in the untapered frame when the shape changes.
    """
    params = _parameters(sq)
    steps = np.diag(std)
    perturbed = _clip_parameters(np.concatenate([params + steps, params - steps]))
    column = perturbed.T
    scale_m = column[_columns(_SCALE_NAMES)].T
    exponents = column[_columns(_EXPONENT_NAMES)].T
    taper = column[_columns(_TAPER_NAMES)].T
    batch_m = np.broadcast_to(local_m, (len(perturbed), *local_m.shape))
    local = radial_surface_points(batch_m, scale_m, exponents, taper)
    yaw, pitch, roll = column[_columns(_ANGLE_NAMES)]
    rotation = rotation_zyx(yaw, pitch, roll)
    translation_m = column[_columns(_POSITION_NAMES)].T
    world = np.matmul(local, np.swapaxes(rotation, 1, 2)) + translation_m[:, None, :]
    count = len(std)
    return np.asarray(0.5 * (world[:count] - world[count:]))


def normal_displacements(displacements_m: FloatArray, normals: FloatArray) -> FloatArray:
    """The part [K, M, 3] of displacements [K, M, 3] along the unit normals [M, 3]: a point
    that slides along the surface (a circle turning about its axis) leaves the surface where
    it was, so only the normal part is uncertainty about the shape."""
    along = np.einsum("kmi,mi->km", displacements_m, normals)
    return np.asarray(along[:, :, None] * normals[None, :, :])


def _columns(names: tuple[str, ...]) -> list[int]:
    """Indices of ``names`` in ``PARAMETER_NAMES``."""
    return [PARAMETER_NAMES.index(name) for name in names]


def _parameters(sq: Superquadric) -> FloatArray:
    """The parameter vector [K] (``PARAMETER_NAMES`` order) of a superquadric."""
    rotation = sq.world_from_sq[:3, :3]
    taper = np.zeros(len(_TAPER_NAMES))
    given = min(len(sq.taper), len(taper))
    taper[:given] = sq.taper[:given]
    values = {
        **dict(zip(_SCALE_NAMES, sq.scale_m, strict=True)),
        **dict(zip(_EXPONENT_NAMES, sq.exponents, strict=True)),
        **dict(zip(_TAPER_NAMES, taper, strict=True)),
        **dict(zip(_POSITION_NAMES, sq.world_from_sq[:3, 3], strict=True)),
        "yaw_rad": np.arctan2(rotation[1, 0], rotation[0, 0]),
        "pitch_rad": np.arctan2(-rotation[2, 0], np.hypot(rotation[0, 0], rotation[1, 0])),
        "roll_rad": np.arctan2(rotation[2, 1], rotation[2, 2]),
    }
    return np.array([values[name] for name in PARAMETER_NAMES], dtype=np.float64)


def _clip_parameters(params: FloatArray) -> FloatArray:
    """Keep perturbed parameter vectors [B, K] valid (positive scale, usable exponents)."""
    clipped = params.copy()
    for names, (low, high) in _PARAMETER_RANGES.items():
        clipped[:, _columns(names)] = np.clip(clipped[:, _columns(names)], low, high)
    return clipped


def surface_normals(sq: Superquadric, local_m: FloatArray) -> FloatArray:
    """Outward unit normals [M, 3] (world frame) at surface points ``local_m`` [M, 3] given in
    the superquadric's frame: central differences of log F (eq. 1-2)."""
    step_m = _NORMAL_STEP * float(np.min(sq.scale_m))
    offsets = step_m * np.concatenate([np.eye(3), -np.eye(3)])
    shifted = local_m[None] + offsets[:, None, :]
    log_f = log_inside_outside(
        remove_taper(shifted, sq.scale_m, sq.taper), sq.scale_m, sq.exponents
    )
    gradient = (log_f[:3] - log_f[3:]).T
    normals = gradient @ sq.world_from_sq[:3, :3].T
    return np.asarray(normals / np.linalg.norm(normals, axis=1, keepdims=True))


def hemisphere_directions(
    count: int, min_elevation_rad: float, max_elevation_rad: float
) -> FloatArray:
    """``count`` unit directions [count, 3] spread evenly (Fibonacci spiral) over the band of
    the upper hemisphere between the two elevations."""
    index = np.arange(count) + 0.5
    sin_low, sin_high = np.sin(min_elevation_rad), np.sin(max_elevation_rad)
    z = sin_low + (sin_high - sin_low) * index / count
    azimuth = _GOLDEN_ANGLE_RAD * index
    ring = np.sqrt(1.0 - z**2)
    return np.stack([ring * np.cos(azimuth), ring * np.sin(azimuth), z], axis=-1)


def look_at(eyes_m: FloatArray, target_m: FloatArray) -> FloatArray:
    """World-from-optical-frame poses [P, 4, 4] of cameras at ``eyes_m`` [P, 3] looking at
    ``target_m`` [3] (eq. 12-13): x right (horizontal), y down, z forward, as the simulated
    camera. Eyes straight above the target are not supported (image right is undefined)."""
    forward = target_m - eyes_m
    forward /= np.linalg.norm(forward, axis=1, keepdims=True)
    right = np.cross(forward, _WORLD_UP)
    right /= np.linalg.norm(right, axis=1, keepdims=True)
    down = np.cross(forward, right)
    poses = np.tile(np.eye(4), (len(eyes_m), 1, 1))
    poses[:, :3, :3] = np.stack([right, down, forward], axis=-1)
    poses[:, :3, 3] = eyes_m
    return poses


def visible_points(
    points_m: FloatArray,
    normals: FloatArray,
    world_from_cameras: FloatArray,
    intrinsics: CameraIntrinsics,
    bin_px: int,
    tolerance_m: float,
) -> FloatArray:
    """Which points each camera sees: in the image, in front, facing it and not occluded.

    points_m, normals: [M, 3]; world_from_cameras: [P, 4, 4]. All cameras at once: the points
    are projected as [P, M, 3]; occlusion is a coarse z-buffer over ``bin_px`` pixel cells of
    all views together (a point is hidden when it lies more than ``tolerance_m`` behind the
    nearest projected point of its cell). Returns a float mask [P, M] (1 = seen).
    """
    rotation, eyes_m = world_from_cameras[:, :3, :3], world_from_cameras[:, :3, 3]
    camera_m = np.matmul(points_m[None] - eyes_m[:, None, :], rotation)
    depth_m = camera_m[..., 2]
    safe_depth = np.where(depth_m > _NEAR_M, depth_m, 1.0)
    u = intrinsics.fx * camera_m[..., 0] / safe_depth + intrinsics.cx
    v = intrinsics.fy * camera_m[..., 1] / safe_depth + intrinsics.cy
    in_image = ((depth_m > _NEAR_M) & (u > -0.5) & (u < intrinsics.width - 0.5)
                & (v > -0.5) & (v < intrinsics.height - 0.5))  # fmt: skip
    facing = np.sum(normals * points_m, axis=1) < eyes_m @ normals.T  # n . (x - eye) < 0
    cell, cell_count = _zbuffer_cells(u, v, intrinsics, bin_px)
    nearest_m = np.full(cell_count, np.inf)
    np.minimum.at(nearest_m, cell[in_image], depth_m[in_image])
    unoccluded = depth_m <= nearest_m[cell] + tolerance_m
    return (in_image & facing & unoccluded).astype(np.float64)


def _zbuffer_cells(
    u: FloatArray, v: FloatArray, intrinsics: CameraIntrinsics, bin_px: int
) -> tuple[NDArray[np.int64], int]:
    """Flat z-buffer cell index [P, M] (distinct per view) of pixel coordinates u, v [P, M],
    and the number of cells of all views together.

    Coordinates outside the image are clipped to its border cells (callers mask them out).
    """
    columns = -(-intrinsics.width // bin_px)
    rows = -(-intrinsics.height // bin_px)
    column = np.clip(np.floor((u + 0.5) / bin_px), 0, columns - 1).astype(np.int64)
    row = np.clip(np.floor((v + 0.5) / bin_px), 0, rows - 1).astype(np.int64)
    view = np.arange(u.shape[0])[:, None]
    return (view * rows + row) * columns + column, u.shape[0] * rows * columns
