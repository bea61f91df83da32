"""The touch particle filter: likelihoods with known values, resampling, and recognition of a
known object from touches on its surface."""

from __future__ import annotations

import re
from math import erf, sqrt
from pathlib import Path

import numpy as np
import pytest
from test_touch_geometry import Ctx, unit_sphere_mesh
from vistac.errors import ConfigError
from vistac.plugins.touch.explore import DhdExplorer, RrtExplorer
from vistac.plugins.touch.library import known_class
from vistac.plugins.touch.meshes import apply_pose, save_mesh
from vistac.plugins.touch.metrics import two_way_hausdorff
from vistac.plugins.touch.pf import (
    ClassGrids,
    Particles,
    TouchParticleFilter,
    contact_log_likelihood,
    miss_log_likelihood,
    stochastic_universal_sampling,
)
from vistac.plugins.touch.types import MlePrior
from vistac.protocols import TouchEstimator, TouchExplorer
from vistac.testing import build_components


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


def test_the_stacked_class_grids_give_each_class_grid_values() -> None:
    """Points of particles of mixed classes, inside and outside the grid boxes, get the values
    of their own class's GridSDF: distance and unit normals."""
    meshes = [known_class(name) for name in ("mug", "guitar", "cone")]
    grids = ClassGrids([mesh.grid_sdf for mesh in meshes])
    rng = np.random.default_rng(3)
    cls = np.array([2, 0, 1, 1, 0])
    local = rng.uniform(-0.2, 0.2, (len(cls), 7, 3))  # [N, K, 3], some outside the boxes
    distance, normals = grids(cls, local)
    for row, index in enumerate(cls):
        expected_distance, expected_normals = meshes[index].grid_sdf(local[row])
        np.testing.assert_allclose(distance[row], expected_distance, atol=1e-8)
        np.testing.assert_allclose(normals[row], expected_normals, atol=1e-6)
        np.testing.assert_allclose(
            grids.distance(cls, local)[row], meshes[index].grid_sdf.distance(local[row]), atol=1e-8
        )
    # far_m: points surely that far (outside the box) get a lower bound, the others their value
    far_m = 0.06
    exact, bounded = grids.distance(cls, local), grids.distance(cls, local, far_m)
    far = bounded >= far_m
    assert far.any() and (~far).any()
    assert np.all(bounded[far] <= exact[far] + 1e-9)
    np.testing.assert_array_equal(bounded[~far], exact[~far])


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


def test_the_mle_is_the_heaviest_particle_after_resampling(tmp_path: Path) -> None:
    """Resampling gives every particle the same weight; the MLE candidates are still ranked by
    posterior mass (copies), not by their place in the list: 90 wrong chairs first, then a
    bottle at the true pose holding half the mass."""
    config = TouchParticleFilter.Config(
        classes=["chair", "bottle"], mle_candidates=8, resample_count=100,
        roughen_position_m=0.0, roughen_rotation_deg=0.0,
    )  # fmt: skip
    pf = TouchParticleFilter(config, Ctx(tmp_path))
    pose = a_pose(0)
    for start, target, contact in surface_touches("bottle", pose, 6, 0):
        pf.update(start, target, contact)
    rotation = np.r_[np.tile(np.eye(3), (90, 1, 1)), np.tile(pose[:3, :3], (10, 1, 1))]
    translation = np.r_[np.tile([0.0, 0.5, 0.3], (90, 1)), np.tile(pose[:3, 3], (10, 1))]
    log_weight = np.r_[np.zeros(90), np.full(10, np.log(9.0))]
    pf.particles = Particles(
        np.r_[np.zeros(90, int), np.ones(10, int)], rotation, translation, log_weight,
        np.zeros(100), np.full(100, np.nan),
    )  # fmt: skip
    outside = np.array([2.0, 2.0, 2.0])  # a miss outside the workspace: no new evidence
    estimate = pf.update(outside, outside - [0.0, 0.0, 0.1], None)
    assert estimate["mle_class"] == "bottle"
    np.testing.assert_allclose(pf.mle_pose(), pose, atol=1e-9)


def test_proposals_on_the_paired_contacts_match_a_full_evaluation(tmp_path: Path) -> None:
    """The contact a proposal was aligned on lies on a model point: its precomputed log
    likelihood there stands in for the grid lookup without changing the result."""
    config = TouchParticleFilter.Config(classes=["chair", "mug", "bottle"])
    pf = TouchParticleFilter(config, Ctx(tmp_path))
    for start, target, contact in surface_touches("chair", a_pose(1), 6, 1):
        pf.update(start, target, contact)
    proposals = pf._proposals()
    assert proposals is not None
    new, counts, subset_ll = proposals
    assert len(new) == counts.sum() > 0
    subset = np.r_[pf._pair_partners(), len(pf.contacts) - 1]
    exact = pf.log_likelihoods(new, pf.contacts[subset], pf.normals[subset]).sum(axis=1)
    np.testing.assert_allclose(subset_ll, exact, rtol=0, atol=1e-9)


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


def test_the_dhd_explorer_stops_when_every_surface_point_is_next_to_a_miss(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    explorer = DhdExplorer(DhdExplorer.Config(), Ctx(tmp_path))
    surface = np.array([[0.0, 0.5, 0.3], [0.005, 0.5, 0.3]])
    estimate = {"contacts": [[0.1, 0.5, 0.3]], "mle_surface_m": surface,
                "mle_surface_normals": np.tile([1.0, 0.0, 0.0], (2, 1))}  # fmt: skip
    explorer._missed = [np.array([0.0, 0.5, 0.3])]  # an unreachable target next to both
    with caplog.at_level("INFO", logger="vistac.plugins.touch.explore"):
        assert explorer.next_touch(estimate, np.random.default_rng(0)) is None
    assert explorer.last_dhd_m == 0.0
    assert "nothing left to touch" in caplog.text


def _sphere_file(path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    save_mesh(unit_sphere_mesh(0.05), path)


@pytest.mark.parametrize(
    ("specs", "message"),
    [(["mug", "run2/learned/cone_learned.ply", "run1/learned/cone_learned.ply"],
      "'run2/learned/cone_learned.ply' and 'run1/learned/cone_learned.ply' are both named "
      "'cone_learned'"),
     (["x/mug.ply", "mug"], "'x/mug.ply' and 'mug' are both named 'mug'")],
    ids=["two-files", "file-and-library"],
)  # fmt: skip
def test_two_classes_with_one_name_are_a_config_error(
    tmp_path: Path, specs: list[str], message: str
) -> None:
    """Class probabilities are keyed by name: two classes named alike would share one entry.
    Refused when the skill is read, before anything is built."""
    for spec in specs:
        if spec.endswith(".ply"):
            _sphere_file(tmp_path / spec)
    estimator = {"estimator": {"plugin": "touch.pf", "with": {"classes": specs}}}
    with pytest.raises(ConfigError, match=re.escape(message) + ".*rename a mesh file"):
        build_components(estimator, tmp_path, skill_dir=tmp_path)


def test_a_class_that_names_no_shape_is_a_config_error(tmp_path: Path) -> None:
    """Refused when the skill is read, before the other classes are built, with the nearest
    library name."""
    estimator = {"estimator": {"plugin": "touch.pf", "with": {"classes": ["cone", "mugg"]}}}
    with pytest.raises(ConfigError, match=r"'mugg' is no library shape.*did you mean 'mug'"):
        build_components(estimator, tmp_path, skill_dir=tmp_path)


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
    from vistac.testing import check_component, check_component_class

    ctx = build_components({role: spec}, tmp_path)
    component = ctx.component(role)
    check_component_class(type(component))
    check_component(component)
