"""``actions.info_gain``: the candidate with the largest N-step information gain (paper 1, III-E).

For every candidate the filter predicts the belief N = round(horizon_s * rate_hz) steps ahead
with its prediction step only (``predict_beliefs`` of ``filters.dual``), and the gain is the
closed-form KL divergence KL(predicted || current) of the two Gaussians over the whole joint
state (pose, twist and parameters). Not over the parameter block alone: the prediction keeps
the parameters constant (eq. 23), so their predicted marginal is the current one for every
candidate. What an action would teach about the parameters shows in the pose block instead:
an action whose outcome depends on an uncertain parameter spreads the predicted pose and
correlates it with that parameter, which raises the trace and log-determinant terms of the
KL. The mean-shift term also counts how far the action moves the object relative to the
current pose uncertainty. The argmax is taken (the first on a tie); with the filter's fixed
noise seed the choice is deterministic.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence

import numpy as np
import torch
from pydantic import Field
from torch import Tensor
from vistac.component import Component, ComponentConfig, ComponentContext
from vistac.errors import ConfigError, DataError
from vistac.plugins.filters.dual import cholesky_safe
from vistac.protocols import Scene
from vistac.types import Action

log = logging.getLogger(__name__)


def gaussian_kl(mean_p: Tensor, cov_p: Tensor, mean_q: Tensor, cov_q: Tensor) -> Tensor:
    """KL(N(mean_p, cov_p) || N(mean_q, cov_q)) in nats, batched.

    mean [..., n], cov [..., n, n] (symmetric positive definite) -> [...]:
    0.5 (tr(S_q^-1 S_p) + (m_q - m_p)^T S_q^-1 (m_q - m_p) - n + ln det S_q - ln det S_p).
    """
    factor_p, factor_q = cholesky_safe(cov_p), cholesky_safe(cov_q)
    whitened = torch.linalg.solve_triangular(factor_q, factor_p, upper=False)
    shift = torch.linalg.solve_triangular(
        factor_q, (mean_q - mean_p).unsqueeze(-1), upper=False
    ).squeeze(-1)
    log_det_q = 2.0 * factor_q.diagonal(dim1=-2, dim2=-1).log().sum(-1)
    log_det_p = 2.0 * factor_p.diagonal(dim1=-2, dim2=-1).log().sum(-1)
    trace = whitened.square().sum((-2, -1))
    n = mean_p.shape[-1]
    return 0.5 * (trace + shift.square().sum(-1) - n + log_det_q - log_det_p)


class InfoGainSelector(Component):
    """Picks the candidate whose predicted belief diverges most from the current one."""

    kind = "action_selector"

    class Config(ComponentConfig):
        horizon_s: float = Field(2.5, gt=0, description="how far ahead each action is predicted")
        sigma_points: int = Field(
            32, ge=2, description="Monte-Carlo points of the look-ahead (fewer than the filter's)"
        )
        rate_hz: float = Field(
            15.0,
            gt=0,
            description="prediction steps per second (the "
            "skill's rate_hz, which the filter was trained at)",
        )

    def __init__(self, config: Config, ctx: ComponentContext) -> None:
        super().__init__(config, ctx)
        self.config: InfoGainSelector.Config = config
        filter_ = ctx.find("filter")
        if filter_ is None or not callable(getattr(filter_, "predict_beliefs", None)):
            raise ConfigError(
                "actions.info_gain needs a filter component with predict_beliefs "
                "(filters.dual) in the skill"
                + ("" if filter_ is None else f"; {type(filter_).__name__} has none")
            )
        self.filter = filter_

    def gains(self, candidates: Sequence[Action]) -> Tensor:
        """IG_N [M] (nats) of each candidate: KL(predicted || current) over the joint state."""
        predicted = self.filter.predict_beliefs(
            candidates, self.config.horizon_s, self.config.rate_hz, self.config.sigma_points
        )
        current_mean, current_cov = self.filter.predict_beliefs(
            candidates[:1], 0.0, self.config.rate_hz
        )[0]
        means = torch.stack([mean for mean, _ in predicted])
        covs = torch.stack([cov for _, cov in predicted])
        return gaussian_kl(means, covs, current_mean, current_cov)

    def select(
        self, candidates: Sequence[Action], scene: Scene, rng: np.random.Generator
    ) -> Action:
        if not candidates:
            raise DataError("actions.info_gain: no candidate actions to choose from")
        gains = self.gains(candidates)
        best = int(torch.argmax(gains))
        log.info(
            "info gain: %s %d of %d, IG %.3g nats (median %.3g)",
            candidates[best].kind, best, len(candidates), float(gains[best]),
            float(gains.median()),
        )  # fmt: skip
        return candidates[best]
