"""GPIS (touch.gpis): thin-plate kernel, posterior on a sphere, scale fit, marching cubes,
incremental updates, and the component's contract."""

from __future__ import annotations

import zlib
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from vistac.errors import DataError
from vistac.plugins.touch.gpis import (
    Gpis,
    GpisNoise,
    GpisSurface,
    enclosed_volume_m3,
    extract_surface,
    joint_covariance,
    sphere_sdf,
    thin_plate_profile,
    value_cross_covariance,
)
from vistac.plugins.touch.metrics import directed_hausdorff, two_way_hausdorff
from vistac.plugins.touch.types import MlePrior

CENTRE = np.array([0.1, 0.4, 0.06])
RADIUS_M = 0.05
SCALE_M = 0.3  # > 1.5 x the diagonal of every box used here


def unit_vectors(count: int, seed: int) -> np.ndarray:
    """``count`` random unit vectors [count, 3]."""
    v = np.random.default_rng(seed).normal(size=(count, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def sphere_gp(count: int = 40, prior_radius_m: float | None = 0.6 * RADIUS_M,
              seed: int = 0) -> Gpis:  # fmt: skip
    """A GP on ``count`` contacts of the sphere (CENTRE, RADIUS_M) with a wrong-size prior."""
    normals = unit_vectors(count, seed)
    prior = None if prior_radius_m is None else sphere_sdf(CENTRE, prior_radius_m)
    gp = Gpis(SCALE_M, GpisNoise(1e-4, 0.02), prior=prior)
    gp.set_contacts(CENTRE + RADIUS_M * normals, normals)
    return gp


# --- kernel -------------------------------------------------------------------------------


def test_kernel_profile_derivatives_match_finite_differences() -> None:
    r, step = np.linspace(0.01, 0.5, 40), 1e-6
    value, first, second = thin_plate_profile(r, 0.6)
    up, down = thin_plate_profile(r + step, 0.6), thin_plate_profile(r - step, 0.6)
    np.testing.assert_allclose(first, (up[0] - down[0]) / (2 * step), atol=1e-7)
    np.testing.assert_allclose(second, (up[1] - down[1]) / (2 * step), atol=1e-6)
    assert thin_plate_profile(np.array([0.6]), 0.6)[0][0] == pytest.approx(0.0)
    assert value[0] == pytest.approx(2 * 0.01**3 - 3 * 0.6 * 0.01**2 + 0.6**3)


def _k(a: np.ndarray, b: np.ndarray, scale: float) -> float:
    return float(thin_plate_profile(np.linalg.norm(a - b), scale)[0])


def test_joint_covariance_blocks_are_kernel_derivatives() -> None:
    a, b, scale, h = np.array([0.01, 0.02, -0.03]), np.array([0.05, -0.04, 0.02]), 0.4, 1e-5
    block = joint_covariance(a[None], b[None], scale)
    eye = np.eye(3)
    d_b = [(_k(a, b + h * e, scale) - _k(a, b - h * e, scale)) / (2 * h) for e in eye]
    d_a = [(_k(a + h * e, b, scale) - _k(a - h * e, b, scale)) / (2 * h) for e in eye]
    d_ab = [[(_k(a + h * ei, b + h * ej, scale) - _k(a + h * ei, b - h * ej, scale)
              - _k(a - h * ei, b + h * ej, scale) + _k(a - h * ei, b - h * ej, scale)) / (4 * h * h)
             for ej in eye] for ei in eye]  # fmt: skip
    assert block[0, 0] == pytest.approx(_k(a, b, scale))
    np.testing.assert_allclose(block[0, 1:], d_b, rtol=1e-6)
    np.testing.assert_allclose(block[1:, 0], d_a, rtol=1e-6)
    np.testing.assert_allclose(block[1:, 1:], d_ab, rtol=1e-4, atol=1e-6)


def test_joint_covariance_is_symmetric_and_positive_definite_within_its_scale() -> None:
    points = CENTRE + RADIUS_M * unit_vectors(60, 1)
    cov = joint_covariance(points, points, SCALE_M)
    np.testing.assert_allclose(cov, cov.T, atol=1e-15)
    assert np.linalg.eigvalsh(cov).min() > -1e-10
    other = points[:7] + 0.01
    np.testing.assert_allclose(joint_covariance(points, other, SCALE_M),
                               joint_covariance(other, points, SCALE_M).T)
    np.testing.assert_allclose(value_cross_covariance(other, points, SCALE_M),
                               joint_covariance(other, points, SCALE_M)[::4])
    assert np.allclose(np.diag(joint_covariance(points[:1], points[:1], SCALE_M)),
                       [SCALE_M**3, 6 * SCALE_M, 6 * SCALE_M, 6 * SCALE_M])


# --- posterior on a sphere ---------------------------------------------------------------


@pytest.mark.parametrize("prior_radius_m", [0.6 * RADIUS_M, None], ids=["small-sphere", "zero"])
def test_posterior_fits_the_sphere(prior_radius_m: float | None) -> None:
    gp = sphere_gp(prior_radius_m=prior_radius_m)
    directions = unit_vectors(300, 7)
    on_surface = CENTRE + RADIUS_M * directions
    assert np.abs(gp.mean(on_surface)).max() < 0.1 * RADIUS_M
    assert gp.mean(CENTRE[None])[0] < -0.5 * RADIUS_M
    assert np.all(gp.mean(CENTRE + 1.5 * RADIUS_M * directions) > 0.2 * RADIUS_M)
    gradient = gp.gradient(on_surface)
    cosine = np.sum(gradient * directions, axis=1) / np.linalg.norm(gradient, axis=1)
    assert cosine.min() > 0.95


def test_posterior_interpolates_contacts_and_normals() -> None:
    gp = sphere_gp()
    np.testing.assert_allclose(gp.mean(gp.points_m), 0.0, atol=1e-3 * RADIUS_M)
    _, normals = gp.sdf(gp.points_m)
    assert np.sum(normals * gp.normals, axis=1).min() > 0.999


def test_fast_mean_equals_the_cross_covariance_mean() -> None:
    gp = sphere_gp(count=30)
    queries = CENTRE + np.random.default_rng(8).uniform(-0.1, 0.1, (500, 3))
    np.testing.assert_allclose(gp.mean(queries), gp.predict(queries)[0], rtol=1e-9, atol=1e-12)


def test_variance_is_smaller_near_contacts_than_far() -> None:
    gp = sphere_gp(count=12)
    near = gp.variance(gp.points_m + 1e-3)
    far = gp.variance(CENTRE + 2.5 * RADIUS_M * unit_vectors(50, 3))
    assert near.max() < 0.01 * far.min()
    assert far.max() <= SCALE_M**3 + 1e-12


def test_exact_prior_leaves_the_prior_unchanged() -> None:
    gp = sphere_gp(prior_radius_m=RADIUS_M)
    queries = CENTRE + np.random.default_rng(0).uniform(-0.08, 0.08, (200, 3))
    np.testing.assert_allclose(gp.mean(queries), sphere_sdf(CENTRE, RADIUS_M)(queries)[0],
                               atol=1e-9)


def test_prior_change_keeps_the_factor() -> None:
    gp = sphere_gp()
    chol = gp._chol.copy()
    gp.set_prior(sphere_sdf(CENTRE, RADIUS_M))
    np.testing.assert_array_equal(gp._chol, chol)
    queries = CENTRE + 0.07 * unit_vectors(20, 2)
    np.testing.assert_allclose(gp.mean(queries), sphere_sdf(CENTRE, RADIUS_M)(queries)[0],
                               atol=1e-9)


# --- incremental update, scale fit -------------------------------------------------------


def test_incremental_update_equals_batch_refit() -> None:
    batch = sphere_gp(count=25)
    incremental = Gpis(SCALE_M, batch.noise, prior=batch.prior)
    for point, normal in zip(batch.points_m, batch.normals, strict=True):
        incremental.add_contact(point, normal)
    np.testing.assert_allclose(incremental._chol, batch._chol, atol=1e-10)
    queries = CENTRE + np.random.default_rng(4).uniform(-0.1, 0.1, (100, 3))
    for got, want in zip(incremental.predict(queries), batch.predict(queries), strict=True):
        np.testing.assert_allclose(got, want, rtol=1e-8, atol=1e-12)
    assert incremental.log_marginal_likelihood() == pytest.approx(
        batch.log_marginal_likelihood(), rel=1e-9)


def test_scale_fit_recovers_the_scale_of_a_gp_sample() -> None:
    """Draw values and gradients from the zero-mean prior at R = 0.5; the fit finds R."""
    rng = np.random.default_rng(0)
    points = rng.uniform(-0.09, 0.09, (70, 3))  # diagonal < 0.32 m
    noise = GpisNoise(1e-3, 1e-2)
    true_scale = 0.5
    cov = joint_covariance(points, points, true_scale) + np.diag(noise.variances(len(points)))
    sample = np.linalg.cholesky(cov) @ rng.normal(size=len(cov))
    # Observations are "value 0, gradient n": encode the sample through a prior m = -sample.
    values, gradients = sample.reshape(-1, 4)[:, 0], sample.reshape(-1, 4)[:, 1:]
    lookup = {tuple(p): (v, g) for p, v, g in zip(points, values, gradients, strict=True)}

    def prior(query: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        pairs = [lookup[tuple(q)] for q in query]
        return -np.array([v for v, _ in pairs]), -np.array([g for _, g in pairs])

    gp = Gpis(1.0, noise, prior=prior)
    gp.set_contacts(points, np.tile([0.0, 0.0, 1.0], (len(points), 1)))
    gp.normals[:] = 0.0  # observed gradients are the sample's (via the prior); n = 0
    gp.set_prior(prior)
    fitted = gp.fit_scale(0.3, 3.0)
    assert 0.7 * true_scale < fitted < 1.4 * true_scale
    assert gp.log_marginal_likelihood() >= gp.log_marginal_likelihood(true_scale) - 1e-6
    assert gp.log_marginal_likelihood() > gp.log_marginal_likelihood(3.0) + 3.0
    assert gp.log_marginal_likelihood() > gp.log_marginal_likelihood(0.3) + 3.0


def test_scale_fit_stays_in_bounds_and_improves_the_likelihood() -> None:
    gp = sphere_gp()
    before = gp.log_marginal_likelihood(1.2)
    fitted = gp.fit_scale(0.2, 1.2)
    assert 0.2 <= fitted <= 1.2
    assert gp.log_marginal_likelihood() >= before
    grid = [gp.log_marginal_likelihood(s) for s in np.geomspace(0.2, 1.2, 9)]
    assert gp.log_marginal_likelihood() >= max(grid) - 1e-3


def test_bad_contacts_are_data_errors() -> None:
    gp = Gpis(SCALE_M)
    with pytest.raises(DataError, match="NaN"):
        gp.add_contact(np.array([np.nan, 0.0, 0.0]), np.array([0.0, 0.0, 1.0]))
    with pytest.raises(DataError, match="non-zero"):
        gp.add_contact(np.zeros(3), np.zeros(3))
    with pytest.raises(DataError, match="positive"):
        Gpis(0.0)


# --- surface extraction, metrics ---------------------------------------------------------


def test_marching_cubes_of_the_posterior_is_the_sphere() -> None:
    gp = sphere_gp(count=60)
    mesh = extract_surface(gp.mean, CENTRE - 0.08, CENTRE + 0.08, grid_points=40)
    radii = np.linalg.norm(mesh.vertices_m - CENTRE, axis=1)
    assert np.abs(radii - RADIUS_M).max() < 0.1 * RADIUS_M
    assert abs(np.median(radii) - RADIUS_M) < 0.02 * RADIUS_M
    volume = enclosed_volume_m3(mesh)
    assert volume == pytest.approx(4 / 3 * np.pi * RADIUS_M**3, rel=0.05)  # outward faces


def test_surface_extraction_without_interior_is_a_data_error() -> None:
    with pytest.raises(DataError, match="no interior"):
        extract_surface(lambda p: np.ones(len(p)), np.zeros(3), np.ones(3), grid_points=8)


def test_hausdorff_distances_known_answer() -> None:
    a = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    b = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 3.0]])
    assert directed_hausdorff(a, b) == pytest.approx(1.0)
    assert directed_hausdorff(b, a) == pytest.approx(3.0)
    assert two_way_hausdorff(a, b) == pytest.approx(3.0)


# --- the touch.gpis component ------------------------------------------------------------


class RoleContext:
    """A component context with named roles (``component(role)`` raises KeyError if absent)."""

    def __init__(self, **roles: Any) -> None:
        self.skill_dir = Path(".")
        self.seed = 0
        self.roles = roles

    def rng(self, stream: str) -> np.random.Generator:
        return np.random.default_rng([self.seed, zlib.crc32(stream.encode())])

    def component(self, role: str) -> Any:
        return self.roles[role]

    def find(self, kind: str) -> Any:
        return None


class SphereRecogniser:
    """A recogniser whose MLE shape is a sphere (an octahedron-ish mesh for the box)."""

    def __init__(self, radius_m: float, known: bool | None = None) -> None:
        vertices = CENTRE + radius_m * np.vstack([np.eye(3), -np.eye(3)])
        self.prior = MlePrior("ball", 0.9, np.eye(4), vertices, np.zeros((0, 3), dtype=np.int64),
                              sphere_sdf(CENTRE, radius_m))  # fmt: skip
        self.is_known = known

    def mle_prior(self) -> MlePrior:
        return self.prior

    def known(self) -> bool | None:
        return self.is_known


def surface_component(explore_grid_points: int | None = None, **roles: Any) -> GpisSurface:
    config = GpisSurface.Config(grid_points=32, value_noise_m=1e-4, normal_noise=0.02,
                                explore_grid_points=explore_grid_points)  # fmt: skip
    return GpisSurface(config, RoleContext(**roles))


def touch_sphere(component: GpisSurface, count: int) -> dict[str, Any]:
    estimate: dict[str, Any] = {}
    for normal in unit_vectors(count, 5):
        point = CENTRE + RADIUS_M * normal
        estimate = component.update(point + 0.05 * normal, point, (point, normal))
    return estimate


def test_component_uses_the_recogniser_prior_and_ignores_misses() -> None:
    component = surface_component(estimator=SphereRecogniser(0.8 * RADIUS_M))
    estimate = touch_sphere(component, 30)
    assert estimate["gpis_contacts"] == 30 and estimate["gpis_prior"] == "ball"
    missed = component.update(CENTRE + 0.2, CENTRE + 0.1, None)
    assert missed["gpis_contacts"] == 30
    diagonal = float(np.linalg.norm(component.surface.upper_m - component.surface.lower_m))
    assert 1.5 * diagonal <= estimate["kernel_scale_m"] <= 4.0 * diagonal + 1e-9
    variance = estimate["surface_variance"]
    assert variance(CENTRE[None] + [[0.0, 0.0, RADIUS_M]]).shape == (1,)
    mesh = estimate["reconstruction"]()
    radii = np.linalg.norm(mesh.vertices_m - CENTRE, axis=1)
    assert np.abs(radii - RADIUS_M).max() < 0.15 * RADIUS_M


def test_component_without_recogniser_uses_a_sphere_prior() -> None:
    component = surface_component()  # no "estimator" role
    estimate = touch_sphere(component, 20)
    assert estimate["gpis_prior"] == "sphere"
    radii = np.linalg.norm(estimate["reconstruction"]().vertices_m - CENTRE, axis=1)
    assert np.abs(radii - RADIUS_M).max() < 0.15 * RADIUS_M


def test_component_reconstruction_before_contact_is_a_data_error() -> None:
    component = surface_component()
    component.update(np.zeros(3), np.ones(3), None)
    with pytest.raises(DataError, match="no contact"):
        component.reconstruction()


@pytest.mark.parametrize("known", [False, True, None])
def test_component_publishes_its_surface_for_novel_objects_only(known: bool | None) -> None:
    recogniser = SphereRecogniser(0.8 * RADIUS_M, known=known)
    estimate = touch_sphere(surface_component(explore_grid_points=20, estimator=recogniser), 20)
    if known is not False:
        assert "surface_points_m" not in estimate
        return
    points, normals = estimate["surface_points_m"], estimate["surface_normals"]
    radial = (points - CENTRE) / np.linalg.norm(points - CENTRE, axis=1, keepdims=True)
    assert np.abs(np.linalg.norm(points - CENTRE, axis=1) - RADIUS_M).max() < 0.15 * RADIUS_M
    assert np.sum(normals * radial, axis=1).min() > 0.95
