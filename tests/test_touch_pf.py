"""The touch particle filter: likelihoods with known values, resampling, and recognition of a
known object from touches on its surface."""

from __future__ import annotations

from math import erf, sqrt
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from test_touch_geometry import Ctx
from vistac.plugins.touch.explore import DhdExplorer, RrtExplorer
from vistac.plugins.touch.library import known_class
from vistac.plugins.touch.meshes import GridStack, apply_pose
from vistac.plugins.touch.metrics import two_way_hausdorff
from vistac.plugins.touch.pf import (
    Particles,
    TouchParticleFilter,
    contact_log_likelihood,
    miss_log_likelihood,
    stochastic_universal_sampling,
)
from vistac.plugins.touch.ppf import rotation_to_x
from vistac.plugins.touch.types import MlePrior
from vistac.protocols import TouchEstimator, TouchExplorer


def test_negative_information_is_the_gaussian_cdf_of_the_signed_distance() -> None:
    sigma = 0.01
    distance = np.array([-0.02, -0.01, 0.0, 0.005, 0.03])
    expected = [0.5 * (1.0 + erf(d / (sqrt(2.0) * sigma))) for d in distance]
    assert np.allclose(np.exp(miss_log_likelihood(distance, sigma)), expected, rtol=1e-12)
    assert np.exp(miss_log_likelihood(np.array([0.0]), sigma))[0] == pytest.approx(0.5)
    assert np.isfinite(miss_log_likelihood(np.array([-1.0]), sigma)).all()  # deep inside


def test_contact_likelihood_is_relative_to_an_exact_contact() -> None:
    value = contact_log_likelihood(np.array([0.0, 0.01]), np.array([0.0, 0.5]), 0.01, 0.5)
    assert np.allclose(value, [0.0, -1.0])


def test_stochastic_universal_sampling_keeps_heavy_particles() -> None:
    weights = np.array([0.5, 0.25, 0.125, 0.125])
    index = stochastic_universal_sampling(weights, 8, np.random.default_rng(0))
    assert np.bincount(index, minlength=4).tolist() == [4, 2, 1, 1]
    index = stochastic_universal_sampling(np.array([0.0, 1.0, 0.0]), 5, np.random.default_rng(1))
    assert index.tolist() == [1] * 5


WORKSPACE_CENTRE_M = np.array([0.0, 0.5, 0.3])


def random_particles(count: int, classes: int, seed: int) -> Particles:
    """``count`` particles of random classes and poses around the workspace centre."""
    rng = np.random.default_rng(seed)
    rotation = Rotation.random(count, random_state=seed).as_matrix()
    translation = rng.uniform(-0.05, 0.05, (count, 3)) + WORKSPACE_CENTRE_M
    return Particles(rng.integers(0, classes, count), rotation, translation, np.zeros(count))


def test_the_grid_stack_matches_each_class_grid_in_its_object_frame() -> None:
    """All classes and poses in one float32 pass = each class's GridSDF at the points moved
    into that particle's object frame (inside and outside the grids)."""
    meshes = [known_class(name) for name in ("mug", "chair", "hammer")]
    stack = GridStack([mesh.grid_sdf for mesh in meshes])
    particles = random_particles(12, len(meshes), seed=3)
    points = np.random.default_rng(4).uniform(-0.18, 0.18, (40, 3)) + WORKSPACE_CENTRE_M
    pose = (particles.cls, particles.rotation, particles.translation)
    distance, normals = stack.distance_and_normals(*pose, points)
    assert distance.shape == (12, 40) and normals.shape == (12, 40, 3)
    assert np.array_equal(stack.distance(*pose, points), distance)
    assert distance.max() > 0.1  # some points lie outside their grid's box
    for n in range(len(particles)):
        local = (points - particles.translation[n]) @ particles.rotation[n]
        expected, expected_normals = meshes[particles.cls[n]].grid_sdf(local)
        assert np.allclose(distance[n], expected, atol=1e-6)
        assert np.allclose(normals[n], expected_normals, atol=1e-4)


def test_the_grid_distance_near_the_surface_is_far_below_the_likelihood_noise() -> None:
    """The grid's approximation of the exact mesh distance within 1 cm of the surface: a
    fraction of sigma_distance_m (6 mm), so the likelihoods barely change."""
    mesh = known_class("chair")
    points, normals = mesh.surface_samples(500, seed=5)
    offset_m = np.random.default_rng(0).uniform(-0.01, 0.01, len(points))
    query = points + offset_m[:, None] * normals
    exact, _ = mesh.sdf()(query)
    approximate, _ = mesh.grid_sdf(query)
    error_m = np.abs(approximate - exact)
    sigma_m = TouchParticleFilter.Config().sigma_distance_m
    assert np.median(error_m) < 0.05 * sigma_m and error_m.max() < 0.6 * sigma_m


def test_batched_likelihoods_match_the_per_particle_equations(tmp_path: Path) -> None:
    pf = TouchParticleFilter(TouchParticleFilter.Config(classes=["mug", "cone"]), Ctx(tmp_path))
    particles = random_particles(9, 2, seed=6)
    rng = np.random.default_rng(7)
    points = rng.uniform(-0.1, 0.1, (5, 3)) + WORKSPACE_CENTRE_M
    normals = rng.normal(size=(5, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    contact = pf.log_likelihoods(particles, points, normals)
    miss = pf.log_likelihoods(particles, points, None)
    sigma_m, sigma_normal = pf.config.sigma_distance_m, pf.config.sigma_normal
    for n in range(len(particles)):
        rotation = particles.rotation[n]
        local = (points - particles.translation[n]) @ rotation
        distance, predicted = pf.classes[particles.cls[n]].grid(local)
        error = np.linalg.norm(normals @ rotation - predicted, axis=1)
        expected = contact_log_likelihood(distance, error, sigma_m, sigma_normal)
        assert np.allclose(contact[n], expected, rtol=1e-5, atol=1e-4)
        assert np.allclose(miss[n], miss_log_likelihood(distance, sigma_m), rtol=1e-5, atol=1e-6)
    assert pf.log_likelihoods(particles, points[:0], None).shape == (9, 0)


def test_proposal_weights_follow_eq_27_per_class(tmp_path: Path) -> None:
    """Each class's best proposal on the contact subset is weighed on all data; the others of
    its class differ from it by their subset log likelihood."""
    pf = TouchParticleFilter(TouchParticleFilter.Config(classes=["mug", "cone"]), Ctx(tmp_path))
    for start, target, contact in surface_touches("mug", a_pose(0), 4, 0):
        pf.update(start, target, contact)
    new = random_particles(10, 2, seed=8)
    order = np.argsort(new.cls, kind="stable")
    new = new.take(order)
    subset_ll = np.random.default_rng(9).normal(size=10)
    weights = pf._approximate_log_weights(new, subset_ll)
    for index in range(2):
        rows = np.flatnonzero(new.cls == index)
        best = rows[np.argmax(subset_ll[rows])]
        contact_ll, miss_ll = pf._all_data(new.take([best]))
        total = contact_ll.sum() + miss_ll.sum()
        assert weights[best] == pytest.approx(pf._reference_log_weight() + total)
        assert np.allclose(weights[rows] - weights[best], subset_ll[rows] - subset_ll[best])


def test_the_rotation_to_x_turns_each_normal_onto_x() -> None:
    normals = np.random.default_rng(10).normal(size=(50, 3))
    normals[:4] = [[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0], [-1.0, 1e-10, 0.0], [0.0, 0.0, 1.0]]
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    rotation = rotation_to_x(normals)
    assert np.allclose(np.einsum("nij,nj->ni", rotation, normals), [1.0, 0.0, 0.0], atol=1e-9)
    assert np.allclose(rotation @ rotation.transpose(0, 2, 1), np.eye(3), atol=1e-9)
    assert np.allclose(np.linalg.det(rotation), 1.0)


def surface_touches(name: str, pose: np.ndarray, count: int, seed: int) -> list[tuple]:
    """``count`` touches straight onto surface samples of ``name`` at ``pose``."""
    mesh = known_class(name)
    points, normals = mesh.surface_samples(count, seed=seed + 7)
    points, normals = apply_pose(pose, points), normals @ pose[:3, :3].T
    return [(p + 0.3 * n, p - 0.02 * n, (p, n)) for p, n in zip(points, normals, strict=True)]


def a_pose(seed: int) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    pose = np.eye(4)
    pose[:3, :3] = Rotation.random(random_state=seed).as_matrix()
    pose[:3, 3] = [0.02, 0.48, 0.31]
    return pose


@pytest.mark.parametrize(("name", "seed"), [("chair", 0), ("bottle", 1), ("sofa", 2)])
def test_the_filter_recognises_a_known_object_and_its_pose(
    tmp_path: Path, name: str, seed: int
) -> None:
    pf = TouchParticleFilter(TouchParticleFilter.Config(), Ctx(tmp_path, seed))
    assert isinstance(pf, TouchEstimator)
    pose = a_pose(seed)
    estimate: dict = {}
    for start, target, contact in surface_touches(name, pose, 25, seed):
        estimate = pf.update(start, target, contact)
    assert estimate["mle_class"] == name
    assert estimate["class_probabilities"][name] > 0.9
    assert 0 < estimate["max_particle_count"] <= 7000
    assert estimate["known"] is True
    truth = apply_pose(pose, known_class(name).vertices_m)
    prior = pf.mle_prior()
    assert isinstance(prior, MlePrior) and prior.class_name == name
    assert two_way_hausdorff(truth, prior.vertices_m) < 0.02  # 10% of the object size
    distance, _ = prior.sdf(truth[::50])
    assert np.abs(distance).max() < 0.02


def test_misses_are_negative_information(tmp_path: Path) -> None:
    pf = TouchParticleFilter(TouchParticleFilter.Config(classes=["cone"]), Ctx(tmp_path))
    assert pf.mle_prior() is None
    estimate = pf.update(np.array([0.0, 0.5, 0.9]), np.array([0.0, 0.5, 0.31]), None)
    assert estimate["misses"] == 1 and estimate["mle_class"] is None
    assert estimate["class_probabilities"] == {"cone": 1.0}
    # points on the probe path inside the workspace are free space
    free = pf.free_path(np.array([0.0, 0.5, 0.9]), np.array([0.0, 0.5, 0.31]))
    assert len(free) > 0 and np.all(free[:, 2] <= 0.5 + 1e-9)


def test_explorers_conform_and_stop_when_the_surface_is_covered(tmp_path: Path) -> None:
    for cls in (DhdExplorer, RrtExplorer):
        explorer = cls(cls.Config(dhd_threshold_m=0.05, min_contacts=2), Ctx(tmp_path))
        assert isinstance(explorer, TouchExplorer)
        rng = np.random.default_rng(0)
        start, _ = explorer.next_touch({}, rng)
        centre = np.array([0.0, 0.5, 0.3])
        assert np.linalg.norm(start - centre) > np.sqrt(3) * 0.2  # outside the workspace
        surface = np.array([[0.0, 0.5, 0.3], [0.1, 0.5, 0.3]])
        estimate = {
            "contacts": surface.tolist(),
            "normals": [[0, 0, 1.0]] * 2,
            "mle_surface_m": surface,
            "mle_surface_normals": np.array([[0, 0, 1.0]] * 2),
        }
        assert explorer.next_touch(estimate, rng) is None
        assert explorer.last_dhd_m == 0.0


def test_the_dhd_target_is_the_surface_point_farthest_from_the_contacts(tmp_path: Path) -> None:
    explorer = DhdExplorer(DhdExplorer.Config(min_contacts=1), Ctx(tmp_path))
    surface = np.array([[0.0, 0.5, 0.3], [0.05, 0.5, 0.3], [0.0, 0.62, 0.3]])
    normals = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [0.0, 1.0, 0.0]])
    estimate = {
        "contacts": [[0.0, 0.5, 0.3]],
        "mle_surface_m": surface,
        "mle_surface_normals": normals,
    }
    start, target = explorer.next_touch(estimate, np.random.default_rng(0))
    assert explorer.last_dhd_m == pytest.approx(0.12)  # eq. 44: max of the nearest distances
    # approached along the normal of (0, 0.62, 0.3), ending past it
    assert np.allclose(start[[0, 2]], [0.0, 0.3]) and start[1] > 0.62
    assert np.allclose(target, [0.0, 0.62 - 0.03, 0.3])
    variance = {**estimate, "surface_variance": lambda p: -np.abs(p[:, 0] - 0.05)}
    fresh = DhdExplorer(DhdExplorer.Config(min_contacts=1), Ctx(tmp_path))
    _, target = fresh.next_touch(variance, np.random.default_rng(0))
    assert np.allclose(target, [0.05, 0.5, 0.3 - 0.03])  # the most uncertain point instead


@pytest.mark.parametrize(
    ("role", "spec"),
    [
        ("probe", {"plugin": "sim.touch_probe", "with": {"object": "cone"}}),
        ("estimator", {"plugin": "touch.pf", "with": {"classes": ["cone", "mug"]}}),
        ("explorer", {"plugin": "touch.dhd"}),
        ("rrt", {"plugin": "touch.rrt"}),
    ],
)
def test_touch_components_conform(tmp_path: Path, role: str, spec: dict) -> None:
    from vistac.testing import build_components, check_component, check_component_class

    ctx = build_components({role: spec}, tmp_path)
    component = ctx.component(role)
    check_component_class(type(component))
    check_component(component)
