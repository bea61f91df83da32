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

Extension beyond the paper: an optional shear after the taper, ``X = f(y) x + s y`` (s
dimensionless, the third element of ``taper``). The symmetric taper only makes isosceles
triangles; taper plus shear makes any triangle (e.g. right triangles) and skewed tapered
shapes. A two-element ``taper`` means no shear.

Every function broadcasts over leading batch dimensions: ``points [..., N, 3]`` with parameters
``scale [..., 3]``, ``exponents [..., 2]``, ``taper [..., 2]`` or ``[..., 3]`` (kappa1, kappa2,
shear).
"""

from __future__ import annotations

from typing import NamedTuple

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


def shear_of(taper: FloatArray) -> FloatArray:
    """The shear s [...] of a taper [..., 2 or 3] (zero when it has two elements)."""
    return taper[..., 2] if taper.shape[-1] > 2 else np.zeros(taper.shape[:-1])


def _tapered_x(x: FloatArray, y: FloatArray, scale_m: FloatArray, taper: FloatArray) -> FloatArray:
    """x after eq. 2 and the shear, from superquadric-frame coordinates x, y [..., N]."""
    return x * taper_factor(y, scale_m[..., 1], taper) + shear_of(taper)[..., None] * y


def _untapered_x(
    x: FloatArray, y: FloatArray, scale_m: FloatArray, taper: FloatArray
) -> FloatArray:
    """Inverse of :func:`_tapered_x` (y is unchanged, so f(y) is known): [..., N]."""
    return (x - shear_of(taper)[..., None] * y) / taper_factor(y, scale_m[..., 1], taper)


def apply_taper(points: FloatArray, scale_m: FloatArray, taper: FloatArray) -> FloatArray:
    """Deform superquadric-frame points [..., N, 3] by eq. 2, then shear. Returns [..., N, 3]."""
    x = _tapered_x(points[..., 0], points[..., 1], scale_m, taper)
    return np.stack([x, points[..., 1], points[..., 2]], axis=-1)


def remove_taper(points: FloatArray, scale_m: FloatArray, taper: FloatArray) -> FloatArray:
    """Inverse of :func:`apply_taper` (y is unchanged, so f(y) is known). [..., N, 3]."""
    x = _untapered_x(points[..., 0], points[..., 1], scale_m, taper)
    return np.stack([x, points[..., 1], points[..., 2]], axis=-1)


def _log_f(points_t: FloatArray, scale_m: FloatArray, exponents: FloatArray) -> FloatArray:
    """log F of eq. 1 from untapered coordinate rows [..., 3, N]: [..., N]."""
    return _log_f_parts(points_t, scale_m, exponents)[-1]


def _log_f_parts(
    points_t: FloatArray, scale_m: FloatArray, exponents: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
    """:func:`_log_f` of untapered coordinate rows [..., 3, N] with its parts: |points|,
    log |points| / a and that times 2 / eps [..., 3, N], log F of the x-y part [..., N]; then
    log F [..., N]."""
    abs_u = np.abs(points_t)
    log_ratio = np.log(np.maximum(abs_u, _TINY_M)) - np.log(scale_m)[..., None]
    scaled = (2.0 / exponents[..., [1, 1, 0]])[..., None] * log_ratio
    log_xy = np.logaddexp(scaled[..., 0, :], scaled[..., 1, :])
    ratio = exponents[..., 1, None] / exponents[..., 0, None]
    return abs_u, log_ratio, scaled, log_xy, np.logaddexp(ratio * log_xy, scaled[..., 2, :])


def log_inside_outside(
    points: FloatArray, scale_m: FloatArray, exponents: FloatArray
) -> FloatArray:
    """log F of eq. 1 for untapered superquadric-frame points [..., N, 3]. Returns [..., N].

    Computed in log space so that small exponents (box-like shapes) cannot overflow.
    """
    return _log_f(np.swapaxes(points, -1, -2), scale_m, exponents)


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
    points_t = np.swapaxes(points, -1, -2)
    forward = _radial_surface(points_t, scale_m, exponents, taper)
    surface = forward.v.copy()
    surface[..., 0, :] = _surface_x(forward, taper)
    return np.swapaxes(surface, -1, -2)


class RadialPass(NamedTuple):
    """The forward pass of the radial distance of points (coordinate rows [..., 3, N]) to
    superquadrics, kept for its gradient (:func:`radial_distance_gradient`). Per point [..., N]
    or per coordinate row [..., 3, N]: the taper coordinate y / a2 clipped to [-1, 1] and f(y)
    of eq. 2 (floored), at the point (``*_in``) and at its untapered surface point
    (``*_out``); the untapered point ``u`` [..., 3, N], its |u| and log |u| / a [..., 3, N],
    that times 2 / eps [..., 3, N]; log F of the x-y part and of eq. 1 [..., N]; the radial
    scale F^(-eps1 / 2) [..., N] and the untapered surface point ``v`` [..., 3, N]; the
    residual point - surface point [..., 3, N] and its length, the distance [..., N]
    (``residual`` and ``distance`` are None for the surface alone)."""

    points_t: FloatArray
    t_in: FloatArray
    f_in: FloatArray
    u: FloatArray
    abs_u: FloatArray
    log_ratio: FloatArray
    scaled: FloatArray
    log_xy: FloatArray
    log_f: FloatArray
    radial: FloatArray
    v: FloatArray
    t_out: FloatArray
    f_out: FloatArray
    residual: FloatArray | None = None
    distance: FloatArray | None = None


def _radial_surface(
    points_t: FloatArray, scale_m: FloatArray, exponents: FloatArray, taper: FloatArray
) -> RadialPass:
    """The forward pass of coordinate rows [..., 3, N] up to the untapered radial surface
    point (without the residual and distance)."""
    a2 = scale_m[..., 1, None]
    k1, k2, shear = taper[..., 0, None], taper[..., 1, None], shear_of(taper)[..., None]
    qx, qy = points_t[..., 0, :], points_t[..., 1, :]
    t_in = _clip_unit(qy / a2)
    f_in = _taper_value(t_in, k1, k2)
    u = _with_x(points_t, (qx - shear * qy) / f_in)
    abs_u, log_ratio, scaled, log_xy, log_f = _log_f_parts(u, scale_m, exponents)
    radial = np.exp(-0.5 * exponents[..., 0, None] * np.maximum(log_f, _MIN_LOG_F))
    v = u * radial[..., None, :]
    t_out = _clip_unit(v[..., 1, :] / a2)
    f_out = _taper_value(t_out, k1, k2)
    return RadialPass(
        points_t, t_in, f_in, u, abs_u, log_ratio, scaled, log_xy, log_f, radial, v, t_out, f_out
    )


def _surface_x(forward: RadialPass, taper: FloatArray) -> FloatArray:
    """x of the (tapered) radial surface point [..., N] of a forward pass."""
    v = forward.v
    return forward.f_out * v[..., 0, :] + shear_of(taper)[..., None] * v[..., 1, :]


def _with_x(points_t: FloatArray, x: FloatArray) -> FloatArray:
    """A copy of coordinate rows [..., 3, N] with the x row replaced by ``x`` [..., N] (the
    rows broadcast to its leading shape)."""
    out = np.empty((*x.shape[:-1], *points_t.shape[-2:]))
    out[...] = points_t
    out[..., 0, :] = x
    return out


def radial_pass(
    points_t: FloatArray, scale_m: FloatArray, exponents: FloatArray, taper: FloatArray
) -> RadialPass:
    """The forward pass of :func:`radial_distance_rows` of coordinate rows [..., 3, N] to
    superquadrics (scale [..., 3], exponents [..., 2], taper [..., 2 or 3]), with the residual
    and the distance."""
    forward = _radial_surface(points_t, scale_m, exponents, taper)
    residual = points_t - forward.v
    residual[..., 0, :] = points_t[..., 0, :] - _surface_x(forward, taper)
    distance = np.sqrt((residual * residual).sum(axis=-2))
    return forward._replace(residual=residual, distance=distance)


def radial_distance_rows(
    points_t: FloatArray, scale_m: FloatArray, exponents: FloatArray, taper: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """:func:`radial_distance_m` [..., N] of points given as coordinate rows [..., 3, N] (the
    fast layout), and log F of eq. 1 [..., N] (< 0 inside), in one pass."""
    forward = radial_pass(points_t, scale_m, exponents, taper)
    assert forward.distance is not None
    return forward.distance, forward.log_f


def radial_distance_m(
    points: FloatArray, scale_m: FloatArray, exponents: FloatArray, taper: FloatArray
) -> FloatArray:
    """Distance from each point [..., N, 3] to its radial surface point. Returns [..., N]."""
    return radial_distance_rows(np.swapaxes(points, -1, -2), scale_m, exponents, taper)[0]


def radial_distance_gradient(
    points_t: FloatArray,
    scale_m: FloatArray,
    exponents: FloatArray,
    taper: FloatArray,
    forward: RadialPass | None = None,
) -> tuple[FloatArray, FloatArray]:
    """Radial distance [..., N] (as :func:`radial_distance_m`) of untransformed
    superquadric-frame points, given as coordinate rows [..., 3, N], to superquadrics (scale
    [..., 3], exponents [..., 2], taper [..., 3]) and its analytic gradient [..., 11, N] with
    respect to (qx, qy, qz, a1, a2, a3, eps1, eps2, kappa1, kappa2, shear), by reverse-mode
    differentiation of the forward pass (``forward``: :func:`radial_pass` of these arguments,
    when already known), the three coordinates together where they are alike: few, larger
    array operations."""
    if forward is None:
        forward = radial_pass(points_t, scale_m, exponents, taper)
    residual, distance = forward.residual, forward.distance
    assert residual is not None and distance is not None
    a2 = scale_m[..., 1, None]
    eps1, eps2 = exponents[..., 0, None], exponents[..., 1, None]
    k1, k2, shear = taper[..., 0, None], taper[..., 1, None], shear_of(taper)[..., None]
    power = (2.0 / exponents[..., [1, 1, 0]])[..., None]
    qy = points_t[..., 1, :]
    t_in, f_in, u, log_ratio = forward.t_in, forward.f_in, forward.u, forward.log_ratio
    log_xy, log_f, radial, v = forward.log_xy, forward.log_f, forward.radial, forward.v
    t_out, f_out = forward.t_out, forward.f_out
    share_x = np.exp(forward.scaled[..., 0, :] - log_xy)
    share_xy = np.exp(eps2 / eps1 * log_xy - log_f)
    clipped_log_f = np.maximum(log_f, _MIN_LOG_F)
    # Backward (g_surface = -residual / distance; the gradient wrt q starts at -g_surface).
    g_surface = residual * (-1.0 / np.maximum(distance, _TINY_M))[..., None, :]
    g_f_out = g_surface[..., 0, :] * v[..., 0, :]
    g_t_out = g_f_out * _taper_slope(t_out, f_out, k1, k2) * (np.abs(v[..., 1, :] / a2) < 1.0)
    g_v = g_surface.copy()
    g_v[..., 0, :] *= f_out
    g_v[..., 1, :] += g_surface[..., 0, :] * shear + g_t_out / a2
    g_radial = (g_v * u).sum(axis=-2)
    g_log_f = (-0.5 * eps1) * radial * g_radial * (log_f > _MIN_LOG_F)
    g_xy = g_log_f * share_xy
    g_log_xy = g_xy * (eps2 / eps1)
    g_x = g_log_xy * share_x
    g_log_ratio = np.empty_like(u)
    g_log_ratio[..., 0, :] = g_x
    np.subtract(g_log_xy, g_x, out=g_log_ratio[..., 1, :])
    np.subtract(g_log_f, g_xy, out=g_log_ratio[..., 2, :])
    g_log_ratio *= power
    g_u = g_v * radial[..., None, :] + g_log_ratio / np.where(forward.abs_u > _TINY_M, u, np.inf)
    g_ux = g_u[..., 0, :] / f_in
    g_t_in = -g_ux * u[..., 0, :] * _taper_slope(t_in, f_in, k1, k2) * (np.abs(qy / a2) < 1.0)
    grad = np.empty((*distance.shape[:-1], 11, distance.shape[-1]))
    np.subtract(g_u, g_surface, out=grad[..., :3, :])
    np.subtract(g_ux, g_surface[..., 0, :], out=grad[..., 0, :])
    grad[..., 1, :] += g_t_in / a2 - g_ux * shear
    grad[..., 3:6, :] = -g_log_ratio / scale_m[..., None]
    grad[..., 4, :] -= (g_t_out * v[..., 1, :] + g_t_in * qy) / (a2 * a2)
    grad[..., 6, :] = (
        -0.5 * radial * g_radial * clipped_log_f
        - (g_xy * eps2 * log_xy + 2.0 * (g_log_f - g_xy) * log_ratio[..., 2, :]) / eps1**2
    )
    grad[..., 7, :] = (
        g_xy * log_xy / eps1
        - g_log_xy
        * 2.0
        * (share_x * log_ratio[..., 0, :] + (1.0 - share_x) * log_ratio[..., 1, :])
        / eps2**2
    )
    g_f_in = -g_ux * u[..., 0, :] * (f_in > _MIN_TAPER_FACTOR)
    g_f_out = g_f_out * (f_out > _MIN_TAPER_FACTOR)
    grad[..., 8, :] = g_f_out * t_out + g_f_in * t_in
    grad[..., 9, :] = g_f_out * t_out * t_out + g_f_in * t_in * t_in
    grad[..., 10, :] = g_surface[..., 0, :] * v[..., 1, :] - g_ux * qy
    return distance, grad


def _clip_unit(t: FloatArray) -> FloatArray:
    """t [..., N] clipped to [-1, 1] (as np.clip, without its Python-level overhead)."""
    return np.minimum(np.maximum(t, -1.0), 1.0)


def _taper_value(t: FloatArray, kappa1: FloatArray, kappa2: FloatArray) -> FloatArray:
    """f(t) of eq. 2 with its floor [..., N]."""
    return np.maximum(1.0 + kappa1 * t + kappa2 * t * t, _MIN_TAPER_FACTOR)


def _taper_slope(
    t: FloatArray, factor: FloatArray, kappa1: FloatArray, kappa2: FloatArray
) -> FloatArray:
    """df/dt of eq. 2 at t [..., N] where the floor of f (``factor``: :func:`_taper_value`) is
    not active, else 0: [..., N]."""
    return (kappa1 + 2.0 * kappa2 * t) * (factor > _MIN_TAPER_FACTOR)


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


def _arc_uniform_angles(
    exponent: float, x_scale: float, y_scale: float, lo: float, hi: float, count: int
) -> FloatArray:
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
    points = np.stack(
        np.broadcast_arrays(
            a1 * ring * _signed_power(np.cos(omega), eps2)[None, :],
            a2 * ring * _signed_power(np.sin(omega), eps2)[None, :],
            a3 * _signed_power(np.sin(eta), eps1)[:, None],
        ),
        axis=-1,
    )
    return apply_taper(points, sq.scale_m, sq.taper)


def sample_surface(sq: Superquadric, count: int, rng: np.random.Generator) -> FloatArray:
    """``count`` points spread roughly uniformly over the surface, world frame: [count, 3].

    Grid cells (even in arc length) are drawn with probability proportional to their area,
    then a point is placed uniformly in the chosen cell by bilinear interpolation.
    """
    grid = _surface_grid(sq)
    corner00, corner10 = grid[:-1, :-1], grid[1:, :-1]
    corner01, corner11 = grid[:-1, 1:], grid[1:, 1:]
    area = 0.5 * (
        np.linalg.norm(np.cross(corner10 - corner00, corner01 - corner00), axis=-1)
        + np.linalg.norm(np.cross(corner10 - corner11, corner01 - corner11), axis=-1)
    )
    cell = rng.choice(area.size, size=count, p=(area / area.sum()).ravel())
    row, col = np.unravel_index(cell, area.shape)
    u, v = rng.random((2, count, 1))
    local = (
        (1 - u) * (1 - v) * corner00[row, col]
        + u * (1 - v) * corner10[row, col]
        + (1 - u) * v * corner01[row, col]
        + u * v * corner11[row, col]
    )
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
    side_xy, side_yz, side_xz = np.hypot(a1, a2), np.hypot(a2, a3), np.hypot(a1, a3)
    box = 8.0 * (a1 * a2 + a2 * a3 + a1 * a3)
    diamond_prism = 8.0 * side_xy * a3 + 4.0 * a1 * a2
    bipyramid = 4.0 * (a1 * side_yz + a2 * side_xz)
    half_perimeter = 0.5 * (side_xy + side_yz + side_xz)
    octahedron = 8.0 * np.sqrt(
        np.maximum(
            half_perimeter
            * (half_perimeter - side_xy)
            * (half_perimeter - side_yz)
            * (half_perimeter - side_xz),
            0.0,
        )
    )
    w1, w2 = 0.5 * exponents[..., 0], 0.5 * exponents[..., 1]
    return (1 - w1) * ((1 - w2) * box + w2 * diamond_prism) + w1 * (
        (1 - w2) * bipyramid + w2 * octahedron
    )
