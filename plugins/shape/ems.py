"""EMS superquadric recovery (Liu et al., CVPR 2022) with tapering: ``shape.ems``.

Paper 1, III-B2/III-B3. Points are explained by a Gaussian around the closest surface point
(approximated radially) mixed with a uniform outlier density ``p0 = 1/V`` over the points'
bounding box. E-step: the inlier posterior of eq. 9. M-step: a few iterations of bounded
nonlinear least squares on the posterior-weighted distances, then the noise variance in closed
form. When the likelihood stops improving, similar candidates (swapped axes, the 45-degree
dual, the sign-flipped and halved taper) are tried and the best replaces the current fit
(the S-step). Multi-link objects (``fit_links``): one more link is proposed by splitting the
largest link at a seam seen from above (a gap, or a step in the top height) or on the largest
cluster of outliers (III-B3); the links are fitted jointly (hard assignment by surface density)
and kept only when a BIC on the surface-density likelihood prefers them.

Parameter vector (14, ``PARAMETER_NAMES``): a1, a2, a3, eps1, eps2, kappa1, kappa2, x, y, yaw,
z, pitch, roll, shear; rotation ``Rz(yaw) Ry(pitch) Rx(roll)``. On a table (the default)
pitch = roll = 0 and z = a3 (the base touches z = 0), leaving 8 parameters plus the 2 of the taper.

Extensions beyond the paper: the shear ``X = f(y) x + s y`` after the taper (``shear``, in
[-1, 1], fitted with the taper and flipped in the S-step; ``Superquadric.taper`` then holds
(kappa1, kappa2, shear)) so that right triangles and skewed tapers are representable; analytic
Jacobians; EM on a coarse subset, then a few iterations on ``max_fit_points``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray
from pydantic import Field
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree
from scipy.special import expit, logsumexp
from vistac.component import Component, ComponentConfig, ComponentContext
from vistac.errors import DataError
from vistac.plugins.shape.superquadric import (
    distance_to_surface_m,
    inside_outside,
    radial_depth_m,
    radial_distance_gradient,
    radial_distance_m,
    surface_area_m2,
)
from vistac.types import FloatArray, PointCloud, ShapeEstimate, Superquadric

logger = logging.getLogger(__name__)

PARAMETER_NAMES: tuple[str, ...] = (
    "a1_m", "a2_m", "a3_m", "eps1", "eps2", "kappa1", "kappa2",
    "x_m", "y_m", "yaw_rad", "z_m", "pitch_rad", "roll_rad", "shear",
)  # fmt: skip
"""Order of the full parameter vector and of ``ShapeEstimate.uncertainty`` columns."""

_SCALE, _EXPONENTS = slice(0, 3), slice(3, 5)
_A2, _A3, _KAPPA1, _KAPPA2, _X, _Y, _YAW, _Z, _PITCH, _ROLL = 1, 2, 5, 6, 7, 8, 9, 10, 11, 12
_SHEAR = 13
_TAPER = [_KAPPA1, _KAPPA2, _SHEAR]
_TAPER_INDICES = (_KAPPA1, _KAPPA2)
_SHAPE_INDICES = [0, 1, 2, 3, 4, _KAPPA1, _KAPPA2, _SHEAR]
_GENERATOR_Z = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
_GENERATOR_Y = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 0.0], [-1.0, 0.0, 0.0]])
_GENERATOR_X = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
_SHEAR_BOUND = 1.0
_TILT_INDICES = (_Z, _PITCH, _ROLL)
_MIN_SCALE_M = 0.002
_EXPONENT_BOUNDS = (0.1, 2.0)
_INIT_EXPONENT = 0.5
_INIT_PERCENTILES = (2.0, 98.0)
_FD_STEP = 1e-6
_FD_FLOOR = 0.01
_MIN_VOLUME_M3 = 1e-9
_LOG_AREA_FLOOR = np.log(1e-8)
_MIN_LINK_POINTS = 10
_REFIT_ROUNDS = 2
_PROFILE_BIN_M = 0.001
_SPAN_PERCENTILES = (1.0, 99.0)
_CUT_RANGE = (0.2, 0.8)
_GAP_BINS = 5
_GAP_SIDE_BINS = 10
_GAP_MARGIN_BINS = 2
_GAP_MAX_RATIO = 0.7
_STEP_BIN_M = 0.005
_STEP_MIN_M = 0.0025
_TOP_PERCENTILE = 90.0
_STEP_DIRECTIONS = 18
_CLEAR_GAIN_NATS = 0.2
_COARSE_FIT_POINTS = 400
_FINE_ITERATIONS = 3
_SWITCH_TRIALS = 2
_LM_INITIAL_DAMPING = 1e-2
_LM_MIN_DAMPING = 1e-6
_LM_DAMPING_FACTOR = 4.0
_LM_MIN_SCALING = 1e-12
_DENSITY_NEIGHBOURS = 8
_DENSITY_KEEP_RATIO = 2.0
_AREA_NOISE_CAP_M = 0.002
_EXCLUSION_LEVELS = (0.25, 0.5, 0.75)
_EXCLUSION_POINTS = 100
_EXCLUSION_WEIGHT = 1.0

IntArray = NDArray[np.int64]


@dataclass(frozen=True)
class EMSOptions:
    """Settings of one EMS fit (see ``EMSEstimator.Config`` for their meaning)."""

    outlier_ratio: float = 0.2
    max_iterations: int = 20
    max_switches: int = 2
    m_step_evaluations: int = 4
    tolerance_nats: float = 1e-3
    min_noise_m: float = 5e-4
    taper: bool = True
    shear: bool = True
    on_table: bool = True
    max_fit_points: int = 1000


@dataclass(frozen=True)
class EMSResult:
    """One fitted superquadric.

    params: [14] in ``PARAMETER_NAMES`` order; std: [14] standard deviations (0 where the
    parameter is fixed by the model); covariance: [14, 14]; inlier_probability: [N] posterior
    of eq. 9 per point.
    """

    superquadric: Superquadric
    params: FloatArray
    std: FloatArray
    covariance: FloatArray
    inlier_probability: FloatArray
    noise_m: float
    nll: float


@dataclass(frozen=True)
class _Problem:
    """The points to fit and what the model may vary."""

    points_m: FloatArray
    free: IntArray
    on_table: bool
    lower: FloatArray
    upper: FloatArray
    log_outlier_density: float
    options: EMSOptions
    exclusion: _Problem | None = None

    def expand(self, free_values: FloatArray, base: FloatArray) -> FloatArray:
        """Full parameter vectors [B, 14] from free values [B, F] on top of ``base`` [14]."""
        full = np.repeat(base[None, :], len(free_values), axis=0)
        full[:, self.free] = free_values
        if self.on_table:
            full[:, _Z] = full[:, _A3]
        return full

    def _local(self, full: FloatArray) -> FloatArray:
        """The points in each superquadric's frame: full [B, 14] -> [B, N, 3]."""
        rotation = rotation_zyx(full[:, _YAW], full[:, _PITCH], full[:, _ROLL])
        return np.matmul(self.points_m - full[:, None, [_X, _Y, _Z]], rotation)

    def distances(self, full: FloatArray) -> FloatArray:
        """Radial distance of every point to each superquadric: full [B, 14] -> [B, N]."""
        return radial_distance_m(self._local(full), full[:, _SCALE], full[:, _EXPONENTS],
                                 full[:, _TAPER])

    def inside(self, full: FloatArray) -> FloatArray:
        """Whether each point lies inside each superquadric: full [B, 14] -> [B, N]."""
        return inside_outside(self._local(full), full[:, _SCALE], full[:, _EXPONENTS],
                              full[:, _TAPER]) < 1

    def penetration(self, full: FloatArray) -> FloatArray:
        """Radial depth of the points inside each superquadric (0 outside): [B, N]."""
        return radial_depth_m(self._local(full), full[:, _SCALE], full[:, _EXPONENTS],
                              full[:, _TAPER])

    def distance_gradient(self, params: FloatArray) -> FloatArray:
        """Gradient [N, F] of each point's radial distance to the superquadric of params [14]
        with respect to the free parameters (on a table, a3's column includes z = a3)."""
        rotation = rotation_zyx(params[None, _YAW], params[None, _PITCH],
                                 params[None, _ROLL])[0]
        offset = self.points_m - params[[_X, _Y, _Z]]
        _, grad = radial_distance_gradient(offset @ rotation, params[_SCALE],
                                           params[_EXPONENTS], params[_TAPER])
        grad_q = grad[:, :3]
        full = np.empty((len(offset), len(PARAMETER_NAMES)))
        full[:, _SHAPE_INDICES] = grad[:, 3:]
        full[:, [_X, _Y, _Z]] = -grad_q @ rotation.T
        angles = (_YAW,) if self.on_table else (_YAW, _PITCH, _ROLL)
        for index, d_rotation in zip(angles, _rotation_derivatives(params, rotation),
                                     strict=False):
            full[:, index] = np.einsum("ij,ij->i", grad_q, offset @ d_rotation)
        if self.on_table:
            full[:, _A3] += full[:, _Z]
        return full[:, self.free]

    def log_inlier_density(self, distance_m: FloatArray, noise_var_m2: float) -> FloatArray:
        return -1.5 * np.log(2 * np.pi * noise_var_m2) - distance_m**2 / (2 * noise_var_m2)

    def log_area(self, full: FloatArray) -> FloatArray:
        """log of the approximate surface area of each superquadric: full [B, 14] -> [B]."""
        return np.log(surface_area_m2(full[:, _SCALE], full[:, _EXPONENTS], full[:, _TAPER]))

    def posterior(self, distance_m: FloatArray, noise_var_m2: float) -> FloatArray:
        """Inlier probability of eq. 9 per point: [..., N]."""
        ratio = self.options.outlier_ratio
        log_outlier = self.log_outlier_density + np.log(ratio / (1 - ratio))
        return expit(self.log_inlier_density(distance_m, noise_var_m2) - log_outlier)

    def nll(self, full: FloatArray, noise_var_m2: float) -> FloatArray:
        """Objective per superquadric, full [B, 14] -> [B]: the negative log-likelihood of the
        Gaussian-uniform mixture (eq. 4) plus the area term of eq. 7 (inlier count x log A),
        which keeps a partly seen shape from growing into the unseen space."""
        ratio = self.options.outlier_ratio
        distance = self.distances(full)
        terms = np.stack(np.broadcast_arrays(
            np.log(1 - ratio) + self.log_inlier_density(distance, noise_var_m2),
            np.log(ratio) + self.log_outlier_density,
        ))
        inliers = self.posterior(distance, noise_var_m2).sum(axis=-1)
        nll = -logsumexp(terms, axis=0).sum(axis=-1) + inliers * self.log_area(full)
        if self.exclusion is not None:
            depth = self.exclusion.penetration(full)
            nll = nll + _EXCLUSION_WEIGHT * (depth**2).sum(axis=-1) / (2 * noise_var_m2)
        return nll


def rotation_zyx(yaw: FloatArray, pitch: FloatArray, roll: FloatArray) -> FloatArray:
    """Rz(yaw) Ry(pitch) Rx(roll) for angle arrays [B]. Returns [B, 3, 3]."""
    cy, sy, cp, sp, cr, sr = (np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch),
                              np.cos(roll), np.sin(roll))
    rotation = np.empty((*np.shape(yaw), 3, 3))
    rotation[..., 0, 0], rotation[..., 0, 1] = cy * cp, cy * sp * sr - sy * cr
    rotation[..., 0, 2], rotation[..., 1, 0] = cy * sp * cr + sy * sr, sy * cp
    rotation[..., 1, 1], rotation[..., 1, 2] = sy * sp * sr + cy * cr, sy * sp * cr - cy * sr
    rotation[..., 2, 0], rotation[..., 2, 1], rotation[..., 2, 2] = -sp, cp * sr, cp * cr
    return rotation


def _rotation_derivatives(params: FloatArray, rotation: FloatArray) -> list[FloatArray]:
    """d R / d (yaw, pitch, roll) [3 x (3, 3)] of R = Rz Ry Rx (``rotation``) at params [14]."""
    zero = np.zeros(1)
    yaw_part = rotation_zyx(params[None, _YAW], zero, zero)[0]
    tilt = rotation_zyx(zero, params[None, _PITCH], params[None, _ROLL])[0]
    return [_GENERATOR_Z @ rotation, yaw_part @ _GENERATOR_Y @ tilt, rotation @ _GENERATOR_X]


def _euler_zyx(rotation: FloatArray) -> tuple[float, float, float]:
    """(yaw, pitch, roll) of a rotation matrix [3, 3] (inverse of :func:`rotation_zyx`)."""
    pitch = float(np.arctan2(-rotation[2, 0], np.hypot(rotation[0, 0], rotation[1, 0])))
    yaw = float(np.arctan2(rotation[1, 0], rotation[0, 0]))
    roll = float(np.arctan2(rotation[2, 1], rotation[2, 2]))
    return yaw, pitch, roll


def _pose(params: FloatArray) -> FloatArray:
    """world_from_sq [4, 4] of a parameter vector [14]."""
    pose = np.eye(4)
    pose[:3, :3] = rotation_zyx(params[None, _YAW], params[None, _PITCH], params[None, _ROLL])[0]
    pose[:3, 3] = params[[_X, _Y, _Z]]
    return pose


def to_superquadric(params: FloatArray) -> Superquadric:
    """The :class:`Superquadric` of a parameter vector [14]."""
    return Superquadric(params[_SCALE].copy(), params[_EXPONENTS].copy(), _pose(params),
                        params[_TAPER].copy())


# ---------------------------------------------------------------------------------------------
# Set-up: initial guess, bounds


def _principal_frame(points_m: FloatArray, on_table: bool) -> FloatArray:
    """Rotation [3, 3] with y along the major principal axis (the taper's axis) and, off the
    table, z along the minor one; on a table only the yaw is free."""
    centred = points_m - points_m.mean(axis=0)
    if on_table:
        _, vectors = np.linalg.eigh(centred[:, :2].T @ centred[:, :2])
        yaw = float(np.arctan2(vectors[1, 1], vectors[0, 1])) - np.pi / 2
        return rotation_zyx(np.array([yaw]), np.zeros(1), np.zeros(1))[0]
    _, vectors = np.linalg.eigh(centred.T @ centred)
    frame = vectors[:, [1, 2, 0]].copy()
    frame[:, 2] = np.cross(frame[:, 0], frame[:, 1])
    return frame


def _dense_mask(points_m: FloatArray) -> NDArray[np.bool_]:
    """Mask [N] of the points whose distance to their ``_DENSITY_NEIGHBOURS``-th neighbour is
    at most ``_DENSITY_KEEP_RATIO`` times the median: surface points, without most uniform
    outliers (which would otherwise inflate the initial extent, notably towards unseen
    sides)."""
    if len(points_m) <= 2 * _DENSITY_NEIGHBOURS:
        return np.ones(len(points_m), dtype=bool)
    spacing = cKDTree(points_m).query(points_m, _DENSITY_NEIGHBOURS + 1)[0][:, -1]
    return np.asarray(spacing <= _DENSITY_KEEP_RATIO * np.median(spacing))


def _initial_params(points_m: FloatArray, on_table: bool) -> FloatArray:
    """Initial guess [14]: principal axes and robust extents of the dense points, exponents
    0.5, no taper."""
    points_m = points_m[_dense_mask(points_m)]
    frame = _principal_frame(points_m, on_table)
    low, high = np.percentile(points_m @ frame, _INIT_PERCENTILES, axis=0)
    half = np.maximum(0.5 * (high - low), _MIN_SCALE_M)
    centre = frame @ (0.5 * (high + low))
    params = np.zeros(len(PARAMETER_NAMES))
    params[_SCALE] = half
    params[_EXPONENTS] = _INIT_EXPONENT
    params[[_X, _Y, _Z]] = centre
    params[[_YAW, _PITCH, _ROLL]] = _euler_zyx(frame)
    if on_table:
        params[_A3] = max(0.5 * float(np.percentile(points_m[:, 2], _INIT_PERCENTILES[1])),
                          _MIN_SCALE_M)
        params[_Z] = params[_A3]
    return params


def _bounds(points_m: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Lower and upper bounds [14] from the extent of the points."""
    low, high = points_m.min(axis=0), points_m.max(axis=0)
    extent = float(np.max(high - low))
    lower = np.array([_MIN_SCALE_M] * 3 + [_EXPONENT_BOUNDS[0]] * 2 + [-1.0, 0.0]
                     + list(low[:2] - extent) + [-np.inf, low[2] - extent, -np.inf, -np.inf]
                     + [-_SHEAR_BOUND])
    upper = np.array([extent] * 3 + [_EXPONENT_BOUNDS[1]] * 2 + [1.0, 1.0]
                     + list(high[:2] + extent) + [np.inf, high[2] + extent, np.inf, np.inf]
                     + [_SHEAR_BOUND])
    return lower, upper


def _free_indices(options: EMSOptions) -> IntArray:
    fixed = set(_TILT_INDICES if options.on_table else ())
    fixed |= set(() if options.taper else _TAPER_INDICES)
    fixed |= set(() if options.taper and options.shear else (_SHEAR,))
    return np.array([i for i in range(len(PARAMETER_NAMES)) if i not in fixed], dtype=np.int64)


def _make_problem(points_m: FloatArray, options: EMSOptions,
                  excluded_m: FloatArray | None = None) -> _Problem:
    """The problem of fitting points [N, 3]; with ``excluded_m`` [M, 3], points that the
    superquadric must not enclose (the hidden volume of other links): their radial depth
    inside is penalised."""
    lower, upper = _bounds(points_m)
    volume_m3 = max(float(np.prod(np.ptp(points_m, axis=0))), _MIN_VOLUME_M3)
    free = _free_indices(options)
    exclusion = (None if excluded_m is None or len(excluded_m) == 0 else
                 _Problem(excluded_m, free, options.on_table, lower, upper, 0.0, options))
    return _Problem(points_m, free, options.on_table, lower, upper, -np.log(volume_m3),
                    options, exclusion)


# ---------------------------------------------------------------------------------------------
# EM with switching


def _m_step(problem: _Problem, params: FloatArray, weights: FloatArray,
            noise_var_m2: float) -> FloatArray:
    """A few bounded Levenberg-Marquardt steps on eq. 7 (times 2 sigma^2): the residuals are
    sqrt(p_i) * distance_i and one area residual. Returns the new params [14].

    The steps solve the small normal equations [F, F] (Marquardt's diagonal scaling) and are
    clipped to the bounds; unlike an SVD of the [N + 1, F] Jacobian this stays fast when the
    BLAS would spread small factorisations over several threads."""
    free = problem.free
    lower, upper = problem.lower[free], problem.upper[free]
    residuals = _Residuals(problem, params, weights, noise_var_m2)
    x = np.clip(params[free], lower, upper)
    value = residuals(x)
    cost, damping = float(value @ value), _LM_INITIAL_DAMPING
    jac = residuals.jacobian(x)
    for _ in range(problem.options.m_step_evaluations):
        normal = jac.T @ jac
        scaling = np.maximum(np.diag(normal), _LM_MIN_SCALING)
        step = np.linalg.solve(normal + damping * np.diag(scaling), -(jac.T @ value))
        trial = np.clip(x + step, lower, upper)
        trial_value = residuals(trial)
        trial_cost = float(trial_value @ trial_value)
        if trial_cost < cost:
            x, value, cost = trial, trial_value, trial_cost
            damping = max(damping / _LM_DAMPING_FACTOR, _LM_MIN_DAMPING)
            jac = residuals.jacobian(x)
        else:
            damping *= _LM_DAMPING_FACTOR
    return problem.expand(x[None, :], params)[0]


class _Residuals:
    """Weighted distances [N] and the area residual [1] of eq. 7 as a function of the free
    parameters [F]; the Jacobian [N + 1, F]: analytic for the distances, forward differences
    for the (cheap) area residual."""

    def __init__(self, problem: _Problem, base: FloatArray, weights: FloatArray,
                 noise_var_m2: float) -> None:
        self.problem, self.base = problem, base
        self.sqrt_w = np.sqrt(weights)
        # sigma^2 is capped in the area term: while the fit is still coarse (large sigma) the
        # area term would otherwise shrink the superquadric to nothing.
        self.area_gain = 2.0 * min(noise_var_m2, _AREA_NOISE_CAP_M**2) * float(weights.sum())

    def batch(self, free_values: FloatArray) -> FloatArray:
        full = self.problem.expand(free_values, self.base)
        distance = self.sqrt_w * self.problem.distances(full)
        out = [distance, self.area_residual(full)[:, None]]
        if self.problem.exclusion is not None:
            out.append(np.sqrt(_EXCLUSION_WEIGHT) * self.problem.exclusion.penetration(full))
        return np.hstack(out)

    def __call__(self, x: FloatArray) -> FloatArray:
        return self.batch(x[None, :])[0]

    def jacobian(self, x: FloatArray) -> FloatArray:
        full = self.problem.expand(x[None, :], self.base)
        grad = self.problem.distance_gradient(full[0])
        step = _FD_STEP * np.maximum(np.abs(x), _FD_FLOOR)
        area = self.area_residual(self.problem.expand(np.vstack([x, x + np.diag(step)]),
                                                      self.base))
        rows = [self.sqrt_w[:, None] * grad, (area[1:] - area[0]) / step]
        exclusion = self.problem.exclusion
        if exclusion is not None:
            inside = exclusion.inside(full)[0]
            rows.append(np.sqrt(_EXCLUSION_WEIGHT) * inside[:, None]
                        * exclusion.distance_gradient(full[0]))
        return np.vstack(rows)

    def area_residual(self, full: FloatArray) -> FloatArray:
        """sqrt(gain (log A - floor)) per superquadric: full [B, 14] -> [B]."""
        return np.sqrt(self.area_gain * (self.problem.log_area(full) - _LOG_AREA_FLOOR))


def _noise_var(problem: _Problem, distance_m: FloatArray, weights: FloatArray) -> float:
    var = float(np.sum(weights * distance_m**2) / (3 * max(float(np.sum(weights)), 1e-9)))
    return max(var, problem.options.min_noise_m**2)


def _candidates(params: FloatArray, options: EMSOptions) -> FloatArray:
    """Similar superquadrics to try when EM is stuck: [C, 14]."""
    swapped = params.copy()
    if options.on_table:
        swapped[[0, 1]] = params[[1, 0]]
        swapped[_YAW] += np.pi / 2
        out = [swapped]
    else:
        out = [_cyclic_axes(params, shift) for shift in (1, 2)]
    if 0.6 < params[0] / params[1] < 1.4:
        out.append(_dual(params))
    if options.taper:
        flipped = params.copy()
        flipped[_KAPPA1] = -params[_KAPPA1]
        halved = params.copy()
        halved[_TAPER] = 0.5 * params[_TAPER]
        out += [flipped, halved]
    if options.taper and options.shear:
        sheared = params.copy()
        sheared[_SHEAR] = -params[_SHEAR]
        out.append(sheared)
    return np.array(out)


def _cyclic_axes(params: FloatArray, shift: int) -> FloatArray:
    """The same box-like extent with the axes renamed cyclically (exponents swapped)."""
    order = np.roll(np.arange(3), -shift)
    frame = to_superquadric(params).world_from_sq[:3, :3][:, order]
    out = params.copy()
    out[_SCALE] = params[_SCALE][order]
    out[_EXPONENTS] = params[_EXPONENTS][::-1]
    out[[_YAW, _PITCH, _ROLL]] = _euler_zyx(frame)
    return out


def _dual(params: FloatArray) -> FloatArray:
    """The 45-degree dual of a near-square cross-section (eps2 -> 2 - eps2, Liu et al.)."""
    eps2 = params[4]
    side = min(params[0], params[1])
    gain = ((1 - np.sqrt(2)) * eps2 + np.sqrt(2) if eps2 <= 1
            else (np.sqrt(2) / 2 - 1) * eps2 + 2 - np.sqrt(2) / 2)
    out = params.copy()
    out[[0, 1]] = gain * side
    out[4] = 2 - eps2
    out[_YAW] += np.pi / 4
    return out


@dataclass
class _State:
    params: FloatArray
    noise_var_m2: float
    nll: float


def _em_iteration(problem: _Problem, state: _State) -> _State:
    weights = problem.posterior(problem.distances(state.params[None])[0], state.noise_var_m2)
    params = _m_step(problem, state.params, weights, state.noise_var_m2)
    noise_var = _noise_var(problem, problem.distances(params[None])[0], weights)
    return _State(params, noise_var, float(problem.nll(params[None], noise_var)[0]))


def _switch(problem: _Problem, state: _State) -> _State | None:
    """The S-step: of the ``_SWITCH_TRIALS`` most likely candidates, the first that improves
    after one EM iteration, or None."""
    candidates = _candidates(state.params, problem.options)
    candidates = np.clip(candidates, problem.lower, problem.upper)
    if problem.on_table:
        candidates[:, _Z] = candidates[:, _A3]
    nll = problem.nll(candidates, state.noise_var_m2)
    for index in np.argsort(nll)[:_SWITCH_TRIALS]:
        trial = _em_iteration(problem, _State(candidates[index], state.noise_var_m2, nll[index]))
        if trial.nll < state.nll - problem.options.tolerance_nats * len(problem.points_m):
            logger.debug("EMS switched to candidate %d (nll %.1f -> %.1f)", index, state.nll,
                         trial.nll)
            return trial
    return None


def _run_ems(problem: _Problem, params: FloatArray, max_iterations: int,
             max_switches: int, noise_var_m2: float | None = None) -> _State:
    """EM from params [14] until the likelihood stops improving, with up to ``max_switches``
    S-steps. The noise variance starts at ``noise_var_m2`` (a coarser fit's) or, without it,
    from the closest 1 - w0 of the points (w0 the outlier ratio): counting the outliers too
    would start EM so loose that it spreads the shape into the unseen side of a partial
    view."""
    if noise_var_m2 is None:
        distance = problem.distances(params[None])[0]
        inlier = distance <= np.quantile(distance, 1 - problem.options.outlier_ratio)
        noise_var_m2 = _noise_var(problem, distance, inlier)
    state = _State(params, noise_var_m2, float(problem.nll(params[None], noise_var_m2)[0]))
    switches = 0
    tolerance = problem.options.tolerance_nats * len(problem.points_m)
    for _ in range(max_iterations):
        new_state = _em_iteration(problem, state)
        improved = state.nll - new_state.nll > tolerance
        state = new_state if new_state.nll < state.nll else state
        if improved:
            continue
        if switches >= max_switches:
            break
        switches += 1
        switched = _switch(problem, state)
        if switched is None:
            break
        state = switched
    return state


def _parameter_covariance(problem: _Problem, params: FloatArray, weights: FloatArray,
                          noise_var_m2: float) -> FloatArray:
    """Covariance [14, 14] from the Jacobian at the optimum, (J^T J)^-1 s^2; zero rows and
    columns for fixed parameters (on a table z = a3, so z copies a3's)."""
    residuals = _Residuals(problem, params, weights, noise_var_m2)
    jac = residuals.jacobian(params[problem.free])
    residual = residuals(params[problem.free])[:-1]
    dof = max(float(weights.sum()) - len(problem.free), 1.0)
    free_cov = np.linalg.pinv(jac.T @ jac) * float(residual @ residual) / dof
    cov = np.zeros((len(PARAMETER_NAMES), len(PARAMETER_NAMES)))
    cov[np.ix_(problem.free, problem.free)] = 0.5 * (free_cov + free_cov.T)
    if problem.on_table:
        cov[_Z, :], cov[:, _Z] = cov[_A3, :], cov[:, _A3]
        cov[_Z, _Z] = cov[_A3, _A3]
    return cov


def _canonical(params: FloatArray, options: EMSOptions) -> FloatArray:
    """Resolve symmetries: kappa1 >= 0 (yaw + pi flips it); angles wrapped to (-pi, pi]."""
    out = params.copy()
    if out[_KAPPA1] < 0:
        out[_KAPPA1] = -out[_KAPPA1]
        out[_YAW] += np.pi
    period = 2 * np.pi if options.taper else np.pi
    if options.on_table:
        out[_YAW] = (out[_YAW] + period / 2) % period - period / 2
    else:
        out[[_YAW, _PITCH, _ROLL]] = _euler_zyx(to_superquadric(out).world_from_sq[:3, :3])
    return out


def fit_superquadric(points_m: FloatArray, options: EMSOptions,
                     excluded_m: FloatArray | None = None,
                     initial: EMSResult | None = None) -> EMSResult:
    """Fit one (tapered) superquadric to points [N, 3] (N >= 10, finite) by EMS: from the
    points' extent, or warm-started from ``initial`` (its parameters and noise, no switching).

    EM with switching runs on a fixed random subset of ``_COARSE_FIT_POINTS``, then at most
    ``_FINE_ITERATIONS`` EM iterations refine it on ``max_fit_points`` (a superset); the
    inlier probabilities and the uncertainty use all points.
    """
    order = np.random.default_rng(0).permutation(len(points_m))
    subset = points_m[order[: options.max_fit_points]]
    coarse = subset[: min(_COARSE_FIT_POINTS, len(subset))]
    problem = _make_problem(coarse, options, excluded_m)
    if initial is None:
        state = _run_ems(problem, _initial_params(subset, options.on_table),
                         options.max_iterations, options.max_switches)
    else:
        state = _run_ems(problem, initial.params, options.max_iterations, 0,
                         initial.noise_m**2)
    if len(subset) > len(coarse):
        state = _run_ems(_make_problem(subset, options, excluded_m), state.params,
                         _FINE_ITERATIONS, 0, state.noise_var_m2)
    params = _canonical(state.params, options)
    problem = _make_problem(points_m, options)
    weights = problem.posterior(problem.distances(params[None])[0], state.noise_var_m2)
    cov = _parameter_covariance(problem, params, weights, state.noise_var_m2)
    return EMSResult(to_superquadric(params), params, np.sqrt(np.clip(np.diag(cov), 0.0, None)),
                     cov, weights, float(np.sqrt(state.noise_var_m2)), state.nll)


# ---------------------------------------------------------------------------------------------
# Multi-link recovery (III-B3)


def largest_cluster(points_m: FloatArray, radius_m: float) -> IntArray:
    """Indices [K] of the largest group of points chained by gaps <= radius_m (DBSCAN with
    min_samples = 1: single-linkage clusters)."""
    pairs = cKDTree(points_m).query_pairs(radius_m, output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])),
                       shape=(len(points_m), len(points_m)))
    _, labels = connected_components(graph, directed=False)
    return np.flatnonzero(labels == np.bincount(labels).argmax())


def fit_links(points_m: FloatArray, options: EMSOptions, max_links: int,
              outlier_threshold_points: int, cluster_radius_m: float,
              previous: list[EMSResult] | None = None) -> list[EMSResult]:
    """Fit superquadrics to points [N, 3], one more at a time while the model selection of
    :func:`_evidence_gain` prefers it (at most ``max_links``).

    With the links of an earlier fit of the same object (``previous``, the last view), those
    links are also refitted once, each from where it was, and kept when they explain the
    points better than the search's result: the split found from one view's seam can be poor
    in the next, and a good split found earlier is not lost.

    Each step tries, in turn, to split the largest link where the view from above shows a
    seam (:func:`_split_labels`) and to add a link on the largest cluster of unexplained points
    (III-B3, when at least ``outlier_threshold_points``); the links of a proposal are fitted
    jointly (:func:`_fit_jointly`) and kept only when they explain the points better.
    """
    links = [fit_superquadric(points_m, options)]
    while len(links) < max_links:
        proposal = _best_proposal(points_m, links, options, outlier_threshold_points,
                                  cluster_radius_m)
        if proposal is None:
            break
        links = proposal
    if previous is not None and 1 < len(previous) <= max_links:
        again = _fit_jointly(points_m, _assign(points_m, previous), options, 1, previous)
        if again is not None and _evidence_gain(points_m, links, again, options) > 0:
            return again
    return links


def _best_proposal(points_m: FloatArray, links: list[EMSResult], options: EMSOptions,
                   outlier_threshold_points: int,
                   cluster_radius_m: float) -> list[EMSResult] | None:
    """The first proposal of one more link whose evidence gain exceeds its threshold, both
    fitted from the proposal's labels and refitted jointly; None when none is accepted."""
    for labels, min_gain in _proposals(points_m, links, options, outlier_threshold_points,
                                       cluster_radius_m):
        threshold = min_gain * len(points_m)
        proposal = _fit_jointly(points_m, labels, options, 1)
        if proposal is None or _evidence_gain(points_m, links, proposal, options) <= threshold:
            continue
        refined = _fit_jointly(points_m, _assign(points_m, proposal), options, _REFIT_ROUNDS,
                               proposal)
        if refined is not None and (_evidence_gain(points_m, links, refined, options)
                                    > threshold):
            logger.debug("EMS: %d links accepted", len(refined))
            return refined
    return None


def _proposals(points_m: FloatArray, links: list[EMSResult], options: EMSOptions,
               outlier_threshold_points: int,
               cluster_radius_m: float) -> list[tuple[IntArray, float]]:
    """The models with one more link to try: point labels [N] (link index per point) and the
    evidence gain per point that the model must exceed. A gap seen from above is itself
    evidence of two parts, so there any BIC gain will do; a step in height or an outlier
    cluster must explain the points clearly better (``_CLEAR_GAIN_NATS`` per point), since an
    imperfect fit of one part leaves such structure too."""
    labels = _assign(points_m, links)
    largest = int(np.bincount(labels).argmax())
    proposals = [(np.where(mask, len(links), labels), 0.0 if at_gap else _CLEAR_GAIN_NATS)
                 for mask, at_gap in _split_masks(points_m, labels == largest)]
    explained = np.max([link.inlier_probability for link in links], axis=0) >= 0.5
    unexplained = np.flatnonzero(~explained)
    if len(unexplained) >= outlier_threshold_points:
        cluster = unexplained[largest_cluster(points_m[unexplained], cluster_radius_m)]
        if len(cluster) >= outlier_threshold_points:
            with_cluster = labels.copy()
            with_cluster[cluster] = len(links)
            proposals.append((with_cluster, _CLEAR_GAIN_NATS))
    return proposals


def _split_masks(points_m: FloatArray, own: FloatArray) -> list[tuple[FloatArray, bool]]:
    """Masks [N] of the points of ``own`` (mask [N]) beyond a seam seen from above, with
    whether it is a gap: a gap across the major axis of their footprint (:func:`_gap_cut`),
    else the line across which the top height steps most clearly (:func:`_step_cut`, over
    ``_STEP_DIRECTIONS`` directions); empty where there is neither."""
    footprint = points_m[own, :2] - points_m[own, :2].mean(axis=0)
    major = np.linalg.eigh(footprint.T @ footprint)[1][:, -1]
    direction, cut, at_gap = major, _gap_cut(footprint @ major), True
    if cut is None:
        angles = np.arctan2(major[1], major[0]) + np.linspace(0, np.pi, _STEP_DIRECTIONS,
                                                                endpoint=False)
        directions = np.column_stack([np.cos(angles), np.sin(angles)])
        steps = [_step_cut(footprint @ d, points_m[own, 2]) for d in directions]
        best = int(np.argmax([gain for gain, _ in steps]))
        if steps[best][0] <= 0:
            return []
        direction, cut, at_gap = directions[best], steps[best][1], False
    mask = np.zeros(len(points_m), dtype=bool)
    mask[np.flatnonzero(own)[footprint @ direction > cut]] = True
    return [(mask, at_gap)]


def _middle_bins(edges: FloatArray) -> FloatArray:
    """Mask [B] of the positions ``edges`` [B] within ``_CUT_RANGE`` of their span."""
    low, high = edges[0] + np.multiply(_CUT_RANGE, edges[-1] - edges[0])
    return (edges >= low) & (edges <= high)


def _gap_cut(along_m: FloatArray) -> float | None:
    """Centre of the emptiest slab across the middle of the points' span (coordinates [N]
    along the axis): a window of ``_GAP_BINS`` bins holding less than ``_GAP_MAX_RATIO``
    of the mean density of ``_GAP_SIDE_BINS`` bins on either side (after a margin of
    ``_GAP_MARGIN_BINS``); None where no slab is that empty."""
    low, high = np.percentile(along_m, _SPAN_PERCENTILES)
    counts = np.histogram(along_m, np.arange(low, high, _PROFILE_BIN_M))[0]
    total = np.concatenate([[0], np.cumsum(counts)])
    width, side, margin = _GAP_BINS, _GAP_SIDE_BINS, _GAP_MARGIN_BINS
    start = np.arange(side + margin, len(counts) - width - side - margin + 1)
    if len(start) == 0:
        return None
    inside = (total[start + width] - total[start]) / width
    left = (total[start - margin] - total[start - margin - side]) / side
    right = (total[start + width + margin + side] - total[start + width + margin]) / side
    ratio = inside / np.maximum(0.5 * (left + right), 1.0)
    centre = low + (start + 0.5 * width) * _PROFILE_BIN_M
    ratio[~_middle_bins(np.concatenate([[low], centre, [high]]))[1:-1]] = np.inf
    best = int(np.argmin(ratio))
    return float(centre[best]) if ratio[best] < _GAP_MAX_RATIO else None


def _step_cut(along_m: FloatArray, height_m: FloatArray) -> tuple[float, float]:
    """The best cut on coordinates [N] between two levels of the top height (the
    ``_TOP_PERCENTILE`` of the heights [N] per ``_STEP_BIN_M`` bin): (the drop of the mean
    absolute deviation of the bins' top from one median to one per side, the cut). The gain
    is 0 where the cut falls outside the middle of the span or the levels differ by less
    than ``_STEP_MIN_M``."""
    top, position = _top_profile(along_m, height_m)
    cuts = [c for c in range(1, len(top))
            if _middle_bins(np.array([position[0], position[c], position[-1]]))[1]]
    if not cuts:
        return 0.0, 0.0
    cost = [np.abs(top[:c] - np.median(top[:c])).sum() + np.abs(top[c:] - np.median(top[c:])).sum()
            for c in cuts]
    best = cuts[int(np.argmin(cost))]
    if abs(float(np.median(top[:best]) - np.median(top[best:]))) < _STEP_MIN_M:
        return 0.0, 0.0
    gain = (float(np.abs(top - np.median(top)).sum()) - min(cost)) / len(top)
    return gain, float(position[best])


def _top_profile(along_m: FloatArray, height_m: FloatArray) -> tuple[FloatArray, FloatArray]:
    """The ``_TOP_PERCENTILE`` of the heights [N] in each ``_STEP_BIN_M`` bin of the
    coordinates [N] holding at least ``_MIN_LINK_POINTS`` points, and the bins' lower edges:
    ([B], [B])."""
    low, high = np.percentile(along_m, _SPAN_PERCENTILES)
    keep = (along_m >= low) & (along_m < high)
    index = ((along_m[keep] - low) / _STEP_BIN_M).astype(np.int64)
    order = np.lexsort((height_m[keep], index))
    counts = np.bincount(index)
    rank = np.cumsum(counts) - counts + (_TOP_PERCENTILE / 100 * (counts - 1)).astype(np.int64)
    filled = np.flatnonzero(counts >= _MIN_LINK_POINTS)
    return height_m[keep][order][rank[filled]], low + filled * _STEP_BIN_M


def _link_log_density(points_m: FloatArray, links: list[EMSResult]) -> FloatArray:
    """log of each link's surface density at each point [K, N]: a Gaussian of the radial
    distance (the link's noise) over the surface, uniform on its area."""
    distance = np.array([distance_to_surface_m(link.superquadric, points_m) for link in links])
    var = np.array([link.noise_m**2 for link in links])[:, None]
    params = np.array([link.params for link in links])
    area = surface_area_m2(params[:, _SCALE], params[:, _EXPONENTS], params[:, _TAPER])
    return -0.5 * np.log(2 * np.pi * var) - distance**2 / (2 * var) - np.log(area)[:, None]


def _assign(points_m: FloatArray, links: list[EMSResult]) -> IntArray:
    """Index [N] of the link of highest surface density at each point."""
    return np.argmax(_link_log_density(points_m, links), axis=0).astype(np.int64)


def _surface_nll(points_m: FloatArray, links: list[EMSResult], options: EMSOptions) -> float:
    """Negative log-likelihood of points [N, 3] under the links' surface densities mixed by
    their shares of the points, and the uniform outlier density of the bounding box."""
    log_density = _link_log_density(points_m, links)
    share = np.bincount(np.argmax(log_density, axis=0), minlength=len(links)) / len(points_m)
    ratio = options.outlier_ratio
    inlier = logsumexp(np.log(1 - ratio) + np.log(np.maximum(share, 1e-9))[:, None]
                       + log_density, axis=0)
    outlier = np.log(ratio) + _make_problem(points_m, options).log_outlier_density
    return -float(np.logaddexp(inlier, outlier).sum())


def _evidence_gain(points_m: FloatArray, links: list[EMSResult], proposal: list[EMSResult],
                   options: EMSOptions) -> float:
    """BIC difference (nats) in favour of ``proposal`` over ``links``: the drop of
    :func:`_surface_nll` less half a log(N) per extra free parameter."""
    extra = (len(proposal) - len(links)) * (len(_free_indices(options)) + 1)
    return (_surface_nll(points_m, links, options) - _surface_nll(points_m, proposal, options)
            - 0.5 * extra * np.log(len(points_m)))


def _fit_jointly(points_m: FloatArray, labels: IntArray, options: EMSOptions, rounds: int,
                 initial: list[EMSResult] | None = None) -> list[EMSResult] | None:
    """Links fitted to the points [N, 3] of each label [N] (0 .. K-1), then for ``rounds`` - 1
    more rounds each point is given to the link of highest surface density and the links are
    refitted, each from its previous fit (the first round from ``initial`` when given, one
    link per label); None when a link is left with fewer than ``_MIN_LINK_POINTS``."""
    links: list[EMSResult] | None = initial
    dense = _dense_mask(points_m)
    for round_index in range(rounds):
        if round_index:
            labels = _assign(points_m, links or [])
        counts = np.bincount(labels, minlength=int(labels.max()) + 1)
        if counts.min() < _MIN_LINK_POINTS:
            return None
        links = [_over_all_points(fit_superquadric(
            points_m[labels == k], options,
            _hidden_volume(points_m[(labels != k) & dense], options),
            None if links is None else links[k]), points_m, options)
            for k in range(len(counts))]
    return links


def _hidden_volume(dense_m: FloatArray, options: EMSOptions) -> FloatArray | None:
    """Points [M, 3] inside the other links, which a link must not enclose: on a table, the
    columns below (a subset of) their dense points [K, 3] at ``_EXCLUSION_LEVELS`` of their
    height; None off the table or with too few points."""
    if not options.on_table or len(dense_m) < _MIN_LINK_POINTS:
        return None
    dense = dense_m[np.random.default_rng(0).permutation(len(dense_m))[:_EXCLUSION_POINTS]]
    levels = np.asarray(_EXCLUSION_LEVELS)
    columns = np.repeat(dense[None, :, :], len(levels), axis=0)
    columns[:, :, 2] *= levels[:, None]
    return columns.reshape(-1, 3)


def _over_all_points(link: EMSResult, points_m: FloatArray, options: EMSOptions) -> EMSResult:
    """``link`` with its inlier probabilities evaluated for all points [N, 3]."""
    distance = distance_to_surface_m(link.superquadric, points_m)
    probability = _make_problem(points_m, options).posterior(distance, link.noise_m**2)
    return replace(link, inlier_probability=probability)


# ---------------------------------------------------------------------------------------------
# The component


class EMSEstimator(Component):
    """Superquadric shape estimator ``shape.ems`` (one superquadric per link).

    Successive fits (the growing cloud of one perception) start from the links of the last
    fit where it found more than one (see :func:`fit_links`)."""

    kind = "shape_estimator"

    class Config(ComponentConfig):
        outlier_ratio: float = Field(0.2, gt=0, lt=1, description="prior outlier probability w0")
        max_iterations: int = Field(20, gt=0, description="EM iterations per fit")
        max_switches: int = Field(2, ge=0, description="S-steps (candidate switches) per fit")
        m_step_evaluations: int = Field(4, gt=0, description="least-squares evaluations per M")
        taper: bool = Field(True, description="fit the tapering of eq. 2")
        shear: bool = Field(True, description="with taper: fit the shear (beyond the paper)")
        on_table: bool = Field(True, description="yaw-only rotation, base on the table z = 0")
        table_clearance_m: float = Field(0.008, ge=0, description="drop points below this z")
        min_points: int = Field(50, ge=10, description="fewer points above the table: error")
        min_noise_m: float = Field(5e-4, gt=0, description="floor of the noise estimate")
        max_fit_points: int = Field(1000, ge=10, description="EM runs on a subset this big")
        max_links: int = Field(1, ge=1, description="superquadrics to fit at most (III-B3)")
        outlier_threshold_points: int = Field(
            100, ge=1, description="O_th: stop adding links below this many unexplained points")
        cluster_radius_m: float = Field(0.01, gt=0, description="DBSCAN radius for outliers")

    def __init__(self, config: Config, ctx: ComponentContext) -> None:
        super().__init__(config, ctx)
        self.config: EMSEstimator.Config = config
        self.options = EMSOptions(
            outlier_ratio=config.outlier_ratio, max_iterations=config.max_iterations,
            max_switches=config.max_switches, m_step_evaluations=config.m_step_evaluations,
            min_noise_m=config.min_noise_m, taper=config.taper, shear=config.shear,
            on_table=config.on_table,
            max_fit_points=config.max_fit_points,
        )
        self._previous_links: list[EMSResult] | None = None

    def fit(self, cloud: PointCloud) -> ShapeEstimate:
        """Fit the object in ``cloud`` (world frame, table at z = 0 may be included)."""
        points = self._object_points(cloud)
        links = fit_links(points, self.options, self.config.max_links,
                          self.config.outlier_threshold_points, self.config.cluster_radius_m,
                          self._previous_links)
        self._previous_links = links
        inlier = np.max([link.inlier_probability for link in links], axis=0) >= 0.5
        logger.info("EMS: %d link(s) from %d points, %d inliers", len(links), len(points),
                    int(inlier.sum()))
        return ShapeEstimate(
            links=tuple(link.superquadric for link in links),
            initial_poses=np.array([link.params[[_X, _Y, _YAW]] for link in links]),
            uncertainty=np.array([link.std for link in links]),
            cloud=PointCloud(points[inlier]),
            covariance=np.array([link.covariance for link in links]),
        )

    def _object_points(self, cloud: PointCloud) -> FloatArray:
        """The finite points above the table clearance: [N, 3]; DataError when too few."""
        points = np.asarray(cloud.points_m, dtype=np.float64)
        if points.ndim != 2 or points.shape[1] != 3 or len(points) == 0:
            raise DataError(f"shape.ems: the point cloud is empty (shape {points.shape}); "
                            "check the camera and the segmentation")
        if not np.all(np.isfinite(points)):
            raise DataError("shape.ems: the point cloud contains NaN or inf points; drop "
                            "invalid depth pixels before fitting")
        clearance = self.config.table_clearance_m
        above = points[points[:, 2] > clearance] if self.config.on_table else points
        if len(above) < self.config.min_points:
            raise DataError(
                f"shape.ems: only {len(above)} of {len(points)} points lie above the table "
                f"(z > {clearance} m), fewer than min_points = {self.config.min_points}; "
                "is the object in view? Move the camera closer, add views, or lower "
                "min_points / table_clearance_m")
        return above
