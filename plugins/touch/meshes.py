"""Triangle meshes for touch: loading, validation, normalisation, signed distance.

A :class:`Mesh` is a closed (watertight) triangle mesh in its object frame. Its signed
distance (:class:`MeshSDF`, exact, open3d ray casting) is positive outside; :class:`GridSDF`
samples it on a voxel grid once and interpolates trilinearly, which is what the particle
filter uses for thousands of poses per step.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray
from vistac.errors import DataError
from vistac.plugins.touch.types import SignedDistance
from vistac.types import FloatArray

if TYPE_CHECKING:
    import torch  # imported where used: loading and probing meshes need no torch

log = logging.getLogger(__name__)

MESH_SUFFIXES = (".obj", ".ply", ".off", ".stl")
DEFAULT_SIZE_M = 0.2
"""Largest bounding-box extent every library class is scaled to."""

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


def trilinear(volumes: torch.Tensor, coordinates: FloatArray) -> FloatArray:
    """Trilinear values [K, M] (float64) of the K channels of volumes [K, X, Y, Z] (float64,
    at least 2 cells along each axis) at grid coordinates [M, 3] (in cells, within the grid:
    clamped by the caller).

    One ``torch.nn.functional.grid_sample`` for all channels: it takes the points in the
    volume's (Z, Y, X) order, scaled so that -1 and 1 are the first and last cells
    (``align_corners``); ``border`` padding only keeps points that rounding puts a hair
    beyond the last cell on it."""
    import torch

    cells = np.array(volumes.shape[1:], dtype=np.float64)
    scaled = coordinates[:, ::-1] * (2.0 / (cells[::-1] - 1.0)) - 1.0  # [M, 3], a new array
    grid = torch.from_numpy(scaled).view(1, 1, 1, -1, 3)
    values = torch.nn.functional.grid_sample(
        volumes[None], grid, mode="bilinear", padding_mode="border", align_corners=True
    )
    return values.view(len(volumes), -1).numpy()


class GridSDF:
    """A signed distance sampled on a regular grid, interpolated trilinearly (``trilinear``).

    Queries outside the grid get the value at the nearest grid point plus the distance to the
    grid box (never smaller than the true distance there by more than the grid's margin)."""

    def __init__(
        self, origin_m: FloatArray, step_m: float, distance: FloatArray, normals: FloatArray
    ) -> None:
        """distance: [X, Y, Z] in m; normals: [X, Y, Z, 3] unit outward normals."""
        self.origin_m = np.asarray(origin_m, dtype=np.float64)
        self.step_m = float(step_m)
        self.shape = np.array(distance.shape)
        self._volumes = np.ascontiguousarray(
            np.concatenate([distance[None], np.moveaxis(normals, -1, 0)]), dtype=np.float32
        )
        self._volumes.flags.writeable = False

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

    def _grid_coordinates(self, points: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Grid coordinates [N, 3] of points [..., 3], clamped to the grid, and each point's
        distance to the grid box [N] in m."""
        flat_m = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        scaled = (flat_m - self.origin_m) / self.step_m
        clamped = np.clip(scaled, 0.0, self.shape - 1)
        outside_m = np.linalg.norm(scaled - clamped, axis=1) * self.step_m
        return clamped, outside_m

    @property
    def volumes(self) -> FloatArray:
        """[4, X, Y, Z] float32: the distance (m), then the normal's x, y and z (read only)."""
        return self._volumes

    @cached_property
    def _interpolated(self) -> torch.Tensor:
        """The volumes as a float64 tensor [4, X, Y, Z], made at the first query."""
        import torch

        return torch.from_numpy(self._volumes.astype(np.float64))

    def distance(self, points: FloatArray) -> FloatArray:
        """points [..., 3] -> signed distance [...] in m (no normals: a quarter of the work)."""
        coordinates, outside_m = self._grid_coordinates(points)
        distance = trilinear(self._interpolated[:1], coordinates)[0] + outside_m
        return distance.reshape(np.shape(points)[:-1])

    def __call__(self, points: FloatArray) -> tuple[FloatArray, FloatArray]:
        """points [..., 3] -> signed distance [...] in m, unit outward normals [..., 3]."""
        lead = np.shape(points)[:-1]
        coordinates, outside_m = self._grid_coordinates(points)
        return split_normals(trilinear(self._interpolated, coordinates), outside_m, lead)


def split_normals(
    values: FloatArray, outside_m: FloatArray, lead: tuple[int, ...]
) -> tuple[FloatArray, FloatArray]:
    """The distance [*lead] in m and unit normals [*lead, 3] from interpolated values [4, M]
    (distance, normal x, y, z) of points outside_m [M] (or [*lead]) from the grid box."""
    normals = values[1:].T
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    distance = values[0].reshape(lead) + np.reshape(outside_m, lead)
    return distance, normals.reshape(*lead, 3)


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
    """Read a .obj/.ply/.off/.stl file into a validated :class:`Mesh` named after the file's
    stem: normalised to ``size_m``, or as saved (m, its own frame) when ``size_m`` is None."""
    path = Path(path)
    legacy = _read_legacy(path)
    return make_mesh(
        path.stem,
        np.asarray(legacy.vertices, dtype=np.float64),
        np.asarray(legacy.triangles, dtype=np.int64),
        str(path),
        size_m,
    )


def _read_legacy(path: Path) -> Any:
    """The open3d triangle mesh in ``path``, duplicated and unreferenced vertices removed;
    DataError for an unsupported suffix, a missing file or a file with no triangles in it."""
    import open3d as o3d

    if path.suffix.lower() not in MESH_SUFFIXES:
        raise DataError(f"{path}: unsupported mesh format; use one of {', '.join(MESH_SUFFIXES)}")
    if not path.is_file():
        raise DataError(f"{path}: no such mesh file")
    legacy = o3d.io.read_triangle_mesh(path)
    if not (legacy.has_vertices() and legacy.has_triangles()):
        raise DataError(
            f"{path}: could not be read as a mesh (the file is corrupt, empty or not a "
            f"{path.suffix.lower()} triangle mesh): {len(legacy.vertices)} vertices and "
            f"{len(legacy.triangles)} triangles read"
        )
    legacy.remove_duplicated_vertices()
    legacy.remove_unreferenced_vertices()
    return legacy


def save_mesh(mesh: Mesh, path: Path | str) -> None:
    """Write ``mesh`` to ``path`` (format from the suffix)."""
    import open3d as o3d

    if not o3d.io.write_triangle_mesh(Path(path), _legacy(mesh.vertices_m, mesh.triangles)):
        raise DataError(f"{path}: could not write the mesh")
