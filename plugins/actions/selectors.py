"""Action selectors that need no model: ``actions.random``."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from vistac.component import Component, ComponentConfig
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
