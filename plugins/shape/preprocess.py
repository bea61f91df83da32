"""Point-cloud pre-processing with open3d: ``shape.open3d_cloud``.

Registration of each new view onto the views so far (point-to-plane ICP, to absorb residual
camera calibration error), then segmentation: voxel downsampling, table removal by a RANSAC
plane, and the largest DBSCAN cluster above it. Each view's normals and object cluster are
found once, when it is added, so a perception of V views clusters each view once rather than
the growing merge V times. Paper 1, III-B1.
"""

from __future__ import annotations

import logging

import numpy as np
import open3d as o3d
from numpy.typing import NDArray
from pydantic import Field
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree
from vistac.component import Component, ComponentConfig, ComponentContext
from vistac.errors import DataError
from vistac.types import FloatArray, PointCloud

log = logging.getLogger(__name__)

IntArray = NDArray[np.int64]

_MIN_HORIZONTAL_NORMAL_Z = 0.9
"""A table plane's unit normal has |n_z| at least this (tilts up to about 25 degrees)."""
_MAX_PLANES = 3
_MIN_PLANE_POINTS = 30
_MAX_SHARE_BELOW_TABLE = 0.05


def _o3d_cloud(points_m: FloatArray) -> o3d.geometry.PointCloud:
    cloud = o3d.geometry.PointCloud()
    cloud.points = o3d.utility.Vector3dVector(np.ascontiguousarray(points_m, dtype=np.float64))
    return cloud


def finite_points(cloud: PointCloud, who: str) -> FloatArray:
    """The cloud's points [N, 3]; DataError when empty or not finite."""
    points = np.asarray(cloud.points_m, dtype=np.float64)
    if len(points) == 0:
        raise DataError(f"{who}: the point cloud is empty; check that the camera sees the object")
    if not np.all(np.isfinite(points)):
        raise DataError(f"{who}: the point cloud has NaN or inf points; drop invalid pixels first")
    return points


def voxel_downsample(points_m: FloatArray, voxel_m: float) -> FloatArray:
    """One point per occupied voxel (the voxel's mean): [M, 3]."""
    if voxel_m <= 0:
        return points_m
    return np.asarray(_o3d_cloud(points_m).voxel_down_sample(voxel_m).points)


def ransac_plane(
    points_m: FloatArray, distance_m: float, iterations: int, rng: np.random.Generator
) -> tuple[FloatArray, NDArray[np.bool_]]:
    """The plane [4] = (a, b, c, d), unit normal with c >= 0, through most points [N, 3]
    (RANSAC over ``iterations`` random triples, vectorised, then a least-squares refit on the
    inliers) and its inlier mask [N]. Deterministic for a given ``rng`` (open3d's parallel
    RANSAC is not)."""
    triples = points_m[rng.integers(len(points_m), size=(iterations, 3))]
    normals = np.cross(triples[:, 1] - triples[:, 0], triples[:, 2] - triples[:, 0])
    norms = np.linalg.norm(normals, axis=1)
    valid = norms > 1e-12
    normals = normals[valid] / norms[valid, None]
    offsets = -np.einsum("ij,ij->i", normals, triples[valid, 0])
    inliers = np.abs(points_m @ normals.T + offsets) < distance_m  # [N, iterations]
    best = int(inliers.sum(axis=0).argmax())
    mask = inliers[:, best]
    centre = points_m[mask].mean(axis=0)
    normal = np.linalg.svd(points_m[mask] - centre, full_matrices=False)[2][-1]
    normal = normal if normal[2] >= 0 else -normal
    return np.append(normal, -normal @ centre), np.abs(
        points_m @ normal - normal @ centre
    ) < distance_m


def table_plane(
    points_m: FloatArray, distance_m: float, iterations: int, rng: np.random.Generator
) -> FloatArray | None:
    """The table: the lowest near-horizontal RANSAC plane [4] = (a, b, c, d) with
    a x + b y + c z + d = 0 and c > 0 (normal up), or None when there is none (a cloud of the
    object only). Planes with many points below them (an object's top face) are skipped."""
    remaining = points_m
    for _ in range(_MAX_PLANES):
        if len(remaining) < _MIN_PLANE_POINTS:
            return None
        plane, inliers = ransac_plane(remaining, distance_m, iterations, rng)
        below = np.mean(points_m @ plane[:3] + plane[3] < -2 * distance_m)
        if plane[2] >= _MIN_HORIZONTAL_NORMAL_Z and below < _MAX_SHARE_BELOW_TABLE:
            return plane
        remaining = remaining[~inliers]
    return None


def dbscan_labels(points_m: FloatArray, radius_m: float, min_points: int) -> IntArray:
    """DBSCAN cluster labels [N] of points [N, 3] (-1: noise), as open3d's ``cluster_dbscan``
    defines them (a core point has at least ``min_points`` points, itself included, within
    ``radius_m``; a border point joins a neighbouring core point's cluster), from one k-d
    tree pair query: about twice as fast as open3d on the merged views. Labels are not
    consecutive."""
    pairs = cKDTree(points_m).query_pairs(radius_m, output_type="ndarray")
    count = len(points_m)
    core = np.bincount(pairs.ravel(), minlength=count) + 1 >= min_points
    inner = pairs[core[pairs[:, 0]] & core[pairs[:, 1]]]
    graph = coo_matrix((np.ones(len(inner)), (inner[:, 0], inner[:, 1])), shape=(count, count))
    labels = np.where(core, connected_components(graph, directed=False)[1], -1)
    border = pairs[core[pairs[:, 0]] != core[pairs[:, 1]]]
    from_core = core[border[:, 0]]
    labels[np.where(from_core, border[:, 1], border[:, 0])] = labels[
        np.where(from_core, border[:, 0], border[:, 1])
    ]
    return labels


def object_cluster(
    points_m: FloatArray,
    height_m: FloatArray,
    radius_m: float,
    min_points: int,
    max_base_height_m: float,
    join_m: float = 0.0,
) -> FloatArray:
    """The object's points [K, 3]: the largest DBSCAN cluster that reaches down to within
    ``max_base_height_m`` of the table (not the gripper hovering above the objects; not
    "touching the table": seen over a gripper, an object may show its top face only), with
    every other such cluster that comes within ``join_m`` of it. A view may show a link apart
    from the rest (the joint hidden behind a taller link); the largest cluster alone would
    drop it from that view.

    points_m: [N, 3]; height_m: [N] height of each point above the table plane. Returns an
    empty array when no cluster qualifies."""
    if len(points_m) == 0:
        return points_m
    labels = dbscan_labels(points_m, radius_m, min_points)
    clustered = labels >= 0
    if not clustered.any():
        return points_m[:0]
    size = np.bincount(labels[clustered])
    base_m = np.full(len(size), np.inf)
    np.minimum.at(base_m, labels[clustered], height_m[clustered])
    size[base_m > max_base_height_m] = 0
    if size.max() == 0:
        return points_m[:0]
    largest = size.argmax()
    keep = np.arange(len(size)) == largest
    if join_m > 0:
        tree = cKDTree(points_m[labels == largest])
        for other in np.flatnonzero((size > 0) & ~keep):
            gap_m, _ = tree.query(points_m[labels == other], distance_upper_bound=join_m)
            keep[other] = bool(np.isfinite(gap_m).any())
    return points_m[clustered & keep[np.maximum(labels, 0)]]


def estimate_normals(points_m: FloatArray, radius_m: float) -> FloatArray:
    """Unit normals [N, 3] of points [N, 3] (open3d, up to 30 neighbours within radius_m;
    unoriented)."""
    cloud = _o3d_cloud(points_m)
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=radius_m, max_nn=30))
    return np.asarray(cloud.normals)


def icp_align(
    source_m: FloatArray, target_m: FloatArray, target_normals: FloatArray, max_distance_m: float
) -> tuple[FloatArray, float, float]:
    """Point-to-plane ICP of ``source_m`` [N, 3] onto ``target_m`` [M, 3] with its normals
    [M, 3], from the identity.

    Returns (transform [4, 4], inlier RMSE before (m), inlier RMSE after (m))."""
    source, target = _o3d_cloud(source_m), _o3d_cloud(target_m)
    target.normals = o3d.utility.Vector3dVector(np.ascontiguousarray(target_normals))
    registration = o3d.pipelines.registration
    before = registration.evaluate_registration(source, target, max_distance_m, np.eye(4))
    result = registration.registration_icp(
        source, target, max_distance_m, np.eye(4),
        registration.TransformationEstimationPointToPlane(),
    )  # fmt: skip
    return np.asarray(result.transformation), before.inlier_rmse, result.inlier_rmse


def transform_points(transform: FloatArray, points_m: FloatArray) -> FloatArray:
    """Apply a homogeneous transform [4, 4] to points [N, 3]."""
    return points_m @ transform[:3, :3].T + transform[:3, 3]


class Open3dCloudProcessor(Component):
    """Implements the ``CloudProcessor`` protocol with open3d.

    Each view is cut down to what lies above its RANSAC table plane (the plane is fitted on a
    random subset, the cut is done on all points), voxel-downsampled, and registered onto the
    object points of the previous views; its object is its largest DBSCAN cluster standing on
    the table with the clusters near it (``cluster_join_m``), and ``segment`` merges those of
    the registered views.
    """

    kind = "cloud_processor"

    class Config(ComponentConfig):
        voxel_m: float = Field(0.003, ge=0, description="voxel size of the downsampling; 0: off")
        table_distance_m: float = Field(0.004, gt=0, description="RANSAC plane inlier distance")
        table_clearance_m: float = Field(
            0.006, ge=0, description="keep points at least this far above the table plane"
        )
        ransac_points: int = Field(5000, gt=2, description="random subset the plane is fitted on")
        ransac_iterations: int = Field(200, gt=0)
        cluster_radius_m: float = Field(0.012, gt=0, description="DBSCAN neighbourhood radius")
        cluster_min_points: int = Field(10, gt=0, description="DBSCAN core point neighbours")
        cluster_join_m: float = Field(
            0.03, ge=0, description="clusters standing on the table within this distance of "
            "the largest are the object too (a link a view shows apart from the rest, its "
            "joint hidden behind a taller link); 0: the largest cluster only",
        )
        min_object_points: int = Field(50, gt=0, description="fewer object points: error")
        max_base_height_m: float = Field(
            0.1,
            gt=0,
            description="a cluster whose lowest point is higher is not the object (the gripper)",
        )
        icp: bool = Field(True, description="register each new view onto the previous ones")
        icp_max_distance_m: float = Field(0.01, gt=0, description="ICP correspondence radius")
        icp_min_rmse_gain: float = Field(
            0.3, ge=0, le=1, description="apply ICP only if it cuts the RMSE by this share"
        )
        icp_max_correction_m: float = Field(
            0.02, gt=0, description="larger ICP corrections are rejected as wrong"
        )

    def __init__(self, config: Config, ctx: ComponentContext) -> None:
        super().__init__(config, ctx)
        self.config: Open3dCloudProcessor.Config = config
        self._rng = ctx.rng("cloud_processor")
        self._object_views: list[FloatArray] = []
        self._view_normals: list[FloatArray] = []
        self._view_objects: list[FloatArray] = []
        self._plane: FloatArray | None = None

    def register(self, view: PointCloud, previous: PointCloud | None) -> PointCloud:
        """``view`` moved onto ``previous`` (both world frame) when ICP on the points above
        the table finds a good match; otherwise ``view`` unchanged."""
        points = finite_points(view, "shape.open3d_cloud")
        source = voxel_downsample(self._above_table(points), self.config.voxel_m)
        if previous is None:
            self._object_views, self._view_normals, self._view_objects = [], [], []
        transform = self._icp(source) if previous is not None else None
        normals = estimate_normals(source, self._normal_radius_m) if self.config.icp else source
        if transform is not None:
            source, normals = transform_points(transform, source), normals @ transform[:3, :3].T
        self._object_views.append(source)
        self._view_normals.append(normals)
        self._view_objects.append(self._object_cluster(source))
        return view if transform is None else PointCloud(transform_points(transform, points))

    def segment(self, cloud: PointCloud) -> PointCloud:
        """The object's points: above the table, downsampled, the largest cluster standing on
        the table and those near it (:func:`object_cluster`; of each registered view, merged,
        when ``cloud`` is their merge); DataError when fewer than ``min_object_points`` remain
        (e.g. a cloud that is all table)."""
        points = finite_points(cloud, "shape.open3d_cloud")
        config = self.config
        if self._view_objects:
            cluster = voxel_downsample(np.concatenate(self._view_objects), config.voxel_m)
        else:
            above = voxel_downsample(self._above_table(points), config.voxel_m)
            cluster = self._object_cluster(above)
        if len(cluster) < config.min_object_points:
            raise DataError(
                f"shape.open3d_cloud: only {len(cluster)} object points stand on the table "
                f"(from {len(points)}), fewer than min_object_points = "
                f"{config.min_object_points}; is the object in view?"
            )
        return PointCloud(cluster)

    def _object_cluster(self, above_m: FloatArray) -> FloatArray:
        """:func:`object_cluster` of points [N, 3] above the last table plane: [K, 3]."""
        config = self.config
        plane = self._plane
        height_m = above_m[:, 2] if plane is None else above_m @ plane[:3] + plane[3]
        return object_cluster(
            above_m, height_m, config.cluster_radius_m, config.cluster_min_points,
            config.max_base_height_m, config.cluster_join_m,
        )  # fmt: skip

    def _icp(self, source: FloatArray) -> FloatArray | None:
        """The ICP correction [4, 4] of source onto the object points of the views so far,
        or None when there is no trustworthy one (too few points, poor fitness, implausibly
        large shift)."""
        config = self.config
        target = np.concatenate(self._object_views) if self._object_views else source[:0]
        if not config.icp or len(source) < config.min_object_points or len(target) < 3:
            return None
        transform, rmse_before_m, rmse_after_m = icp_align(
            source, target, np.concatenate(self._view_normals), config.icp_max_distance_m
        )
        # How far the correction moves the points: the transform's translation is about the
        # world origin, where a small turn about the object counts its lever arm too.
        moved = source @ transform[:3, :3].T + transform[:3, 3] - source
        correction_m = float(np.linalg.norm(moved, axis=1).max())
        gain = 1.0 - rmse_after_m / rmse_before_m if rmse_before_m > 0 else 0.0
        if gain < config.icp_min_rmse_gain or correction_m > config.icp_max_correction_m:
            # Already aligned (ICP would only fit the noise, sliding along flat faces) or
            # an implausibly large jump.
            log.info("ICP not applied (RMSE gain %.0f%%, shift %.1f mm)", 100 * gain,
                     1e3 * correction_m)  # fmt: skip
            return None
        log.info("ICP: RMSE %.2f -> %.2f mm, shift %.2f mm", 1e3 * rmse_before_m,
                 1e3 * rmse_after_m, 1e3 * correction_m)  # fmt: skip
        return transform

    @property
    def _normal_radius_m(self) -> float:
        return max(3 * self.config.voxel_m, 0.005)

    def _above_table(self, points_m: FloatArray) -> FloatArray:
        """Points [K, 3] more than the clearance above the RANSAC table plane (all points when
        no horizontal plane is found, e.g. a cloud of the object only)."""
        config = self.config
        count = min(len(points_m), config.ransac_points)
        subset = points_m[self._rng.choice(len(points_m), size=count, replace=False)]
        plane = table_plane(subset, config.table_distance_m, config.ransac_iterations, self._rng)
        if plane is None:
            return points_m
        self._plane = plane
        height_m = points_m @ plane[:3] + plane[3]
        return points_m[height_m > config.table_clearance_m]
