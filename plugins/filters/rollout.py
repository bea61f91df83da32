"""Push-level evidence: the parameters scored by where a whole interaction took the object.

The dual filter (paper 1, III-F) scores the parameters step by step: each sigma point's
one-step prediction against the next image. A centre of mass shows in how fast the object
turns, so one step shows a CoM only through ``dt * (change of the turn rate)``, far below a
pixel, and the steps' evidence is discounted for the model's persistent error
(``evidence_steps``). Summed over an interaction, the same turn rate moves the object by
tens of degrees. This update rolls the process model out open loop through the whole
recorded interaction for parameter samples and weighs each by how near its end pose comes
to the pose the filter tracked. The model's error is its process variance summed along the
rollout, at least ``std_floor``: the shipped push GNN, trained on 25-step windows, says 2.5
times too little for a whole push. Measured in docs/results.md.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Sequence

import torch
from pydantic import BaseModel, ConfigDict, Field, PositiveFloat, field_validator
from torch import Tensor
from vistac.plugins.filters.dual import (
    Belief,
    antithetic_noise,
    bound_twist,
    check_prediction,
    cholesky_safe,
    feasible,
    symmetrize,
    temper_log_weights,
    weighted_moments,
)
from vistac.plugins.filters.mirror import Forward
from vistac.plugins.filters.state import (
    DTYPE,
    LINK_PARAMETER_FIELDS,
    ProcessInput,
    StateLayout,
)

log = logging.getLogger(__name__)


class PushEvidence(BaseModel):
    """Settings of the push-level update (``filters.dual`` ``push_evidence``)."""

    model_config = ConfigDict(extra="forbid")

    enabled: bool = Field(False, description="score the parameters by whole interactions too")
    max_links: int = Field(
        2, ge=1, description="objects with more links get no push-level evidence; on the "
        "two-link test objects it lowered the heterogeneous NRMSE by 0.02-0.03 in each of "
        "three seeds and brought the welded pairs' combined CoM nearer (docs/results.md)",
    )
    parameters: tuple[str, ...] = Field(
        ("com_",), description="state entries whose names start with one of these are scored"
    )
    mirror_average: bool = Field(
        True, description="roll out the average of the model's prediction and its mirror "
        "image about the push line (vistac.plugins.filters.mirror), which cancels the part "
        "of a learned model's error that turns the object to one side",
    )
    samples: int = Field(64, ge=4, description="parameter samples rolled out")
    min_ess_fraction: float = Field(
        0.8, gt=0, le=1, description="temper the weights to keep this share of the samples"
    )
    std_floor: tuple[PositiveFloat, PositiveFloat] = Field(
        (0.015, 0.25), description="least model error std of an end pose (m, rad): the "
        "shipped push GNN's rollouts at the true parameters end 10-13 mm and 0.26 rad (RMS) "
        "from the tracked pose on the validation objects, 2.5 times its summed process std",
    )

    @field_validator("parameters")
    @classmethod
    def _known_entries(cls, prefixes: tuple[str, ...]) -> tuple[str, ...]:
        names = tuple(f"{field}_" for field in (*LINK_PARAMETER_FIELDS, "f_j"))
        for prefix in prefixes:
            if not any(name.startswith(prefix) or prefix.startswith(name) for name in names):
                raise ValueError(f"{prefix!r} starts no parameter's name ({', '.join(names)})")
        return prefixes


def scored_rows(layout: StateLayout, prefixes: Sequence[str]) -> list[int]:
    """Indices of the parameters whose names start with one of ``prefixes``."""
    names = layout.names[layout.n_pose :]
    return [layout.n_pose + i for i, name in enumerate(names) if name.startswith(tuple(prefixes))]


def with_marginal(belief: Belief, rows: Sequence[int], mean: Tensor, cov: Tensor) -> Belief:
    """The joint belief [n] with the marginal of ``rows`` replaced by N(mean [k], cov [k, k])
    and the rest moved by its regression on them (Jeffrey's rule for Gaussians)."""
    index = torch.as_tensor(rows)
    scored = set(rows)
    rest = torch.as_tensor([i for i in range(belief.mean.shape[-1]) if i not in scored])
    cov_kk = belief.cov[index][:, index]
    cov_rk = belief.cov[rest][:, index]
    regression = torch.cholesky_solve(cov_rk.T, cholesky_safe(cov_kk)).T  # [n - k, k]
    new_mean = belief.mean.clone()
    new_mean[index] = mean
    new_mean[rest] += regression @ (mean - belief.mean[index])
    new_cov = belief.cov.clone()
    cross = regression @ cov
    new_cov[rest[:, None], rest] += regression @ (cov - cov_kk) @ regression.T
    new_cov[rest[:, None], index] = cross
    new_cov[index[:, None], rest] = cross.T
    new_cov[index[:, None], index] = cov
    return Belief(new_mean, symmetrize(new_cov))


def end_poses(
    predict: Forward,
    layout: StateLayout,
    states: Tensor,
    inputs: Sequence[ProcessInput],
    dt_s: float,
    twist_bound: tuple[float, float] | None,
) -> tuple[Tensor, Tensor]:
    """Open-loop mean rollout of states [K, n] through ``inputs`` (one per step) by a process
    model's ``predict``.

    Returns each rollout's end (x, y, theta) per link [K, L, 3] and the process variance of
    those entries summed along the rollout [K, L, 3].
    """
    params = states[:, layout.parameter_slice]
    var = states.new_zeros(states.shape[0], layout.n_pose)
    for step in inputs:
        prediction = predict(states, step, dt_s)
        check_prediction(prediction, layout)
        pose = prediction.pose
        if twist_bound is not None:
            pose = bound_twist(pose, *twist_bound)
        var = var + prediction.process_var.expand_as(var)
        states = torch.cat([pose, params], -1)
    ends = layout.link_pose(states)[..., :3]
    return ends, var.unflatten(-1, (layout.n_links, 6))[..., :3]


def push_log_likelihood(
    ends: Tensor, model_var: Tensor, tracked: Tensor, tracked_var: Tensor
) -> Tensor:
    """Gaussian log likelihood [K] of the tracked end poses tracked [L, 3] (variance
    tracked_var [L, 3]) given rollout ends [K, L, 3] with model variance [K, L, 3]."""
    residual = ends - tracked
    residual[..., 2] = torch.remainder(residual[..., 2] + math.pi, 2 * math.pi) - math.pi
    var = model_var + tracked_var
    return -0.5 * (residual.square() / var + var.log()).sum((-1, -2))


def push_update(
    belief: Belief,
    start: Belief,
    layout: StateLayout,
    settings: PushEvidence,
    rollout: Callable[[Tensor], tuple[Tensor, Tensor]],
    link_size_m: Tensor,
    generator: torch.Generator,
) -> Belief:
    """The belief after an interaction with its push-level evidence on the scored entries.

    belief: after the interaction's last filter step; start: after its first (the object at
    rest where the rollouts start); rollout: states [K, n] -> (end poses [K, L, 3], model
    variance [K, L, 3]); link_size_m [L, 2] bounds the CoM samples.
    """
    rows = scored_rows(layout, settings.parameters)
    if not rows or layout.n_links > settings.max_links:
        return belief
    index = torch.as_tensor(rows)
    mean, cov = belief.mean[index], belief.cov[index][:, index]
    white = torch.randn((settings.samples, len(rows)), generator=generator, dtype=DTYPE)
    white = antithetic_noise(white)
    samples = mean + white @ cholesky_safe(cov).T  # [K, k]
    states = belief.mean.expand(len(samples), -1).clone()
    states[:, layout.pose_slice] = layout.at_rest(start.mean)[layout.pose_slice]
    states[:, index] = samples
    allowed = feasible(states, layout, link_size_m)
    if 2 * int(allowed.sum()) < len(samples):
        log.info(
            "push evidence: %d of %d CoM samples lie outside the fitted footprint; the "
            "push's evidence is not used", len(samples) - int(allowed.sum()), len(samples),
        )  # fmt: skip
        return belief
    samples, states = samples[allowed], states[allowed]
    ends, model_var = rollout(states)
    floor = torch.tensor([settings.std_floor[0]] * 2 + [settings.std_floor[1]], dtype=DTYPE)
    model_var = torch.maximum(model_var, floor.square())
    pose_var = torch.diagonal(belief.cov)[layout.pose_slice] + torch.diagonal(start.cov)[
        layout.pose_slice
    ]
    tracked = layout.link_pose(belief.mean)[..., :3]
    tracked_var = pose_var.unflatten(-1, (layout.n_links, 6))[..., :3]
    log_likelihood = push_log_likelihood(ends, model_var, tracked, tracked_var)
    log_weights, beta = temper_log_weights(log_likelihood, settings.min_ess_fraction * len(samples))
    if log.isEnabledFor(logging.DEBUG):
        log.debug(
            "push evidence: model std %s, tracked std %s, end spread %s, beta %.3g",
            model_var.mean(0).sqrt().flatten().tolist(), tracked_var.sqrt().flatten().tolist(),
            ends.std(0).flatten().tolist(), float(beta),
        )  # fmt: skip
    new_mean, new_cov = weighted_moments(samples, log_weights.exp())
    return with_marginal(belief, rows, new_mean, new_cov)

