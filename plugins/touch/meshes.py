"""Triangle meshes for touch: loading, validation, normalisation, signed distance.

A :class:`Mesh` is a closed (watertight) triangle mesh in its object frame. Its signed
distance (:class:`MeshSDF`, exact, open3d ray casting) is positive outside; :class:`GridSDF`
samples it on a voxel grid once and interpolates trilinearly; :class:`GridStack` evaluates
several such grids at thousands of poses in one pass, which is what the particle filter uses.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from vistac.errors import DataError
from vistac.plugins.touch.types import SignedDistance
from vistac.types import FloatArray

log = logging.getLogger(__name__)

MESH_SUFFIXES = (".obj", ".ply", ".off", ".stl")
DEFAULT_SIZE_M = 0.2
"""Largest bounding-box extent every class is scaled to."""

IntArray = NDArray[np.int64]


@dataclass(frozen=True, eq=False)
class Mesh:
    """A watertight triangle mesh: vertices_m [V, 3] (object frame, m), triangles [T, 3]."""

    name: str
    vertices_m: FloatArray
    triangles: IntArray
    source: str = field(default="")
    """Where it came from (a library class name or a file path)."""

    def sdf(self) -> MeshSDF:
        """The exact signed distance of this mesh (object frame), built once."""
        return self._sdf

    @cached_property
    def _sdf(self) -> MeshSDF:
        return MeshSDF(self.vertices_m, self.triangles)

    @cached_property
    def grid_sdf(self) -> GridSDF:
        """A voxel-grid approximation of :meth:`sdf` (fast, for many queries)."""
        return GridSDF.from_sdf(self.sdf(), self.vertices_m)

    @property
    def extent_m(self) -> FloatArray:
        """Bounding-box size [3] in m."""
        return np.ptp(self.vertices_m, axis=0)

    @property
    def radius_m(self) -> float:
        """Largest distance of a vertex from the object-frame origin."""
        return float(np.linalg.norm(self.vertices_m, axis=1).max())

    def surface_samples(self, count: int, seed: int = 0) -> tuple[FloatArray, FloatArray]:
        """``count`` Poisson-disk surface samples: points [count, 3], outward normals [count, 3]."""
        return _poisson_samples(self, count, seed)

    def transformed(self, world_from_object: FloatArray) -> Mesh:
        """The mesh with its vertices in the world frame ([4, 4] pose)."""
        vertices = apply_pose(world_from_object, self.vertices_m)
        return Mesh(self.name, vertices, self.triangles, self.source)


def apply_pose(pose: FloatArray, points: FloatArray) -> FloatArray:
    """``pose`` [4, 4] applied to points [N, 3] -> [N, 3]."""
    return np.asarray(points @ pose[:3, :3].T + pose[:3, 3], dtype=np.float64)


def _legacy(vertices_m: FloatArray, triangles: IntArray) -> Any:
    import open3d as o3d

    mesh = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(np.asarray(vertices_m, dtype=np.float64)),
        o3d.utility.Vector3iVector(np.asarray(triangles, dtype=np.int32)),
    )
    mesh.compute_vertex_normals()
    return mesh


def _poisson_samples(mesh: Mesh, count: int, seed: int) -> tuple[FloatArray, FloatArray]:
    import open3d as o3d

    o3d.utility.random.seed(seed)
    cloud = _legacy(mesh.vertices_m, mesh.triangles).sample_points_poisson_disk(
        count, use_triangle_normal=True
    )
    points = np.asarray(cloud.points, dtype=np.float64)
    _, normals = mesh.sdf()(points)  # outward normals of the nearest surface point
    return points, normals


class MeshSDF:
    """Exact signed distance of a watertight mesh (open3d ``RaycastingScene``).

    ``sdf(points [N, 3]) -> (distance [N] m, positive outside; unit outward normal [N, 3] of
    the nearest surface point, interpolated from the vertex normals)``."""

    def __init__(self, vertices_m: FloatArray, triangles: IntArray) -> None:
        import open3d as o3d

        legacy = _legacy(vertices_m, triangles)
        self._vertex_normals = np.asarray(legacy.vertex_normals, dtype=np.float64)
        self._triangles = np.asarray(triangles, dtype=np.int64)
        self._scene = o3d.t.geometry.RaycastingScene()
        self._scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(legacy))

    def __call__(self, points: FloatArray) -> tuple[FloatArray, FloatArray]:
        import open3d as o3d

        query = o3d.core.Tensor.from_numpy(
            np.ascontiguousarray(np.asarray(points, dtype=np.float32).reshape(-1, 3))
        )
        distance = self._scene.compute_signed_distance(query, nsamples=3).numpy()
        closest = self._scene.compute_closest_points(query)
        return distance.astype(np.float64), self._normals(closest)

    def _normals(self, closest: dict[str, Any]) -> FloatArray:
        """Vertex normals interpolated with the closest point's barycentric coordinates."""
        ids = closest["primitive_ids"].numpy().astype(np.int64)
        uv = closest["primitive_uvs"].numpy().astype(np.float64)
        corners = self._vertex_normals[self._triangles[ids]]  # [N, 3 corners, 3]
        weights = np.stack([1.0 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]], axis=1)
        normals = np.einsum("nc,ncd->nd", weights, corners)
        return normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)

    def cast(self, origins_m: FloatArray, directions: FloatArray) -> tuple[FloatArray, FloatArray]:
        """First hits of rays (origins [N, 3], unit directions [N, 3]): distance along the ray
        [N] (inf for a miss) and the hit triangle's outward normal [N, 3]."""
        import open3d as o3d

        rays = np.concatenate([origins_m, directions], axis=1).astype(np.float32)
        hits = self._scene.cast_rays(o3d.core.Tensor.from_numpy(np.ascontiguousarray(rays)))
        return (
            hits["t_hit"].numpy().astype(np.float64),
            hits["primitive_normals"].numpy().astype(np.float64),
        )


_CORNERS = [(dx, dy, dz) for dx in (0, 1) for dy in (0, 1) for dz in (0, 1)]
"""The 8 corners of a grid cell, x slowest (the order :func:`_trilinear` pairs them in)."""


def _trilinear(
    values: NDArray[np.float32],
    coords: NDArray[np.float32],
    upper: NDArray[np.float32],
    base: IntArray | int,
    strides: tuple[IntArray | int, IntArray | int],
) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """Trilinear interpolation of ``values`` [V, C] (flat grids, one row per grid point, z
    fastest) at continuous grid indices ``coords`` [3, M], each clamped to [0, upper] ([3, M]
    or [3, 1]: the last index per axis of its grid). ``base`` [M] (or one int) is the flat
    index of each point's grid origin, ``strides`` the flat steps of x and y ([M] each, or
    ints; z is 1). Returns the values [M, C] and the distance [M] in cells from each point to
    its grid box (0 inside)."""
    clamped = np.clip(coords, np.float32(0.0), upper)
    gap = coords - clamped
    outside = np.sqrt(gap[0] * gap[0] + gap[1] * gap[1] + gap[2] * gap[2])
    cell = np.minimum(clamped.astype(np.int64), upper.astype(np.int64) - 1)
    fx, fy, fz = (clamped - cell.astype(np.float32))[:, :, None]
    step_x, step_y = strides
    flat = base + cell[0] * step_x + cell[1] * step_y + cell[2]
    v = [values.take(flat + (dx * step_x + dy * step_y + dz), axis=0) for dx, dy, dz in _CORNERS]
    x = [v[i] + fx * (v[i + 4] - v[i]) for i in range(4)]
    y = [x[i] + fy * (x[i + 2] - x[i]) for i in range(2)]
    return y[0] + fz * (y[1] - y[0]), outside


def _unit(vectors: NDArray[np.float32]) -> NDArray[np.float32]:
    """Unit vectors [M, 3] along the rows of ``vectors`` [M, 3] (0 stays 0)."""
    norm = np.sqrt(np.einsum("mi,mi->m", vectors, vectors))[:, None]
    return np.asarray(vectors / np.maximum(norm, np.float32(1e-12)), dtype=np.float32)


class GridSDF:
    """A signed distance sampled on a regular grid, interpolated trilinearly (float32).

    Queries outside the grid get the value at the nearest grid point plus the distance to the
    grid box (never smaller than the true distance there by more than the grid's margin)."""

    def __init__(
        self, origin_m: FloatArray, step_m: float, distance: FloatArray, normals: FloatArray
    ) -> None:
        """distance: [X, Y, Z] in m; normals: [X, Y, Z, 3] unit outward normals."""
        self.origin_m = np.asarray(origin_m, dtype=np.float64)
        self.step_m = float(step_m)
        self.shape = np.array(distance.shape)
        self.values = (
            np.concatenate([distance[..., None], normals], axis=-1)
            .reshape(-1, 4)
            .astype(np.float32)
        )
        """[X * Y * Z, 4]: distance and normal x, y, z per grid point (z fastest)."""

    @property
    def strides(self) -> tuple[int, int]:
        """Flat index steps of x and y (z is 1)."""
        return int(self.shape[1] * self.shape[2]), int(self.shape[2])

    @classmethod
    def from_sdf(
        cls, sdf: SignedDistance, vertices_m: FloatArray, cells: int = 56, margin_m: float = 0.04
    ) -> GridSDF:
        """Sample ``sdf`` on a cubic grid of ``cells`` per axis over the vertices' bounding box
        grown by ``margin_m``."""
        low = vertices_m.min(axis=0) - margin_m
        high = vertices_m.max(axis=0) + margin_m
        step = float((high - low).max() / (cells - 1))
        counts = np.ceil((high - low) / step).astype(int) + 1
        axes = [low[i] + step * np.arange(counts[i]) for i in range(3)]
        grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
        distance, normals = sdf(grid)
        return cls(low, step, distance.reshape(*counts), normals.reshape(*counts, 3))

    def __call__(self, points: FloatArray) -> tuple[FloatArray, FloatArray]:
        """points [N, 3] (any leading shape) -> distance [N], unit normals [N, 3]."""
        points = np.asarray(points, dtype=np.float64)
        lead = points.shape[:-1]
        coords = ((points.reshape(-1, 3) - self.origin_m) / self.step_m).T.astype(np.float32)
        upper = (self.shape - 1).astype(np.float32)[:, None]
        result, outside = _trilinear(self.values, coords, upper, 0, self.strides)
        distance = result[:, 0].astype(np.float64) + outside * self.step_m
        normals = _unit(result[:, 1:]).astype(np.float64)
        return distance.reshape(lead), normals.reshape(*lead, 3)


class GridStack:
    """Several :class:`GridSDF` in one array, evaluated together: the signed distance (and
    normal) of many points in the frames of many (shape, pose) pairs in one pass, as the
    particle filter needs. Same values as each grid's own ``__call__``."""

    def __init__(self, grids: list[GridSDF]) -> None:
        self._values = np.concatenate([grid.values for grid in grids])
        self._distance = np.ascontiguousarray(self._values[:, :1])  # compact for misses
        sizes = [len(grid.values) for grid in grids]
        self._base = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64)
        self._strides = np.array([grid.strides for grid in grids], dtype=np.int64).T  # [2, C]
        self._upper = np.array([grid.shape - 1 for grid in grids], dtype=np.float32).T  # [3, C]
        self._origin_m = np.array([grid.origin_m for grid in grids])
        self._step_m = np.array([grid.step_m for grid in grids])

    def distance(
        self, shape: IntArray, rotation: FloatArray, translation: FloatArray, points_m: FloatArray
    ) -> FloatArray:
        """Signed distance [N, K] (m) of world points [K, 3] from N objects: grid ``shape`` [N]
        at world_from_object rotation [N, 3, 3], translation [N, 3]."""
        distance, _ = self._sample(self._distance, shape, rotation, translation, points_m)
        return distance

    def distance_and_normals(
        self, shape: IntArray, rotation: FloatArray, translation: FloatArray, points_m: FloatArray
    ) -> tuple[FloatArray, NDArray[np.float32]]:
        """As :meth:`distance`, plus the unit outward normals [N, K, 3] in each object's
        frame."""
        distance, result = self._sample(self._values, shape, rotation, translation, points_m)
        count, points = distance.shape
        return distance, _unit(result[:, 1:]).reshape(points, count, 3).transpose(1, 0, 2)

    def _sample(
        self,
        values: NDArray[np.float32],
        shape: IntArray,
        rotation: FloatArray,
        translation: FloatArray,
        points_m: FloatArray,
    ) -> tuple[FloatArray, NDArray[np.float32]]:
        """Signed distance [N, K] (m, float64) and the interpolated ``values`` rows [K N, C]
        (point-major: row k N + n is point k seen from object n)."""
        count, points = len(shape), len(points_m)
        per_point = np.tile(shape, points)
        step_x, step_y = self._strides.take(per_point, axis=1)
        result, outside = _trilinear(
            values,
            self._grid_coordinates(shape, rotation, translation, points_m),
            self._upper.take(per_point, axis=1),
            self._base.take(per_point),
            (step_x, step_y),
        )
        step_m = np.tile(self._step_m[shape].astype(np.float32), points)
        distance = (result[:, 0] + outside * step_m).astype(np.float64)
        return distance.reshape(points, count).T, result

    def _grid_coordinates(
        self, shape: IntArray, rotation: FloatArray, translation: FloatArray, points_m: FloatArray
    ) -> NDArray[np.float32]:
        """Continuous grid indices [3, K * N] (point-major) of points [K, 3] in N objects'
        grids: the affine maps world -> object -> grid index [3, 4, N] applied to the
        homogeneous points [4, K] (einsum, not BLAS: a threaded BLAS stalls on a busy machine
        for so small a product)."""
        scaled = rotation / self._step_m[shape][:, None, None]  # [n, j, i] = (R^T)_ij / step
        offset = -np.einsum("nji,nj->ni", scaled, translation) - (
            self._origin_m[shape] / self._step_m[shape][:, None]
        )
        affine = np.concatenate([scaled, offset[:, None, :]], axis=1).transpose(2, 1, 0)
        homogeneous = np.vstack([points_m.T, np.ones(len(points_m))]).astype(np.float32)
        coords = np.einsum("ijn,jk->ikn", np.ascontiguousarray(affine, np.float32), homogeneous)
        return coords.reshape(3, -1)


def transform_sdf(sdf: SignedDistance, world_from_object: FloatArray) -> SignedDistance:
    """``sdf`` (object frame) evaluated at world points: world points [N, 3] -> (distance [N],
    world-frame normals [N, 3])."""
    pose = np.asarray(world_from_object, dtype=np.float64)
    rotation, translation = pose[:3, :3], pose[:3, 3]

    def world_sdf(points: FloatArray) -> tuple[FloatArray, FloatArray]:
        local = (np.asarray(points, dtype=np.float64) - translation) @ rotation
        distance, normals = sdf(local)
        return distance, normals @ rotation.T

    return world_sdf


def validate(vertices_m: FloatArray, triangles: IntArray, source: str) -> None:
    """Raise DataError unless the mesh is non-empty, finite and watertight."""
    if len(vertices_m) == 0 or len(triangles) == 0:
        raise DataError(f"{source}: the mesh is empty (no vertices or no triangles)")
    if not np.all(np.isfinite(vertices_m)):
        raise DataError(f"{source}: the mesh has NaN or infinite vertex coordinates")
    legacy = _legacy(vertices_m, triangles)
    closed = legacy.is_edge_manifold(allow_boundary_edges=False) and legacy.is_vertex_manifold()
    if not closed:
        raise DataError(
            f"{source}: the mesh is not watertight (it has holes, boundary edges or "
            "non-manifold edges), so inside and outside are undefined; close the holes "
            "(e.g. in MeshLab: Filters > Remeshing > Close Holes, or a Poisson/voxel "
            "remesh) and save it again"
        )


def normalise(vertices_m: FloatArray, size_m: float = DEFAULT_SIZE_M) -> FloatArray:
    """Centre the bounding box at the origin and scale its largest extent to ``size_m``."""
    low, high = vertices_m.min(axis=0), vertices_m.max(axis=0)
    scale = size_m / float((high - low).max())
    return np.asarray((vertices_m - (low + high) / 2.0) * scale, dtype=np.float64)


def make_mesh(
    name: str,
    vertices_m: FloatArray,
    triangles: IntArray,
    source: str,
    size_m: float | None = DEFAULT_SIZE_M,
) -> Mesh:
    """Validate, clean and (unless ``size_m`` is None) normalise into a :class:`Mesh`."""
    vertices_m = np.asarray(vertices_m, dtype=np.float64)
    triangles = np.asarray(triangles, dtype=np.int64)
    validate(vertices_m, triangles, source)
    if size_m is not None:
        vertices_m = normalise(vertices_m, size_m)
    return Mesh(name, vertices_m, triangles, source)


def load_mesh(path: Path | str, size_m: float | None = DEFAULT_SIZE_M) -> Mesh:
    """Read a .obj/.ply/.off/.stl file into a validated, normalised :class:`Mesh` named after
    the file's stem."""
    import open3d as o3d

    path = Path(path)
    if path.suffix.lower() not in MESH_SUFFIXES:
        raise DataError(f"{path}: unsupported mesh format; use one of {', '.join(MESH_SUFFIXES)}")
    if not path.is_file():
        raise DataError(f"{path}: no such mesh file")
    legacy = o3d.io.read_triangle_mesh(path)
    legacy.remove_duplicated_vertices()
    legacy.remove_unreferenced_vertices()
    return make_mesh(
        path.stem,
        np.asarray(legacy.vertices, dtype=np.float64),
        np.asarray(legacy.triangles, dtype=np.int64),
        str(path),
        size_m,
    )


def save_mesh(mesh: Mesh, path: Path | str) -> None:
    """Write ``mesh`` to ``path`` (format from the suffix)."""
    import open3d as o3d

    if not o3d.io.write_triangle_mesh(Path(path), _legacy(mesh.vertices_m, mesh.triangles)):
        raise DataError(f"{path}: could not write the mesh")
