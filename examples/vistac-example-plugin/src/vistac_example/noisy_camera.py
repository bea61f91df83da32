"""``example.noisy_camera``: wraps another camera of the skill and degrades its depth."""

from __future__ import annotations

import numpy as np
from pydantic import Field
from vistac.component import Component, ComponentConfig, ComponentContext
from vistac.types import RGBD, PixelWindow, Viewpoint


class NoisyCamera(Component):
    """Adds zero-mean Gaussian depth noise and random dropouts to the ``source`` camera."""

    kind = "camera"

    class Config(ComponentConfig):
        source: str = Field(description="role of the wrapped camera in the skill")
        extra_noise_m: float = Field(0.003, ge=0)
        dropout_prob: float = Field(0.02, ge=0, le=1)

    def __init__(self, config: Config, ctx: ComponentContext) -> None:
        super().__init__(config, ctx)
        self.source = ctx.component(config.source)
        self.movable = self.source.movable
        self.rng = ctx.rng("example.noisy_camera")

    def move_to(self, view: Viewpoint) -> None:
        self.source.move_to(view)

    def capture(
        self, width: int | None = None, height: int | None = None, window: PixelWindow | None = None
    ) -> RGBD:
        frame = self.source.capture(width, height, window)
        depth = frame.depth_m + self.rng.normal(0.0, self.config.extra_noise_m, frame.depth_m.shape)
        depth[self.rng.random(depth.shape) < self.config.dropout_prob] = np.nan
        return RGBD(depth, frame.intrinsics, frame.world_from_camera, frame.timestamp_s, frame.rgb)
