"""``shape.ems`` internals that make it fast: batched fits, the batched analytic gradient and
the vectorised seam search give what the one-at-a-time versions give."""

from __future__ import annotations

import numpy as np
import pytest
from vistac.plugins.shape import ems
from vistac.plugins.shape.superquadric import (
    radial_distance_gradient,
    radial_distance_m,
    sample_surface,
)
from vistac.types import Superquadric

NOISE_M = 0.001


def _upright(scale_m: list[float], xy_m: list[float], yaw_rad: float,
             taper: list[float]) -> Superquadric:
    """A tapered and sheared superquadric standing on the table at (x, y) turned by yaw."""
    pose = np.eye(4)
    pose[:3, :3] = ems.rotation_zyx(np.array([yaw_rad]), np.zeros(1), np.zeros(1))[0]
    pose[:3, 3] = [xy_m[0], xy_m[1], scale_m[2]]
    return Superquadric(np.array(scale_m), np.array([0.3, 0.4]), pose, np.array(taper))


def _cloud(sq: Superquadric, count: int, rng: np.random.Generator) -> np.ndarray:
    """Noisy surface points [count, 3] above the table."""
    points = sample_surface(sq, 2 * count, rng)
    points = points[points[:, 2] > 0.01][:count]
    return points + rng.normal(0.0, NOISE_M, points.shape)


def test_batched_fits_match_the_fits_one_at_a_time() -> None:
    """Two fits in one batch (one with excluded points, one without; one cold, one warm)
    end where each ends alone."""
    rng = np.random.default_rng(4)
    first = _cloud(_upright([0.03, 0.05, 0.025], [0.0, 0.4], 0.3, [0.3, 0.1, 0.2]), 1500, rng)
    second = _cloud(_upright([0.04, 0.03, 0.02], [0.1, 0.4], -0.5, [0.0, 0.0, 0.0]), 1200, rng)
    options = ems.EMSOptions()
    centre = np.array([0.0, 0.4])
    excluded = np.column_stack([centre + rng.uniform(-0.02, 0.02, (200, 2)),
                                rng.uniform(0.0, 0.04, 200)])
    start = ems.fit_superquadric(second[::2], options)
    alone = [ems.fit_superquadric(first, options, excluded),
             ems.fit_superquadric(second, options, None, start)]
    together = ems._fit_superquadrics([first, second], options, [excluded, None], [None, start])
    for one, batched in zip(alone, together, strict=True):
        np.testing.assert_allclose(batched.params, one.params, atol=1e-6)
        np.testing.assert_allclose(batched.std, one.std, rtol=1e-3, atol=1e-9)
        assert batched.noise_m == pytest.approx(one.noise_m, rel=1e-4)


def test_radial_distance_gradient_matches_finite_differences() -> None:
    """The gradient [B, 11, N] of the radial distance with respect to the point and the shape
    (a1, a2, a3, eps1, eps2, kappa1, kappa2, shear), for two superquadrics at once."""
    rng = np.random.default_rng(2)
    scale = np.array([[0.03, 0.05, 0.02], [0.04, 0.03, 0.025]])
    exponents = np.array([[0.4, 0.7], [1.2, 0.3]])
    taper = np.array([[0.3, 0.2, 0.1], [-0.2, 0.1, -0.3]])
    points_t = rng.normal(0.0, 0.03, (2, 3, 50))
    distance, grad = radial_distance_gradient(points_t, scale, exponents, taper)

    def distances(points: np.ndarray, shape: np.ndarray) -> np.ndarray:
        return radial_distance_m(points.swapaxes(1, 2), shape[:, :3], shape[:, 3:5],
                                 shape[:, 5:])

    shape = np.hstack([scale, exponents, taper])
    np.testing.assert_allclose(distance, distances(points_t, shape))
    step = 1e-7
    for row in range(11):
        moved_points, moved_shape = points_t.copy(), shape.copy()
        if row < 3:
            moved_points[:, row] += step
        else:
            moved_shape[:, row - 3] += step
        numeric = (distances(moved_points, moved_shape) - distance) / step
        np.testing.assert_allclose(grad[:, row], numeric, rtol=1e-3, atol=1e-5)


def _step_cut_one_cut_at_a_time(along_m: np.ndarray, height_m: np.ndarray) -> tuple[float, float]:
    """The seam search of :func:`ems._step_cut` written as a loop over the cuts."""
    top, position = ems._top_profile(along_m, height_m)
    cuts = [c for c in range(1, len(top)) if ems._middle_bins(position)[c]]
    if not cuts:
        return 0.0, 0.0
    cost = [np.abs(top[:c] - np.median(top[:c])).sum() + np.abs(top[c:] - np.median(top[c:])).sum()
            for c in cuts]
    best = cuts[int(np.argmin(cost))]
    if abs(float(np.median(top[:best]) - np.median(top[best:]))) < ems._STEP_MIN_M:
        return 0.0, 0.0
    return (float(np.abs(top - np.median(top)).sum()) - min(cost)) / len(top), float(position[best])


@pytest.mark.parametrize("seed", range(20))
def test_step_cut_matches_the_search_one_cut_at_a_time(seed: int) -> None:
    rng = np.random.default_rng(seed)
    along = rng.uniform(-0.08, 0.08, 2000)
    height = np.where(along > rng.uniform(-0.04, 0.04), 0.03, 0.05) + rng.normal(0, 0.002, 2000)
    if seed % 4 == 0:
        height = rng.uniform(0.01, 0.06, 2000)
    order = np.argsort(height)
    along, height = along[order], height[order]
    gain, cut = ems._step_cut(along, height)
    want_gain, want_cut = _step_cut_one_cut_at_a_time(along, height)
    assert cut == want_cut
    assert gain == pytest.approx(want_gain, rel=1e-9, abs=1e-15)


@pytest.mark.parametrize("seed", range(5))
def test_top_profile_is_the_top_percentile_of_each_bin(seed: int) -> None:
    rng = np.random.default_rng(seed)
    along = rng.uniform(-0.08, 0.08, 3000)
    height = np.sort(rng.uniform(0.01, 0.06, 3000))
    top, edges = ems._top_profile(along, height)
    low, high = np.percentile(along, ems._SPAN_PERCENTILES)
    want_top, want_edges = [], []
    for edge in np.arange(low, high, ems._STEP_BIN_M):
        inside = np.sort(height[(along >= edge) & (along < min(edge + ems._STEP_BIN_M, high))])
        if len(inside) >= ems._MIN_LINK_POINTS:
            want_top.append(inside[int(ems._TOP_PERCENTILE / 100 * (len(inside) - 1))])
            want_edges.append(edge)
    np.testing.assert_allclose(top, want_top)
    np.testing.assert_allclose(edges, want_edges)


def test_masked_median_is_the_median_of_each_row() -> None:
    rng = np.random.default_rng(0)
    values = rng.normal(size=9)
    mask = rng.random((30, 9)) < 0.5
    mask[:, 0] = True
    want = [np.median(values[row]) for row in mask]
    np.testing.assert_array_equal(ems._masked_median(values, mask), want)
