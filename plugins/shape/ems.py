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

Speed: the fits of one step (the links of a joint fit; the single link and the last view's
links refitted) run as one batch, each row with its own EM, S-step and Levenberg-Marquardt
state, so that each array operation serves all of them; a Jacobian is computed only when a
step is accepted and will be used, and distances, the other links' excluded points and
covariances are evaluated once (the covariance only when asked for).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from functools import cached_property
from typing import Any, ClassVar, Self

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
    RadialPass,
    distance_to_surface_m,
    radial_distance_gradient,
    radial_pass,
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
_SHEAR_CHECKED = 0.02
"""A fitted |shear| above this is refitted without (:func:`without_needless_shear`)."""
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
_FAR_M = 1e3  # where excluded points are padded to one count per batch: never inside

IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]


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
    shear_gain_nats: float = 0.1
    on_table: bool = True
    max_fit_points: int = 1000


@dataclass(frozen=True)
class EMSResult:
    """One fitted superquadric.

    params: [14] in ``PARAMETER_NAMES`` order; std: [14] standard deviations (0 where the
    parameter is fixed by the model); covariance: [14, 14]; inlier_probability: [N] posterior
    of eq. 9 per point of ``cloud_m`` [N, 3] (the fitted points, or a whole cloud of which
    they are part), whose radial distances are ``distance_m`` [N].
    """

    superquadric: Superquadric
    params: FloatArray
    inlier_probability: FloatArray
    noise_m: float
    nll: float
    fit_points_m: FloatArray = field(repr=False, compare=False)
    """The points [M, 3] the superquadric was fitted to (for the covariance)."""
    options: EMSOptions = field(repr=False, compare=False)
    cloud_m: FloatArray = field(repr=False, compare=False)
    distance_m: FloatArray = field(repr=False, compare=False)

    def distance_to(self, points_m: FloatArray) -> FloatArray:
        """Radial distance [N] of points [N, 3] to the superquadric (known for ``cloud_m``)."""
        if points_m is self.cloud_m:
            return self.distance_m
        return distance_to_surface_m(self.superquadric, points_m)

    @cached_property
    def covariance(self) -> FloatArray:
        """[14, 14], from the Jacobian at the optimum over ``fit_points_m`` (computed when
        first asked: most fits of a multi-link search are discarded)."""
        problem = _make_problem([self.fit_points_m], self.options)
        noise_var_m2 = np.array([self.noise_m**2])
        weights = problem.posterior(problem.evaluate(self.params[None]).distance, noise_var_m2)
        return _parameter_covariance(problem, self.params, weights[0], float(noise_var_m2[0]))

    @property
    def std(self) -> FloatArray:
        """[14]."""
        return np.sqrt(np.clip(np.diag(self.covariance), 0.0, None))

    @property
    def planar_pose(self) -> FloatArray:
        """(x m, y m, yaw rad) of the superquadric's frame: [3]."""
        return self.params[[_X, _Y, _YAW]]


@dataclass(frozen=True)
class _Rows:
    """Values batched by row (B rows): the fields named in ``ROWS`` (arrays, or other
    :class:`_Rows`) have one row per fit; ``take`` and ``put`` select and replace rows."""

    ROWS: ClassVar[tuple[str, ...]]

    def __len__(self) -> int:
        return len(getattr(self, self.ROWS[0]))

    def take(self, rows: IntArray) -> Self:
        """The rows [B'] alone (repeats allowed); itself when they are all rows in order."""
        if np.array_equal(rows, np.arange(len(self))):
            return self
        return replace(self, **{name: _take(getattr(self, name), rows) for name in self.ROWS})

    def put(self, rows: IntArray, other: Self) -> Self:
        """A copy with the rows [B'] (sorted, distinct) replaced by those of ``other``."""
        if len(rows) in (0, len(self)):
            return other if len(rows) else self
        return replace(
            self,
            **{name: _put(getattr(self, name), rows, getattr(other, name)) for name in self.ROWS},
        )


def _take(value: Any, rows: IntArray) -> Any:
    """The rows [B'] of an array, of :class:`_Rows` or of a :class:`RadialPass`."""
    if isinstance(value, RadialPass):
        return RadialPass(*(None if v is None else v[rows] for v in value))
    return value.take(rows) if isinstance(value, _Rows) else value[rows]


def _put(value: Any, rows: IntArray, other: Any) -> Any:
    """A copy of an array or of :class:`_Rows` with the rows [B'] replaced by ``other``."""
    if isinstance(value, _Rows):
        return value.put(rows, other)
    out = value.copy()
    out[rows] = other
    return out


@dataclass(frozen=True)
class _Forward(_Rows):
    """What the gradient of the radial distances of a problem's points to superquadrics [B]
    reuses of their evaluation: the rotations [B, 3, 3], the points less the centres
    [B, 3, N + M] and the forward pass in the superquadrics' frames (:func:`radial_pass`)."""

    ROWS = ("rotation", "offset", "radial")
    rotation: FloatArray
    offset: FloatArray
    radial: RadialPass


@dataclass(frozen=True)
class _Evaluation(_Rows):
    """Superquadrics [B] against their problems' points: the radial distance [B, N] of the
    points to fit, and of the excluded points whether they lie inside [B, M] and their radial
    depth inside [B, M] (0 outside); the forward pass for the gradient, or None where rows
    of several evaluations were put together (copying it would cost more than computing it
    again where needed)."""

    ROWS = ("distance", "inside", "depth")
    distance: FloatArray
    inside: BoolArray
    depth: FloatArray
    forward: _Forward | None

    def take(self, rows: IntArray) -> Self:
        """The rows [B'] alone, with their forward pass."""
        out = super().take(rows)
        if out is self or self.forward is None:
            return out
        return replace(out, forward=self.forward.take(rows))

    def put(self, rows: IntArray, other: Self) -> Self:
        """A copy with the rows [B'] (sorted, distinct) replaced by those of ``other``,
        without a forward pass unless all rows come from one of the two."""
        out = super().put(rows, other)
        return out if out is self or out is other else replace(out, forward=None)


@dataclass(frozen=True)
class _Problem(_Rows):
    """Fitting problems of one size, one per row (B of them): the points to fit and what the
    model may vary.

    points_t [B, 3, N + M]: the coordinate rows of the N points to fit, then of M points that
    the superquadric must not enclose (the hidden volume of other links; their radial depth
    inside is penalised), evaluated in one pass; lower, upper [B, 14]; log_outlier_density
    [B]."""

    ROWS = ("points_t", "lower", "upper", "log_outlier_density")
    points_t: FloatArray
    count: int
    free: IntArray
    on_table: bool
    lower: FloatArray
    upper: FloatArray
    log_outlier_density: FloatArray
    options: EMSOptions

    def expand(self, free_values: FloatArray, base: FloatArray) -> FloatArray:
        """Full parameter vectors [B, 14] from free values [B, F] on top of ``base`` [B, 14]."""
        full = base.copy()
        full[:, self.free] = free_values
        if self.on_table:
            full[:, _Z] = full[:, _A3]
        return full

    def evaluate(self, full: FloatArray) -> _Evaluation:
        """The points against the superquadric of each row, full [B, 14]."""
        forward = self._forward(full)
        distance, excluded = forward.radial.distance, slice(self.count, None)
        assert distance is not None
        inside = forward.radial.log_f[:, excluded] < 0
        return _Evaluation(
            distance[:, : self.count], inside, distance[:, excluded] * inside, forward
        )

    def _forward(self, full: FloatArray) -> _Forward:
        """The forward pass of the radial distances to the superquadric of each row, full
        [B, 14]."""
        rotation = rotation_zyx(full[:, _YAW], full[:, _PITCH], full[:, _ROLL])
        offset = self.points_t - full[:, [_X, _Y, _Z], None]
        radial = radial_pass(
            np.matmul(rotation.swapaxes(1, 2), offset),
            full[:, _SCALE],
            full[:, _EXPONENTS],
            full[:, _TAPER],
        )
        return _Forward(rotation, offset, radial)

    def distance_gradient(self, full: FloatArray, evaluation: _Evaluation) -> FloatArray:
        """Gradient [B, F, N + M] of the radial distance of each point to the superquadric of
        each row, full [B, 14] (``evaluation``: its evaluation, whose forward pass is reused),
        with respect to the free parameters (on a table, a3's row includes z = a3)."""
        forward = self._forward(full) if evaluation.forward is None else evaluation.forward
        rotation, offset, radial = forward.rotation, forward.offset, forward.radial
        _, grad = radial_distance_gradient(
            radial.points_t, full[:, _SCALE], full[:, _EXPONENTS], full[:, _TAPER], radial
        )
        out = np.empty((len(full), len(PARAMETER_NAMES), offset.shape[2]))
        out[:, _SHAPE_INDICES] = grad[:, 3:]
        out[:, [_X, _Y, _Z]] = -(rotation @ grad[:, :3])
        angles = (_YAW,) if self.on_table else (_YAW, _PITCH, _ROLL)
        for index, d_rotation in zip(
            angles, _rotation_derivatives(full, rotation, len(angles)), strict=True
        ):
            moved = d_rotation.swapaxes(1, 2) @ offset
            out[:, index] = (
                grad[:, 0] * moved[:, 0] + grad[:, 1] * moved[:, 1] + grad[:, 2] * moved[:, 2]
            )
        if self.on_table:
            out[:, _A3] += out[:, _Z]
        return out[:, self.free]

    def log_area(self, full: FloatArray) -> FloatArray:
        """log of the approximate surface area of each superquadric: full [B, 14] -> [B]."""
        return np.log(surface_area_m2(full[:, _SCALE], full[:, _EXPONENTS], full[:, _TAPER]))

    def posterior(self, distance_m: FloatArray, noise_var_m2: FloatArray) -> FloatArray:
        """Inlier probability of eq. 9 per point, distances [B, N], noise variances [B]:
        [B, N]."""
        return _inlier_probability(
            _log_inlier_density(distance_m, noise_var_m2),
            self.log_outlier_density,
            self.options.outlier_ratio,
        )

    def nll(
        self, full: FloatArray, noise_var_m2: FloatArray, evaluation: _Evaluation | None = None
    ) -> FloatArray:
        """Objective per row, full [B, 14] at noise variances [B] -> [B]: the negative
        log-likelihood of the Gaussian-uniform mixture (eq. 4) plus the area term of eq. 7
        (inlier count x log A), which keeps a partly seen shape from growing into the unseen
        space, plus the penalised depth of the excluded points (``evaluation``: that of full,
        when known)."""
        ratio = self.options.outlier_ratio
        evaluation = self.evaluate(full) if evaluation is None else evaluation
        log_inlier = _log_inlier_density(evaluation.distance, noise_var_m2)
        mixture = np.logaddexp(
            np.log(1 - ratio) + log_inlier, (np.log(ratio) + self.log_outlier_density)[:, None]
        )
        inliers = _inlier_probability(log_inlier, self.log_outlier_density, ratio).sum(axis=-1)
        depth = _EXCLUSION_WEIGHT * (evaluation.depth**2).sum(axis=-1) / (2 * noise_var_m2)
        return -mixture.sum(axis=-1) + inliers * self.log_area(full) + depth


def _log_inlier_density(distance_m: FloatArray, noise_var_m2: FloatArray) -> FloatArray:
    """log of the Gaussian of the distances [B, N] at each row's noise variance [B]."""
    var = noise_var_m2[:, None]
    return -1.5 * np.log(2 * np.pi * var) - distance_m**2 / (2 * var)


def _inlier_probability(
    log_inlier: FloatArray, log_outlier_density: FloatArray, outlier_ratio: float
) -> FloatArray:
    """Inlier probability of eq. 9 [B, N] from the log inlier densities [B, N] and each row's
    log outlier density [B]."""
    prior = log_outlier_density + np.log(outlier_ratio / (1 - outlier_ratio))
    return expit(log_inlier - prior[:, None])


def rotation_zyx(yaw: FloatArray, pitch: FloatArray, roll: FloatArray) -> FloatArray:
    """Rz(yaw) Ry(pitch) Rx(roll) for angle arrays [B]. Returns [B, 3, 3]."""
    cy, sy, cp, sp, cr, sr = (
        np.cos(yaw),
        np.sin(yaw),
        np.cos(pitch),
        np.sin(pitch),
        np.cos(roll),
        np.sin(roll),
    )
    rotation = np.empty((*np.shape(yaw), 3, 3))
    rotation[..., 0, 0], rotation[..., 0, 1] = cy * cp, cy * sp * sr - sy * cr
    rotation[..., 0, 2], rotation[..., 1, 0] = cy * sp * cr + sy * sr, sy * cp
    rotation[..., 1, 1], rotation[..., 1, 2] = sy * sp * sr + cy * cr, sy * sp * cr - cy * sr
    rotation[..., 2, 0], rotation[..., 2, 1], rotation[..., 2, 2] = -sp, cp * sr, cp * cr
    return rotation


def _rotation_derivatives(
    full: FloatArray, rotation: FloatArray, count: int = 3
) -> list[FloatArray]:
    """d R / d (yaw, pitch, roll) [count x (B, 3, 3)] of R = Rz Ry Rx (``rotation`` [B, 3, 3])
    at full [B, 14]: the first ``count`` of them (1: the yaw's alone)."""
    if count == 1:
        return [_GENERATOR_Z @ rotation]
    zero = np.zeros(len(full))
    yaw_part = rotation_zyx(full[:, _YAW], zero, zero)
    tilt = rotation_zyx(zero, full[:, _PITCH], full[:, _ROLL])
    return [_GENERATOR_Z @ rotation, yaw_part @ _GENERATOR_Y @ tilt, rotation @ _GENERATOR_X][
        :count
    ]


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
    return Superquadric(
        params[_SCALE].copy(), params[_EXPONENTS].copy(), _pose(params), params[_TAPER].copy()
    )


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
    # Only the k-th distance is asked for; an unbalanced tree builds and answers faster here.
    tree = cKDTree(points_m, balanced_tree=False)
    spacing = tree.query(points_m, [_DENSITY_NEIGHBOURS + 1])[0][:, 0]
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
        params[_A3] = max(
            0.5 * float(np.percentile(points_m[:, 2], _INIT_PERCENTILES[1])), _MIN_SCALE_M
        )
        params[_Z] = params[_A3]
    return params


def _bounds(points_m: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Lower and upper bounds [14] from the extent of the points."""
    low, high = points_m.min(axis=0), points_m.max(axis=0)
    extent = float(np.max(high - low))
    lower = np.array(
        [_MIN_SCALE_M] * 3
        + [_EXPONENT_BOUNDS[0]] * 2
        + [-1.0, 0.0]
        + list(low[:2] - extent)
        + [-np.inf, low[2] - extent, -np.inf, -np.inf]
        + [-_SHEAR_BOUND]
    )
    upper = np.array(
        [extent] * 3
        + [_EXPONENT_BOUNDS[1]] * 2
        + [1.0, 1.0]
        + list(high[:2] + extent)
        + [np.inf, high[2] + extent, np.inf, np.inf]
        + [_SHEAR_BOUND]
    )
    return lower, upper


def _free_indices(options: EMSOptions) -> IntArray:
    fixed = set(_TILT_INDICES if options.on_table else ())
    fixed |= set(() if options.taper else _TAPER_INDICES)
    fixed |= set(() if options.taper and options.shear else (_SHEAR,))
    return np.array([i for i in range(len(PARAMETER_NAMES)) if i not in fixed], dtype=np.int64)


def _log_outlier_density(points_m: FloatArray) -> float:
    """log of the uniform outlier density p0 = 1/V over the bounding box of points [N, 3]."""
    return float(-np.log(max(float(np.prod(np.ptp(points_m, axis=0))), _MIN_VOLUME_M3)))


def _make_problem(
    points_m: Sequence[FloatArray],
    options: EMSOptions,
    excluded_m: Sequence[FloatArray | None] | None = None,
) -> _Problem:
    """The problems of fitting each set of points [N, 3] (all N alike); with ``excluded_m``
    (one [M_k, 3] or None per set), points that the superquadric must not enclose (the hidden
    volume of other links): their radial depth inside is penalised. The excluded points are
    padded to one count with points far away (never inside)."""
    excluded = [np.empty((0, 3)) if e is None else e for e in excluded_m or [None] * len(points_m)]
    width = max(len(e) for e in excluded)
    stacked = [
        np.vstack([p, e, np.full((width - len(e), 3), _FAR_M)])
        for p, e in zip(points_m, excluded, strict=True)
    ]
    lower, upper = zip(*(_bounds(p) for p in points_m), strict=True)
    return _Problem(
        np.ascontiguousarray(np.stack(stacked).transpose(0, 2, 1)),
        len(points_m[0]),
        _free_indices(options),
        options.on_table,
        np.array(lower),
        np.array(upper),
        np.array([_log_outlier_density(p) for p in points_m]),
        options,
    )


# ---------------------------------------------------------------------------------------------
# EM with switching


def _m_step(
    problem: _Problem, state: _State, weights: FloatArray
) -> tuple[FloatArray, _Evaluation]:
    """A few bounded Levenberg-Marquardt steps on eq. 7 (times 2 sigma^2) from the state's
    params, row by row: the residuals are sqrt(p_i) * distance_i (weights p [B, N]), one area
    residual and the depths of the excluded points. Returns the new params [B, 14] and their
    evaluation.

    The steps solve the small normal equations [F, F] (Marquardt's diagonal scaling) and are
    clipped to the bounds; each row accepts its step or raises its damping on its own."""
    free = problem.free
    lower, upper = problem.lower[:, free], problem.upper[:, free]
    residuals = _residuals(problem, state.params, weights, state.noise_var_m2)
    x = np.clip(state.params[:, free], lower, upper)
    known = np.array_equal(problem.expand(x, state.params), state.params)
    value, evaluation = residuals(x, state.evaluation if known else None)
    cost = np.einsum("bk,bk->b", value, value)
    damping = np.full(len(x), _LM_INITIAL_DAMPING)
    normal, gradient = residuals.normal_equations(x, evaluation, value)
    evaluations = problem.options.m_step_evaluations
    for index in range(evaluations):
        scaling = np.maximum(np.diagonal(normal, axis1=1, axis2=2), _LM_MIN_SCALING)
        damped = normal + (damping[:, None] * scaling)[:, :, None] * np.eye(len(free))
        trial = np.clip(x - np.linalg.solve(damped, gradient[:, :, None])[:, :, 0], lower, upper)
        trial_value, trial_evaluation = residuals(trial)
        trial_cost = np.einsum("bk,bk->b", trial_value, trial_value)
        better = trial_cost < cost
        rows = np.flatnonzero(better)
        x, value, cost = (
            np.where(better[:, None], trial, x),
            np.where(better[:, None], trial_value, value),
            np.where(better, trial_cost, cost),
        )
        accepted = trial_evaluation.take(rows)
        evaluation = evaluation.put(rows, accepted)
        damping = np.where(
            better,
            np.maximum(damping / _LM_DAMPING_FACTOR, _LM_MIN_DAMPING),
            damping * _LM_DAMPING_FACTOR,
        )
        if len(rows) and index + 1 < evaluations:  # the last step's would go unused
            normal[rows], gradient[rows] = residuals.take(rows).normal_equations(
                x[rows], accepted, value[rows]
            )
    return problem.expand(x, state.params), evaluation


@dataclass(frozen=True)
class _Residuals(_Rows):
    """Per row: weighted distances [N], the depths [M] of the excluded points and the area
    residual [1] of eq. 7, as a function of the free parameters [F]; their Jacobian is
    analytic for the distances and depths, forward differences for the (cheap) area residual.

    base [B, 14]: the full parameters under the free ones; sqrt_w [B, N]: square roots of the
    weights; area_gain [B]."""

    ROWS = ("problem", "base", "sqrt_w", "area_gain")
    problem: _Problem
    base: FloatArray
    sqrt_w: FloatArray
    area_gain: FloatArray

    def __call__(
        self, x: FloatArray, evaluation: _Evaluation | None = None
    ) -> tuple[FloatArray, _Evaluation]:
        """The residuals [B, N + M + 1] (points, excluded points, area) at free values x [B, F]
        and the evaluation of x (given as ``evaluation`` when already known)."""
        full = self.problem.expand(x, self.base)
        evaluation = self.problem.evaluate(full) if evaluation is None else evaluation
        value = np.concatenate(
            [
                self.sqrt_w * evaluation.distance,
                np.sqrt(_EXCLUSION_WEIGHT) * evaluation.depth,
                self.area_residual(full, self.area_gain)[:, None],
            ],
            axis=1,
        )
        return value, evaluation

    def normal_equations(
        self, x: FloatArray, evaluation: _Evaluation, value: FloatArray
    ) -> tuple[FloatArray, FloatArray]:
        """J J^T [B, F, F] and J r [B, F] of the Jacobian J [B, F, N + M + 1] at free values
        x [B, F] (``evaluation`` and the residuals r, ``value``: those of x), the points' part
        and the area's summed apart. The depth of an excluded point outside is 0 nearby, and so
        is its gradient."""
        jac = self.problem.distance_gradient(self.problem.expand(x, self.base), evaluation)
        jac *= np.concatenate(
            [self.sqrt_w, np.sqrt(_EXCLUSION_WEIGHT) * evaluation.inside], axis=1
        )[:, None, :]
        area = self._area_jacobian(x)
        normal = jac @ jac.swapaxes(1, 2) + area[:, :, None] * area[:, None, :]
        gradient = (jac @ value[:, :-1, None])[:, :, 0] + area * value[:, -1:]
        return normal, gradient

    def _area_jacobian(self, x: FloatArray) -> FloatArray:
        """Forward differences [B, F] of the area residual at free values x [B, F]."""
        rows, free = x.shape
        step = _FD_STEP * np.maximum(np.abs(x), _FD_FLOOR)
        moved = x[:, None, :] + step[:, :, None] * np.eye(free)
        values = np.concatenate([x[:, None, :], moved], axis=1).reshape(-1, free)
        full = self.problem.expand(values, np.repeat(self.base, free + 1, axis=0))
        area = self.area_residual(full, np.repeat(self.area_gain, free + 1)).reshape(rows, -1)
        return (area[:, 1:] - area[:, :1]) / step

    def area_residual(self, full: FloatArray, gain: FloatArray) -> FloatArray:
        """sqrt(gain (log A - floor)) per superquadric: full [B, 14], gain [B] -> [B]."""
        return np.sqrt(gain * (self.problem.log_area(full) - _LOG_AREA_FLOOR))


def _residuals(
    problem: _Problem, base: FloatArray, weights: FloatArray, noise_var_m2: FloatArray
) -> _Residuals:
    """The residuals of each row about base [B, 14] with weights [B, N] and noise variances
    [B]."""
    # sigma^2 is capped in the area term: while the fit is still coarse (large sigma) the
    # area term would otherwise shrink the superquadric to nothing.
    area_gain = 2.0 * np.minimum(noise_var_m2, _AREA_NOISE_CAP_M**2) * weights.sum(axis=1)
    return _Residuals(problem, base, np.sqrt(weights), area_gain)


def _noise_var(problem: _Problem, distance_m: FloatArray, weights: FloatArray) -> FloatArray:
    """The noise variance [B] of eq. 8 from the distances and weights [B, N]."""
    var = (weights * distance_m**2).sum(axis=1) / (3 * np.maximum(weights.sum(axis=1), 1e-9))
    return np.maximum(var, problem.options.min_noise_m**2)


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
    gain = (
        (1 - np.sqrt(2)) * eps2 + np.sqrt(2)
        if eps2 <= 1
        else (np.sqrt(2) / 2 - 1) * eps2 + 2 - np.sqrt(2) / 2
    )
    out = params.copy()
    out[[0, 1]] = gain * side
    out[4] = 2 - eps2
    out[_YAW] += np.pi / 4
    return out


@dataclass(frozen=True)
class _State(_Rows):
    """EM's current fit of each row: params [B, 14], noise variances [B], objectives [B] and
    the evaluation of the params."""

    ROWS = ("params", "noise_var_m2", "nll", "evaluation")
    params: FloatArray
    noise_var_m2: FloatArray
    nll: FloatArray
    evaluation: _Evaluation


def _state(
    problem: _Problem,
    params: FloatArray,
    noise_var_m2: FloatArray,
    evaluation: _Evaluation | None = None,
) -> _State:
    """The states of params [B, 14] at noise variances [B] (``evaluation``: the params', if
    known)."""
    evaluation = problem.evaluate(params) if evaluation is None else evaluation
    return _State(params, noise_var_m2, problem.nll(params, noise_var_m2, evaluation), evaluation)


def _em_iteration(problem: _Problem, state: _State) -> _State:
    weights = problem.posterior(state.evaluation.distance, state.noise_var_m2)
    params, evaluation = _m_step(problem, state, weights)
    return _state(problem, params, _noise_var(problem, evaluation.distance, weights), evaluation)


def _switch(problem: _Problem, state: _State) -> tuple[BoolArray, _State]:
    """The S-step of each row: of its ``_SWITCH_TRIALS`` most likely candidates, the first
    that improves after one EM iteration. Returns whether one did [B] and, for those rows,
    the switched states."""
    candidates = [_candidates(params, problem.options) for params in state.params]
    owner = np.repeat(np.arange(len(candidates)), [len(c) for c in candidates])
    problems = problem.take(owner)
    params = np.clip(np.concatenate(candidates), problems.lower, problems.upper)
    if problem.on_table:
        params[:, _Z] = params[:, _A3]
    noise_var = state.noise_var_m2[owner]
    evaluation = problems.evaluate(params)
    nll = problems.nll(params, noise_var, evaluation)
    picks = np.concatenate(
        [
            np.flatnonzero(owner == row)[np.argsort(nll[owner == row])][:_SWITCH_TRIALS]
            for row in range(len(candidates))
        ]
    )
    trials = _em_iteration(
        problems.take(picks),
        _State(params[picks], noise_var[picks], nll[picks], evaluation.take(picks)),
    )
    tolerance = problem.options.tolerance_nats * problem.count
    improved = trials.nll < state.nll[owner[picks]] - tolerance
    chosen = [
        next((k for k in np.flatnonzero(owner[picks] == row) if improved[k]), None)
        for row in range(len(candidates))
    ]
    switched = np.array([k is not None for k in chosen])
    for row, k in enumerate(chosen):
        if k is not None:
            logger.debug(
                "EMS fit %d switched (nll %.1f -> %.1f)", row, state.nll[row], trials.nll[k]
            )
    return switched, trials.take(np.array([k for k in chosen if k is not None], dtype=np.int64))


def _initial_noise_var(problem: _Problem, distance_m: FloatArray) -> FloatArray:
    """The noise variance [B] of the closest 1 - w0 of the points (w0 the outlier ratio) at
    their distances [B, N]: counting the outliers too would start EM so loose that it spreads
    the shape into the unseen side of a partial view."""
    quantile = np.quantile(distance_m, 1 - problem.options.outlier_ratio, axis=1)
    return _noise_var(problem, distance_m, distance_m <= quantile[:, None])


def _run_ems(
    problem: _Problem,
    params: FloatArray,
    max_iterations: int,
    max_switches: IntArray,
    noise_var_m2: FloatArray,
    evaluation: _Evaluation | None = None,
) -> _State:
    """EM from params [B, 14] at noise variances [B] (``evaluation``: that of the params, if
    known), each row until its likelihood stops improving, with up to ``max_switches`` [B]
    S-steps; the rows still improving iterate together."""
    state = _state(problem, params, noise_var_m2, evaluation)
    switches = np.zeros(len(params), dtype=np.int64)
    active = np.ones(len(params), dtype=bool)
    tolerance = problem.options.tolerance_nats * problem.count
    for _ in range(max_iterations):
        rows = np.flatnonzero(active)
        current = state.take(rows)
        new = _em_iteration(problem.take(rows), current)
        improved = current.nll - new.nll > tolerance
        better = np.flatnonzero(new.nll < current.nll)
        state = state.put(rows[better], new.take(better))
        stuck = rows[~improved]
        active[stuck[switches[stuck] >= max_switches[stuck]]] = False
        stuck = stuck[switches[stuck] < max_switches[stuck]]
        if len(stuck):
            switches[stuck] += 1
            switched, switched_state = _switch(problem.take(stuck), state.take(stuck))
            state = state.put(stuck[switched], switched_state)
            active[stuck[~switched]] = False
        if not active.any():
            break
    return state


def _parameter_covariance(
    problem: _Problem, params: FloatArray, weights: FloatArray, noise_var_m2: float
) -> FloatArray:
    """Covariance [14, 14] of params [14] fitted to the points of a one-row problem with
    weights [N], from the Jacobian at the optimum, (J^T J)^-1 s^2; zero rows and columns for
    fixed parameters (on a table z = a3, so z copies a3's)."""
    residuals = _residuals(problem, params[None], weights[None], np.array([noise_var_m2]))
    x = params[None, problem.free]
    value, evaluation = residuals(x)
    normal, _ = residuals.normal_equations(x, evaluation, value)
    residual = value[0, : problem.count]
    dof = max(float(weights.sum()) - len(problem.free), 1.0)
    free_cov = np.linalg.pinv(normal[0]) * float(residual @ residual) / dof
    cov = np.zeros((len(PARAMETER_NAMES), len(PARAMETER_NAMES)))
    cov[np.ix_(problem.free, problem.free)] = 0.5 * (free_cov + free_cov.T)
    if problem.on_table:
        cov[_Z, :], cov[:, _Z] = cov[_A3, :], cov[:, _A3]
        cov[_Z, _Z] = cov[_A3, _A3]
    return cov


def _canonical(params: FloatArray, options: EMSOptions) -> FloatArray:
    """Resolve symmetries: kappa1 >= 0 (a half turn about the shape's own z axis, which maps
    (x, y) to (-x, -y), flips it and keeps the shear); angles wrapped to (-pi, pi]."""
    out = params.copy()
    frame = to_superquadric(out).world_from_sq[:3, :3]
    if out[_KAPPA1] < 0:
        out[_KAPPA1] = -out[_KAPPA1]
        frame = frame @ np.diag([-1.0, -1.0, 1.0])
    period = 2 * np.pi if options.taper else np.pi
    out[[_YAW, _PITCH, _ROLL]] = _euler_zyx(frame)
    if options.on_table:
        out[_YAW] = (out[_YAW] + period / 2) % period - period / 2
    return out


def fit_superquadric(
    points_m: FloatArray,
    options: EMSOptions,
    excluded_m: FloatArray | None = None,
    initial: EMSResult | None = None,
) -> EMSResult:
    """Fit one (tapered) superquadric to points [N, 3] (N >= 10, finite) by EMS: from the
    points' extent, or warm-started from ``initial`` (its parameters and noise, no switching).

    EM with switching runs on a fixed random subset of ``_COARSE_FIT_POINTS``, then at most
    ``_FINE_ITERATIONS`` EM iterations refine it on ``max_fit_points`` (a superset); the
    inlier probabilities and the uncertainty use all points.
    """
    return _fit_superquadrics([points_m], options, [excluded_m], [initial])[0]


def _fit_superquadrics(
    points_m: Sequence[FloatArray],
    options: EMSOptions,
    excluded_m: Sequence[FloatArray | None],
    initial: Sequence[EMSResult | None],
    cloud_m: FloatArray | None = None,
) -> list[EMSResult]:
    """:func:`fit_superquadric` of each set of points [N_k, 3] (with its excluded points and
    initial fit, or None); the fits whose subsets have the same size run as one batch.
    ``cloud_m`` [N, 3]: the cloud of which the sets are part, for the fits' inlier
    probabilities (default: each fit's own points)."""
    groups: dict[int, list[int]] = {}
    for k, points in enumerate(points_m):
        groups.setdefault(min(len(points), options.max_fit_points), []).append(k)
    results: dict[int, EMSResult] = {}
    for members in groups.values():
        fits = _fit_batch(
            [points_m[k] for k in members],
            options,
            [excluded_m[k] for k in members],
            [initial[k] for k in members],
            cloud_m,
        )
        results.update(zip(members, fits, strict=True))
    return [results[k] for k in range(len(points_m))]


def _fit_batch(
    points_m: list[FloatArray],
    options: EMSOptions,
    excluded_m: list[FloatArray | None],
    initial: list[EMSResult | None],
    cloud_m: FloatArray | None = None,
) -> list[EMSResult]:
    """:func:`fit_superquadric` of sets of points whose subsets have one size, as one batch
    (cold fits switch, warm-started ones do not; ``cloud_m``: as in
    :func:`_fit_superquadrics`)."""
    subsets = [
        p[np.random.default_rng(0).permutation(len(p))[: options.max_fit_points]] for p in points_m
    ]
    coarse = [s[: min(_COARSE_FIT_POINTS, len(s))] for s in subsets]
    problem = _make_problem(coarse, options, excluded_m)
    cold = np.array([start is None for start in initial])
    params = np.array(
        [
            _initial_params(s, options.on_table) if start is None else start.params
            for s, start in zip(subsets, initial, strict=True)
        ]
    )
    evaluation = problem.evaluate(params)
    noise_var = np.array([np.nan if start is None else start.noise_m**2 for start in initial])
    if cold.any():
        noise_var[cold] = _initial_noise_var(
            problem.take(np.flatnonzero(cold)), evaluation.distance[cold]
        )
    state = _run_ems(
        problem,
        params,
        options.max_iterations,
        np.where(cold, options.max_switches, 0),
        noise_var,
        evaluation,
    )
    if len(subsets[0]) > len(coarse[0]):
        state = _run_ems(
            _make_problem(subsets, options, excluded_m),
            state.params,
            _FINE_ITERATIONS,
            np.zeros(len(cold), dtype=np.int64),
            state.noise_var_m2,
        )
    noise_var, nll = state.noise_var_m2.tolist(), state.nll.tolist()
    return [
        _result(points, state.params[k], noise_var[k], nll[k], options, cloud_m)
        for k, points in enumerate(points_m)
    ]


def _result(
    points_m: FloatArray,
    params: FloatArray,
    noise_var_m2: float,
    nll: float,
    options: EMSOptions,
    cloud_m: FloatArray | None = None,
) -> EMSResult:
    """The fit of params [14] to points [N, 3], with the inlier probabilities of the points
    of ``cloud_m`` [M, 3], of which they are part (default: of themselves)."""
    cloud_m = points_m if cloud_m is None else cloud_m
    params = _canonical(params, options)
    superquadric, noise_m = to_superquadric(params), float(np.sqrt(noise_var_m2))
    return EMSResult(
        superquadric,
        params,
        noise_m=noise_m,
        nll=nll,
        fit_points_m=points_m,
        options=options,
        **_cloud_fields(superquadric, noise_m, cloud_m, options),
    )


def _cloud_fields(
    superquadric: Superquadric, noise_m: float, points_m: FloatArray, options: EMSOptions
) -> dict[str, FloatArray]:
    """The fields of an :class:`EMSResult` that refer to its cloud, points [N, 3]."""
    distance = distance_to_surface_m(superquadric, points_m)
    log_inlier = _log_inlier_density(distance[None], np.array([noise_m**2]))
    probability = _inlier_probability(
        log_inlier, np.array([_log_outlier_density(points_m)]), options.outlier_ratio
    )[0]
    return {"inlier_probability": probability, "cloud_m": points_m, "distance_m": distance}


# ---------------------------------------------------------------------------------------------
# Multi-link recovery (III-B3)


def largest_cluster(points_m: FloatArray, radius_m: float) -> IntArray:
    """Indices [K] of the largest group of points chained by gaps <= radius_m (DBSCAN with
    min_samples = 1: single-linkage clusters)."""
    pairs = cKDTree(points_m).query_pairs(radius_m, output_type="ndarray")
    graph = coo_matrix(
        (np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(points_m), len(points_m))
    )
    _, labels = connected_components(graph, directed=False)
    return np.flatnonzero(labels == np.bincount(labels).argmax())


def fit_links(
    points_m: FloatArray,
    options: EMSOptions,
    max_links: int,
    outlier_threshold_points: int,
    cluster_radius_m: float,
    previous: list[EMSResult] | None = None,
    dense: BoolArray | None = None,
) -> list[EMSResult]:
    """Fit superquadrics to points [N, 3], one more at a time while the model selection of
    :func:`_evidence_gain` prefers it (at most ``max_links``; ``dense``: :func:`_dense_mask`
    of the points [N], when known).

    With the links of an earlier fit of the same object (``previous``, the last view), those
    links are also refitted once, each from where it was, and kept when they explain the
    points better than the search's result: the split found from one view's seam can be poor
    in the next, and a good split found earlier is not lost.

    Each step tries, in turn, to split the largest link where the view from above shows a
    seam (:func:`_seam_proposals`) and to add a link on the largest cluster of unexplained points
    (III-B3, when at least ``outlier_threshold_points``); the links of a proposal are fitted
    jointly (:func:`_fit_jointly`) and kept only when they explain the points better. The
    last view's links and the first round of the single link's seam proposal (the seam is
    found without the link's fit) are fitted in one batch with the single link: fewer,
    larger array operations, the same fits.
    """
    if max_links == 1:
        return [fit_superquadric(points_m, options)]
    dense = _dense_mask(points_m) if dense is None else dense
    starts = previous if previous is not None and 1 < len(previous) <= max_links else []
    warm = _link_sets(points_m, dense, _assign(points_m, starts), options) if starts else None
    if warm is None:
        starts, warm = [], ([], [])
    # The single link's seam is found without its fit, so its first round joins the batch.
    seams = _seam_proposals(points_m, np.zeros(len(points_m), dtype=np.int64), 1)
    seam_sets = [_link_sets(points_m, dense, seam.labels, options) for seam in seams]
    seams = [seam for seam, sets in zip(seams, seam_sets, strict=True) if sets is not None]
    cold = [sets for sets in seam_sets if sets is not None]
    cold_points, cold_excluded = _joined(cold)
    fits = _fit_superquadrics(
        [points_m, *warm[0], *cold_points],
        options,
        [None, *warm[1], *cold_excluded],
        [None, *starts, *[None] * len(cold_points)],
        points_m,
    )
    links, again, rest = fits[:1], fits[1 : 1 + len(starts)], fits[1 + len(starts) :]
    for seam, (points, _) in zip(seams, cold, strict=True):
        seam.first_round, rest = rest[: len(points)], rest[len(points) :]
    while len(links) < max_links:
        proposals = _proposals(
            points_m, links, options, outlier_threshold_points, cluster_radius_m,
            seams if len(links) == 1 else None,
        )  # fmt: skip
        proposal = _best_proposal(
            points_m, dense, links, options, proposals, outlier_threshold_points
        )
        if proposal is None:
            break
        links = proposal
    again = [link for link in again if _explained_points(link) >= outlier_threshold_points]
    if again and _evidence_gain(points_m, links, again, options) > 0:
        return again
    return links


def _explained_points(link: EMSResult) -> int:
    """How many points of the cloud the link explains (inlier probability of eq. 9 at least
    0.5). A link refitted from the last view's can end up explaining none (a sliver beside
    the object's outline: its covariance is then undefined); it counts as a link only when it
    explains at least ``outlier_threshold_points``, as a link added on unexplained points
    must."""
    return int(np.count_nonzero(link.inlier_probability >= 0.5))


def without_needless_shear(
    points_m: FloatArray,
    links: list[EMSResult],
    options: EMSOptions,
    dense: BoolArray | None = None,
) -> list[EMSResult]:
    """``links`` fitted to points [N, 3], each sheared one refitted without its shear where
    the shear lowers the surface NLL by less than ``options.shear_gain_nats`` per point
    (``dense``: :func:`_dense_mask` of the points [N], when known).

    A sheared ellipse is another ellipse, turned: an ellipse's fit can trade its yaw for a
    shear and lie up to 40 deg off the object's axes with nearly the same outline (over
    views of the elliptic footprints the shear explained at most 0.06 nats a point, over
    those of the triangles at least 0.16). The link frame is the one the filter's process
    models see the link in."""
    sheared = [k for k, link in enumerate(links) if abs(link.params[_SHEAR]) > _SHEAR_CHECKED]
    if not (options.taper and options.shear and sheared):
        return links
    plain = replace(options, shear=False)
    dense = _dense_mask(points_m) if dense is None else dense
    sets = _link_sets(points_m, dense, _assign(points_m, links), plain)
    if sets is None:
        return links
    refits = _fit_superquadrics(
        [sets[0][k] for k in sheared], plain, [sets[1][k] for k in sheared],
        [None] * len(sheared), points_m,
    )  # fmt: skip
    nll = _surface_nll(points_m, links, options)
    for k, refit in zip(sheared, refits, strict=True):
        candidate = [*links[:k], refit, *links[k + 1 :]]
        candidate_nll = _surface_nll(points_m, candidate, options)
        loss_per_point = (candidate_nll - nll) / len(points_m)
        if loss_per_point <= options.shear_gain_nats:
            logger.debug("EMS: link %d's shear %.3f dropped (%.4f nats a point)",
                         k, links[k].params[_SHEAR], loss_per_point)  # fmt: skip
            links, nll = candidate, candidate_nll
    return links


def _joined(
    sets: list[tuple[list[FloatArray], list[FloatArray | None]]],
) -> tuple[list[FloatArray], list[FloatArray | None]]:
    """The link sets of several :func:`_link_sets` results, one after the other."""
    return [p for points, _ in sets for p in points], [e for _, excluded in sets for e in excluded]


@dataclass
class _Proposal:
    """A model with one more link: point labels [N] (link index per point), the evidence
    gain per point it must exceed, and its links' first fit when already done."""

    labels: IntArray
    min_gain_nats: float
    first_round: list[EMSResult] | None = None


def _best_proposal(
    points_m: FloatArray,
    dense: NDArray[np.bool_],
    links: list[EMSResult],
    options: EMSOptions,
    proposals: list[_Proposal],
    min_points: int,
) -> list[EMSResult] | None:
    """The first of the proposals whose evidence gain exceeds its threshold, both fitted
    from the proposal's labels and refitted jointly (``dense``: :func:`_dense_mask` of the
    points [N]), each of whose links explains at least ``min_points`` points; None when
    none is accepted."""
    for candidate in proposals:
        threshold = candidate.min_gain_nats * len(points_m)
        proposal = candidate.first_round or _fit_jointly(
            points_m, dense, candidate.labels, options, 1
        )
        if proposal is None or _evidence_gain(points_m, links, proposal, options) <= threshold:
            continue
        refined = _fit_jointly(
            points_m, dense, _assign(points_m, proposal), options, _REFIT_ROUNDS, proposal
        )
        if (
            refined is not None
            and min(_explained_points(link) for link in refined) >= min_points
            and _evidence_gain(points_m, links, refined, options) > threshold
        ):
            logger.debug("EMS: %d links accepted", len(refined))
            return refined
    return None


def _proposals(
    points_m: FloatArray,
    links: list[EMSResult],
    options: EMSOptions,
    outlier_threshold_points: int,
    cluster_radius_m: float,
    seams: list[_Proposal] | None = None,
) -> list[_Proposal]:
    """The models with one more link to try: the split of the largest link at its seam
    (``seams``: those, when known) and a link on the largest cluster of unexplained points.
    A gap seen from above is itself evidence of two parts, so there any BIC gain will do; a
    step in height or an outlier cluster must explain the points clearly better
    (``_CLEAR_GAIN_NATS`` per point), since an imperfect fit of one part leaves such
    structure too."""
    labels = _assign(points_m, links)
    proposals = _seam_proposals(points_m, labels, len(links)) if seams is None else seams
    explained = np.max([link.inlier_probability for link in links], axis=0) >= 0.5
    unexplained = np.flatnonzero(~explained)
    if len(unexplained) >= outlier_threshold_points:
        cluster = unexplained[largest_cluster(points_m[unexplained], cluster_radius_m)]
        if len(cluster) >= outlier_threshold_points:
            with_cluster = labels.copy()
            with_cluster[cluster] = len(links)
            proposals = [*proposals, _Proposal(with_cluster, _CLEAR_GAIN_NATS)]
    return proposals


def _seam_proposals(points_m: FloatArray, labels: IntArray, new_label: int) -> list[_Proposal]:
    """The split of the largest label's points (labels [N]) at their seam
    (:func:`_split_masks`), the far side taking ``new_label``."""
    largest = int(np.bincount(labels).argmax())
    return [
        _Proposal(np.where(mask, new_label, labels), 0.0 if at_gap else _CLEAR_GAIN_NATS)
        for mask, at_gap in _split_masks(points_m, labels == largest)
    ]


def _split_masks(points_m: FloatArray, own: FloatArray) -> list[tuple[FloatArray, bool]]:
    """Masks [N] of the points of ``own`` (mask [N]) beyond a seam seen from above, with
    whether it is a gap: a gap across the major axis of their footprint (:func:`_gap_cut`),
    else the line across which the top height steps most clearly (:func:`_step_cut`, over
    ``_STEP_DIRECTIONS`` directions); empty where there is neither."""
    footprint = points_m[own, :2] - points_m[own, :2].mean(axis=0)
    major = np.linalg.eigh(footprint.T @ footprint)[1][:, -1]
    direction, cut, at_gap = major, _gap_cut(footprint @ major), True
    if cut is None:
        angles = np.arctan2(major[1], major[0]) + np.linspace(
            0, np.pi, _STEP_DIRECTIONS, endpoint=False
        )
        directions = np.column_stack([np.cos(angles), np.sin(angles)])
        by_height = np.argsort(points_m[own, 2])
        flat, height = footprint[by_height], points_m[own, 2][by_height]
        steps = [_step_cut(flat @ d, height) for d in directions]
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
    ``_TOP_PERCENTILE`` of the heights [N], in ascending order, per ``_STEP_BIN_M`` bin):
    (the drop of the mean absolute deviation of the bins' top from one median to one per
    side, the cut). The gain is 0 where the cut falls outside the middle of the span or the
    levels differ by less than ``_STEP_MIN_M``."""
    top, position = _top_profile(along_m, height_m)
    if len(top) == 0:
        return 0.0, 0.0
    cuts = np.flatnonzero(_middle_bins(position)[1:]) + 1
    if len(cuts) == 0:
        return 0.0, 0.0
    before = np.arange(len(top)) < cuts[:, None]
    left, right = _masked_median(top, before), _masked_median(top, ~before)
    cost = np.where(before, np.abs(top - left[:, None]), 0.0).sum(axis=1) + np.where(
        before, 0.0, np.abs(top - right[:, None])
    ).sum(axis=1)
    best = int(np.argmin(cost))
    if abs(float(left[best] - right[best])) < _STEP_MIN_M:
        return 0.0, 0.0
    gain = (float(np.abs(top - np.median(top)).sum()) - float(cost[best])) / len(top)
    return gain, float(position[cuts[best]])


def _masked_median(values: FloatArray, mask: BoolArray) -> FloatArray:
    """The median of the values [B] where each row of ``mask`` [C, B] holds (none empty):
    [C]."""
    ordered = np.sort(np.where(mask, values, np.inf), axis=1)
    count = mask.sum(axis=1)[:, None]
    middle = np.take_along_axis(ordered, np.hstack([(count - 1) // 2, count // 2]), axis=1)
    return 0.5 * (middle[:, 0] + middle[:, 1])


def _top_profile(along_m: FloatArray, height_m: FloatArray) -> tuple[FloatArray, FloatArray]:
    """The ``_TOP_PERCENTILE`` of the heights [N] (in ascending order) in each
    ``_STEP_BIN_M`` bin of the coordinates [N] holding at least ``_MIN_LINK_POINTS`` points,
    and the bins' lower edges: ([B], [B])."""
    low, high = np.percentile(along_m, _SPAN_PERCENTILES)
    keep = (along_m >= low) & (along_m < high)
    index = ((along_m[keep] - low) / _STEP_BIN_M).astype(np.int64)
    # A stable sort by bin keeps each bin's heights in order (a radix sort for 16 bits).
    narrow = np.uint16 if len(index) == 0 or index.max() < 2**16 else np.int64
    order = np.argsort(index.astype(narrow), kind="stable")
    counts = np.bincount(index)
    rank = np.cumsum(counts) - counts + (_TOP_PERCENTILE / 100 * (counts - 1)).astype(np.int64)
    filled = np.flatnonzero(counts >= _MIN_LINK_POINTS)
    return height_m[keep][order][rank[filled]], low + filled * _STEP_BIN_M


def _link_log_density(points_m: FloatArray, links: list[EMSResult]) -> FloatArray:
    """log of each link's surface density at each point [K, N]: a Gaussian of the radial
    distance (the link's noise) over the surface, uniform on its area."""
    distance = np.array([link.distance_to(points_m) for link in links])
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
    inlier = logsumexp(
        np.log(1 - ratio) + np.log(np.maximum(share, 1e-9))[:, None] + log_density, axis=0
    )
    outlier = np.log(ratio) + _log_outlier_density(points_m)
    return -float(np.logaddexp(inlier, outlier).sum())


def _evidence_gain(
    points_m: FloatArray, links: list[EMSResult], proposal: list[EMSResult], options: EMSOptions
) -> float:
    """BIC difference (nats) in favour of ``proposal`` over ``links``: the drop of
    :func:`_surface_nll` less half a log(N) per extra free parameter."""
    extra = (len(proposal) - len(links)) * (len(_free_indices(options)) + 1)
    return (
        _surface_nll(points_m, links, options)
        - _surface_nll(points_m, proposal, options)
        - 0.5 * extra * np.log(len(points_m))
    )


def _fit_jointly(
    points_m: FloatArray,
    dense: NDArray[np.bool_],
    labels: IntArray,
    options: EMSOptions,
    rounds: int,
    initial: list[EMSResult] | None = None,
) -> list[EMSResult] | None:
    """Links fitted to the points [N, 3] of each label [N] (0 .. K-1), then for ``rounds`` - 1
    more rounds each point is given to the link of highest surface density and the links are
    refitted, each from its previous fit (the first round from ``initial`` when given, one
    link per label); None when a link is left with fewer than ``_MIN_LINK_POINTS``. The other
    links' hidden volume comes from their dense points (``dense``: :func:`_dense_mask` [N])."""
    links: list[EMSResult] | None = initial
    for round_index in range(rounds):
        if round_index:
            labels = _assign(points_m, links or [])
        sets = _link_sets(points_m, dense, labels, options)
        if sets is None:
            return None
        links = _fit_superquadrics(
            sets[0], options, sets[1], [None] * len(sets[0]) if links is None else links, points_m
        )
    return links


def _link_sets(
    points_m: FloatArray, dense: NDArray[np.bool_], labels: IntArray, options: EMSOptions
) -> tuple[list[FloatArray], list[FloatArray | None]] | None:
    """The points [N_k, 3] of each label [N] (0 .. K-1) and the hidden volume of the other
    links (:func:`_hidden_volume` of their dense points, ``dense``: :func:`_dense_mask` [N]);
    None when a link has fewer than ``_MIN_LINK_POINTS``."""
    counts = np.bincount(labels, minlength=int(labels.max()) + 1)
    if counts.min() < _MIN_LINK_POINTS:
        return None
    return (
        [points_m[labels == k] for k in range(len(counts))],
        [_hidden_volume(points_m[(labels != k) & dense], options) for k in range(len(counts))],
    )


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
        shear_gain_nats: float = Field(
            0.1, ge=0, description="keep a link's shear only where it lowers the surface NLL "
            "by more than this per point; else the link is refitted without (an ellipse's fit "
            "can trade its yaw for a shear; a right triangle's fit needs one)",
        )
        on_table: bool = Field(True, description="yaw-only rotation, base on the table z = 0")
        table_clearance_m: float = Field(0.008, ge=0, description="drop points below this z")
        min_points: int = Field(50, ge=10, description="fewer points above the table: error")
        min_noise_m: float = Field(5e-4, gt=0, description="floor of the noise estimate")
        max_fit_points: int = Field(1000, ge=10, description="EM runs on a subset this big")
        max_links: int = Field(1, ge=1, description="superquadrics to fit at most (III-B3)")
        outlier_threshold_points: int = Field(
            100, ge=1, description="O_th: stop adding links below this many unexplained points"
        )
        cluster_radius_m: float = Field(0.01, gt=0, description="DBSCAN radius for outliers")

    def __init__(self, config: Config, ctx: ComponentContext) -> None:
        super().__init__(config, ctx)
        self.config: EMSEstimator.Config = config
        self.options = EMSOptions(
            outlier_ratio=config.outlier_ratio,
            max_iterations=config.max_iterations,
            max_switches=config.max_switches,
            m_step_evaluations=config.m_step_evaluations,
            min_noise_m=config.min_noise_m,
            taper=config.taper,
            shear=config.shear,
            shear_gain_nats=config.shear_gain_nats,
            on_table=config.on_table,
            max_fit_points=config.max_fit_points,
        )
        self._previous_links: list[EMSResult] | None = None

    def fit(self, cloud: PointCloud) -> ShapeEstimate:
        """Fit the object in ``cloud`` (world frame, table at z = 0 may be included)."""
        points = self._object_points(cloud)
        # The multi-link search and the shear check share the dense points.
        dense = _dense_mask(points) if self.config.max_links > 1 else None
        links = fit_links(
            points,
            self.options,
            self.config.max_links,
            self.config.outlier_threshold_points,
            self.config.cluster_radius_m,
            self._previous_links,
            dense,
        )
        links = without_needless_shear(points, links, self.options, dense)
        self._previous_links = links
        inlier = np.max([link.inlier_probability for link in links], axis=0) >= 0.5
        logger.info(
            "EMS: %d link(s) from %d points, %d inliers", len(links), len(points), int(inlier.sum())
        )
        return ShapeEstimate(
            links=tuple(link.superquadric for link in links),
            initial_poses=np.array([link.planar_pose for link in links]),
            uncertainty=np.array([link.std for link in links]),
            cloud=PointCloud(points[inlier]),
            covariance=np.array([link.covariance for link in links]),
        )

    def _object_points(self, cloud: PointCloud) -> FloatArray:
        """The finite points above the table clearance: [N, 3]; DataError when too few."""
        points = np.asarray(cloud.points_m, dtype=np.float64)
        if points.ndim != 2 or points.shape[1] != 3 or len(points) == 0:
            raise DataError(
                f"shape.ems: the point cloud is empty (shape {points.shape}); "
                "check the camera and the segmentation"
            )
        if not np.all(np.isfinite(points)):
            raise DataError(
                "shape.ems: the point cloud contains NaN or inf points; drop "
                "invalid depth pixels before fitting"
            )
        clearance = self.config.table_clearance_m
        if not self.config.on_table:
            if len(points) < self.config.min_points:
                raise DataError(
                    f"shape.ems: only {len(points)} points, fewer than min_points = "
                    f"{self.config.min_points}; is the object in view? Move the camera closer, "
                    "add views, or lower min_points"
                )
            return points
        above = points[points[:, 2] > clearance]
        if len(above) < self.config.min_points:
            raise DataError(
                f"shape.ems: only {len(above)} of {len(points)} points lie above the table "
                f"(z > {clearance} m), fewer than min_points = {self.config.min_points}; "
                "is the object in view? Move the camera closer, add views, or lower "
                "min_points / table_clearance_m"
            )
        return above
