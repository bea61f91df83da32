"""Vectorised geometry of tapered superquadrics (paper 1, III-B1, eq. 1-2).

Superquadric frame: semi-axes ``a1, a2, a3`` along x, y, z. Inside-outside function (eq. 1)

    F(x, y, z) = ((x/a1)^(2/eps2) + (y/a2)^(2/eps2))^(eps2/eps1) + (z/a3)^(2/eps1),

F < 1 inside, F = 1 on the surface. Tapering (eq. 2) acts along the frame's y axis, as in the
paper, so that for an upright superquadric the footprint narrows from one end to the other:

    X = f(y) x,  Y = y,  Z = z,  f(y) = 1 + kappa1 (y/a2) + kappa2 (y/a2)^2,

with kappa1 in [-1, 1] and kappa2 in [0, 1] (then f >= 0 on the surface). The paper's
``f(y) = kappa1 y + kappa2 y^2`` is read as the deformation added to the identity, so zero taper
is the plain superquadric. ``y/a2`` is clipped to [-1, 1] inside ``f`` so the map stays
invertible off the surface.

Every function broadcasts over leading batch dimensions: ``points [..., N, 3]`` with parameters
``scale [..., 3]``, ``exponents [..., 2]``, ``taper [..., 2]``.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree
from vistac.types import FloatArray, Superquadric

_TINY_M = 1e-12
_MIN_TAPER_FACTOR = 1e-3
_MIN_LOG_F = -200.0
_GRID_ETA = 48
_GRID_OMEGA = 96
_ARC_SAMPLES = 2048


def taper_factor(y_m: FloatArray, a2_m: FloatArray, taper: FloatArray) -> FloatArray:
    """f(y) of eq. 2. y_m: [..., N]; a2_m: [...]; taper: [..., 2]. Returns [..., N]."""
    t = np.clip(y_m / a2_m[..., None], -1.0, 1.0)
    factor = 1.0 + taper[..., 0, None] * t + taper[..., 1, None] * t * t
    return np.maximum(factor, _MIN_TAPER_FACTOR)


def apply_taper(points: FloatArray, scale_m: FloatArray, taper: FloatArray) -> FloatArray:
    """Deform superquadric-frame points [..., N, 3] by eq. 2. Returns [..., N, 3]."""
    factor = taper_factor(points[..., 1], scale_m[..., 1], taper)
    return np.concatenate([points[..., :1] * factor[..., None], points[..., 1:]], axis=-1)


def remove_taper(points: FloatArray, scale_m: FloatArray, taper: FloatArray) -> FloatArray:
    """Inverse of :func:`apply_taper` (y is unchanged, so f(y) is known). [..., N, 3]."""
    factor = taper_factor(points[..., 1], scale_m[..., 1], taper)
    return np.concatenate([points[..., :1] / factor[..., None], points[..., 1:]], axis=-1)


def log_inside_outside(
    points: FloatArray, scale_m: FloatArray, exponents: FloatArray
) -> FloatArray:
    """log F of eq. 1 for untapered superquadric-frame points [..., N, 3]. Returns [..., N].

    Computed in log space so that small exponents (box-like shapes) cannot overflow.
    """
    log_ratio = np.log(np.maximum(np.abs(points), _TINY_M)) - np.log(scale_m)[..., None, :]
    eps1, eps2 = exponents[..., 0, None], exponents[..., 1, None]
    log_xy = np.logaddexp(2.0 / eps2 * log_ratio[..., 0], 2.0 / eps2 * log_ratio[..., 1])
    return np.logaddexp(eps2 / eps1 * log_xy, 2.0 / eps1 * log_ratio[..., 2])


def inside_outside(
    points: FloatArray, scale_m: FloatArray, exponents: FloatArray, taper: FloatArray
) -> FloatArray:
    """F of eq. 1 with the tapering of eq. 2 (< 1 inside, 1 on the surface). Returns [..., N]."""
    untapered = remove_taper(points, scale_m, taper)
    with np.errstate(over="ignore"):
        return np.exp(log_inside_outside(untapered, scale_m, exponents))


def radial_surface_points(
    points: FloatArray, scale_m: FloatArray, exponents: FloatArray, taper: FloatArray
) -> FloatArray:
    """The surface point on the ray from the centre through each point (in the untapered frame).

    This is the closest-point approximation of EMS: exact for spheres, and within a few
    percent of the true distance for points near the surface. Returns [..., N, 3].
    """
    untapered = remove_taper(points, scale_m, taper)
    log_f = np.maximum(log_inside_outside(untapered, scale_m, exponents), _MIN_LOG_F)
    radial_scale = np.exp(-0.5 * exponents[..., 0, None] * log_f)
    return apply_taper(untapered * radial_scale[..., None], scale_m, taper)


def radial_distance_m(
    points: FloatArray, scale_m: FloatArray, exponents: FloatArray, taper: FloatArray
) -> FloatArray:
    """Distance from each point [..., N, 3] to its radial surface point. Returns [..., N]."""
    surface = radial_surface_points(points, scale_m, exponents, taper)
    return np.linalg.norm(points - surface, axis=-1)


def to_superquadric_frame(sq: Superquadric, points_m: FloatArray) -> FloatArray:
    """World points [N, 3] expressed in the superquadric's frame. Returns [N, 3]."""
    rotation, translation = sq.world_from_sq[:3, :3], sq.world_from_sq[:3, 3]
    return (points_m - translation) @ rotation


def distance_to_surface_m(sq: Superquadric, points_m: FloatArray) -> FloatArray:
    """Radial distance of world points [N, 3] to the superquadric's surface. Returns [N]."""
    local = to_superquadric_frame(sq, points_m)
    return radial_distance_m(local, sq.scale_m, sq.exponents, sq.taper)


def _signed_power(value: FloatArray, exponent: float) -> FloatArray:
    return np.sign(value) * np.abs(value) ** exponent


def _arc_uniform_angles(exponent: float, x_scale: float, y_scale: float, lo: float,
                        hi: float, count: int) -> FloatArray:
    """Angles in [lo, hi] [count] evenly spaced in arc length along the scaled superellipse."""
    angle = np.linspace(lo, hi, _ARC_SAMPLES)
    x = x_scale * _signed_power(np.cos(angle), exponent)
    y = y_scale * _signed_power(np.sin(angle), exponent)
    arc = np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(x), np.diff(y)))])
    return np.interp(np.linspace(0.0, arc[-1], count), arc, angle)


def _surface_grid(sq: Superquadric) -> FloatArray:
    """Surface points on a grid evenly spaced in arc length: [E, W, 3] (superquadric frame)."""
    a1, a2, a3 = (float(v) for v in sq.scale_m)
    eps1, eps2 = (float(v) for v in sq.exponents)
    eta = _arc_uniform_angles(eps1, max(a1, a2), a3, -np.pi / 2, np.pi / 2, _GRID_ETA)
    omega = _arc_uniform_angles(eps2, a1, a2, -np.pi, np.pi, _GRID_OMEGA)
    ring = _signed_power(np.cos(eta), eps1)[:, None]
    points = np.stack(np.broadcast_arrays(
        a1 * ring * _signed_power(np.cos(omega), eps2)[None, :],
        a2 * ring * _signed_power(np.sin(omega), eps2)[None, :],
        a3 * _signed_power(np.sin(eta), eps1)[:, None],
    ), axis=-1)
    return apply_taper(points, sq.scale_m, sq.taper)


def sample_surface(sq: Superquadric, count: int, rng: np.random.Generator) -> FloatArray:
    """``count`` points spread roughly uniformly over the surface, world frame: [count, 3].

    Grid cells (even in arc length) are drawn with probability proportional to their area,
    then a point is placed uniformly in the chosen cell by bilinear interpolation.
    """
    grid = _surface_grid(sq)
    corner00, corner10 = grid[:-1, :-1], grid[1:, :-1]
    corner01, corner11 = grid[:-1, 1:], grid[1:, 1:]
    area = 0.5 * (np.linalg.norm(np.cross(corner10 - corner00, corner01 - corner00), axis=-1)
                  + np.linalg.norm(np.cross(corner10 - corner11, corner01 - corner11), axis=-1))
    cell = rng.choice(area.size, size=count, p=(area / area.sum()).ravel())
    row, col = np.unravel_index(cell, area.shape)
    u, v = rng.random((2, count, 1))
    local = ((1 - u) * (1 - v) * corner00[row, col] + u * (1 - v) * corner10[row, col]
             + (1 - u) * v * corner01[row, col] + u * v * corner11[row, col])
    rotation, translation = sq.world_from_sq[:3, :3], sq.world_from_sq[:3, 3]
    return local @ rotation.T + translation


def chamfer_distance_m(points_a: FloatArray, points_b: FloatArray) -> float:
    """Symmetric mean nearest-neighbour distance between points_a [N, 3] and points_b [M, 3]."""
    a_to_b, _ = cKDTree(points_b).query(points_a)
    b_to_a, _ = cKDTree(points_a).query(points_b)
    return 0.5 * (float(np.mean(a_to_b)) + float(np.mean(b_to_a)))


def surface_area_m2(scale_m: FloatArray, exponents: FloatArray, taper: FloatArray) -> FloatArray:
    """Approximate surface area [...] of superquadrics (scale [..., 3], exponents [..., 2]).

    Bilinear interpolation in (eps1, eps2) between the exact areas of the four corner shapes
    (eps in {0, 2}: box, diamond prism, rectangular bipyramid, octahedron), as in Liu et al.;
    the taper widens x by its mean factor 1 + kappa2 / 3 along y.
    """
    a1 = scale_m[..., 0] * (1.0 + taper[..., 1] / 3.0)
    a2, a3 = scale_m[..., 1], scale_m[..., 2]
    box = 8.0 * (a1 * a2 + a2 * a3 + a1 * a3)
    diamond_prism = 8.0 * np.hypot(a1, a2) * a3 + 4.0 * a1 * a2
    bipyramid = 4.0 * (a1 * np.hypot(a2, a3) + a2 * np.hypot(a1, a3))
    side_xy, side_yz, side_xz = np.hypot(a1, a2), np.hypot(a2, a3), np.hypot(a1, a3)
    half_perimeter = 0.5 * (side_xy + side_yz + side_xz)
    octahedron = 8.0 * np.sqrt(np.maximum(half_perimeter * (half_perimeter - side_xy)
                                          * (half_perimeter - side_yz)
                                          * (half_perimeter - side_xz), 0.0))
    w1, w2 = 0.5 * exponents[..., 0], 0.5 * exponents[..., 1]
    return ((1 - w1) * ((1 - w2) * box + w2 * diamond_prism)
            + w1 * ((1 - w2) * bipyramid + w2 * octahedron))
