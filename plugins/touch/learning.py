"""Shape transfer learning by touch (paper 2, III-G/H, IV-B3/4) and its evaluation.

After exploring an object the recogniser declared novel, ``learn_shape`` takes the GPIS
reconstruction (built on the recogniser's maximum-likelihood shape as prior mean), moves it
into the object frame of that shape's pose and saves it as a watertight ``.ply`` file. The file
is a new known class: list its path in ``touch.pf``'s ``classes``.

The skill-end hook adds, when the probe knew the true object, the reconstruction error: the
two-way Hausdorff distance (TWD, eq. 46) between the saved shape and the true one (exact
distances from surface samples of each to the other's triangles), and the same error of the
peer, open3d's screened Poisson reconstruction of the run's contacts. :func:`compare_with_poisson`
is the paper's Table II trial outside a skill (contacts spread over the true surface, the
parent class at the true pose as prior).

This module is also a plugin module (``vistac_register``, ``vistac_skill_end``); it imports
nothing heavy at import time.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from py_trees.common import Status
from pydantic import Field
from vistac.component import ComponentConfig, SkillPath
from vistac.errors import DataError
from vistac.tree import SkillBehaviour
from vistac.types import FloatArray

if TYPE_CHECKING:
    from vistac.plugins.touch.gpis import GpisSettings, SurfaceMesh
    from vistac.plugins.touch.meshes import Mesh

log = logging.getLogger(__name__)

ERROR_SAMPLES = 5000
"""Surface samples per shape for the TWD."""


# --- meshes ------------------------------------------------------------------------------


def outward(mesh: Mesh) -> Mesh:
    """``mesh`` with its triangles facing outward (reversed when its signed volume is < 0)."""
    from vistac.plugins.touch.gpis import SurfaceMesh, enclosed_volume_m3
    from vistac.plugins.touch.meshes import Mesh

    if enclosed_volume_m3(SurfaceMesh(mesh.vertices_m, mesh.triangles)) >= 0.0:
        return mesh
    return Mesh(mesh.name, mesh.vertices_m, mesh.triangles[:, ::-1].copy(), mesh.source)


def surface_samples(vertices_m: FloatArray, triangles: Any, count: int, seed: int) -> FloatArray:
    """``count`` points [count, 3] uniformly (by area) on a triangle mesh (open3d)."""
    import open3d as o3d

    legacy = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(np.asarray(vertices_m, dtype=np.float64)),
        o3d.utility.Vector3iVector(np.asarray(triangles, dtype=np.int32)),
    )
    o3d.utility.random.seed(seed)
    return np.asarray(legacy.sample_points_uniformly(count).points, dtype=np.float64)


def distance_to_surface_m(
    points_m: FloatArray, vertices_m: FloatArray, triangles: Any
) -> FloatArray:
    """Exact distance [N] from points [N, 3] to a triangle mesh (open3d ray-casting scene)."""
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    tensor = o3d.core.Tensor.from_numpy
    scene.add_triangles(tensor(np.asarray(vertices_m, dtype=np.float32)),
                        tensor(np.asarray(triangles, dtype=np.uint32)))  # fmt: skip
    query = tensor(np.asarray(points_m, dtype=np.float32))
    return scene.compute_distance(query).numpy().astype(np.float64)


def reconstruction_error_m(
    reconstruction: tuple[FloatArray, Any], truth: tuple[FloatArray, Any],
    samples: int = ERROR_SAMPLES, seed: int = 0,
) -> float:  # fmt: skip
    """TWD (eq. 46, m) between two meshes (vertices_m [V, 3], triangles [T, 3]).

    Each directed distance is the largest exact distance from ``samples`` uniform surface
    samples of one mesh to the other mesh's triangles (no sampling floor on the far side).
    """
    a_to_b = distance_to_surface_m(surface_samples(*reconstruction, samples, seed), *truth)
    b_to_a = distance_to_surface_m(surface_samples(*truth, samples, seed + 1), *reconstruction)
    return float(max(a_to_b.max(), b_to_a.max()))


def poisson_reconstruction(
    points_m: FloatArray, normals: FloatArray, depth: int = 8
) -> SurfaceMesh:
    """The peer: open3d's screened Poisson surface of oriented points [N, 3] / normals [N, 3].

    Runs on one thread: open3d's multi-threaded Poisson solver crashes the process at random
    (a known race in its solver), and these clouds are small enough not to need more.
    """
    import open3d as o3d
    from vistac.plugins.touch.gpis import SurfaceMesh

    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points_m))
    cloud.normals = o3d.utility.Vector3dVector(normals)
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        mesh, _ = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(
            cloud, depth=depth, n_threads=1
        )
    return SurfaceMesh(np.asarray(mesh.vertices, dtype=np.float64),
                       np.asarray(mesh.triangles, dtype=np.int64))  # fmt: skip


# --- saving a learned shape --------------------------------------------------------------


def available_path(directory: Path, name: str) -> Path:
    """``directory/name.ply``, or ``name_2.ply``, ``name_3.ply``, ... if taken."""
    path, index = directory / f"{name}.ply", 1
    while path.exists():
        index += 1
        path = directory / f"{name}_{index}.ply"
    return path


def save_learned_shape(
    surface: SurfaceMesh, directory: Path, name: str, world_from_object: FloatArray
) -> Path:
    """Save a reconstruction (world frame) in the object frame ``world_from_object`` [4, 4] as
    a watertight .ply under ``directory`` (created); returns the file's absolute path (as
    it can be listed in ``touch.pf``'s classes from anywhere).

    Raises DataError when the surface is not watertight (it could not serve as a class).
    """
    from vistac.plugins.touch.meshes import make_mesh, save_mesh

    pose = np.asarray(world_from_object, dtype=np.float64)
    vertices_m = (surface.vertices_m - pose[:3, 3]) @ pose[:3, :3]
    mesh = make_mesh(name, vertices_m, surface.triangles, f"learned:{name}", size_m=None)
    directory.mkdir(parents=True, exist_ok=True)
    path = available_path(directory, name).resolve()
    save_mesh(mesh, path)
    log.info("saved the learned shape %s (%d triangles) to %s", name, len(mesh.triangles), path)
    return path


def centred_pose(vertices_m: FloatArray) -> FloatArray:
    """A [4, 4] frame at the centre of the vertices' bounding box, axes of the world."""
    pose = np.eye(4)
    pose[:3, 3] = (vertices_m.min(axis=0) + vertices_m.max(axis=0)) / 2.0
    return pose


class LearnShape(SkillBehaviour):
    """``learn_shape``: save the GPIS reconstruction of a novel object as a new class.

    Runs once after exploration. When the recogniser (role ``estimator``) says the object is
    known (``known()`` True) or has not decided yet (None), nothing is saved unless
    ``only_novel`` is false. The shape is saved in the object frame of the recogniser's MLE
    pose (or centred without one) as ``directory/name.ply`` (default directory: the run's
    ``OUT/learned``). The summary gets
    ``learned_shape``: saved (bool), path, class_name, world_from_saved, prior_class, reason.
    """

    reads = ("touch",)
    role_fields = {"surface": "touch_estimator", "estimator": "touch_estimator"}

    class Config(ComponentConfig):
        surface: str = "surface"
        estimator: str = "estimator"
        directory: SkillPath | None = Field(
            None,
            description="where learned shapes go (relative to the skill file); "
            "default: OUT/learned of the run",
        )
        name: str | None = Field(
            None,
            pattern=r"^[A-Za-z0-9_.-]+$",
            description="class name = file stem; default: the most likely known class + '_learned'",
        )
        only_novel: bool = True

    def update(self) -> Status:
        estimator = self.component("estimator")
        known = _call(estimator, "known")
        mle = _call(estimator, "mle_prior")
        record: dict[str, Any] = {
            "saved": False, "known": known, "prior_class": getattr(mle, "class_name", None),
        }  # fmt: skip
        if self.config.only_novel and known is not False:
            record["reason"] = "recognised as a known class" if known else "known/novel undecided"
        else:
            surface = self.component("surface").reconstruction()
            pose = mle.world_from_object if mle is not None else centred_pose(surface.vertices_m)
            directory = self.config.directory or self.run.info.out_dir / "learned"
            name = self.config.name or f"{getattr(mle, 'class_name', 'shape')}_learned"
            path = save_learned_shape(surface, directory, name, pose)
            record.update(saved=True, path=str(path), class_name=path.stem,
                          world_from_saved=np.asarray(pose).tolist(),
                          triangles=len(surface.triangles))  # fmt: skip
        self.run.results["learned_shape"] = record
        return Status.SUCCESS


def _call(component: Any, method: str) -> Any:
    """``component.method()`` when it has such a method, else None."""
    function = getattr(component, method, None)
    return function() if callable(function) else None


# --- evaluation --------------------------------------------------------------------------


def _world_mesh(path_or_class: str, world_from_object: Any, base: Path,
                exact: bool) -> tuple[FloatArray, Any]:  # fmt: skip
    """(vertices_m [V, 3] in the world, triangles [T, 3]) of a mesh file (``exact``: as saved,
    no normalisation) or a library/class spec, placed at ``world_from_object`` [4, 4]."""
    from vistac.plugins.touch.library import resolve_shape
    from vistac.plugins.touch.meshes import apply_pose, load_mesh

    mesh = load_mesh(path_or_class, size_m=None) if exact else resolve_shape(path_or_class, base)
    return apply_pose(np.asarray(world_from_object), mesh.vertices_m), mesh.triangles


def add_learning_metrics(summary: dict[str, Any], base: Path) -> None:
    """Complete ``summary["learned_shape"]``: steps (touches taken) and, when the probe's
    truth (``touch_truth``) is known, reconstruction_error_m (TWD of the saved shape to the true
    object) and poisson_error_m (TWD of screened Poisson on the run's contacts, the peer)."""
    record, truth = summary.get("learned_shape"), summary.get("touch_truth")
    if not isinstance(record, dict):
        return
    touch = summary.get("touch") if isinstance(summary.get("touch"), dict) else None
    record["steps"] = None if touch is None else touch.get("touches")
    if not (record.get("saved") and isinstance(truth, dict) and "world_from_object" in truth):
        return
    reference = _world_mesh(truth["object"], truth["world_from_object"], base, exact=False)
    saved = _world_mesh(record["path"], record["world_from_saved"], base, exact=True)
    record["reconstruction_error_m"] = reconstruction_error_m(saved, reference)
    contacts = np.asarray((touch or {}).get("contacts") or np.zeros((0, 3)), dtype=np.float64)
    normals = np.asarray((touch or {}).get("normals") or np.zeros((0, 3)), dtype=np.float64)
    poisson = poisson_reconstruction(contacts, normals) if len(contacts) >= 4 else None
    record["poisson_error_m"] = (
        reconstruction_error_m((poisson.vertices_m, poisson.triangles), reference)
        if poisson is not None and len(poisson.triangles) else None
    )  # fmt: skip


# --- the Table II comparison -------------------------------------------------------------


@dataclass(frozen=True)
class ReconstructionComparison:
    """TWD (m) to the true shape of: the MLE prior shape, the GPIS with it, screened Poisson."""

    name: str
    contacts: int
    mle_m: float
    gpis_m: float
    poisson_m: float


def coverage_contacts(
    mesh: Mesh, count: int, rng: np.random.Generator, point_noise_m: float = 1e-3,
    normal_noise_rad: float = 0.03,
) -> tuple[FloatArray, FloatArray]:  # fmt: skip
    """``count`` contacts spread over a (world-frame) mesh like a coverage-driven exploration:
    farthest-point order from a random start, with Gaussian point and normal noise.
    Returns points [count, 3] and unit outward normals [count, 3]."""
    from scipy.spatial.transform import Rotation

    dense = surface_samples(mesh.vertices_m, mesh.triangles, 40 * count, int(rng.integers(1 << 30)))
    chosen = [int(rng.integers(len(dense)))]
    distance = np.linalg.norm(dense - dense[chosen[0]], axis=1)
    for _ in range(count - 1):
        chosen.append(int(distance.argmax()))
        distance = np.minimum(distance, np.linalg.norm(dense - dense[chosen[-1]], axis=1))
    points = dense[chosen]
    _, normals = mesh.sdf()(points)
    tilts = Rotation.from_rotvec(rng.normal(0.0, normal_noise_rad, (count, 3)))
    normals = tilts.apply(normals)
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    return points + rng.normal(0.0, point_noise_m, points.shape), normals


def compare_with_poisson(
    novel: str, contacts: int, seed: int = 0, settings: GpisSettings | None = None,
    poisson_depth: int = 8,
) -> ReconstructionComparison:  # fmt: skip
    """One Table II trial: the novel variant ``novel`` at a random pose, ``contacts`` coverage
    contacts, the GPIS with its parent class at the true pose as MLE prior, and screened
    Poisson on the same oriented points; TWD of each (and of the prior) to the truth."""
    from scipy.spatial.transform import Rotation
    from vistac.plugins.touch.gpis import GpisSettings, TouchSurface
    from vistac.plugins.touch.library import NOVEL, known_class, novel_class
    from vistac.plugins.touch.meshes import apply_pose, transform_sdf
    from vistac.plugins.touch.types import MlePrior

    if novel not in NOVEL:
        raise DataError(f"unknown novel shape {novel!r}; novel: {', '.join(NOVEL)}")
    rng = np.random.default_rng(seed)
    pose = np.eye(4)
    pose[:3, :3] = Rotation.random(random_state=rng).as_matrix()
    pose[:3, 3] = [0.0, 0.5, 0.3]
    truth = outward(novel_class(novel)).transformed(pose)
    parent = outward(known_class(NOVEL[novel][0]))
    mle = MlePrior(parent.name, 1.0, pose, apply_pose(pose, parent.vertices_m), parent.triangles,
                   transform_sdf(parent.sdf(), pose))  # fmt: skip
    points, normals = coverage_contacts(truth, contacts, rng)
    surface = TouchSurface(settings or GpisSettings())
    for point, normal in zip(points, normals, strict=True):
        surface.update((point, normal), mle)
    gpis = surface.reconstruction()
    poisson = poisson_reconstruction(points, normals, poisson_depth)
    reference = (truth.vertices_m, truth.triangles)
    return ReconstructionComparison(
        novel, contacts,
        reconstruction_error_m((mle.vertices_m, mle.triangles), reference),
        reconstruction_error_m((gpis.vertices_m, gpis.triangles), reference),
        reconstruction_error_m((poisson.vertices_m, poisson.triangles), reference),
    )  # fmt: skip
