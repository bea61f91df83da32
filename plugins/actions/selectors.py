"""Action selectors that need no model: ``actions.random`` and ``actions.uniform``."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from pydantic import Field
from vistac.component import Component, ComponentConfig, ComponentContext
from vistac.errors import DataError
from vistac.protocols import Scene
from vistac.types import Action


class RandomSelector(Component):
    """Picks one candidate uniformly at random (the R-GNN baseline's selection rule)."""

    kind = "action_selector"

    class Config(ComponentConfig):
        pass

    def select(
        self, candidates: Sequence[Action], scene: Scene, rng: np.random.Generator
    ) -> Action:
        if not candidates:
            raise DataError("actions.random: no candidate actions to choose from")
        return candidates[int(rng.integers(len(candidates)))]


class UniformSelector(Component):
    """``actions.uniform``: cycles through ``directions`` evenly spaced push directions,
    starting at ``start_rad``; each call takes the candidate whose direction is closest to the
    next one (the first such candidate on a tie), so the choice does not depend on the rng."""

    kind = "action_selector"

    class Config(ComponentConfig):
        directions: int = Field(8, gt=0, description="K, evenly spaced directions per cycle")
        start_rad: float = Field(0.0, description="the first direction (rad)")

    def __init__(self, config: Config, ctx: ComponentContext) -> None:
        super().__init__(config, ctx)
        self.config: UniformSelector.Config = config
        self.calls = 0

    def select(
        self, candidates: Sequence[Action], scene: Scene, rng: np.random.Generator
    ) -> Action:
        if not candidates:
            raise DataError("actions.uniform: no candidate actions to choose from")
        step = self.calls % self.config.directions
        target = self.config.start_rad + 2.0 * np.pi * step / self.config.directions
        self.calls += 1
        directions = np.array([action.pd_rad for action in candidates])
        gap = np.abs(np.angle(np.exp(1j * (directions - target))))
        return candidates[int(np.argmin(gap))]
