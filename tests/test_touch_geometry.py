"""Touch geometry with known answers: mesh loading and validation, signed distance of a sphere
and a box against the analytic values, the shape library, the probe, PPF, pair alignment,
Hausdorff distances."""

from __future__ import annotations

import zlib
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import SKILLS
from scipy.spatial.transform import Rotation
from vistac.errors import ConfigError, DataError
from vistac.plugins.hardware.sim.touch_probe import SimTouchProbe
from vistac.plugins.touch.library import (
    KNOWN,
    NOVEL,
    box,
    known_classes,
    load_class,
    mesh_from_field,
    novel_classes,
    resolve_shape,
    sphere,
)
from vistac.plugins.touch.meshes import GridSDF, Mesh, load_mesh, save_mesh, transform_sdf
from vistac.plugins.touch.metrics import directed_hausdorff, two_way_hausdorff
from vistac.plugins.touch.ppf import (
    PpfTable,
    Quantisation,
    align_pairs,
    point_pair_features,
)


class Ctx:
    """The parts of a run context a touch component uses."""

    def __init__(self, skill_dir: Path, seed: int = 0) -> None:
        self.skill_dir, self.seed = skill_dir, seed

    def rng(self, stream: str) -> np.random.Generator:
        return np.random.default_rng([self.seed, zlib.crc32(stream.encode())])

    def component(self, role: str) -> Any:
        raise KeyError(role)

    def find(self, kind: str) -> Any:
        return None


def unit_sphere_mesh(radius_m: float = 0.1) -> Mesh:
    import open3d as o3d

    legacy = o3d.geometry.TriangleMesh.create_sphere(radius_m, resolution=60)
    return Mesh("sphere", np.asarray(legacy.vertices), np.asarray(legacy.triangles, dtype=np.int64))


def test_sphere_sdf_matches_the_analytic_distance_and_normal() -> None:
    mesh = unit_sphere_mesh(0.1)
    rng = np.random.default_rng(0)
    directions = rng.normal(size=(200, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    radii = rng.uniform(0.02, 0.3, 200)
    distance, normals = mesh.sdf()(directions * radii[:, None])
    # the tessellation is within 0.2 mm of the true sphere at this resolution
    assert np.allclose(distance, radii - 0.1, atol=3e-4)
    assert np.all(np.sum(normals * directions, axis=1) > 0.999)


def test_box_sdf_and_its_grid_match_the_analytic_distance() -> None:
    import open3d as o3d

    legacy = o3d.geometry.TriangleMesh.create_box(0.2, 0.1, 0.1)
    legacy.translate([-0.1, -0.05, -0.05])
    mesh = Mesh("box", np.asarray(legacy.vertices), np.asarray(legacy.triangles, dtype=np.int64))
    points = np.array([[0.15, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.08, 0.0], [0.15, 0.09, 0.0]])
    expected = [0.05, -0.05, 0.03, np.hypot(0.05, 0.04)]
    distance, normals = mesh.sdf()(points)
    assert np.allclose(distance, expected, atol=1e-6)
    assert np.allclose(normals[0], [1.0, 0.0, 0.0], atol=1e-6)
    grid = GridSDF.from_sdf(mesh.sdf(), mesh.vertices_m, cells=60)
    grid_distance, _ = grid(points)
    assert np.allclose(grid_distance, expected, atol=0.004)


def test_grid_sdf_interpolates_a_linear_field_exactly_and_extends_outside() -> None:
    """Trilinear interpolation reproduces a linear distance inside the grid, its corners
    included; outside, the nearest grid value plus the distance to the grid box; ``distance``
    agrees with the full query."""
    axes = np.arange(5) * 0.1
    x, y, z = np.meshgrid(axes, axes, axes, indexing="ij")
    distance = 0.3 * x - 0.2 * y + 0.1 * z
    normals = np.broadcast_to(np.array([0.3, -0.2, 0.1]) / np.sqrt(0.14), (5, 5, 5, 3))
    grid = GridSDF(np.zeros(3), 0.1, distance, normals)
    rng = np.random.default_rng(0)
    inside = rng.uniform(0.0, 0.4, size=(2, 7, 3))
    inside[1, -2:] = [[0.4, 0.4, 0.4], [0.0, 0.4, 0.0]]  # on the last cells
    got, got_normals = grid(inside)
    assert got.shape == (2, 7) and got_normals.shape == (2, 7, 3)
    np.testing.assert_allclose(got, inside @ [0.3, -0.2, 0.1], atol=1e-6)
    np.testing.assert_allclose(got_normals, normals[0, 0, 0] + 0 * inside, atol=1e-6)
    outside = np.array([[0.6, 0.2, 0.2], [-0.3, -0.4, 0.0]])
    expected = np.array([0.3 * 0.4 - 0.04 + 0.02 + 0.2, 0.0 + 0.5])
    np.testing.assert_allclose(grid(outside)[0], expected, atol=1e-6)
    np.testing.assert_allclose(grid.distance(inside), got, atol=1e-12)
    np.testing.assert_allclose(grid.distance(outside), expected, atol=1e-6)


def test_transform_sdf_evaluates_in_the_world_frame() -> None:
    mesh = unit_sphere_mesh(0.1)
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_euler("z", 40, degrees=True).as_matrix()
    pose[:3, 3] = [1.0, 2.0, 3.0]
    distance, normals = transform_sdf(mesh.sdf(), pose)(np.array([[1.25, 2.0, 3.0]]))
    assert distance[0] == pytest.approx(0.15, abs=3e-4)
    assert normals[0] @ [1.0, 0.0, 0.0] > 0.999  # vertex normals of a tessellated sphere


def test_a_mesh_file_round_trips_and_is_normalised_on_request(tmp_path: Path) -> None:
    path = tmp_path / "ball.ply"
    save_mesh(unit_sphere_mesh(0.3), path)
    mesh = load_mesh(path, size_m=0.2)
    assert mesh.name == "ball"
    assert mesh.extent_m.max() == pytest.approx(0.2, abs=1e-9)
    assert np.allclose(mesh.vertices_m.min(axis=0) + mesh.vertices_m.max(axis=0), 0.0)


def test_a_mesh_file_class_keeps_its_size_and_frame(tmp_path: Path) -> None:
    """Classes from files are read as saved (metres, own frame); library classes are 0.2 m."""
    sphere_mesh = unit_sphere_mesh(0.05)
    offset = np.array([0.03, -0.01, 0.02])
    save_mesh(Mesh("ball", sphere_mesh.vertices_m + offset, sphere_mesh.triangles),
              tmp_path / "ball.ply")  # fmt: skip
    name, mesh = load_class(tmp_path / "ball.ply")
    assert name == "ball"
    assert mesh.extent_m[2] == pytest.approx(0.1, abs=1e-6)  # the poles
    centre = (mesh.vertices_m.min(axis=0) + mesh.vertices_m.max(axis=0)) / 2.0
    np.testing.assert_allclose(centre, offset, atol=1e-6)
    assert resolve_shape("ball.ply", tmp_path).extent_m[2] == pytest.approx(0.1, abs=1e-6)
    assert resolve_shape("cone", tmp_path).extent_m.max() == pytest.approx(0.2, abs=1e-9)


def test_a_corrupt_mesh_file_is_named_as_unreadable(tmp_path: Path) -> None:
    path = tmp_path / "garbage.ply"
    path.write_text("this is not a mesh\n", encoding="utf-8")
    with pytest.raises(DataError, match=r"garbage\.ply: could not be read as a mesh \(the file "
                       r"is corrupt, empty or not a \.ply triangle mesh\)"):  # fmt: skip
        load_mesh(path)


def test_an_open_mesh_is_rejected_with_a_fix(tmp_path: Path) -> None:
    sphere_mesh = unit_sphere_mesh()
    path = tmp_path / "holey.obj"
    save_mesh(Mesh("holey", sphere_mesh.vertices_m, sphere_mesh.triangles[10:]), path)
    with pytest.raises(DataError, match=r"holey\.obj.*not watertight.*close the holes"):
        load_mesh(path)


def test_an_empty_mesh_is_rejected(tmp_path: Path) -> None:
    path = tmp_path / "empty.obj"
    path.write_text("# nothing\n", encoding="utf-8")
    with pytest.raises(DataError, match="empty"):
        load_mesh(path)


def test_library_meshes_are_watertight_and_in_the_common_box() -> None:
    from vistac.plugins.touch.meshes import _legacy

    shapes = {**known_classes(), **novel_classes()}
    assert len(KNOWN) == 10 and len(NOVEL) == 10 and len(shapes) == 20
    for name, mesh in shapes.items():
        legacy = _legacy(mesh.vertices_m, mesh.triangles)
        assert legacy.is_edge_manifold(allow_boundary_edges=False), name
        assert mesh.extent_m.max() == pytest.approx(0.2, abs=1e-9), name
        outside, _ = mesh.sdf()(np.array([[0.5, 0.0, 0.0]]))
        assert outside[0] > 0.3, name  # outward orientation
    for novel, (known, _) in NOVEL.items():
        assert known in KNOWN, novel
        assert two_way_hausdorff(shapes[novel].vertices_m, shapes[known].vertices_m) > 0.01


def test_a_field_union_meshes_as_one_closed_surface() -> None:
    from vistac.plugins.touch.library import union

    mesh = mesh_from_field("pair", union(sphere((0, 0, 0), 0.5), box((0.6, 0, 0), (0.3, 0.2, 0.2))))
    distance, _ = mesh.sdf()(np.array([[-0.09, 0.0, 0.0], [0.0, 0.0, 0.0]]))
    assert distance[1] < -0.02  # the sphere's centre is inside
    assert abs(distance[0]) < 0.01  # its far pole is on the surface


def probe_for(tmp_path: Path, **config: Any) -> SimTouchProbe:
    return SimTouchProbe(SimTouchProbe.Config(**config), Ctx(tmp_path))


def test_the_probe_hits_a_sphere_at_the_analytic_point(tmp_path: Path) -> None:
    path = tmp_path / "ball.ply"
    save_mesh(unit_sphere_mesh(0.1), path)  # normalised to a 0.2 m box: radius 0.1 m
    probe = probe_for(
        tmp_path,
        object="ball.ply",
        position_m=(0.1, 0.5, 0.3),
        rotation_xyz_deg=(10, 20, 30),
        point_noise_m=0.0,
        normal_noise_rad=0.0,
    )
    hit = probe.probe(np.array([0.1, 0.5, 0.8]), np.array([0.1, 0.5, 0.1]))
    assert hit is not None
    assert np.allclose(hit[0], [0.1, 0.5, 0.4], atol=3e-4)
    assert np.allclose(hit[1], [0.0, 0.0, 1.0], atol=2e-2)
    assert probe.probe(np.array([0.3, 0.5, 0.8]), np.array([0.3, 0.5, 0.1])) is None  # beside it
    assert probe.probe(np.array([0.1, 0.5, 0.8]), np.array([0.1, 0.5, 0.45])) is None  # short
    truth = probe.ground_truth()
    assert truth["class"] == "ball" and np.allclose(
        np.array(truth["world_from_object"])[:3, 3], [0.1, 0.5, 0.3]
    )


def test_a_probe_path_starting_inside_the_object_is_an_error(tmp_path: Path) -> None:
    probe = probe_for(tmp_path, object="bottle", position_m=(0.0, 0.5, 0.3))
    with pytest.raises(DataError, match="starts inside the object"):
        probe.probe(np.array([0.0, 0.5, 0.3]), np.array([0.0, 0.5, 1.0]))


def test_an_unknown_object_is_named_in_the_error(tmp_path: Path) -> None:
    with pytest.raises(DataError, match="teapot"):
        probe_for(tmp_path, object="teapot")


@pytest.mark.parametrize("obj", ["teapot", "ball.ply", "notes.txt"])
def test_a_skill_with_an_object_that_is_not_there_is_refused(tmp_path: Path, obj: str) -> None:
    """In a skill the object is checked before anything is built (exit 2, the option named)."""
    from vistac.pluginmanager import load_plugins
    from vistac.skill import load_skill

    (tmp_path / "notes.txt").write_text("not a mesh")
    skill = tmp_path / "touch.yaml"
    skill.write_text((SKILLS / "touch_recognise.yaml").read_text())
    registry = load_plugins().registry
    with pytest.raises(ConfigError, match=rf"components\.probe\.with\.object: .*'{obj}' is no "
                       r"library shape \(mug, "):  # fmt: skip
        load_skill(skill, registry, [f"components.probe.with.object={obj}"])
    save_mesh(unit_sphere_mesh(0.1), tmp_path / "ball.ply")
    load_skill(skill, registry, ["components.probe.with.object=ball.ply"])  # the skill's folder
    with pytest.raises(ConfigError, match=r"there is \(did you mean 'chair'\?\)"):
        load_skill(skill, registry, ["components.probe.with.object=chiar"])


def test_random_poses_follow_the_seed(tmp_path: Path) -> None:
    first = probe_for(tmp_path, object="cone").world_from_object
    again = probe_for(tmp_path, object="cone").world_from_object
    other = SimTouchProbe(SimTouchProbe.Config(object="cone"), Ctx(tmp_path, 1)).world_from_object
    assert np.allclose(first, again) and not np.allclose(first, other)
    assert np.allclose(first[:3, :3] @ first[:3, :3].T, np.eye(3))


def test_point_pair_feature_of_a_hand_computed_pair() -> None:
    p1, n1 = np.array([[0.0, 0.0, 0.0]]), np.array([[0.0, 0.0, 1.0]])
    p2, n2 = np.array([[0.1, 0.0, 0.0]]), np.array([[1.0, 0.0, 0.0]])
    feature = point_pair_features(p1, n1, p2, n2)[0]
    assert np.allclose(feature, [0.1, np.pi / 2, 0.0, np.pi / 2])
    p2b, n2b = np.array([[0.0, 0.3, 0.4]]), np.array([[0.0, 0.0, -1.0]])
    feature = point_pair_features(p1, n1, p2b, n2b)[0]
    angle = np.arccos(0.8)  # d = (0, 0.3, 0.4), |d| = 0.5
    assert np.allclose(feature, [0.5, angle, np.pi - angle, np.pi])


def test_the_pose_aligning_two_point_pairs_recovers_a_rigid_transform() -> None:
    rng = np.random.default_rng(3)
    count = 20
    m1, m2 = rng.normal(size=(count, 3)) * 0.1, rng.normal(size=(count, 3)) * 0.1
    n1 = rng.normal(size=(count, 3))
    n1 /= np.linalg.norm(n1, axis=1, keepdims=True)
    n1[0] = [-1.0, 0.0, 0.0]  # the degenerate direction of the frame construction
    rotation = Rotation.random(count, random_state=4).as_matrix()
    translation = rng.normal(size=(count, 3))
    s1 = np.einsum("nij,nj->ni", rotation, m1) + translation
    s2 = np.einsum("nij,nj->ni", rotation, m2) + translation
    sn1 = np.einsum("nij,nj->ni", rotation, n1)
    poses = align_pairs(m1, n1, m2, s1, sn1, s2)
    assert np.allclose(poses[:, :3, :3], rotation, atol=1e-9)
    assert np.allclose(poses[:, :3, 3], translation, atol=1e-9)


def test_the_ppf_table_finds_the_pairs_with_equal_features() -> None:
    mesh = known_classes()["chair"]
    points, normals = mesh.surface_samples(60)
    table = PpfTable(points, normals, Quantisation(0.01, np.deg2rad(30)))
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_euler("xyz", [30, -20, 70], degrees=True).as_matrix()
    moved, moved_normals = points @ pose[:3, :3].T + [0.3, 0.1, 0.2], normals @ pose[:3, :3].T
    keys = table.quantisation.keys(
        point_pair_features(moved[[5]], moved_normals[[5]], moved[[17]], moved_normals[[17]])
    )
    first, second, query = table.lookup(keys)
    assert ((first == 5) & (second == 17)).any()  # the same pair, seen rigidly moved
    assert np.all(query == 0) and len(first) < 60 * 59 / 10
    assert table.build_s > 0


def test_hausdorff_distances_of_hand_computed_sets() -> None:
    a = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    b = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [3.0, 0.0, 0.0]])
    assert directed_hausdorff(a, b) == 0.0
    assert directed_hausdorff(b, a) == 2.0
    assert two_way_hausdorff(a, b) == 2.0
    with pytest.raises(DataError):
        directed_hausdorff(a, np.zeros((0, 3)))
