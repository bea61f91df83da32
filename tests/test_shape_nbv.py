"""View planners ``shape.entropy_nbv`` and ``shape.random_views`` against known answers."""

from __future__ import annotations

import zlib
from collections.abc import Callable

import numpy as np
import pytest
from pydantic import ValidationError
from vistac.errors import DataError
from vistac.plugins.shape.ems import PARAMETER_NAMES
from vistac.plugins.shape.nbv import (
    EntropyNBV,
    EntropySettings,
    RandomViews,
    gaussian_entropy,
    look_at,
    normal_displacements,
    parameter_displacements,
    surface_entropy,
    surface_normals,
    visible_points,
)
from vistac.plugins.shape.superquadric import sample_surface, to_superquadric_frame
from vistac.plugins.shape.views import UniformViews
from vistac.testing import check_component, check_component_class
from vistac.types import CameraIntrinsics, PointCloud, ShapeEstimate, Superquadric, Viewpoint

CENTRE_XY_M = (0.0, 0.45)
BOX_SCALE_M = (0.045, 0.045, 0.025)
SMALL_STD = 1e-4
SETTINGS = EntropySettings(seen_distance_m=0.005, unseen_spread_m=0.02, sensor_noise_m=0.002)


class _Context:
    """skill_dir, seed and ``rng(stream)``: all the planners use."""

    skill_dir = None

    def __init__(self, seed: int = 0) -> None:
        self.seed = seed

    def rng(self, stream: str) -> np.random.Generator:
        return np.random.default_rng([self.seed, zlib.crc32(stream.encode())])


def make_nbv(seed: int = 0, **options: object) -> EntropyNBV:
    return EntropyNBV(EntropyNBV.Config.model_validate(options), _Context(seed))


def make_random(seed: int = 0, **options: object) -> RandomViews:
    return RandomViews(RandomViews.Config.model_validate(options), _Context(seed))


def box(xy_m: tuple[float, float] = CENTRE_XY_M, yaw_rad: float = 0.0,
        exponents: tuple[float, float] = (0.1, 0.1)) -> Superquadric:
    """A box-like superquadric standing on the table at ``xy_m``."""
    pose = np.eye(4)
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    pose[:2, :2] = [[c, -s], [s, c]]
    pose[:3, 3] = [xy_m[0], xy_m[1], BOX_SCALE_M[2]]
    return Superquadric(np.array(BOX_SCALE_M), np.array(exponents), pose, np.zeros(2))


def estimate(links: tuple[Superquadric, ...], cloud: PointCloud, std: float = SMALL_STD
             ) -> ShapeEstimate:
    poses = np.array([[sq.world_from_sq[0, 3], sq.world_from_sq[1, 3], 0.0] for sq in links])
    return ShapeEstimate(links, poses, np.full((len(links), len(PARAMETER_NAMES)), std), cloud)


Mask = Callable[[np.ndarray], np.ndarray]


def observed(sq: Superquadric, keep: Mask | None = None, count: int = 6000) -> PointCloud:
    """Dense surface points of ``sq`` above the table, optionally only where ``keep`` says."""
    points = sample_surface(sq, count, np.random.default_rng(7))
    mask = points[:, 2] > 0.002
    if keep is not None:
        mask &= keep(points)
    return PointCloud(points[mask])


def horizontal_direction(view: Viewpoint) -> np.ndarray:
    offset = (view.eye_m - view.target_m)[:2]
    return offset / np.linalg.norm(offset)


# --- entropy NBV: known answers -----------------------------------------------------------


@pytest.mark.parametrize(
    ("seen", "unseen_direction"),
    [
        (lambda p: p[:, 1] < CENTRE_XY_M[1], np.array([0.0, 1.0])),
        (lambda p: p[:, 0] > CENTRE_XY_M[0], np.array([-1.0, 0.0])),
        (lambda p: p[:, 0] < CENTRE_XY_M[0], np.array([1.0, 0.0])),
    ],
    ids=["-y seen", "+x seen", "-x seen"],
)
def test_half_seen_object_is_viewed_from_its_unseen_side(
    seen: Mask, unseen_direction: np.ndarray
) -> None:
    sq = box()
    cloud = observed(sq, seen)
    view = make_nbv().next_view(cloud, estimate((sq,), cloud), 1)
    assert view is not None
    assert horizontal_direction(view) @ unseen_direction > 0.5
    np.testing.assert_allclose(view.target_m, [*CENTRE_XY_M, BOX_SCALE_M[2]], atol=0.005)
    assert np.linalg.norm(view.eye_m - view.target_m) == pytest.approx(0.5)


def test_unseen_side_wins_over_a_rotated_second_link() -> None:
    """Two links (the second turned by 30 deg) seen only from -y: look from +y."""
    links = (box((-0.06, 0.45)), box((0.06, 0.45), yaw_rad=np.radians(30)))
    points = np.concatenate([observed(sq, lambda p: p[:, 1] < 0.45).points_m for sq in links])
    cloud = PointCloud(points)
    view = make_nbv().next_view(cloud, estimate(links, cloud), 1)
    assert view is not None
    assert horizontal_direction(view)[1] > 0.5


def test_fully_observed_certain_object_stops() -> None:
    sq = box()
    cloud = observed(sq)
    assert make_nbv().next_view(cloud, estimate((sq,), cloud), 1) is None


def test_large_parameter_uncertainty_keeps_looking() -> None:
    """Fully observed, but the fit is uncertain: the shape term alone keeps the planner going."""
    sq = box()
    cloud = observed(sq)
    assert make_nbv().next_view(cloud, estimate((sq,), cloud, std=0.01), 1) is not None


def test_views_from_simulated_observations_converge() -> None:
    """Observing what each chosen view sees (points of the true surface) ends the planning
    within a few views, and every view after the first looks at something new."""
    sq = box()
    truth = sample_surface(sq, 8000, np.random.default_rng(3))
    normals = surface_normals(sq, to_superquadric_frame(sq, truth))
    planner = make_nbv(max_views=8)
    intrinsics = planner.intrinsics
    seen = np.zeros(len(truth), dtype=bool)
    views = 0
    cloud = None
    while (view := planner.next_view(cloud, estimate((sq,), cloud) if cloud else None, views)):
        pose = look_at(view.eye_m[None], view.target_m)
        new = visible_points(truth, normals, pose, intrinsics, 4, 0.01)[0] > 0
        assert views == 0 or np.any(new & ~seen), "a view must add unseen surface"
        seen |= new
        cloud = PointCloud(truth[seen])
        views += 1
    assert 2 <= views <= 5


def test_foreign_uncertainty_layout_falls_back_to_the_unseen_term(
    caplog: pytest.LogCaptureFixture,
) -> None:
    sq = box()
    cloud = observed(sq, lambda p: p[:, 1] < CENTRE_XY_M[1])
    shape = ShapeEstimate((sq,), np.zeros((1, 3)), np.full((1, 4), 5.0), cloud)
    view = make_nbv().next_view(cloud, shape, 1)
    assert view is not None and horizontal_direction(view)[1] > 0.5
    assert "unseen term only" in caplog.text
    bad = estimate((sq,), cloud, std=np.nan)
    with pytest.raises(DataError, match="uncertainty"):
        make_nbv().next_view(cloud, bad, 1)


def test_first_view_is_the_uniform_first_view() -> None:
    nbv = make_nbv(max_views=4)
    uniform = UniformViews(UniformViews.Config(views=4), _Context())
    for views_taken in range(4):
        mine, theirs = nbv.next_view(None, None, views_taken), uniform.next_view(None, None,
                                                                                views_taken)
        assert mine is not None and theirs is not None
        np.testing.assert_allclose(mine.eye_m, theirs.eye_m)
        np.testing.assert_allclose(mine.target_m, theirs.target_m)


def test_max_views_is_honoured() -> None:
    sq = box()
    cloud = observed(sq, lambda p: p[:, 1] < CENTRE_XY_M[1])
    shape = estimate((sq,), cloud)
    assert make_nbv(max_views=3).next_view(cloud, shape, 2) is not None
    assert make_nbv(max_views=3).next_view(cloud, shape, 3) is None
    assert make_nbv(max_views=3).next_view(None, None, 3) is None


def test_a_returned_view_is_not_returned_again() -> None:
    sq = box()
    cloud = observed(sq, lambda p: p[:, 1] < CENTRE_XY_M[1])
    planner = make_nbv(min_view_separation_deg=20.0)
    first = planner.next_view(cloud, estimate((sq,), cloud), 1)
    second = planner.next_view(cloud, estimate((sq,), cloud), 2)
    assert first is not None and second is not None
    cosine = (first.eye_m - first.target_m) @ (second.eye_m - second.target_m) / 0.25
    assert cosine < np.cos(np.radians(20.0))


# --- entropy NBV: the pieces --------------------------------------------------------------


def test_pose_and_scale_std_propagate_exactly() -> None:
    """On a tilted, tapered ellipsoid: x moves every point by its std, yaw rotates it about
    world z by the std, a1 moves the point on the local x axis along that axis."""
    pose = np.eye(4)
    pose[:3, :3] = look_at(np.array([[0.3, -0.2, 0.4]]), np.zeros(3))[0, :3, :3]
    pose[:3, 3] = [0.05, 0.4, 0.06]
    sq = Superquadric(np.array(BOX_SCALE_M), np.ones(2), pose, np.array([0.0, 0.3]))
    local = np.array([[0.045, 0.0, 0.0], [0.0, 0.0, 0.025]])  # on the surface, f(0) = 1
    x, yaw, a1 = (PARAMETER_NAMES.index(name) for name in ("x_m", "yaw_rad", "a1_m"))
    std = np.zeros(len(PARAMETER_NAMES))
    std[x], std[yaw], std[a1] = 0.004, 0.1, 0.003
    displacement = parameter_displacements(sq, local, std)
    np.testing.assert_allclose(displacement[x], [[0.004, 0, 0]] * 2, atol=1e-12)
    offset = local @ pose[:3, :3].T
    expected_yaw = np.sin(0.1) * np.cross([0.0, 0.0, 1.0], offset)
    np.testing.assert_allclose(displacement[yaw], expected_yaw, atol=1e-12)
    expected_a1 = np.stack([0.003 * pose[:3, 0], np.zeros(3)])
    np.testing.assert_allclose(displacement[a1], expected_a1, atol=1e-12)
    others = np.delete(displacement, [x, yaw, a1], axis=0)
    np.testing.assert_allclose(others, 0.0, atol=1e-12)
    entropy = gaussian_entropy(displacement[[x]], np.zeros(2), SETTINGS)
    np.testing.assert_allclose(entropy, 0.5 * np.log(1 + (0.004 / 0.002) ** 2))


def test_a_circle_turning_about_its_axis_is_certain() -> None:
    """Yaw moves the points of a circular cylinder along its surface only: no entropy."""
    cylinder = Superquadric(np.array([0.04, 0.04, 0.025]), np.array([0.1, 1.0]),
                            box().world_from_sq, np.zeros(2))
    points = sample_surface(cylinder, 500, np.random.default_rng(2))
    local = to_superquadric_frame(cylinder, points)
    std = np.zeros(len(PARAMETER_NAMES))
    std[PARAMETER_NAMES.index("yaw_rad")] = 0.3
    moved = parameter_displacements(cylinder, local, std)
    assert np.abs(moved).max() > 0.005  # the points do slide
    along = normal_displacements(moved, surface_normals(cylinder, local))
    np.testing.assert_allclose(along, 0.0, atol=1e-6)


def test_correlated_parameters_count_once() -> None:
    """x and y perfectly anti-correlated with equal std (the box slides along x = -y): the
    positional spread of each point is that of the joint move, not of two separate ones."""
    sq = box()
    cloud = observed(sq)
    std = np.zeros((1, len(PARAMETER_NAMES)))
    x, y = PARAMETER_NAMES.index("x_m"), PARAMETER_NAMES.index("y_m")
    std[0, [x, y]] = 0.003
    cov = np.zeros((1, len(PARAMETER_NAMES), len(PARAMETER_NAMES)))
    cov[0, [x, y, x, y], [x, y, y, x]] = [9e-6, 9e-6, -9e-6, -9e-6]
    poses = np.array([[CENTRE_XY_M[0], CENTRE_XY_M[1], 0.0]])
    settings = EntropySettings(0.005, 0.02, 0.002)

    def entropy(covariance: np.ndarray | None) -> np.ndarray:
        shape = ShapeEstimate((sq,), poses, std, cloud, covariance)
        points, normals, value = surface_entropy(shape, cloud.points_m, 400,
                                                 np.random.default_rng(1), settings)
        return np.asarray(points), np.asarray(normals), np.asarray(value)

    points, normals, correlated = entropy(cov)
    _, _, independent = entropy(None)
    joint = 0.003 * (normals[:, 0] - normals[:, 1])  # the normal part of the move (d, -d)
    expected = 0.5 * np.log1p(joint**2 / 0.002**2)
    seen = (np.abs(normals[:, 2]) < 0.5) & (points[:, 2] > 0.01)  # the walls the cloud shows
    np.testing.assert_allclose(correlated[seen], expected[seen], atol=1e-9)
    assert independent[seen].mean() > correlated[seen].mean()


def test_points_below_the_table_clearance_count_as_seen() -> None:
    """The cloud never has points below the clearance; a wall point down there is seen when
    the wall above it is."""
    sq = box()
    cloud = observed(sq, keep=lambda p: p[:, 2] > 0.008)
    shape = estimate((sq,), cloud, std=0.0)
    low = EntropySettings(0.005, 0.02, 0.002, table_clearance_m=0.0)
    raised = EntropySettings(0.005, 0.02, 0.002, table_clearance_m=0.008)
    rng = np.random.default_rng(3)
    points, normals, without = surface_entropy(shape, cloud.points_m, 2000, rng, low)
    _, _, with_clearance = surface_entropy(shape, cloud.points_m, 2000,
                                           np.random.default_rng(3), raised)
    wall_bottom = (points[:, 2] < 0.002) & (np.abs(normals[:, 2]) < 0.5)
    assert wall_bottom.any() and without[wall_bottom].min() > 0.2
    np.testing.assert_allclose(with_clearance[wall_bottom], 0.0, atol=1e-9)


def test_unseen_points_get_the_capped_entropy() -> None:
    entropy = gaussian_entropy(np.zeros((13, 3, 3)), np.array([0.0, 0.02, 0.01]), SETTINGS)
    expected = 1.5 * np.log(1 + (np.array([0.0, 0.02, 0.01]) / 0.002) ** 2)
    np.testing.assert_allclose(entropy, expected)


def test_sphere_normals_are_radial() -> None:
    pose = np.eye(4)
    pose[:3, :3] = look_at(np.array([[1.0, 2.0, 0.5]]), np.zeros(3))[0, :3, :3]
    pose[:3, 3] = [0.1, 0.4, 0.05]
    sphere = Superquadric(np.full(3, 0.05), np.ones(2), pose, np.zeros(2))
    points = sample_surface(sphere, 200, np.random.default_rng(0))
    normals = surface_normals(sphere, to_superquadric_frame(sphere, points))
    radial = points - pose[:3, 3]
    np.testing.assert_allclose(normals, radial / np.linalg.norm(radial, axis=1, keepdims=True),
                               atol=1e-6)


def test_look_at_centres_the_target() -> None:
    target = np.array([0.1, 0.4, 0.03])
    eyes = target + 0.5 * np.array([[1.0, 0.0, 0.2], [-0.3, -1.0, 1.0], [0.2, 0.1, -0.1]])
    poses = look_at(eyes, target)
    rotation = poses[:, :3, :3]
    np.testing.assert_allclose(rotation @ np.swapaxes(rotation, 1, 2), [np.eye(3)] * 3, atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(rotation), 1.0)
    np.testing.assert_allclose(rotation[:, 2, 0], 0.0, atol=1e-12)  # image right is horizontal
    assert np.all(rotation[:, 2, 1] < 0)  # image down points down in the world
    in_camera = np.einsum("pij,pi->pj", rotation, target - eyes)
    np.testing.assert_allclose(in_camera[:, :2], 0.0, atol=1e-12)
    assert np.all(in_camera[:, 2] > 0)


def loop_visible(points: np.ndarray, normals: np.ndarray, poses: np.ndarray,
                 intrinsics: CameraIntrinsics, bin_px: int, tolerance_m: float) -> np.ndarray:
    """A plain per-view, per-point version of ``visible_points``: [P, M]."""
    result = np.zeros((len(poses), len(points)))
    for p, pose in enumerate(poses):
        rotation, eye = pose[:3, :3], pose[:3, 3]
        projected = {}
        for j, point in enumerate(points):
            x, y, z = rotation.T @ (point - eye)
            if z <= 1e-3:
                continue
            u, v = intrinsics.fx * x / z + intrinsics.cx, intrinsics.fy * y / z + intrinsics.cy
            if -0.5 < u < intrinsics.width - 0.5 and -0.5 < v < intrinsics.height - 0.5:
                projected[j] = (int((u + 0.5) // bin_px), int((v + 0.5) // bin_px), z)
        nearest: dict[tuple[int, int], float] = {}
        for column, row, z in projected.values():
            nearest[column, row] = min(nearest.get((column, row), np.inf), z)
        for j, (column, row, z) in projected.items():
            facing = normals[j] @ (points[j] - eye) < 0
            result[p, j] = float(facing and z <= nearest[column, row] + tolerance_m)
    return result


def test_vectorised_visibility_equals_a_loop() -> None:
    rng = np.random.default_rng(5)
    centre = np.array([0.0, 0.45, 0.05])
    points = rng.normal(scale=0.05, size=(300, 3)) + centre
    normals = rng.normal(size=(300, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    eyes = centre + 0.4 * rng.normal(size=(12, 3)) * [1, 1, 0.2] + [0, 0, 0.3]
    poses = look_at(eyes, centre)
    intrinsics = CameraIntrinsics.from_fov(40, 30, np.radians(58.0))
    entropy = rng.random(300)
    fast = visible_points(points, normals, poses, intrinsics, 4, 0.01)
    slow = loop_visible(points, normals, poses, intrinsics, 4, 0.01)
    np.testing.assert_array_equal(fast, slow)
    np.testing.assert_allclose(fast @ entropy, slow @ entropy)
    assert 0 < slow.sum() < 0.5 * slow.size  # some points seen, many hidden or facing away


# --- random views ---------------------------------------------------------------------------


def views_of(planner: RandomViews) -> list[Viewpoint]:
    views: list[Viewpoint] = []
    while (view := planner.next_view(None, None, len(views))) is not None:
        views.append(view)
    return views


def test_random_views_are_reproducible_and_in_range() -> None:
    options = {"views": 6, "min_elevation_deg": 20.0, "max_elevation_deg": 40.0}
    first, again, other = (views_of(make_random(seed, **options)) for seed in (1, 1, 2))
    assert len(first) == 6
    np.testing.assert_array_equal([v.eye_m for v in first], [v.eye_m for v in again])
    assert not np.allclose([v.eye_m for v in first], [v.eye_m for v in other])
    for view in first:
        offset = view.eye_m - view.target_m
        assert np.linalg.norm(offset) == pytest.approx(0.5)
        assert 20.0 <= np.degrees(np.arcsin(offset[2] / 0.5)) <= 40.0
    azimuths = [np.arctan2(*(v.eye_m - v.target_m)[1::-1]) for v in first]
    assert np.ptp(azimuths) > 1.0  # spread around, not one direction


def test_random_views_aim_at_the_cloud() -> None:
    cloud = PointCloud(np.array([[0.2, 0.3, 0.05], [0.2, 0.31, 0.04], [0.0, 0.0, 0.0]]))
    view = make_random().next_view(cloud, None, 0)
    assert view is not None
    np.testing.assert_allclose(view.target_m, [0.2, 0.305, 0.045])


# --- configuration and conformance ----------------------------------------------------------


@pytest.mark.parametrize(
    ("cls", "options"),
    [
        (EntropyNBV, {"radius_m": -0.5}),
        (EntropyNBV, {"candidates": 0}),
        (EntropyNBV, {"min_elevation_deg": 60.0, "max_elevation_deg": 30.0}),
        (EntropyNBV, {"max_elevation_deg": 90.0}),
        (EntropyNBV, {"sensor_noise_m": 0.0}),
        (EntropyNBV, {"entropy_threshold": -1.0}),
        (EntropyNBV, {"unknown_option": 1}),
        (RandomViews, {"radius_m": -0.5}),
        (RandomViews, {"views": 0}),
        (RandomViews, {"min_elevation_deg": 50.0, "max_elevation_deg": 10.0}),
    ],
)
def test_bad_config_is_rejected(
    cls: type[EntropyNBV] | type[RandomViews], options: dict[str, float]
) -> None:
    cls.Config.model_validate({})
    with pytest.raises(ValidationError):
        cls.Config.model_validate(options)


@pytest.mark.parametrize("make", [make_nbv, make_random])
def test_planners_conform(make: Callable[[], EntropyNBV | RandomViews]) -> None:
    planner = make()
    check_component_class(type(planner))
    check_component(planner, advance=lambda dt_s: None)
