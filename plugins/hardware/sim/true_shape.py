"""``sim.true_shape``: the shape estimate a perfect camera and segmentation would give.

A shape estimator for simulated skills that reads the object from the MuJoCo world (the
``world`` component, ``sim.mujoco``) instead of the point cloud: each link's true surface,
sampled densely and without noise where the link stands now, gets its own superquadric fit by
``shape.ems``'s fitting (a shear kept only where it pays, as there), the likeliest of a few
restarts. The links are never merged or split wrongly and no face is hidden, so
swapping it for ``shape.ems`` in a skill measures what the fit from the camera costs the
estimates downstream (``vistac eval ... --set components.shape.plugin=sim.true_shape``).

The estimate keeps the observed cloud's points above the table as its ``cloud``: the filter's
depth observation needs the points the camera saw.
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np
from pydantic import Field
from vistac.component import Component, ComponentConfig, ComponentContext
from vistac.errors import ConfigError, DataError
from vistac.objects import link_surface_points
from vistac.plugins.shape.ems import (
    EMSOptions,
    EMSResult,
    fit_superquadric,
    without_needless_shear,
)
from vistac.types import FloatArray, PointCloud, ShapeEstimate

logger = logging.getLogger(__name__)


class TrueShape(Component):
    """Superquadrics fitted to the simulated object's true link surfaces."""

    kind = "shape_estimator"

    class Config(ComponentConfig):
        points_per_link: int = Field(2000, ge=100, description="true surface points per link")
        restarts: int = Field(
            3, ge=1, description="fits per link, each to a fresh sample of its surface; the "
            "likeliest is kept (a fit can settle in a poor optimum, as from a camera)",
        )
        table_clearance_m: float = Field(
            0.008, ge=0, description="the cloud kept for the filter: points above this z"
        )

    def __init__(self, config: Config, ctx: ComponentContext) -> None:
        super().__init__(config, ctx)
        self.config: TrueShape.Config = config
        self.options = EMSOptions()
        self._rng = ctx.rng("true_shape")

    def _world(self) -> Any:
        world = self.ctx.find("world")
        if world is None or not hasattr(world, "spec") or not hasattr(world, "link_poses"):
            raise ConfigError(
                "sim.true_shape reads the object from the simulated world: the skill needs "
                "components.world with plugin sim.mujoco (on a real robot use shape.ems)"
            )
        return world

    def _fit_link(self, points_m: FloatArray) -> EMSResult:
        """One link's superquadric fitted to its surface points [N, 3]."""
        link = fit_superquadric(points_m, self.options)
        return without_needless_shear(points_m, [link], self.options)[0]

    def fit(self, cloud: PointCloud) -> ShapeEstimate:
        """The true links' superquadrics where they stand now; ``cloud`` (world frame) gives
        the estimate's observed points only."""
        world = self._world()
        samples = [
            link_surface_points(world.spec, world.link_poses(), self.config.points_per_link,
                                self._rng)
            for _ in range(self.config.restarts)
        ]  # fmt: skip
        links = [
            min((self._fit_link(sample[i]) for sample in samples), key=lambda link: link.nll)
            for i in range(len(world.spec.links))
        ]
        points = np.asarray(cloud.points_m, dtype=np.float64).reshape(-1, 3)
        above = points[np.isfinite(points).all(axis=1)]
        above = above[above[:, 2] > self.config.table_clearance_m]
        if len(above) == 0:
            raise DataError(
                "sim.true_shape: no observed point lies above the table; the filter needs the "
                "object's points: check the camera"
            )
        logger.info("true shape: %d link(s), %d observed points", len(links), len(above))
        return ShapeEstimate(
            links=tuple(link.superquadric for link in links),
            initial_poses=np.array([link.planar_pose for link in links]),
            uncertainty=np.array([link.std for link in links]),
            cloud=PointCloud(above),
            covariance=np.array([link.covariance for link in links]),
        )
