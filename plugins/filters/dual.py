"""Numerical core of the dual differentiable filter (paper 1, III-F, eq. 19-36).

The belief over the joint state ``s = (psi, phi)`` (pose/twist block, then parameters; see
``state.StateLayout``) is one Gaussian. A step has two halves:

- **Predict** (eq. 21-26): C Monte-Carlo sigma points ``mu + L eps`` (``L`` the Cholesky
  factor), the draws ``eps`` and the process noise's made antithetic pairs with sample mean 0
  and covariance I (``antithetic_noise``), so that the points' moments are the belief's and
  no odd moment of their scatter correlates with their parameters by chance (the paper's raw
  draws make static parameters drift and collapse by the sample error, step after step; see
  ``standardise_noise``). Points that break the
  physical constraints reach the process model as a projected (clamped) copy, but every
  point keeps its own unprojected parameters in the moments, so the parameter variance is
  preserved. Parameters stay constant (eq. 23), the process noise is
  added by reparameterisation (eq. 24), and the moments use weights 1/C (eq. 25-26).
- **Update**: the parameters by importance weights (eq. 31, in log space, diagonal R; by
  default marginal over the points' pose scatter and less the sampling noise of fitting that
  on C points, see ``marginal_log_likelihood``) and
  Liu-West kernel smoothing in its textbook form (``a = (3 delta - 1) / (2 delta)``,
  ``h^2 = 1 - a^2``; the paper's eq. 33 and ``a = h = 0.01`` are not used); the kernel mixture's
  covariance, ``a^2 V + h^2 V``, equals the weighted particle covariance ``V``. A mass,
  friction or joint friction whose mean has left the feasible set (the unprojected points
  below zero outweighing the rest) takes the moments of the Gaussian truncated at zero
  (``truncate_negative_means``). Then the pose,
  conditioned on the updated parameter mean (eq. 34-35), by an unscented update whose
  innovation covariance ``S = U W U^T + R`` is only ever inverted through the Woodbury
  identity in sigma-point space (k = 4098 observations in practice, never a k x k matrix).
- **Joint posterior** (eq. 36): the product of the parameter Gaussian ``N(mu_phi, S_phi)`` and
  the updated conditional pose Gaussian ``N(a + B' phi, S_psi|phi)``. The paper keeps the
  cross-covariance constant, which can make the joint covariance indefinite; here the
  regression coefficient ``B = S_psi,phi S_phi^-1`` of the prior is carried through the
  update as ``B' = S_psi|phi,new S_psi|phi^-1 B`` (= ``(I - K H) B`` for a linear observation,
  the statistical linearisation otherwise). The product of the two factors is SPD, and for a
  linear-Gaussian system the step equals the Kalman filter on the joint state.

All math is torch float64, differentiable end to end, with optional leading batch dimensions.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple, Protocol

import torch
from torch import Tensor
from vistac.errors import DataError
from vistac.plugins.filters.nets import rotate
from vistac.plugins.filters.state import DTYPE, Prediction, ProcessInput, StateLayout

logger = logging.getLogger(__name__)

POSITIVE_FLOOR = 1e-6
"""Value a non-positive mass (kg) or table friction coefficient is projected to."""
_JITTER_START = 1e-12
"""First diagonal jitter tried by ``cholesky_safe``, relative to the mean diagonal."""
_JITTER_GROWTH = 10.0
_JITTER_TRIES = 10


class ProcessModel(Protocol):
    """Predicts the next pose block of C sigma points (eq. 22)."""

    def predict(self, states: Tensor, inputs: ProcessInput, dt_s: float) -> Prediction:
        """states: [..., C, n], all feasible -> Prediction with [..., C, ...] fields."""
        ...


class ObservationModel(Protocol):
    """Expected observations of sigma points and the observation noise (eq. 27-30)."""

    def expected(self, states: Tensor, force_n: Tensor) -> Tensor:
        """states: [..., C, n] (pose block used), force_n: [..., C, 2] -> [..., C, k], a new
        tensor that the caller owns (the filter overwrites it with its residuals)."""
        ...

    def noise_var(self, observation: Tensor) -> Tensor:
        """observation: [..., k] -> diagonal of R, [..., k], positive."""
        ...


UNEXPLAINED_VAR = 1e6
"""Noise variance given to observation entries the model cannot explain (``unexplained``):
large enough that they carry no weight, finite so that every check still applies."""


@dataclass(frozen=True)
class Belief:
    """Gaussian belief over the joint state: mean [..., n], cov [..., n, n]."""

    mean: Tensor
    cov: Tensor

    def check_finite(self, names: Sequence[str] | None = None) -> None:
        """Raise DataError naming the first non-finite entry (by ``names`` when given)."""
        require_finite(self.mean, "belief mean", names)
        require_finite(self.cov, "belief covariance", names, entry_dims=2)


def require_finite(
    values: Tensor, what: str, names: Sequence[str] | None = None, entry_dims: int = 1
) -> None:
    """Raise DataError if ``values`` has a NaN or inf; the message names the first one.

    The last ``entry_dims`` dimensions index entries (named by ``names`` when given), the
    leading ones are batch (and sigma point) dimensions.
    """
    if bool(torch.isfinite(values.detach().sum())):
        return  # a NaN or inf anywhere makes the sum non-finite: one reduction, no mask
    bad = ~torch.isfinite(values.detach())
    if not bool(bad.any()):
        return  # finite values whose sum overflows
    index = [int(i) for i in bad.nonzero()[0]]
    leading, entry = index[: len(index) - entry_dims], index[len(index) - entry_dims :]
    labels = [names[i] if names is not None else str(i) for i in entry]
    where = f" at leading index {tuple(leading)}" if leading else ""
    value = float(values.detach()[tuple(index)])
    raise DataError(f"{what} is not finite: {what}[{', '.join(labels)}] = {value}{where}")


def require_finite_summary(summary: Tensor, values: Tensor, what: str) -> None:
    """Cheap check of a large tensor through a ``summary`` it propagates NaN and inf into.

    Only when the summary is not finite is ``values`` searched (DataError naming the entry);
    a finite ``values`` with a non-finite summary is reported as an overflow.
    """
    if bool(torch.isfinite(summary.detach()).all()):
        return
    require_finite(values, what)
    raise DataError(f"{what} overflows: its likelihood or mean is not finite")


def symmetrize(matrix: Tensor) -> Tensor:
    """[..., d, d] -> (A + A^T) / 2, exactly symmetric."""
    return 0.5 * (matrix + matrix.transpose(-1, -2))


def cholesky_safe(cov: Tensor) -> Tensor:
    """Lower Cholesky factor of the symmetrised ``cov`` [..., d, d] -> [..., d, d].

    Where the factorisation fails, a diagonal jitter relative to the mean diagonal is added
    (only to the failing batch elements), growing tenfold per try. Raises DataError if the
    matrix is not finite or still fails.
    """
    require_finite(cov, "covariance", entry_dims=2)
    sym = symmetrize(cov)
    factor, info = torch.linalg.cholesky_ex(sym)
    failed = info != 0
    if not bool(failed.any()):
        return factor
    eye = torch.eye(sym.shape[-1], dtype=sym.dtype, device=sym.device)
    scale = sym.diagonal(dim1=-2, dim2=-1).abs().mean(-1)
    scale = torch.where(scale > 0, scale, torch.ones_like(scale))
    jitter = _JITTER_START
    for _ in range(_JITTER_TRIES):
        shift = (jitter * scale * failed.to(sym.dtype))[..., None, None] * eye
        factor, info = torch.linalg.cholesky_ex(sym + shift)
        if not bool((info != 0).any()):
            logger.debug("cholesky needed a relative jitter of %.1e", jitter)
            return factor
        jitter *= _JITTER_GROWTH
    raise DataError(f"covariance is not positive definite even with a relative jitter {jitter}")


def standardise_noise(noise: Tensor) -> Tensor:
    """Draws [..., C, n] moved and rotated to sample mean exactly 0 and covariance (weights
    1/C) exactly I; unchanged where C <= n or the draws do not span the space.

    The parameters are static, so the filter's predicted parameter moments must be the
    belief's. From C raw draws they are not: each step the belief would be refitted to a
    sample whose mean is off by ``L eps_mean`` and whose covariance shrinks by ``1 - 1/C`` on
    average, and over a few hundred steps the parameters would wander and collapse even when
    no observation tells them apart (std 0.43 -> 0.05 kg over 225 steps of a push skill).
    """
    count, size = noise.shape[-2], noise.shape[-1]
    if count <= size:
        return noise
    centred = noise - noise.mean(-2, keepdim=True)
    factor, info = torch.linalg.cholesky_ex(centred.mT @ centred / count)
    white = torch.linalg.solve_triangular(factor, centred.mT, upper=False).mT
    return torch.where((info == 0)[..., None, None], white, noise)


def antithetic_noise(noise: Tensor) -> Tensor:
    """Draws [..., C, n] as antithetic pairs: the first C/2 rows whitened to second moment
    exactly I, then the same negated. Mean and covariance are then exactly 0 and I (as
    ``standardise_noise``, which is used instead for C odd, C/2 <= n or draws that do not
    span the space) and so is every odd moment: a quadratic effect of the points' scatter on
    what the filter compares has no sample correlation with their parameters, which the
    parameter likelihood would otherwise read as information (``marginal_log_likelihood``).

    The whitening is lower triangular, so the first columns of the result depend on the first
    columns of the draws alone: drawing more columns behind them leaves them as they are."""
    pairs = _pairs(noise)
    return standardise_noise(noise) if pairs is None else pairs


def _pairs(noise: Tensor) -> Tensor | None:
    """``antithetic_noise`` of noise [..., C, n], or None where it falls back."""
    count, size = noise.shape[-2], noise.shape[-1]
    half = count // 2
    if count % 2 or half <= size:
        return None
    draws = noise[..., :half, :]
    factor, info = torch.linalg.cholesky_ex(draws.mT @ draws / half)
    if not bool((info == 0).all()):
        return None
    white = torch.linalg.solve_triangular(factor, draws.mT, upper=False).mT
    return torch.cat([white, -white], -2)


def sigma_points_from_noise(belief: Belief, noise: Tensor) -> Tensor:
    """Reparameterised points ``mu + L eps`` (eq. 21) of noise [..., C, n] made antithetic
    (``antithetic_noise``) -> [..., C, n]: their moments are the belief's."""
    return _points(belief, antithetic_noise(noise))


def _points(belief: Belief, white: Tensor) -> Tensor:
    """``mu + L eps`` of noise [..., C, n] used as it is."""
    return belief.mean.unsqueeze(-2) + white @ cholesky_safe(belief.cov).transpose(-1, -2)


def _antithetic_jointly(
    state_noise: Tensor, process_noise: Tensor
) -> tuple[Tensor, Tensor, Tensor | None]:
    """State [..., C, n] and process [..., C, m] noise made antithetic together (``_pairs``),
    so that their sample correlation is exactly 0 too; the state part is ``antithetic_noise``
    of the state noise. Returns both and the joint pairs [..., C, n + m]; where joint pairs
    cannot be, the process noise is left as it is and the pairs are None."""
    joint = _pairs(torch.cat([state_noise, process_noise], -1))
    if joint is None:
        return antithetic_noise(state_noise), process_noise, None
    size = state_noise.shape[-1]
    return joint[..., :size], joint[..., size:], joint


def _standard_normal(
    shape: tuple[int, ...], generator: torch.Generator, device: torch.device
) -> Tensor:
    """Float64 N(0, 1) draws of ``shape`` from ``generator``."""
    return torch.randn(shape, generator=generator, dtype=DTYPE, device=device)


def sample_sigma_points(belief: Belief, count: int, generator: torch.Generator) -> Tensor:
    """C Monte-Carlo sigma points of the belief: -> [..., C, n]."""
    mean = belief.mean
    shape = (*mean.shape[:-1], count, mean.shape[-1])
    return sigma_points_from_noise(belief, _standard_normal(shape, generator, mean.device))


def on_load_ridge(states: Tensor, layout: StateLayout, reference: Tensor, push: Tensor) -> Tensor:
    """Copy of states [..., C, n] (m, f > 0) where, in the push rows, each link's mass and
    friction are moved along its friction load ``m f`` (kept) to the ratio ``m / f`` of
    reference [..., n] (the belief's mean). push [...] is true for a push.

    A quasi-static push shows a link's load, not how it splits into m and f: fed the moved
    points, a process model cannot tell points apart along ``m f = const``, so whatever it
    learned of m and f apart (from the training's spread of both) cannot make the belief
    wander along that curve.
    """
    if not bool(push.any()):
        return states.clone()
    params = layout.link_parameters(states)
    load = params[..., 0] * params[..., 1]  # [..., C, L]
    mean = layout.link_parameters(reference).clamp_min(POSITIVE_FLOOR)
    ratio = (mean[..., 0] / mean[..., 1]).unsqueeze(-2)  # [..., 1, L]
    mass_friction = torch.stack([(load * ratio).sqrt(), (load / ratio).sqrt()], -1)
    if not bool(push.all()):
        mass_friction = torch.where(push[..., None, None, None], mass_friction, params[..., :2])
    links = torch.cat([mass_friction, params[..., 2:]], -1).flatten(-2)
    joints = layout.joint_friction(states)
    return torch.cat([states[..., layout.pose_slice], links, joints], -1)


def feasible(states: Tensor, layout: StateLayout, link_size_m: Tensor) -> Tensor:
    """Physical constraints per point: states [..., C, n], link_size_m [..., L, 2] -> [..., C].

    m > 0, f > 0, f_j >= 0, and the CoM inside the link's footprint box |com_x| <= a1,
    |com_y| <= a2.
    """
    params = layout.link_parameters(states)
    half_extent_m = link_size_m.unsqueeze(-3)
    links_ok = (params[..., 0] > 0) & (params[..., 1] > 0)
    links_ok = links_ok & (params[..., 2:].abs() <= half_extent_m).all(-1)
    joints_ok = (layout.joint_friction(states) >= 0).all(-1)
    return links_ok.all(-1) & joints_ok


def project_feasible(states: Tensor, layout: StateLayout, link_size_m: Tensor) -> Tensor:
    """Projected copy of states [..., C, n] on the feasible set; feasible points are unchanged.

    Non-positive m and f become ``POSITIVE_FLOOR``, negative f_j become 0, the CoM is clamped
    to the footprint box of ``link_size_m`` [..., L, 2].
    """
    params = layout.link_parameters(states)
    half_extent_m = link_size_m.unsqueeze(-3)
    mass_friction = params[..., :2]
    mass_friction = torch.where(mass_friction > 0, mass_friction, POSITIVE_FLOOR)
    com_m = torch.maximum(torch.minimum(params[..., 2:], half_extent_m), -half_extent_m)
    links = torch.cat([mass_friction, com_m], -1).flatten(-2)
    joints = layout.joint_friction(states).clamp_min(0.0)
    return torch.cat([states[..., layout.pose_slice], links, joints], -1)


def weighted_moments(points: Tensor, weights: Tensor) -> tuple[Tensor, Tensor]:
    """points [..., C, d], normalised weights [..., C] -> mean [..., d], cov [..., d, d]."""
    mean = (weights.unsqueeze(-1) * points).sum(-2)
    deviation = points - mean.unsqueeze(-2)
    cov = (weights.unsqueeze(-1) * deviation).transpose(-1, -2) @ deviation
    return mean, symmetrize(cov)


def truncate_negative_means(
    mean: Tensor, cov: Tensor, rows: Sequence[int]
) -> tuple[Tensor, Tensor]:
    """A Gaussian mean [..., p], cov [..., p, p] whose entry ``i`` of ``rows`` has a mean <= 0
    replaced by its moments truncated to ``x_i > 0``; the other entries follow by their
    regression on ``x_i`` (exact for one truncation of a Gaussian; ``rows`` in turn).

    Entries with a positive mean are left alone, so a belief that has not left the feasible
    set is unchanged: truncating every step would push a mean near a bound away from it step
    after step, each moment-matched Gaussian again having a tail below zero.
    """
    if not bool((mean[..., list(rows)] <= 0).any()):
        return mean, cov  # the usual case, at the cost of one comparison
    for row in rows:
        var = cov[..., row, row].clamp_min(1e-30)
        std = var.sqrt()
        alpha = -mean[..., row] / std
        log_pdf = -0.5 * alpha.square() - 0.5 * math.log(2.0 * math.pi)
        mills = torch.exp(log_pdf - torch.special.log_ndtr(-alpha))  # phi(a) / (1 - Phi(a))
        new_mean = mean[..., row] + std * mills
        new_var = var * (1.0 + alpha * mills - mills.square()).clamp_min(1e-9)
        apply = (mean[..., row] <= 0).unsqueeze(-1)
        gain = cov[..., row] / var.unsqueeze(-1)
        shifted = mean + gain * (new_mean - mean[..., row]).unsqueeze(-1)
        rescaled = cov + gain.unsqueeze(-1) * gain.unsqueeze(-2) * (new_var - var)[..., None, None]
        mean = torch.where(apply, shifted, mean)
        cov = torch.where(apply.unsqueeze(-1), symmetrize(rescaled), cov)
    return mean, cov


def liu_west(particles: Tensor, weights: Tensor, delta: float) -> tuple[Tensor, Tensor]:
    """Moments of the Liu-West kernel mixture: particles [..., C, p], weights [..., C].

    Kernel locations ``a chi_i + (1 - a) mu`` with ``a = (3 delta - 1) / (2 delta)``, kernel
    covariance ``h^2 V`` with ``h^2 = 1 - a^2``, ``mu`` and ``V`` the weighted particle mean and
    covariance. Returns the mixture's mean [..., p] (= mu) and covariance [..., p, p] (= V).
    """
    shrink = (3.0 * delta - 1.0) / (2.0 * delta)
    mean, particle_cov = weighted_moments(particles, weights)
    locations = shrink * particles + (1.0 - shrink) * mean.unsqueeze(-2)
    _, location_cov = weighted_moments(locations, weights)
    return mean, location_cov + (1.0 - shrink**2) * particle_cov


def consume_subtract(values: Tensor, offset: Tensor) -> Tensor:
    """``values - offset``, written over ``values`` when autograd does not track them (the
    caller gives ``values`` up): no new multi-megabyte tensor per filter step."""
    return values - offset if values.requires_grad else values.sub_(offset)


def squared_residuals(expected: Tensor, observation: Tensor, consume: bool = False) -> Tensor:
    """Squared residuals of C points: expected [..., C, k], observation [..., k] ->
    (expected - observation)^2 [..., C, k].

    One new [..., C, k] tensor (k = 4098), or none with ``consume`` (see
    ``consume_subtract``).
    """
    offset = observation.unsqueeze(-2)
    residual = consume_subtract(expected, offset) if consume else expected - offset
    return residual.square() if residual.requires_grad else residual.square_()


class ParameterFit(NamedTuple):
    """Least-squares linear fit of the C points' expected observations [..., C, k] on their
    parameters [..., C, p] (``parameter_fit``): ``deviation`` [..., C, p] of the parameters
    from their mean, ``gram`` [..., p, p] their Gram matrix (plus a tiny ridge) and
    ``coefficients`` [..., p, k]."""

    deviation: Tensor
    gram: Tensor
    coefficients: Tensor


def parameter_fit(parameters: Tensor, expected: Tensor) -> ParameterFit:
    """Fit ``expected`` [..., C, k] on ``parameters`` [..., C, p] (one [p, C] x [C, k] product:
    the centred deviations make centring ``expected`` unnecessary, and the Gram matrix is
    solved against the deviations [p, C] before it, not against the [p, k] result). A tiny
    ridge keeps a degenerate parameter block solvable."""
    deviation = parameters - parameters.mean(-2, keepdim=True)
    gram = deviation.mT @ deviation
    scale = gram.diagonal(dim1=-2, dim2=-1).mean(-1).clamp_min(1e-300)
    eye = torch.eye(gram.shape[-1], dtype=gram.dtype, device=gram.device)
    gram = gram + (1e-9 * scale)[..., None, None] * eye
    return ParameterFit(deviation, gram, torch.linalg.solve(gram, deviation.mT) @ expected)


def marginal_inverse_var(fit: ParameterFit, centred_sums: Tensor, noise_var: Tensor) -> Tensor:
    """``1 / (R + s)`` [..., k] of ``marginal_log_likelihood``: ``s`` the residual variance of
    the fit (C - p - 1 dof), the points' pose scatter its parameters do not explain.
    centred_sums [..., k] is ``sum_i (h_i - mean_i(h_i))^2``, noise_var (R) [..., k]."""
    deviation, gram, coefficients = fit
    count, size = deviation.shape[-2], deviation.shape[-1]
    explained = (coefficients * (gram @ coefficients)).sum(-2)
    scatter = (centred_sums - explained).clamp_min(0.0) / max(count - size - 1, 1)
    return (noise_var + scatter).reciprocal()


class FitNoise(NamedTuple):
    """Sampling noise of ``parameter_fit`` in the frame where its Gram matrix G is the
    identity: ``information`` [...] is what it adds on average to every eigenvalue of the
    fitted information ``sum_k B_k B_k' / v_k``; ``score`` [...] is the variance of every entry
    of the fitted score ``sum_k B_k r_k / v_k``."""

    information: Tensor
    score: Tensor


def iid_fit_noise(
    fit: ParameterFit, inverse_var: Tensor, noise_var: Tensor, projection: Tensor
) -> FitNoise:
    """``FitNoise`` of C independent points. Each slope B_k has the covariance ``s_k G^-1``,
    s_k = ``1 / inverse_var - noise_var`` the fit's residual variance; the score is the slope
    of projection [..., C] (the points' ``y_i = sum_k h_ik r_k / v_k``) on the parameters, so
    the residual variance of that fit is its noise. For antithetic points this is an upper
    bound (``paired_fit_noise``)."""
    deviation, gram, _ = fit
    count, size = deviation.shape[-2], deviation.shape[-1]
    with torch.no_grad():
        deviation = deviation.detach()
        centred = (projection - projection.mean(-1, keepdim=True)).detach().unsqueeze(-1)
        slope = torch.linalg.solve(gram.detach(), deviation.mT @ centred)
        residual = centred - deviation @ slope
        score = residual.square().sum((-2, -1)) / max(count - size - 1, 1)
        information = (1.0 - noise_var * inverse_var).detach().sum(-1)
    return FitNoise(information, score)


NOISE_EDGE = 4.0
"""How far above its mean ``paired_fit_noise`` puts the fit's noise: the upper edge
``(1 + sqrt(p / nu))^2`` of the eigenvalues of a p-dim noise from nu = p independent sources.
All pixels' noise comes from the same few draws, so the eigenvalues of the information's noise
spread that far, and clamping at 0 (``_fit_noise_removed``) keeps what lies above the mean:
with the mean alone the parameters of a pose-only image still collapsed (std to 0.5 % of the
prior's in 200 steps, 0.74 with ``evidence_scale`` 1/25); with this edge they keep 95-99 %."""


def paired_fit_noise(
    expected: Tensor, pairs: Tensor, inverse_var: Tensor, weights: Tensor
) -> FitNoise | None:
    """``FitNoise`` of antithetic points: expected [..., C, k] at points made from the standard
    draws pairs [..., C, q] (``antithetic_noise``: row C/2 + j is minus row j).

    With pairs, a slope fitted to all C points is the fit of the odd part
    ``(h_j - h_{j + C/2}) / 2`` on the first C/2 draws' parameters. The part of it that is
    linear in the draws has exact sample moments (the draws are white), so only the rest, the
    odd part's residual after a linear fit on all q draws, is noise: variance ``2 s_k G^-1``
    with s_k that residual's variance (C/2 - q dof). The same for the score with
    ``y = sum_k h_k weights_k`` (weights [..., k] = ``r_k / v_k``). Both are scaled by
    ``NOISE_EDGE``. None when C/2 <= q."""
    half, size = expected.shape[-2] // 2, pairs.shape[-1]
    dof = half - size
    if dof <= 0:
        return None
    with torch.no_grad():
        odd = 0.5 * (expected[..., :half, :] - expected[..., half : 2 * half, :]).detach()
        # Only entries where some pair differs have noise (most pixels see the table), and
        # float32 is plenty for a variance: else this is the update's largest product.
        columns = odd.ne(0).reshape(-1, odd.shape[-1]).any(0).nonzero()[:, 0]
        odd = odd.index_select(-1, columns).to(torch.float32)
        projected = pairs[..., :half, :].mT.to(torch.float32) @ odd  # the draws' Gram: half * I
        scatter = odd.square().sum(-2) - projected.square().sum(-2) / half
        scale = 2.0 * NOISE_EDGE / dof
        inverse_var = inverse_var.index_select(-1, columns)
        information = scale * (scatter.clamp_min(0.0).to(DTYPE) * inverse_var).sum(-1)
        weights_32 = weights.detach().index_select(-1, columns).to(torch.float32).unsqueeze(-1)
        odd_y, projected_y = odd @ weights_32, projected @ weights_32
        scatter_y = odd_y.square().sum((-2, -1)) - projected_y.square().sum((-2, -1)) / half
        score = scale * scatter_y.clamp_min(0.0).to(DTYPE)
    return FitNoise(information, score)


def fitted_parameters(
    expected: Tensor,
    observation: Tensor,
    mean_residual: Tensor,
    noise_var: Tensor,
    parameters: Tensor,
    pairs: Tensor | None = None,
) -> tuple[ParameterFit, Tensor, FitNoise]:
    """What ``marginal_log_likelihood`` needs of the C points: the fit of expected [..., C, k]
    on parameters [..., C, p], ``marginal_inverse_var`` and the fit's sampling noise
    (``paired_fit_noise`` when the points were made from the antithetic draws pairs
    [..., C, q], else ``iid_fit_noise``). mean_residual [..., k] is ``mean_i(h_i) - z`` for
    the observation z [..., k]."""
    fit = parameter_fit(parameters, expected)
    count = expected.shape[-2]  # (torch.var along this axis took 3 ms of a 13 ms step)
    squares = torch.linalg.vecdot(expected, expected, dim=-2)
    centred_sums = squares - count * (mean_residual + observation).square()
    inverse_var = marginal_inverse_var(fit, centred_sums, noise_var)
    weights = inverse_var * mean_residual
    fit_noise = None if pairs is None else paired_fit_noise(expected, pairs, inverse_var, weights)
    if fit_noise is None:
        projection = (expected @ weights.unsqueeze(-1))[..., 0]
        fit_noise = iid_fit_noise(fit, inverse_var, noise_var, projection)
    return fit, inverse_var, fit_noise


def marginal_log_likelihood(
    fit: ParameterFit,
    mean_residual: Tensor,
    inverse_var: Tensor,
    fit_noise: FitNoise | None = None,
    kept_entries: int = 0,
) -> Tensor:
    """Log likelihood [..., C] of each point's parameters, marginal over the points' pose
    scatter: ``N(z; fitted_i, R + s)`` with ``fitted_i`` the fit's value at the point's
    parameters (``E[h | phi_i]``) and ``1 / (R + s)`` = inverse_var [..., k]
    (``marginal_inverse_var``). mean_residual [..., k] is ``mean_i(h_i) - z``; nothing of size
    C x k is formed (the fitted values are expanded in the parameters' deviations d_i):
    ``-(g . d_i + d_i' Q d_i / 2)`` plus a constant, with the score ``g = sum_k B_k r_k / v_k``
    and the information ``Q = sum_k B_k B_k' / v_k`` of the fitted slopes B_k.

    The slopes are fitted to C points, so they carry sampling noise. Summed over thousands of
    pixels it is information the observation does not hold: step after step it made the
    parameters wander and collapse even where only the pose shows (their std to 0 within 200
    steps when the image depends on the pose alone). With ``fit_noise`` (``iid_fit_noise``,
    ``paired_fit_noise``) it is taken out (``_fit_noise_removed``); without, the plain
    formula. The last ``kept_entries`` (the tactile ones) are added after that, whole: the
    correction is the noise of thousands of pixels, and taken from their sum it erased the two
    forces' evidence too (a light homogeneous object: the score set to 0 in half the steps)."""
    deviation, gram, coefficients = fit
    weighted = inverse_var * mean_residual
    split = coefficients.shape[-1] - (0 if fit_noise is None else kept_entries)
    score, information = _score_and_information(
        coefficients[..., :split], weighted[..., :split], inverse_var[..., :split]
    )
    if fit_noise is not None:
        score, information = _fit_noise_removed(gram, score, information, fit_noise)
        kept = _score_and_information(
            coefficients[..., split:], weighted[..., split:], inverse_var[..., split:]
        )
        score, information = score + kept[0], information + kept[1]
    linear = deviation @ score  # [..., C, 1]
    squares = ((deviation @ information) * deviation).sum(-1)
    constant = (weighted * mean_residual).sum(-1, keepdim=True)
    return -0.5 * (constant + 2.0 * linear[..., 0] + squares)


def _score_and_information(
    coefficients: Tensor, weighted: Tensor, inverse_var: Tensor
) -> tuple[Tensor, Tensor]:
    """Score ``sum_k B_k r_k / v_k`` [..., p, 1] and information ``sum_k B_k B_k' / v_k``
    [..., p, p] of the slopes coefficients [..., p, k], weighted = ``r / v`` [..., k] and
    inverse_var = ``1 / v`` [..., k]."""
    score = coefficients @ weighted.unsqueeze(-1)
    information = (coefficients * inverse_var.unsqueeze(-2)) @ coefficients.mT
    return score, information


def _fit_noise_removed(
    gram: Tensor, score: Tensor, information: Tensor, noise: FitNoise
) -> tuple[Tensor, Tensor]:
    """Score [..., p, 1] and information [..., p, p] of ``marginal_log_likelihood`` less the
    fit's sampling noise, in the frame where G is the identity (G = L L', w = L^-1 d):

    - the information's eigenvalues less ``noise.information``, those below 0 set to 0;
    - the score shrunk towards 0 by ``1 - (p - 2) noise.score / |L' g|^2`` (positive-part
      James-Stein).

    Both corrections are computed without gradient (training sees them as constants). Nothing
    is changed for a non-finite fit (the caller reports that) or a singular Gram matrix."""
    size = score.shape[-2]
    if not bool(torch.isfinite(information).all()):
        return score, information
    with torch.no_grad():
        factor, info = torch.linalg.cholesky_ex(gram.detach())
        if bool((info != 0).any()):
            return score, information
        white = factor.mT @ information.detach() @ factor
        eigenvalues, vectors = torch.linalg.eigh(white)
        excess = torch.minimum(eigenvalues, noise.information.unsqueeze(-1))
        removed_white = (vectors * excess.unsqueeze(-2)) @ vectors.mT
        half = torch.linalg.solve_triangular(factor.mT, removed_white, upper=True)
        removed = torch.linalg.solve_triangular(factor.mT, half.mT, upper=True)
        white_sq = (factor.mT @ score.detach()).square().sum((-2, -1))
        shrink = 1.0 - max(size - 2, 0) * noise.score / white_sq.clamp_min(1e-300)
    return score * shrink.clamp_min(0.0)[..., None, None], information - symmetrize(removed)


def varying_columns(expected: Tensor, n_kept: int = 0) -> Tensor:
    """Indices [j] (ascending) of the entries of expected observations [..., C, k] that differ
    between the C points in any batch, and the last ``n_kept`` entries always. In the other
    entries every point expects the same value, so they carry no evidence between the points
    (equal residuals, zero deviations): most of a depth image sees the table either way."""
    size = expected.shape[-1]
    # max != min: two passes that reduce along the rows, faster than a [C, k] comparison
    varies = (expected.amax(-2) != expected.amin(-2)).reshape(-1, size).any(0)
    varies[size - n_kept :] = True
    return varies.nonzero()[:, 0]


def weighted_squared_sums(squared: Tensor, inverse_var: Tensor) -> Tensor:
    """Sums over the entries of squared residuals [..., C, k] weighted by each row of
    inverse_var [..., m, k] -> [..., C, m] (one matrix product for all m weightings)."""
    return (inverse_var @ squared.transpose(-1, -2)).transpose(-1, -2)


def modality_inverse_var(noise_var: Tensor, n_tactile: int) -> Tensor:
    """Weights of ``weighted_squared_sums`` for the per-modality terms of eq. 37:
    noise_var [..., k] -> [..., 2, k]; row 0 is ``1 / (R n_visual)`` on the depth entries
    (zero on the tactile ones), row 1 ``1 / (R n_tactile)`` on the last ``n_tactile``."""
    n_visual = noise_var.shape[-1] - n_tactile
    scale = noise_var.new_zeros(2, noise_var.shape[-1])
    scale[0, :n_visual] = 1.0 / n_visual
    scale[1, n_visual:] = 1.0 / n_tactile
    return scale / noise_var.unsqueeze(-2)


def log_mean_likelihood(squared_sums: Tensor) -> Tensor:
    """log of the mean over C points of ``exp(-squared_sums / 2)``: [..., C, m] -> [..., m]."""
    return torch.logsumexp(-0.5 * squared_sums, -2) - math.log(squared_sums.shape[-2])


def observation_log_likelihood(expected: Tensor, observation: Tensor, noise_var: Tensor) -> Tensor:
    """Gaussian log likelihood (eq. 31, up to a constant) of C points.

    expected [..., C, k], observation [..., k], noise_var (diagonal R) [..., k] -> [..., C].
    """
    squared = squared_residuals(expected, observation)
    inverse_var = noise_var.reciprocal().unsqueeze(-2)
    log_likelihood = -0.5 * weighted_squared_sums(squared, inverse_var)[..., 0]
    require_finite_summary(log_likelihood, expected, "expected observation")
    return log_likelihood


def modality_log_likelihoods(
    expected: Tensor, observation: Tensor, noise_var: Tensor, n_tactile: int
) -> Tensor:
    """The observation likelihood of eq. 37 per modality, for change detection.

    Per modality (the depth entries, then the last ``n_tactile`` tactile entries): the log of
    the mean over the C points of eq. 37, divided by the modality's number of entries so that
    images and forces read on one scale. expected [..., C, k], observation [..., k],
    noise_var [..., k] -> [..., 2] (visual, tactile).
    """
    squared = squared_residuals(expected, observation)
    inverse_var = modality_inverse_var(noise_var, n_tactile)
    return log_mean_likelihood(weighted_squared_sums(squared, inverse_var))


def observation_log_weights(expected: Tensor, observation: Tensor, noise_var: Tensor) -> Tensor:
    """Normalised log importance weights (eq. 31) of C points with uniform prior weights.

    expected [..., C, k], observation [..., k], noise_var (diagonal R) [..., k] -> [..., C].
    """
    log_likelihood = observation_log_likelihood(expected, observation, noise_var)
    return log_likelihood - torch.logsumexp(log_likelihood, -1, keepdim=True)


def effective_sample_size(log_weights: Tensor) -> Tensor:
    """1 / sum w^2 of normalised log weights [..., C] -> [...]."""
    return (-torch.logsumexp(2.0 * log_weights, -1)).exp()


_BISECTION_BITS = 5
"""Bits of ``beta`` that one round of ``temper_log_weights`` settles (2^5 - 1 trials)."""


def temper_log_weights(
    log_likelihood: Tensor, min_ess: float, iterations: int = 40
) -> tuple[Tensor, Tensor]:
    """Normalised log weights ``beta l`` with the largest ``beta`` in (0, 1] whose effective
    sample size is at least ``min_ess`` (a count of points, <= C).

    log_likelihood [..., C] (any constant offset) -> (log weights [..., C], beta [...]).
    ``beta = 1`` (the plain eq. 31 weights) wherever they already have the ESS; otherwise
    ``beta`` is found by bisection to ``iterations`` bits (the ESS falls monotonically with
    ``beta``), without gradient; the weights stay differentiable in the likelihood. Over
    thousands of pixels whose noise is not independent, the untempered weights put all mass
    on one point.

    The bisection settles ``_BISECTION_BITS`` bits per round by trying all the dyadic points
    between the bounds at once: the same bracket as halving one bit at a time, in a fifth of
    the rounds.
    """
    with torch.no_grad():
        detached = log_likelihood.detach()
        ones = detached.new_ones(detached.shape[:-1])
        full_ok = effective_sample_size(_tempered(detached, ones)) >= min_ess
        low = torch.zeros_like(ones)
        if not bool(full_ok.all()):
            low = _largest_ok_beta(detached, min_ess, iterations)
        beta = torch.where(full_ok, ones, low)
    return _tempered(log_likelihood, beta), beta


def _largest_ok_beta(log_likelihood: Tensor, min_ess: float, bits: int) -> Tensor:
    """The lower end [...] of the bisection bracket of ``temper_log_weights`` after ``bits``
    halvings (rounded up to whole rounds) of (0, 1].

    The ESS of ``beta l`` is ``(sum_i e_i)^2 / sum_i e_i^2`` with ``e_i = exp(beta (l_i -
    max l))`` in (0, 1]: no log-sum-exp needed.
    """
    trials = 2**_BISECTION_BITS
    steps = torch.arange(1, trials, dtype=log_likelihood.dtype, device=log_likelihood.device)
    shifted = (log_likelihood - log_likelihood.amax(-1, keepdim=True)).unsqueeze(-2)
    low = log_likelihood.new_zeros(log_likelihood.shape[:-1])
    width = 1.0
    for _ in range(-(-bits // _BISECTION_BITS)):
        width /= trials
        beta = low.unsqueeze(-1) + width * steps  # [..., trials - 1], exact dyadic values
        unnormalised = (beta.unsqueeze(-1) * shifted).exp_()  # [..., trials - 1, C]
        total = unnormalised.sum(-1)
        ok = total.square() >= min_ess * unnormalised.square_().sum(-1)
        low = low + width * (ok.to(steps.dtype) * steps).amax(-1)  # the last passing trial
    return low


def _tempered(log_likelihood: Tensor, beta: Tensor) -> Tensor:
    """Normalised ``beta l``: log_likelihood [..., C], beta [...] -> [..., C]."""
    scaled = beta.unsqueeze(-1) * log_likelihood
    return scaled - torch.logsumexp(scaled, -1, keepdim=True)


def unscented_points(mean: Tensor, factor: Tensor, kappa: float) -> tuple[Tensor, Tensor]:
    """Julier's 2d + 1 points of N(mean [..., d], factor factor^T) -> [..., 2d+1, d], [2d+1].

    Weights ``kappa / (d + kappa)`` for the centre and ``1 / (2 (d + kappa))`` for the others:
    non-negative for kappa >= 0.
    """
    d = mean.shape[-1]
    offsets = math.sqrt(d + kappa) * factor.transpose(-1, -2)
    centre = mean.unsqueeze(-2)
    points = torch.cat([centre, centre + offsets, centre - offsets], -2)
    weights = torch.full((2 * d + 1,), 1.0 / (2.0 * (d + kappa)), dtype=DTYPE, device=mean.device)
    weights = torch.cat([weights.new_full((1,), kappa / (d + kappa)), weights[1:]])
    return points, weights


def woodbury_update(
    mean: Tensor,
    state_deviation: Tensor,
    observation_deviation: Tensor,
    weights: Tensor,
    innovation: Tensor,
    noise_var: Tensor,
) -> tuple[Tensor, Tensor]:
    """Kalman update from sigma points without a k x k matrix.

    mean [..., d]; state_deviation X [..., m, d] and observation_deviation U [..., m, k]: the
    points minus their weighted means; weights W [m] >= 0, with ``X^T W X`` the prior
    covariance (true for ``unscented_points``); innovation z - z_mean [..., k]; noise_var the
    diagonal of R [..., k]. With ``X' = W^1/2 X``, ``U' = W^1/2 U``, ``G = U' R^-1 U'^T`` and
    ``M = I + G`` [m, m], Woodbury gives ``U' S^-1 = M^-1 U' R^-1`` for
    ``S = U'^T U' + R``, so the gain ``K = P_xz S^-1 = X'^T M^-1 U' R^-1`` and the posterior
    covariance ``X'^T X' - K S K^T = X'^T M^-1 X'`` (PSD by construction). The only
    [..., m, k] temporary is ``U R^-1/2``; the weights are applied in sigma-point space.
    Returns the posterior mean [..., d] and covariance [..., d, d].
    """
    root_weights = weights.sqrt().unsqueeze(-1)
    state_dev = root_weights * state_deviation
    inverse_std = noise_var.rsqrt()
    whitened = observation_deviation * inverse_std.unsqueeze(-2)  # U R^-1/2
    gram = whitened @ whitened.transpose(-1, -2)  # U R^-1 U^T
    eye = torch.eye(weights.shape[-1], dtype=mean.dtype, device=mean.device)
    core = eye + root_weights * gram * root_weights.transpose(-1, -2)
    core_factor, info = torch.linalg.cholesky_ex(core)
    if bool((info != 0).any()):
        require_finite(whitened, "whitened observation deviation")
        raise DataError(
            "the unscented pose update is numerically singular: the sigma points' expected "
            f"observations spread by up to {float(whitened.abs().max()):.3g} noise stds"
        )
    whitened_innovation = (innovation * inverse_std).unsqueeze(-1)
    projected = root_weights.squeeze(-1) * (whitened @ whitened_innovation).squeeze(-1)
    solved = torch.cholesky_solve(torch.cat([projected.unsqueeze(-1), state_dev], -1), core_factor)
    correction = (state_dev.transpose(-1, -2) @ solved[..., :1]).squeeze(-1)
    cov = state_dev.transpose(-1, -2) @ solved[..., 1:]
    return mean + correction, symmetrize(cov)


def condition_pose(
    belief: Belief, layout: StateLayout, parameter_mean: Tensor
) -> tuple[Tensor, Tensor, Tensor]:
    """Pose block given the parameters = ``parameter_mean`` [..., p] (eq. 34-35).

    Returns the conditional mean [..., d], covariance [..., d, d] and the regression
    coefficient ``B = S_psi,phi S_phi^-1`` [..., d, p].
    """
    pose, params = layout.pose_slice, layout.parameter_slice
    cov_pose_param = belief.cov[..., pose, params]
    param_factor = cholesky_safe(belief.cov[..., params, params])
    cov_param_pose = cov_pose_param.transpose(-1, -2)
    regression = torch.cholesky_solve(cov_param_pose, param_factor).transpose(-1, -2)
    shift = parameter_mean - belief.mean[..., params]
    mean = belief.mean[..., pose] + (regression @ shift.unsqueeze(-1)).squeeze(-1)
    cov = belief.cov[..., pose, pose] - regression @ cov_param_pose
    return mean, symmetrize(cov), regression


def joint_belief(
    pose_mean: Tensor,
    pose_cov: Tensor,
    regression: Tensor,
    parameter_mean: Tensor,
    parameter_cov: Tensor,
) -> Belief:
    """Product N(psi | a + B phi, pose_cov) N(phi | parameter_mean, parameter_cov) (eq. 36).

    pose_mean [..., d] is the conditional mean at ``phi = parameter_mean``, pose_cov
    [..., d, d], regression B [..., d, p], parameter_cov [..., p, p] -> Belief over (psi, phi).
    """
    cross = regression @ parameter_cov
    top = torch.cat([pose_cov + cross @ regression.transpose(-1, -2), cross], -1)
    bottom = torch.cat([cross.transpose(-1, -2), parameter_cov], -1)
    cov = symmetrize(torch.cat([top, bottom], -2))
    return Belief(torch.cat([pose_mean, parameter_mean], -1), cov)


def bound_twist(pose: Tensor, max_speed_mps: float, max_rate_radps: float) -> Tensor:
    """Pose blocks [..., 6 L] with each link's planar speed scaled down to at most
    ``max_speed_mps`` and its yaw rate clipped to +-``max_rate_radps``; the rest unchanged."""
    links = pose.unflatten(-1, (-1, 6))
    velocity, rate = links[..., 3:5], links[..., 5:6]
    speed = torch.linalg.vector_norm(velocity, dim=-1, keepdim=True)
    velocity = velocity * (max_speed_mps / speed.clamp_min(max_speed_mps))
    rate = rate.clamp(-max_rate_radps, max_rate_radps)
    return torch.cat([links[..., :3], velocity, rate], -1).flatten(-2)


class HeldJoints(NamedTuple):
    """Joints the pose update holds together (``DualFilter`` ``joints``)."""

    ends_m: Tensor
    """[L - 1, 2, 2]: joint k in link k's frame, then in link k + 1's (m)."""
    std_m: float
    """The std of the gap between a joint's two ends, observed as zero each step."""


def joint_gaps(poses: Tensor, ends_m: Tensor) -> Tensor:
    """How far apart each joint's two ends lie (world x, y; m).

    poses [..., 6 L]: each link's block, its x, y, theta first; ends_m [L - 1, 2, 2]: joint k
    in link k's frame, then in link k + 1's (``HeldJoints.ends_m``) -> [..., 2 (L - 1)].
    Zero wherever the links keep together as they were found, hinged or welded.
    """
    links = poses.unflatten(-1, (-1, 6))
    parent, child = links[..., :-1, :], links[..., 1:, :]
    gap = parent[..., :2] + rotate(ends_m[:, 0], parent[..., 2])
    gap = gap - child[..., :2] - rotate(ends_m[:, 1], child[..., 2])
    return gap.flatten(-2)


def check_prediction(prediction: Prediction, layout: StateLayout) -> None:
    """Raise DataError for a non-finite process model output or a negative process noise."""
    pose_names = layout.names[layout.pose_slice]
    require_finite(prediction.pose, "prediction.pose", pose_names)
    require_finite(prediction.force_n, "prediction.force_n", ("fx", "fy"))
    require_finite(prediction.process_var, "prediction.process_var", pose_names)
    if bool((prediction.process_var < 0).any()):
        raise DataError("prediction.process_var has a negative variance")


class DualFilter:
    """Predict and update a joint pose/parameter Gaussian (paper 1, III-F; see module doc).

    process_model: ``predict(states [..., C, n], inputs, dt_s) -> Prediction``;
    observation_model: ``expected(states [..., C, n], force_n [..., C, 2]) -> [..., C, k]`` and
    ``noise_var(observation [..., k]) -> [..., k]``. ``sigma_points`` is C;
    ``liu_west_delta`` in (1/3, 1] the kernel discount factor; ``ukf_kappa >= 0`` Julier's
    kappa; ``parameter_var_floor`` (state units squared) is added to the parameter covariance's
    diagonal after each update to keep it SPD.

    Robustness (see ``update``): ``min_ess_fraction`` in [0, 1] tempers the parameter weights
    until their effective sample size is at least that fraction of C (0: plain eq. 31);
    ``marginal_parameter_likelihood`` weighs the parameters by the Gaussian marginal over the
    points' pose scatter: the observation expected at each point's parameters is the linear
    fit of the points' expected observations on their parameters, its variance ``R`` plus the
    fit's residual variance (``marginal_log_likelihood``; otherwise the pose scatter of the
    points, not their parameters, decides the weights); ``pose_std_floor`` [6] (m, rad, m/s,
    rad/s per link entry, or None) is the least std of the predicted pose block: the unscented
    points must spread over at least about a pixel for the rendered depth to tell them apart.
    An observation model with an ``unexplained(observation [..., k], expected [..., C, k],
    tcp_xy_m [..., 2] | None) -> bool [..., k]`` method marks entries it cannot explain (the
    gripper in front of the object); they get the noise variance ``UNEXPLAINED_VAR``.
    ``evidence_scale`` in (0, 1] multiplies the parameter log likelihoods (a power
    likelihood): ``1 / tau`` counts ``tau`` steps as one independent observation, for a model
    whose errors persist over ``tau`` steps (otherwise the same error, seen every step, makes
    the parameters overconfident).
    ``twist_bound`` (m/s, rad/s, or None): the most a link can move; predicted points beyond
    it are brought back (``bound_twist``), so that a learned model fed its own
    out-of-distribution velocities cannot run away (the camera sees positions, not speeds).
    ``push_load_only``: in a push, the process model sees each point's links on the curve
    ``m f = const`` through it at the belief mean's ratio ``m / f`` (``on_load_ridge``).
    """

    def __init__(
        self,
        layout: StateLayout,
        process_model: ProcessModel,
        observation_model: ObservationModel,
        sigma_points: int = 100,
        liu_west_delta: float = 0.97,
        ukf_kappa: float = 1.0,
        parameter_var_floor: float = 1e-12,
        min_ess_fraction: float = 0.8,
        marginal_parameter_likelihood: bool = True,
        pose_std_floor: Sequence[float] | None = (0.006, 0.006, 0.06, 0.0, 0.0, 0.0),
        evidence_scale: float = 1.0,
        twist_bound: tuple[float, float] | None = None,
        push_load_only: bool = False,
        joints: HeldJoints | None = None,
    ) -> None:
        if sigma_points < 2:
            raise ValueError(f"sigma_points must be >= 2, got {sigma_points}")
        if not 1.0 / 3.0 < liu_west_delta <= 1.0:
            raise ValueError(f"liu_west_delta must be in (1/3, 1], got {liu_west_delta}")
        if ukf_kappa < 0:
            raise ValueError(f"ukf_kappa must be >= 0 (non-negative weights), got {ukf_kappa}")
        if parameter_var_floor < 0:
            raise ValueError(f"parameter_var_floor must be >= 0, got {parameter_var_floor}")
        self.layout = layout
        self.process_model = process_model
        self.observation_model = observation_model
        self.sigma_points = sigma_points
        self.liu_west_delta = liu_west_delta
        self.ukf_kappa = ukf_kappa
        self.parameter_var_floor = parameter_var_floor
        if not 0.0 < evidence_scale <= 1.0:
            raise ValueError(f"evidence_scale must be in (0, 1], got {evidence_scale}")
        self.evidence_scale = evidence_scale
        if not 0.0 <= min_ess_fraction <= 1.0:
            raise ValueError(f"min_ess_fraction must be in [0, 1], got {min_ess_fraction}")
        self.min_ess_fraction = min_ess_fraction
        self.marginal_parameter_likelihood = marginal_parameter_likelihood
        self.pose_var_floor: Tensor | None = None
        if pose_std_floor is not None:
            floor = torch.as_tensor(pose_std_floor, dtype=DTYPE)
            if floor.shape != (6,) or bool((floor < 0).any()):
                raise ValueError(f"pose_std_floor: expected 6 values >= 0, got {pose_std_floor}")
            self.pose_var_floor = floor.square().repeat(layout.n_links)
        if twist_bound is not None and min(twist_bound) <= 0:
            raise ValueError(f"twist_bound: expected (m/s, rad/s) > 0, got {twist_bound}")
        self.twist_bound = twist_bound
        self.push_load_only = push_load_only
        if joints is not None and tuple(joints.ends_m.shape) != (layout.n_joints, 2, 2):
            raise ValueError(
                f"joints.ends_m: expected [{layout.n_joints}, 2, 2] (m), got "
                f"{tuple(joints.ends_m.shape)}"
            )
        if joints is not None and joints.std_m <= 0:
            raise ValueError(f"joints.std_m must be > 0, got {joints.std_m}")
        self.joints = joints
        self.last_log_likelihood: Tensor | None = None
        """After ``update``: [..., 2] eq. 37 per modality (see ``modality_log_likelihoods``)."""

    def predict(
        self, belief: Belief, inputs: ProcessInput, dt_s: float, generator: torch.Generator
    ) -> tuple[Belief, Tensor, Prediction]:
        """Draw the noise from ``generator`` and ``propagate``; see there for the outputs."""
        return self.propagate(belief, inputs, dt_s, *self._draws(belief, generator))

    def _draws(self, belief: Belief, generator: torch.Generator) -> tuple[Tensor, Tensor]:
        """Standard normal state [..., C, n] and process [..., C, 6L] draws."""
        batch = (*belief.mean.shape[:-1], self.sigma_points)
        device = belief.mean.device
        state_noise = _standard_normal((*batch, self.layout.size), generator, device)
        return state_noise, _standard_normal((*batch, self.layout.n_pose), generator, device)

    def propagate(
        self,
        belief: Belief,
        inputs: ProcessInput,
        dt_s: float,
        state_noise: Tensor,
        process_noise: Tensor,
    ) -> tuple[Belief, Tensor, Prediction]:
        """Prediction step (eq. 21-26) from given standard normal draws.

        state_noise [..., C, n], process_noise [..., C, 6L] -> predicted belief, predicted
        sigma points [..., C, n] (unprojected parameters) and the model's Prediction. Draws
        [C, n] and [C, 6L] serve every element of a batch of beliefs [..., n] alike (a
        look-ahead of many actions), made antithetic once.
        """
        if state_noise.shape[:-1] != process_noise.shape[:-1]:
            raise ValueError(
                f"propagate: state_noise {tuple(state_noise.shape)} and process_noise "
                f"{tuple(process_noise.shape)} need the same leading dimensions ([..., C] or "
                "[C] for every belief)"
            )
        state_white, process_white, _ = _antithetic_jointly(state_noise, process_noise)
        return self._propagate_white(belief, inputs, dt_s, state_white, process_white)

    def _propagate_white(
        self,
        belief: Belief,
        inputs: ProcessInput,
        dt_s: float,
        state_white: Tensor,
        process_white: Tensor,
    ) -> tuple[Belief, Tensor, Prediction]:
        """``propagate`` from draws already made antithetic (``_antithetic_jointly``)."""
        belief.check_finite(self.layout.names)
        sigma = _points(belief, state_white)
        model_states = project_feasible(sigma, self.layout, inputs.link_size_m)
        if self.push_load_only:
            push = inputs.is_pull.expand(belief.mean.shape[:-1]) < 0.5
            model_states = on_load_ridge(model_states, self.layout, belief.mean, push)
        prediction = self.process_model.predict(model_states, inputs, dt_s)
        check_prediction(prediction, self.layout)
        process_var = prediction.process_var
        if process_var.dim() < prediction.pose.dim():
            process_var = process_var.unsqueeze(-2)
        pose = prediction.pose + process_white * process_var.sqrt()
        if self.twist_bound is not None:
            pose = bound_twist(pose, *self.twist_bound)
        sigma_pred = torch.cat([pose, sigma[..., self.layout.parameter_slice]], -1)
        weights = sigma_pred.new_full(sigma_pred.shape[:-1], 1.0 / self.sigma_points)
        mean, cov = weighted_moments(sigma_pred, weights)
        return Belief(mean, cov), sigma_pred, prediction

    def update(
        self,
        belief_pred: Belief,
        sigma_pred: Tensor,
        prediction: Prediction,
        observation: Tensor,
        tcp_xy_m: Tensor | None = None,
        pairs: Tensor | None = None,
    ) -> Belief:
        """Dual update against observation [..., k]: parameters, then the conditional pose.
        tcp_xy_m [..., 2]: where the robot is, for the observation model's ``unexplained``;
        pairs [..., C, n + 6L]: the antithetic draws the points were made from, if they were
        (``step`` passes them; see ``fitted_parameters``)."""
        require_finite(observation, "observation")
        noise_var = self.observation_model.noise_var(observation)
        require_finite(noise_var, "observation noise_var")
        if bool((noise_var <= 0).any()):
            raise DataError("observation noise_var must be positive")
        expected = self.observation_model.expected(sigma_pred, prediction.force_n)
        unexplained = getattr(self.observation_model, "unexplained", None)
        if unexplained is not None:
            mask = unexplained(observation, expected, tcp_xy_m)
            noise_var = torch.where(mask, torch.full_like(noise_var, UNEXPLAINED_VAR), noise_var)
        parameters = sigma_pred[..., self.layout.parameter_slice]
        log_likelihood = self._log_likelihoods(
            expected, observation, noise_var, prediction.force_n.shape[-1], parameters, pairs
        )
        log_weights, beta = temper_log_weights(
            self.evidence_scale * log_likelihood, self.min_ess_fraction * self.sigma_points
        )
        weights = log_weights.exp()
        if logger.isEnabledFor(logging.DEBUG):
            ess = effective_sample_size(log_weights.detach())
            logger.debug(
                "effective sample size %s of %d (tempering %s)",
                ess.tolist(),
                self.sigma_points,
                beta.tolist(),
            )
        parameter_mean, parameter_cov = liu_west(parameters, weights, self.liu_west_delta)
        eye = torch.eye(parameter_cov.shape[-1], dtype=DTYPE, device=parameter_cov.device)
        parameter_cov = parameter_cov + self.parameter_var_floor * eye
        parameter_mean, parameter_cov = truncate_negative_means(
            parameter_mean, parameter_cov, self.layout.bounded_below
        )
        force_n = (weights.unsqueeze(-1) * prediction.force_n).sum(-2)
        pose = self._update_pose(belief_pred, parameter_mean, force_n, observation, noise_var)
        posterior = joint_belief(*pose, parameter_mean, parameter_cov)
        posterior.check_finite(self.layout.names)
        return posterior

    def step(
        self,
        belief: Belief,
        inputs: ProcessInput,
        dt_s: float,
        observation: Tensor,
        generator: torch.Generator,
    ) -> Belief:
        """One filter step: ``predict`` then ``update``."""
        state_white, process_white, pairs = _antithetic_jointly(*self._draws(belief, generator))
        belief_pred, sigma_pred, prediction = self._propagate_white(
            belief, inputs, dt_s, state_white, process_white
        )
        return self.update(
            belief_pred, sigma_pred, prediction, observation, inputs.tcp[..., :2], pairs
        )

    def _log_likelihoods(
        self,
        expected: Tensor,
        observation: Tensor,
        noise_var: Tensor,
        n_tactile: int,
        parameters: Tensor,
        pairs: Tensor | None,
    ) -> Tensor:
        """The parameter log likelihoods (eq. 31) of the C points [..., C] with parameters
        [..., C, p] (pairs: see ``update``), up to a constant; sets ``last_log_likelihood``
        (eq. 37 per modality).

        Only the entries where the points' expected observations differ
        (``varying_columns``) are compared point by point; the others add the same residual
        to every point, which only ``last_log_likelihood`` needs (one [..., k] product)."""
        modality_weights = modality_inverse_var(noise_var, n_tactile)
        full_expected = expected  # a bad entry is named by its place in the whole observation
        columns = varying_columns(expected.detach(), n_tactile)
        same = torch.ones(expected.shape[-1], dtype=torch.bool, device=expected.device)
        same[columns] = False
        shared = (expected[..., 0, :] - observation).square() * same
        shared_sums = weighted_squared_sums(shared.unsqueeze(-2), modality_weights)
        expected, observation, noise_var, modality_weights = (
            tensor.index_select(-1, columns)
            for tensor in (expected, observation, noise_var, modality_weights)
        )
        mean_residual = expected.mean(-2) - observation
        if self.marginal_parameter_likelihood:
            fit, inverse_var, fit_noise = fitted_parameters(
                expected, observation, mean_residual, noise_var, parameters, pairs
            )
        squared = squared_residuals(expected, observation, consume=True)
        modality_sums = weighted_squared_sums(squared, modality_weights) + shared_sums
        self.last_log_likelihood = log_mean_likelihood(modality_sums)
        if self.marginal_parameter_likelihood:
            log_likelihood = marginal_log_likelihood(
                fit, mean_residual, inverse_var, fit_noise, n_tactile
            )
        else:
            sums = weighted_squared_sums(squared, noise_var.reciprocal().unsqueeze(-2))
            log_likelihood = -0.5 * sums[..., 0]
        summary = log_likelihood.sum() + self.last_log_likelihood.sum()
        require_finite_summary(summary, full_expected, "expected observation")
        return log_likelihood

    def _widest_pose_entry(self, mean: Tensor, cov: Tensor) -> str:
        """Where a diverged pose belief (mean [..., d], cov [..., d, d]) is widest, in words."""
        std = cov.detach().diagonal(dim1=-2, dim2=-1).clamp_min(0.0).sqrt()
        flat = int(std.reshape(-1).argmax())
        batch, entry = divmod(flat, std.shape[-1])
        name = self.layout.names[self.layout.pose_slice][entry]
        value = float(mean.detach().reshape(-1, std.shape[-1])[batch, entry])
        return (
            f"the belief has diverged (widest pose entry {name} = {value:.3g} +- "
            f"{float(std.reshape(-1)[flat]):.3g}); check the process model's checkpoint and "
            "the object's first look"
        )

    def _with_joints(
        self,
        points: Tensor,
        weights: Tensor,
        expected: Tensor,
        expected_mean: Tensor,
        observation: Tensor,
        noise_var: Tensor,
    ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """The unscented update's expected [..., m, k], their mean [..., k], observation
        [..., k] and noise variance [..., k], each with the joint gaps (``joint_gaps``) of the
        pose points [..., m, 6 L] appended as observed zeros of std ``joints.std_m``."""
        assert self.joints is not None
        gaps = joint_gaps(points, self.joints.ends_m.to(points))
        gap_mean = weights @ gaps
        zeros = gap_mean.new_zeros(gap_mean.shape)
        gap_var = zeros + self.joints.std_m**2
        return (
            torch.cat([expected, gaps], -1),
            torch.cat([expected_mean, gap_mean], -1),
            torch.cat([observation.expand(*gap_mean.shape[:-1], -1), zeros], -1),
            torch.cat([noise_var.expand(*gap_mean.shape[:-1], -1), gap_var], -1),
        )

    def _update_pose(
        self,
        belief_pred: Belief,
        parameter_mean: Tensor,
        force_n: Tensor,
        observation: Tensor,
        noise_var: Tensor,
    ) -> tuple[Tensor, Tensor, Tensor]:
        """Unscented update of the pose given ``parameter_mean`` [..., p].

        force_n [..., 2] is the tactile prediction used for every unscented point. Returns the
        conditional pose mean [..., d], covariance [..., d, d] and the updated regression
        coefficient ``B'`` [..., d, p].
        """
        prior_mean, prior_cov, regression = condition_pose(belief_pred, self.layout, parameter_mean)
        if self.pose_var_floor is not None:
            variance = prior_cov.diagonal(dim1=-2, dim2=-1)
            raise_by = (self.pose_var_floor.to(prior_cov.device) - variance).clamp_min(0.0)
            prior_cov = prior_cov + torch.diag_embed(raise_by)
        prior_factor = cholesky_safe(prior_cov)
        points, weights = unscented_points(prior_mean, prior_factor, self.ukf_kappa)
        count = points.shape[-2]
        params = parameter_mean.unsqueeze(-2).expand(*parameter_mean.shape[:-1], count, -1)
        forces = force_n.unsqueeze(-2).expand(*force_n.shape[:-1], count, -1)
        expected = self.observation_model.expected(torch.cat([points, params], -1), forces)
        expected_mean = weights @ expected
        require_finite_summary(expected_mean, expected, "expected observation")
        columns = varying_columns(expected.detach())  # elsewhere: no gain, nothing to update
        expected, expected_mean, observation, noise_var = (
            tensor.index_select(-1, columns)
            for tensor in (expected, expected_mean, observation, noise_var)
        )
        if self.joints is not None:
            expected, expected_mean, observation, noise_var = self._with_joints(
                points, weights, expected, expected_mean, observation, noise_var
            )
        try:
            mean, cov = woodbury_update(
                prior_mean,
                points - prior_mean.unsqueeze(-2),
                consume_subtract(expected, expected_mean.unsqueeze(-2)),
                weights,
                observation - expected_mean,
                noise_var,
            )
        except DataError as error:
            raise DataError(f"{error}; {self._widest_pose_entry(prior_mean, prior_cov)}") from error
        regression = cov @ torch.cholesky_solve(regression, prior_factor)
        return mean, cov, regression
