"""EMS superquadric fitting (``shape.ems``) against clouds sampled from known superquadrics."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest
from conftest import ROOT
from vistac.errors import DataError
from vistac.objects import FOOTPRINTS, footprint_polygon, prism_surface_points, to_world_xy
from vistac.plugins.shape.ems import (
    PARAMETER_NAMES,
    EMSEstimator,
    EMSOptions,
    EMSResult,
    fit_links,
    to_superquadric,
)
from vistac.plugins.shape.superquadric import (
    chamfer_distance_m,
    distance_to_surface_m,
    inside_outside,
    sample_surface,
    to_superquadric_frame,
)
from vistac.types import PointCloud, ShapeEstimate, Superquadric

NOISE_M = 0.002
OUTLIER_FRACTION = 0.2
SCALE_TOL_M = 0.005
YAW_TOL_RAD = np.radians(5.0)
CHAMFER_TOL_M = 0.003
PRISM_HEIGHT_M = 0.05
PRISM_NOISE_M = 0.001
PRISM_POINTS = 3000
PRISM_CHAMFER_TOL_M = 0.0015
VIEW_DIRECTION = np.array([np.cos(0.4), np.sin(0.4), 1.0]) / np.sqrt(2.0)


class _Context:
    """The little of a component context that ``shape.ems`` uses (nothing)."""

    skill_dir = None
    seed = 0


def make_estimator(**options: object) -> EMSEstimator:
    return EMSEstimator(EMSEstimator.Config.model_validate(options), _Context())  # type: ignore[arg-type]


def upright(scale_m: list[float], exponents: list[float], xy_m: list[float], yaw_rad: float,
            taper: list[float] | None = None) -> Superquadric:
    """A superquadric standing on the table (z = 0) at (x, y) turned by yaw."""
    pose = np.eye(4)
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    pose[:2, :2] = [[c, -s], [s, c]]
    pose[:3, 3] = [xy_m[0], xy_m[1], scale_m[2]]
    return Superquadric(np.array(scale_m), np.array(exponents, dtype=float), pose,
                        np.array(taper or [0.0, 0.0]))


def yaw_of(sq: Superquadric) -> float:
    return float(np.arctan2(sq.world_from_sq[1, 0], sq.world_from_sq[0, 0]))


def visible(sq: Superquadric, points_m: np.ndarray) -> np.ndarray:
    """Mask [N] of surface points whose outward normal faces VIEW_DIRECTION."""
    local = to_superquadric_frame(sq, points_m)
    step = 1e-5
    gradient = np.stack([
        inside_outside(local + step * axis, sq.scale_m, sq.exponents, sq.taper)
        - inside_outside(local - step * axis, sq.scale_m, sq.exponents, sq.taper)
        for axis in np.eye(3)
    ], axis=-1)
    return gradient @ sq.world_from_sq[:3, :3].T @ VIEW_DIRECTION > 0


def noisy_cloud(sq: Superquadric, rng: np.random.Generator, count: int = 2000,
                half: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Noisy surface points with uniform outliers: (points [count, 3], outlier mask [count])."""
    surface = sample_surface(sq, 6 * count, rng)
    keep = surface[:, 2] > 0.01
    if half:
        keep &= visible(sq, surface)
    surface = surface[keep]
    points = surface[rng.choice(len(surface), count, replace=False)]
    points += rng.normal(0.0, NOISE_M, points.shape)
    outlier = np.zeros(count, dtype=bool)
    outlier[: int(OUTLIER_FRACTION * count)] = True
    low, high = points.min(axis=0) - 0.03, points.max(axis=0) + 0.03
    low[2] = 0.01
    points[outlier] = rng.uniform(low, high, (int(outlier.sum()), 3))
    return points, outlier


def random_sq(rng: np.random.Generator, exponents: list[float],
              taper: list[float] | None = None) -> Superquadric:
    """Random upright superquadric with a1 at least 15 mm shorter than a2 (yaw well defined)."""
    a1 = rng.uniform(0.03, 0.045)
    scale = [a1, a1 + rng.uniform(0.015, 0.035), rng.uniform(0.02, 0.03)]
    return upright(scale, exponents, [rng.uniform(-0.1, 0.1), rng.uniform(0.35, 0.5)],
                   rng.uniform(-np.pi, np.pi), taper)


def angle_error(a_rad: float, b_rad: float, period_rad: float) -> float:
    diff = (a_rad - b_rad) % period_rad
    return min(diff, period_rad - diff)


@dataclass(frozen=True)
class Case:
    name: str
    exponents: list[float]
    taper: list[float] | None = None
    half: bool = False


CASES = [
    Case("box", [0.1, 0.1]),
    Case("ellipsoid", [1.0, 1.0]),
    Case("rounded_box", [0.4, 0.3]),
    Case("tapered", [0.2, 0.3], [0.4, 0.2]),
    Case("box_half_view", [0.1, 0.1], half=True),
    Case("ellipsoid_half_view", [1.0, 1.0], half=True),
    Case("tapered_half_view", [0.2, 0.3], [0.4, 0.0], half=True),
]
def _compare_parameters(truth: Superquadric, fitted: Superquadric, tapered: bool) -> None:
    scale, yaw = fitted.scale_m.copy(), yaw_of(fitted)
    if not tapered and scale[0] > scale[1]:  # the same untapered shape, axes renamed
        scale[[0, 1]], yaw = scale[[1, 0]], yaw + np.pi / 2
    np.testing.assert_allclose(scale, truth.scale_m, atol=SCALE_TOL_M)
    period = 2 * np.pi if tapered else np.pi
    assert angle_error(yaw, yaw_of(truth), period) < YAW_TOL_RAD
    np.testing.assert_allclose(fitted.world_from_sq[:2, 3], truth.world_from_sq[:2, 3],
                               atol=SCALE_TOL_M)


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
@pytest.mark.parametrize("case", CASES, ids=lambda case: case.name)
def test_recovers_random_superquadric(case: Case, seed: int) -> None:
    rng = np.random.default_rng([seed, len(case.name)])
    truth = random_sq(rng, case.exponents, case.taper)
    points, _ = noisy_cloud(truth, rng, half=case.half)
    estimate = make_estimator(taper=case.taper is not None).fit(PointCloud(points))
    fitted = estimate.links[0]
    chamfer = chamfer_distance_m(sample_surface(truth, 20000, rng),
                                 sample_surface(fitted, 20000, rng))
    assert chamfer < CHAMFER_TOL_M
    if not (case.half and case.taper):  # half a tapered shape: only the surface is asserted
        _compare_parameters(truth, fitted, case.taper is not None)


@pytest.mark.parametrize("footprint", FOOTPRINTS)
def test_fits_benchmark_prism(footprint: str) -> None:
    """Every pushing-benchmark footprint, extruded to 5 cm and seen from all sides but below,
    is fitted (defaults, with the shear extension) to within 1.5 mm Chamfer."""
    rng = np.random.default_rng([FOOTPRINTS.index(footprint), 29])
    polygon = footprint_polygon(footprint)
    pose = np.array([rng.uniform(-0.1, 0.1), rng.uniform(0.35, 0.5), rng.uniform(-np.pi, np.pi)])
    surface = to_world_xy(prism_surface_points(polygon, PRISM_HEIGHT_M, 2 * PRISM_POINTS, rng),
                          pose)
    points = surface[surface[:, 2] > 0.001][:PRISM_POINTS]
    points += rng.normal(0.0, PRISM_NOISE_M, points.shape)
    fitted = make_estimator().fit(PointCloud(points)).links[0]
    truth = to_world_xy(prism_surface_points(polygon, PRISM_HEIGHT_M, 20000, rng), pose)
    assert chamfer_distance_m(sample_surface(fitted, 20000, rng), truth) < PRISM_CHAMFER_TOL_M


def _prism_view(footprint: str, seed: int) -> tuple[np.ndarray, float]:
    """Noisy points [<= 3000, 3] of a footprint's 5 cm prism at a random pose as one side
    and the top see it, and its yaw (rad)."""
    rng = np.random.default_rng([seed, 7])
    pose = np.array([rng.uniform(-0.1, 0.1), rng.uniform(0.35, 0.5), rng.uniform(-np.pi, np.pi)])
    surface = to_world_xy(prism_surface_points(footprint_polygon(footprint), PRISM_HEIGHT_M,
                                               2 * PRISM_POINTS, rng), pose)  # fmt: skip
    side = np.array([np.cos(pose[2] + 1.0), np.sin(pose[2] + 1.0)])
    seen = ((surface[:, :2] - pose[:2]) @ side > -0.01) | (surface[:, 2] > PRISM_HEIGHT_M - 0.001)
    points = surface[seen & (surface[:, 2] > 0.001)][:PRISM_POINTS]
    return points + rng.normal(0.0, PRISM_NOISE_M, points.shape), float(pose[2])


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("footprint", ["ellip2", "ellip3"])
def test_an_ellipse_fit_lies_along_the_ellipse_axes(footprint: str, seed: int) -> None:
    """A fit may not trade an ellipse's yaw for a shear (which turns the link frame the
    process models see by 20-40 deg in these views when kept)."""
    points, yaw_rad = _prism_view(footprint, seed)
    fitted = make_estimator().fit(PointCloud(points)).links[0]
    assert angle_error(yaw_of(fitted), yaw_rad, np.pi / 2) < YAW_TOL_RAD
    assert fitted.taper[2] == 0.0


@pytest.mark.parametrize("footprint", ["tri2", "tri3"])
def test_a_right_triangle_keeps_its_shear(footprint: str) -> None:
    points, _ = _prism_view(footprint, 0)
    assert abs(make_estimator().fit(PointCloud(points)).links[0].taper[2]) > 0.1
    assert make_estimator(shear_gain_nats=100.0).fit(PointCloud(points)).links[0].taper[2] == 0.0


@pytest.mark.parametrize("kappa1", [0.5, -0.5])
def test_a_tilted_tapered_shape_off_the_table_is_fitted_in_place(kappa1: float) -> None:
    """Off the table a fit's negative kappa1 is flipped by a half turn about the shape's own z
    axis; a turn about the world's would move a tilted shape away from its points."""
    from vistac.plugins.shape.ems import fit_superquadric

    params = np.zeros(len(PARAMETER_NAMES))
    params[0:3] = [0.03, 0.06, 0.02]
    params[3:5] = [0.4, 0.6]
    params[5] = kappa1
    params[8:13] = [0.5, 0.3, 0.3, 0.5, -0.3]  # y, yaw, z, pitch, roll
    points = sample_surface(to_superquadric(params), 800, np.random.default_rng(1))
    result = fit_superquadric(points, EMSOptions(on_table=False, shear=False))
    assert result.params[5] >= 0.0
    assert abs(result.params[5] - abs(kappa1)) < 0.05
    assert distance_to_surface_m(result.superquadric, points).mean() < 0.001


def test_estimate_layout_and_inlier_cloud() -> None:
    rng = np.random.default_rng(7)
    truth = upright([0.04, 0.06, 0.025], [0.1, 0.1], [0.05, 0.4], 0.3)
    points, outlier = noisy_cloud(truth, rng)
    table = np.column_stack([rng.uniform(-0.1, 0.2, (500, 2)), rng.normal(0, 0.001, 500)])
    estimate = make_estimator(taper=False).fit(PointCloud(np.vstack([points, table])))
    assert isinstance(estimate, ShapeEstimate)
    assert estimate.initial_poses.shape == (1, 3)
    assert estimate.uncertainty.shape == (1, len(PARAMETER_NAMES))
    std = dict(zip(PARAMETER_NAMES, estimate.uncertainty[0], strict=True))
    assert std["pitch_rad"] == std["roll_rad"] == std["kappa1"] == std["shear"] == 0.0
    assert 0.0 < std["a1_m"] < 0.002 and 0.0 < std["yaw_rad"] < np.radians(2)
    # The returned cloud is the object's inliers: no table points, most outliers gone.
    kept = estimate.cloud.points_m
    assert kept[:, 2].min() > 0.008
    assert len(kept) < len(points) and len(kept) > 0.75 * (~outlier).sum()
    assert np.mean(distance_to_surface_m(truth, kept) < 4 * NOISE_M) > 0.97


def test_inlier_probability_separates_outliers() -> None:
    from vistac.plugins.shape.ems import EMSOptions, fit_superquadric

    rng = np.random.default_rng(3)
    truth = upright([0.035, 0.055, 0.03], [0.5, 0.5], [0.0, 0.4], -0.7)
    points, outlier = noisy_cloud(truth, rng)
    far = outlier & (distance_to_surface_m(truth, points) > 4 * NOISE_M)
    result = fit_superquadric(points, EMSOptions(taper=False))
    assert result.inlier_probability[~outlier].mean() > 0.9
    assert result.inlier_probability[far].mean() < 0.05
    assert NOISE_M / 2 < result.noise_m < 2 * NOISE_M


def test_two_touching_boxes_are_two_links() -> None:
    points = _two_box_points(np.random.default_rng(11))
    estimate = make_estimator(taper=False, max_links=3, outlier_threshold_points=150).fit(
        PointCloud(points))
    assert len(estimate.links) == 2
    poses = estimate.initial_poses[np.argsort(estimate.initial_poses[:, 0])]
    np.testing.assert_allclose(poses[:, :2], [[0.0, 0.4], [0.075, 0.4]], atol=0.006)


def _two_box_points(rng: np.random.Generator, dx_m: float = 0.0) -> np.ndarray:
    """Two touching boxes (the tall one beside the low one, offset by dx_m in x), as the
    camera would see them (the shared face hidden)."""
    low_box = upright([0.045, 0.045, 0.02], [0.1, 0.1], [dx_m, 0.4], 0.0)
    tall_box = upright([0.03, 0.045, 0.035], [0.1, 0.1], [dx_m + 0.075, 0.4], 0.0)
    points = np.vstack([noisy_cloud(sq, rng, 1200)[0] for sq in (low_box, tall_box)])
    return points[(np.abs(points[:, 0] - dx_m - 0.045) > 0.004) | (points[:, 2] > 0.04)]


def test_successive_fits_keep_the_better_links() -> None:
    """The estimator refits the last fit's links as well as searching anew and keeps what
    explains the points better: after a good two-link fit, a later fit is no worse than a
    cold one, and links left from elsewhere (another place) do not spoil it."""
    rng = np.random.default_rng(11)
    options = {"taper": False, "max_links": 3, "outlier_threshold_points": 150}
    estimator = make_estimator(**options)
    estimator.fit(PointCloud(_two_box_points(rng, dx_m=0.1)))
    moved = estimator.fit(PointCloud(_two_box_points(rng)))
    cold = make_estimator(**options).fit(PointCloud(_two_box_points(np.random.default_rng(11))))
    for estimate in (moved, cold):
        poses = estimate.initial_poses[np.argsort(estimate.initial_poses[:, 0])]
        np.testing.assert_allclose(poses[:, :2], [[0.0, 0.4], [0.075, 0.4]], atol=0.006)
    again = estimator.fit(PointCloud(_two_box_points(rng)))
    assert len(again.links) == 2


def test_covariance_matches_the_standard_deviations() -> None:
    rng = np.random.default_rng(5)
    truth = upright([0.035, 0.055, 0.03], [0.3, 0.3], [0.0, 0.4], 0.4)
    estimate = make_estimator().fit(PointCloud(noisy_cloud(truth, rng)[0]))
    assert estimate.covariance is not None
    cov = estimate.covariance[0]
    np.testing.assert_allclose(cov, cov.T)
    np.testing.assert_allclose(np.sqrt(np.diag(cov)), estimate.uncertainty[0], rtol=1e-9)
    assert np.linalg.eigvalsh(cov).min() > -1e-12


DATA = ROOT / "tests/data"
LAST_VIEW_LINKS = (
    # PARAMETER_NAMES order, noise (m): a tapered link and a 2 mm sliver beside it.
    ([0.032916, 0.070097, 0.024211, 0.140511, 0.1, 0.884607, 0.066013, -0.272594, 0.452642,
      -2.393801, 0.024211, 0.0, 0.0, 0.402693], 0.001611),
    ([0.002, 0.03875, 0.022776, 0.595321, 1.511181, 0.24632, 1.0, -0.2548, 0.484153, 0.74785,
      0.022776, 0.0, 0.0, 0.000638], 0.002344),
)


def test_a_link_refitted_from_the_last_view_must_explain_points_to_be_kept() -> None:
    """A view of a triangle, warm-started from the last view's links: the sliver, refitted,
    explained none of the points, yet the pair was kept for the better fit of the other link,
    and its undefined covariance (NaN) then ended the run. Every link kept explains at least
    the outlier threshold's points, and every covariance is finite."""
    points_m = np.loadtxt(DATA / "tri2_view_sliver_mm.txt") / 1000.0
    options = EMSOptions()
    nothing = np.zeros((0, 3))
    last = [
        EMSResult(to_superquadric(np.array(params)), np.array(params), np.zeros(0), noise_m,
                  0.0, nothing, options, nothing, np.zeros(0))
        for params, noise_m in LAST_VIEW_LINKS
    ]  # fmt: skip
    threshold = 33
    links = fit_links(points_m, options, 2, threshold, 0.01, last)
    assert min(int((link.inlier_probability >= 0.5).sum()) for link in links) >= threshold
    assert all(np.isfinite(link.covariance).all() for link in links)


def _cloud_with_nan() -> PointCloud:
    cloud = PointCloud(np.full((100, 3), 0.05))
    object.__setattr__(cloud, "points_m", np.full((100, 3), np.nan))
    return cloud


@pytest.mark.parametrize(
    ("cloud", "message"),
    [
        (PointCloud(np.zeros((0, 3))), "point cloud is empty"),
        (_cloud_with_nan(), "NaN or inf"),
        (PointCloud(np.column_stack([np.random.default_rng(0).uniform(0, 0.2, (400, 2)),
                                     np.zeros(400)])), "only 0 of 400 points lie above"),
        (PointCloud(np.full((20, 3), 0.05)), "fewer than min_points = 50"),
    ],
    ids=["empty", "nan", "all_table", "too_few"],
)
def test_bad_input_is_a_data_error(cloud: PointCloud, message: str) -> None:
    with pytest.raises(DataError, match=message):
        make_estimator().fit(cloud)


def test_too_few_points_off_the_table_names_no_table() -> None:
    with pytest.raises(DataError, match="only 20 points, fewer than min_points = 50") as error:
        make_estimator(on_table=False).fit(PointCloud(np.full((20, 3), -0.5)))
    assert "table" not in str(error.value)


def test_sampled_surface_points_lie_on_the_surface() -> None:
    rng = np.random.default_rng(0)
    sq = upright([0.04, 0.07, 0.03], [0.3, 0.6], [0.1, 0.3], 1.0, [0.5, 0.3])
    points = sample_surface(sq, 3000, rng)
    assert np.median(np.abs(inside_outside(to_superquadric_frame(sq, points), sq.scale_m,
                                           sq.exponents, sq.taper) - 1)) < 0.01
    assert np.percentile(distance_to_surface_m(sq, points), 99) < 5e-4


def test_surface_samples_are_spread_by_area() -> None:
    box = upright([0.04, 0.07, 0.03], [0.1, 0.1], [0.0, 0.0], 0.0)
    points = sample_surface(box, 20000, np.random.default_rng(1))
    top_share = 0.08 * 0.14 / (2 * (0.08 * 0.14 + 0.08 * 0.06 + 0.14 * 0.06))
    assert np.mean(points[:, 2] > 0.0595) == pytest.approx(top_share, rel=0.1)


def test_chamfer_distance_of_shifted_copy() -> None:
    points = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    assert chamfer_distance_m(points, points) == 0.0
    shifted = points + np.array([0.0, 0.0, 0.002])
    assert chamfer_distance_m(points, shifted) == pytest.approx(0.002)
