"""Gaussian process implicit surface (GPIS) from touches (paper 2, III-G, eq. 29-36).

The surface is the zero level set of a signed distance function f (negative inside). f is a
Gaussian process with a prior mean m (the recogniser's maximum-likelihood shape, or a sphere)
and the thin-plate covariance k(r) = 2 r^3 - 3 R r^2 + R^3 (Williams & Fitzgibbon 2006). Every
contact observes the value f(x) = 0 and the gradient grad f(x) = outward normal, so each
contact adds four jointly Gaussian observations; their covariances are the kernel's first and
second derivatives.

The kernel is a covariance only on a region small compared with R: values alone need every
distance <= R, and with gradient observations we measured negative eigenvalues up to R = 1.25 x
the region's diameter (points on a sphere). So R is bounded below by 1.5 x the diagonal of the
box holding the contacts, the prior shape and every query; within its bounds R is fitted by
maximising the log marginal likelihood of the contacts.

Observations are ordered per contact: ``[f, df/dx, df/dy, df/dz]`` of contact 0, then of
contact 1, ... so that a new contact appends four rows and the Cholesky factor grows by one
block (no refactorisation).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray
from pydantic import Field
from scipy.linalg import cho_solve, solve_triangular
from scipy.optimize import minimize_scalar
from vistac.component import Component, ComponentConfig, ComponentContext
from vistac.errors import DataError
from vistac.plugins.touch.types import MlePrior, SignedDistance
from vistac.types import FloatArray

log = logging.getLogger(__name__)

OUTPUTS = 4
"""Observations per contact: the value and the three gradient components."""

SCALE_WINDOW = 1.5
"""A refit of the kernel scale searches within this factor of the current scale."""

QUERY_CHUNK = 8192
"""Query points per block when predicting (bounds the [chunk, 4n] cross-covariance)."""


def thin_plate_profile(
    r_m: FloatArray, scale_m: float
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """The thin-plate kernel as a function of distance, and its first two derivatives.

    r_m: distances [...]; scale_m: R. Returns (k, dk/dr, d2k/dr2), each shaped like ``r_m``:
    k = 2 r^3 - 3 R r^2 + R^3, k' = 6 r^2 - 6 R r, k'' = 12 r - 6 R (eq. 33-36).
    """
    r = np.asarray(r_m, dtype=np.float64)
    value = 2.0 * r**3 - 3.0 * scale_m * r**2 + scale_m**3
    first = 6.0 * r**2 - 6.0 * scale_m * r
    second = 12.0 * r - 6.0 * scale_m
    return value, first, second


def _differences(a_m: FloatArray, b_m: FloatArray) -> tuple[FloatArray, FloatArray]:
    """d = a_i - b_j [n, m, 3] and its norm r [n, m]."""
    d = a_m[:, None, :] - b_m[None, :, :]
    return d, np.sqrt(np.einsum("nmk,nmk->nm", d, d))


def joint_covariance(a_m: FloatArray, b_m: FloatArray, scale_m: float) -> FloatArray:
    """Covariance of (f, grad f) at points ``a_m`` [n, 3] with (f, grad f) at ``b_m`` [m, 3].

    Returns [4n, 4m] in the per-point order ``[f, fx, fy, fz]``. With d = a - b, r = |d|:
    cov(f, f) = k(r); cov(f(a), d_j f(b)) = 6 (R - r) d_j; cov(d_i f(a), f(b)) = -6 (R - r) d_i;
    cov(d_i f(a), d_j f(b)) = 6 (R - r) delta_ij - 6 d_i d_j / r.
    """
    d, r = _differences(a_m, b_m)
    n, m = r.shape
    out = np.empty((n, OUTPUTS, m, OUTPUTS))  # viewed as [4n, 4m] at the end
    out[:, 0, :, 0] = thin_plate_profile(r, scale_m)[0]
    slope = 6.0 * (scale_m - r)  # -k'(r) / r
    six_over_r = np.divide(6.0, r, out=np.zeros_like(r), where=r > 0.0)
    for i in range(3):
        slope_d = slope * d[..., i]
        out[:, 0, :, 1 + i] = slope_d
        out[:, 1 + i, :, 0] = -slope_d
        scaled = six_over_r * d[..., i]
        for j in range(i, 3):
            block = -scaled * d[..., j]
            if i == j:
                block += slope
            out[:, 1 + i, :, 1 + j] = block
            out[:, 1 + j, :, 1 + i] = block
    return out.reshape(OUTPUTS * n, OUTPUTS * m)


def value_cross_covariance(q_m: FloatArray, b_m: FloatArray, scale_m: float) -> FloatArray:
    """Covariance [p, 4m] of f at query points ``q_m`` [p, 3] with (f, grad f) at ``b_m`` [m, 3]."""
    d, r = _differences(q_m, b_m)
    block = np.empty((*r.shape, OUTPUTS))
    block[..., 0] = thin_plate_profile(r, scale_m)[0]
    block[..., 1:] = (6.0 * (scale_m - r))[..., None] * d
    return block.reshape(r.shape[0], OUTPUTS * r.shape[1])


def sphere_sdf(centre_m: FloatArray, radius_m: float) -> SignedDistance:
    """Sphere signed distance: points [N, 3] -> (|x - c| - r [N], outward normal [N, 3])."""
    centre = np.asarray(centre_m, dtype=np.float64)

    def sdf(points_m: FloatArray) -> tuple[FloatArray, FloatArray]:
        offset = np.asarray(points_m, dtype=np.float64) - centre
        norm = np.linalg.norm(offset, axis=1)
        normal = np.divide(offset, norm[:, None], out=np.zeros_like(offset),
                           where=norm[:, None] > 0)
        normal[norm == 0.0, 2] = 1.0
        return norm - radius_m, normal

    return sdf


def fit_sphere(
    points_m: FloatArray, normals: FloatArray, min_radius_m: float
) -> tuple[FloatArray, float]:
    """A sphere (centre [3], radius) for contacts [n, 3] with outward normals [n, 3], n >= 1.

    The radius is the mean distance of the contacts to their centroid, at least
    ``min_radius_m``; each contact then votes for the centre ``x - r n`` (a single contact
    gives a sphere of the minimum radius touching it).
    """
    centroid = points_m.mean(axis=0)
    radius_m = max(float(np.linalg.norm(points_m - centroid, axis=1).mean()), min_radius_m)
    return (points_m - radius_m * normals).mean(axis=0), radius_m


@dataclass(frozen=True)
class GpisNoise:
    """Observation noise std: of the value (m) and of each gradient (normal) component."""

    value_m: float = 1e-3
    gradient: float = 0.1

    def variances(self, count: int) -> FloatArray:
        """Diagonal noise variances [4 count] in the per-point observation order."""
        block = np.array([self.value_m**2, self.gradient**2, self.gradient**2, self.gradient**2])
        return np.tile(block, count)


class Gpis:
    """GP posterior of a signed distance function given contacts and a prior mean.

    Holds the contacts [n, 3], their normals [n, 3], the Cholesky factor of the noisy joint
    covariance [4n, 4n] and the weights alpha = K^-1 (y - m) [4n].
    """

    def __init__(
        self,
        scale_m: float,
        noise: GpisNoise | None = None,
        prior: SignedDistance | None = None,
        jitter: float = 1e-10,
    ) -> None:
        """``prior``: the prior mean (signed distance, gradient); None: zero mean."""
        if scale_m <= 0.0:
            raise DataError(f"GPIS kernel scale must be positive, got {scale_m}")
        self.scale_m = float(scale_m)
        self.noise = noise or GpisNoise()
        self.prior = prior
        self.jitter = jitter
        self.points_m = np.zeros((0, 3))
        self.normals = np.zeros((0, 3))
        self._chol = np.zeros((0, 0))
        self._alpha = np.zeros(0)

    @property
    def count(self) -> int:
        """Number of contacts."""
        return len(self.points_m)

    def _prior_at(self, points_m: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Prior mean value [N] and gradient [N, 3] at ``points_m`` [N, 3]."""
        if self.prior is None:
            return np.zeros(len(points_m)), np.zeros((len(points_m), 3))
        value, gradient = self.prior(points_m)
        return np.asarray(value, dtype=np.float64), np.asarray(gradient, dtype=np.float64)

    def _residual(self) -> FloatArray:
        """Observations minus prior [4n]: (0 - m(x), normal - grad m(x)) per contact."""
        value, gradient = self._prior_at(self.points_m)
        block = np.concatenate([-value[:, None], self.normals - gradient], axis=1)
        return block.reshape(-1)

    def _noisy_covariance(self, points_m: FloatArray, scale_m: float) -> FloatArray:
        """K(X, X) + noise + jitter [4n, 4n]."""
        cov = joint_covariance(points_m, points_m, scale_m)
        cov[np.diag_indices_from(cov)] += self.noise.variances(len(points_m)) + self.jitter
        return cov

    def _factor(self, points_m: FloatArray, scale_m: float) -> FloatArray:
        """Lower Cholesky factor of the noisy covariance; DataError when not positive definite."""
        try:
            return np.linalg.cholesky(self._noisy_covariance(points_m, scale_m))
        except np.linalg.LinAlgError as error:
            raise DataError(
                f"GPIS covariance of {len(points_m)} contacts is not positive definite at "
                f"scale {scale_m:.4g} m (contacts too close for the noise level?)"
            ) from error

    def _solve_alpha(self) -> None:
        self._alpha = cho_solve((self._chol, True), self._residual()) if self.count else np.zeros(0)

    def set_contacts(self, points_m: FloatArray, normals: FloatArray) -> None:
        """Replace all contacts [n, 3] and normals [n, 3] (normals are normalised) and refactor."""
        points_m, normals = _checked_contacts(points_m, normals)
        self.points_m, self.normals = points_m, normals
        self._chol = self._factor(points_m, self.scale_m) if len(points_m) else np.zeros((0, 0))
        self._solve_alpha()

    def add_contact(self, point_m: FloatArray, normal: FloatArray) -> None:
        """Append a contact [3] and its outward normal [3]; the factor grows by a block, O(n^2)."""
        point, unit = _checked_contacts(np.reshape(point_m, (1, 3)), np.reshape(normal, (1, 3)))
        cross = joint_covariance(self.points_m, point, self.scale_m)  # [4n, 4]
        corner = joint_covariance(point, point, self.scale_m)
        corner[np.diag_indices_from(corner)] += self.noise.variances(1) + self.jitter
        solved = solve_triangular(self._chol, cross, lower=True) if self.count else cross[:0]
        try:
            tail = np.linalg.cholesky(corner - solved.T @ solved)
        except np.linalg.LinAlgError as error:
            raise DataError(
                f"GPIS: contact {point[0]} makes the covariance singular (duplicate contact?)"
            ) from error
        size = OUTPUTS * self.count
        chol = np.zeros((size + OUTPUTS, size + OUTPUTS))
        chol[:size, :size] = self._chol
        chol[size:, :size] = solved.T
        chol[size:, size:] = tail
        self._chol = chol
        self.points_m = np.vstack([self.points_m, point])
        self.normals = np.vstack([self.normals, unit])
        self._solve_alpha()

    def set_prior(self, prior: SignedDistance | None) -> None:
        """Change the prior mean; the factor is unchanged, only the weights are re-solved."""
        self.prior = prior
        self._solve_alpha()

    def set_scale(self, scale_m: float) -> None:
        """Change the kernel scale R and refactor."""
        self.scale_m = float(scale_m)
        if self.count:
            self._chol = self._factor(self.points_m, self.scale_m)
        self._solve_alpha()

    def log_marginal_likelihood(self, scale_m: float | None = None) -> float:
        """log p(y | X, R) of the contacts' residuals under the GP (at ``scale_m``, default R)."""
        if self.count == 0:
            return 0.0
        if scale_m is None or scale_m == self.scale_m:
            chol = self._chol
        else:
            chol = self._factor(self.points_m, scale_m)
        residual = self._residual()
        whitened = solve_triangular(chol, residual, lower=True)
        log_det = 2.0 * np.log(np.diag(chol)).sum()
        return float(-0.5 * whitened @ whitened - 0.5 * log_det
                     - 0.5 * residual.size * np.log(2.0 * np.pi))

    def fit_scale(self, low_m: float, high_m: float, tolerance: float = 0.03) -> float:
        """Set R to the maximiser of the log marginal likelihood in [low_m, high_m]; return it.

        Bounded scalar search over log R (``tolerance``: relative precision of R).
        """
        if not 0.0 < low_m <= high_m:
            raise DataError(f"GPIS scale bounds need 0 < low <= high, got {low_m}, {high_m}")
        if self.count == 0 or low_m == high_m:
            self.set_scale(low_m if self.count == 0 else high_m)
            return self.scale_m

        def negative(log_scale: float) -> float:
            try:
                return -self.log_marginal_likelihood(float(np.exp(log_scale)))
            except DataError:
                return np.inf

        bounds = (np.log(low_m), np.log(high_m))
        result = minimize_scalar(negative, bounds=bounds, method="bounded",
                                 options={"xatol": tolerance})
        candidates = {float(result.x): float(result.fun)}
        candidates.update({bound: negative(bound) for bound in bounds})  # optimum at a bound
        best = min(candidates, key=candidates.__getitem__)
        self.set_scale(float(np.exp(best)))
        log.debug("GPIS scale %.4g m (log likelihood %.4g)", self.scale_m, -candidates[best])
        return self.scale_m

    def mean(self, points_m: FloatArray) -> FloatArray:
        """Posterior mean signed distance [N] at query points [N, 3] (eq. 30)."""
        return self._predict(points_m, want_variance=False)[0]

    def predict(self, points_m: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Posterior mean [N] and variance [N] at points [N, 3] (eq. 30, 31)."""
        mean, variance = self._predict(points_m, want_variance=True)
        assert variance is not None
        return mean, variance

    def variance(self, points_m: FloatArray) -> FloatArray:
        """Posterior variance [N] of the signed distance at points [N, 3]."""
        return self.predict(points_m)[1]

    def _predict(
        self, points_m: FloatArray, want_variance: bool
    ) -> tuple[FloatArray, FloatArray | None]:
        points = np.asarray(points_m, dtype=np.float64).reshape(-1, 3)
        mean = self._prior_at(points)[0].copy()
        variance = np.full(len(points), self.scale_m**3) if want_variance else None
        if self.count == 0:
            return mean, variance
        for start in range(0, len(points), QUERY_CHUNK):
            rows = slice(start, start + QUERY_CHUNK)
            if variance is None:
                mean[rows] += self._mean_correction(points[rows])
                continue
            cross = value_cross_covariance(points[rows], self.points_m, self.scale_m)
            mean[rows] += cross @ self._alpha
            whitened = solve_triangular(self._chol, cross.T, lower=True)
            variance[rows] -= np.einsum("ij,ij->j", whitened, whitened)
        if variance is not None:
            np.maximum(variance, 0.0, out=variance)
        return mean, variance

    def _mean_correction(self, points_m: FloatArray) -> FloatArray:
        """K(q, X) alpha [p] for query points [p, 3] without forming the [p, 4n] matrix.

        With weights (a_j, g_j) per contact b_j: sum_j k(r_ij) a_j + 6 (R - r_ij) (q_i - b_j) g_j,
        where q_i g_j - b_j g_j and the distances come from matrix products.
        """
        weights = self._alpha.reshape(-1, OUTPUTS)
        contacts = self.points_m
        squared = (np.einsum("pk,pk->p", points_m, points_m)[:, None]
                   + np.einsum("nk,nk->n", contacts, contacts)[None, :]
                   - 2.0 * points_m @ contacts.T)  # fmt: skip
        r = np.sqrt(np.maximum(squared, 0.0))
        scale = self.scale_m
        kernel = r * r * (2.0 * r - 3.0 * scale) + scale**3
        along = points_m @ weights[:, 1:].T - np.einsum("nk,nk->n", contacts, weights[:, 1:])
        return np.asarray(kernel @ weights[:, 0] + 6.0 * ((scale - r) * along).sum(axis=1))

    def gradient(self, points_m: FloatArray) -> FloatArray:
        """Posterior mean gradient [N, 3] of the signed distance at points [N, 3]."""
        points = np.asarray(points_m, dtype=np.float64).reshape(-1, 3)
        gradient = self._prior_at(points)[1].copy()
        if self.count == 0:
            return gradient
        for start in range(0, len(points), QUERY_CHUNK // OUTPUTS):
            rows = slice(start, start + QUERY_CHUNK // OUTPUTS)
            cross = joint_covariance(points[rows], self.points_m, self.scale_m)
            gradient[rows] += (cross @ self._alpha).reshape(-1, OUTPUTS)[:, 1:]
        return gradient

    def sdf(self, points_m: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Posterior mean as a ``SignedDistance``: (value [N], unit gradient [N, 3])."""
        gradient = self.gradient(points_m)
        norm = np.linalg.norm(gradient, axis=1, keepdims=True)
        return self.mean(points_m), np.divide(gradient, norm, out=np.zeros_like(gradient),
                                              where=norm > 0)


def _checked_contacts(points_m: FloatArray, normals: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Validate contacts [n, 3] and normals [n, 3]; return them with unit normals."""
    points = np.asarray(points_m, dtype=np.float64)
    normals = np.asarray(normals, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or normals.shape != points.shape:
        raise DataError(f"GPIS contacts must be [n, 3] with normals [n, 3], got "
                        f"{points.shape} and {normals.shape}")
    if not (np.all(np.isfinite(points)) and np.all(np.isfinite(normals))):
        raise DataError("GPIS contacts or normals contain NaN or inf")
    norm = np.linalg.norm(normals, axis=1, keepdims=True)
    if np.any(norm < 1e-9):
        raise DataError("GPIS contact normals must be non-zero")
    return points, normals / norm


@dataclass(frozen=True)
class SurfaceMesh:
    """A reconstructed surface: vertices_m [V, 3] (m) and triangles [T, 3] (outward facing)."""

    vertices_m: FloatArray
    triangles: NDArray[np.int64]


def box_around(points_m: FloatArray, margin_m: float) -> tuple[FloatArray, FloatArray]:
    """Axis-aligned box (lower [3], upper [3]) around points [N, 3] grown by ``margin_m``."""
    return points_m.min(axis=0) - margin_m, points_m.max(axis=0) + margin_m


def extract_surface(
    field: Callable[[FloatArray], FloatArray],
    lower_m: FloatArray,
    upper_m: FloatArray,
    grid_points: int,
    min_component_fraction: float = 0.02,
) -> SurfaceMesh:
    """Zero level set of ``field`` (points [N, 3] -> signed distance [N]) by marching cubes.

    The grid has ``grid_points`` samples along the box's longest side (cubic cells). The
    outermost grid layer is forced outside, so the surface is closed; connected components
    with fewer than ``min_component_fraction`` of the largest one's triangles are dropped.
    """
    from skimage.measure import marching_cubes

    step_m = float(np.max(upper_m - lower_m)) / (grid_points - 1)
    counts = np.maximum(np.ceil((upper_m - lower_m) / step_m).astype(int) + 1, 2)
    axes = [lower_m[i] + step_m * np.arange(counts[i]) for i in range(3)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    values = field(grid).reshape(*counts)
    values[values == 0.0] = 1e-12  # exact zeros on grid points give non-manifold vertices
    shell = np.ones(values.shape, dtype=bool)
    shell[1:-1, 1:-1, 1:-1] = False
    values[shell] = np.maximum(values[shell], step_m)
    if values.min() >= 0.0:
        raise DataError("the reconstructed signed distance has no interior in its box")
    vertices, faces, _, _ = marching_cubes(values, 0.0, spacing=(step_m,) * 3,
                                           allow_degenerate=False)
    mesh = _drop_small_components(SurfaceMesh(vertices + lower_m, faces.astype(np.int64)),
                                  min_component_fraction)
    if enclosed_volume_m3(mesh) < 0.0:  # face the triangles outward
        mesh = SurfaceMesh(mesh.vertices_m, mesh.triangles[:, ::-1].copy())
    return mesh


def _drop_small_components(mesh: SurfaceMesh, min_fraction: float) -> SurfaceMesh:
    """Keep connected components with >= ``min_fraction`` of the largest one's triangles."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    tri = mesh.triangles
    edges = np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]]])
    size = len(mesh.vertices_m)
    graph = coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(size, size))
    _, labels = connected_components(graph, directed=False)
    tri_labels = labels[tri[:, 0]]
    counts = np.bincount(tri_labels)
    keep = counts[tri_labels] >= min_fraction * counts.max()
    used = np.unique(tri[keep])
    remap = np.full(size, -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    return SurfaceMesh(mesh.vertices_m[used], remap[tri[keep]])


def enclosed_volume_m3(mesh: SurfaceMesh) -> float:
    """Signed volume of a closed mesh (positive when its triangles face outward)."""
    a, b, c = (mesh.vertices_m[mesh.triangles[:, i]] for i in range(3))
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


class GpisSettings(ComponentConfig):
    """Settings of a touch surface reconstruction (``touch.gpis``'s Config without roles)."""

    grid_points: int = Field(
        48, ge=8, le=256, description="marching-cubes samples along the box's longest side")
    value_noise_m: float = Field(1e-3, gt=0.0, description="std of a contact's distance")
    normal_noise: float = Field(0.1, gt=0.0, description="std of each normal component")
    margin_m: float = Field(
        0.02, ge=0.0, description="box margin around the prior shape and the contacts")
    min_scale_factor: float = Field(
        1.5, ge=1.3, description="kernel scale R >= this x box diagonal (with gradient "
        "observations the kernel is indefinite below about 1.25)")
    max_scale_factor: float = Field(4.0, ge=1.3, description="R <= this x box diagonal")
    scale_fit_every: int = Field(
        5, ge=1, description="refit R by marginal likelihood every this many contacts")
    sphere_radius_m: float = Field(
        0.03, gt=0.0, description="smallest radius of the sphere prior (no recogniser)")


class TouchSurface:
    """A GPIS over contacts with a (changing) prior shape, its box, scale and surface.

    The prior mean is the given :class:`MlePrior`'s signed distance, or a sphere fitted to the
    contacts without one. The GP lives in the box around the prior shape and the contacts; the
    kernel scale R is refitted by marginal likelihood every ``scale_fit_every`` contacts within
    [min_scale_factor, max_scale_factor] x the box diagonal.
    """

    def __init__(self, settings: GpisSettings) -> None:
        self.settings = settings
        self.gp = Gpis(1.0, GpisNoise(settings.value_noise_m, settings.normal_noise))
        self.mle: MlePrior | None = None
        self.lower_m = np.zeros(3)
        self.upper_m = np.zeros(3)
        self._surface: SurfaceMesh | None = None
        self._scale_fitted = False

    def update(self, contact: tuple[FloatArray, FloatArray] | None, mle: MlePrior | None) -> None:
        """Add a contact (point [3], outward normal [3]) if any, with the current prior shape."""
        self.mle = mle
        self._surface = None
        if contact is not None:
            point, normal = np.asarray(contact[0], float), np.asarray(contact[1], float)
            if self.gp.count == 0:
                self.gp.set_contacts(point[None], normal[None])
            else:
                self.gp.add_contact(point, normal)
            self._refresh(fit=(self.gp.count - 1) % self.settings.scale_fit_every == 0)
        elif self.gp.count:
            self._refresh(fit=False)

    def reconstruction(self) -> SurfaceMesh:
        """Zero level set of the posterior mean (marching cubes; cached until the next update)."""
        if self.gp.count == 0:
            raise DataError("touch.gpis: no contact yet, nothing to reconstruct")
        if self._surface is None:
            self._surface = extract_surface(self.gp.mean, self.lower_m, self.upper_m,
                                            self.settings.grid_points)
        return self._surface

    def zero_level_set(self, grid_points: int) -> tuple[FloatArray, FloatArray]:
        """Vertices [V, 3] of the posterior mean's zero level set at a (coarse) grid and the
        unit posterior gradients [V, 3] there (outward normals)."""
        mesh = extract_surface(self.gp.mean, self.lower_m, self.upper_m, grid_points)
        return mesh.vertices_m, self.gp.sdf(mesh.vertices_m)[1]

    def _refresh(self, fit: bool) -> None:
        """Set the prior and the box; refit R when ``fit`` or when R left its bounds."""
        prior, extent_m = self._prior_and_extent()
        self.gp.set_prior(prior)
        self.lower_m, self.upper_m = box_around(extent_m, self.settings.margin_m)
        diagonal_m = float(np.linalg.norm(self.upper_m - self.lower_m))
        low = self.settings.min_scale_factor * diagonal_m
        high = max(self.settings.max_scale_factor, self.settings.min_scale_factor) * diagonal_m
        if fit:
            self.gp.fit_scale(*self._scale_window(low, high))
            self._scale_fitted = True
        elif not low <= self.gp.scale_m <= high:
            self.gp.set_scale(float(np.clip(self.gp.scale_m, low, high)))

    def _scale_window(self, low_m: float, high_m: float) -> tuple[float, float]:
        """Search bounds for R: all of [low, high] the first time, then within a factor
        ``SCALE_WINDOW`` of the current R (the optimum moves little between refits)."""
        scale_m = self.gp.scale_m
        if not self._scale_fitted or not low_m <= scale_m <= high_m:
            return low_m, high_m
        return max(low_m, scale_m / SCALE_WINDOW), min(high_m, scale_m * SCALE_WINDOW)

    def _prior_and_extent(self) -> tuple[SignedDistance, FloatArray]:
        """The prior mean and points [M, 3] the box must hold (contacts and the prior shape)."""
        if self.mle is not None:
            return self.mle.sdf, np.vstack([self.gp.points_m, self.mle.vertices_m])
        centre, radius = fit_sphere(self.gp.points_m, self.gp.normals,
                                    self.settings.sphere_radius_m)
        corners = np.stack([centre - radius, centre + radius])
        return sphere_sdf(centre, radius), np.vstack([self.gp.points_m, corners])


class GpisSurface(Component):
    """``touch.gpis``: the surface of a touched object as a GPIS with the recogniser's prior.

    Every contact is added to the GP; misses carry no signed-distance value and are left to
    the recogniser. At each update the prior mean is the maximum-likelihood shape of the
    component in role ``prior`` (its ``mle_prior()``), or a sphere without one (see
    :class:`TouchSurface`). With ``explore_grid_points`` set, once the recogniser calls the
    object novel (``known()`` False) the estimate also carries the GPIS zero level set
    (``surface_points_m``, ``surface_normals``) so that exploration and its termination use
    the reconstructed surface instead of the MLE shape (eq. 40, 45).
    """

    kind = "touch_estimator"

    class Config(GpisSettings):
        prior: str | None = Field("estimator", description="role of the recogniser whose "
                                  "mle_prior() is the prior mean (None: a sphere prior)")
        explore_grid_points: int | None = Field(
            None, ge=8, le=128, description="publish the GPIS surface for exploration, from "
            "marching cubes at this grid, once the object is novel (None: never)")

    def __init__(self, config: GpisSurface.Config, ctx: ComponentContext) -> None:
        super().__init__(config, ctx)
        self.surface = TouchSurface(config)
        self._novel = False

    @property
    def gp(self) -> Gpis:
        return self.surface.gp

    def update(
        self,
        start_m: FloatArray,
        target_m: FloatArray,
        contact: tuple[FloatArray, FloatArray] | None,
    ) -> dict[str, Any]:
        """Add a contact (point [3], outward normal [3]); a miss (None) only refreshes the prior."""
        self.surface.update(contact, self._recogniser_prior())
        return self.estimate()

    def estimate(self) -> dict[str, Any]:
        """The current estimate: variance callable, contact count, scale, lazy reconstruction
        and, when exploring a novel object on the GPIS, its surface points and normals."""
        mle = self.surface.mle
        estimate: dict[str, Any] = {
            "surface_variance": self.gp.variance,
            "gpis_contacts": self.gp.count,
            "kernel_scale_m": self.gp.scale_m,
            "gpis_prior": mle.class_name if mle is not None else "sphere",
            "reconstruction": self.surface.reconstruction,
        }
        if self.config.explore_grid_points is not None and self._novel and self.gp.count:
            points, normals = self.surface.zero_level_set(self.config.explore_grid_points)
            estimate.update(surface_points_m=points, surface_normals=normals)
        return estimate

    def reconstruction(self) -> SurfaceMesh:
        """Zero level set of the posterior mean (world frame)."""
        return self.surface.reconstruction()

    def _recogniser_prior(self) -> MlePrior | None:
        """The recogniser's MLE shape, or None (no role configured, no such role, no estimate);
        also notes whether the recogniser calls the object novel."""
        if self.config.prior is None:
            self._novel = True
            return None
        try:
            recogniser = self.ctx.component(self.config.prior)
        except KeyError:
            self._novel = True
            return None
        known = getattr(recogniser, "known", None)
        self._novel = callable(known) and known() is False
        getter = getattr(recogniser, "mle_prior", None)
        return getter() if callable(getter) else None
