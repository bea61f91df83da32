"""View planners that need no shape model: ``shape.uniform_views``.

The camera circles the object on a hemisphere. The target is ``target_m`` until a first
cloud is available, then the centroid of the points above the table.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np
from pydantic import Field
from vistac.component import Component, ComponentConfig, ComponentContext
from vistac.types import FloatArray, PointCloud, ShapeEstimate, Viewpoint


def object_centroid(
    cloud: PointCloud | None, fallback_m: FloatArray, clearance_m: float
) -> FloatArray:
    """Centroid [3] of the cloud's points above the table, or ``fallback_m`` when none."""
    if cloud is None:
        return fallback_m
    above = cloud.points_m[cloud.points_m[:, 2] > clearance_m]
    return above.mean(axis=0) if len(above) else fallback_m


class UniformViewSettings(Protocol):
    """The configuration fields :func:`uniform_view` reads."""

    radius_m: float
    elevation_deg: float
    start_azimuth_deg: float
    target_m: tuple[float, float, float]
    table_clearance_m: float


def uniform_view(
    cloud: PointCloud | None, index: int, count: int, config: UniformViewSettings
) -> Viewpoint:
    """View ``index`` of ``count`` evenly spaced in azimuth from ``start_azimuth_deg`` at
    ``elevation_deg``, aimed at the object (``target_m`` before any cloud)."""
    target = object_centroid(cloud, np.array(config.target_m), config.table_clearance_m)
    azimuth = np.radians(config.start_azimuth_deg) + 2 * np.pi * index / count
    return Viewpoint.on_hemisphere(
        target, config.radius_m, azimuth, np.radians(config.elevation_deg)
    )


class UniformViews(Component):
    """``views`` viewpoints evenly spaced in azimuth at a fixed elevation and radius."""

    kind = "view_planner"

    class Config(ComponentConfig):
        views: int = Field(4, gt=0)
        radius_m: float = Field(0.5, gt=0)
        elevation_deg: float = Field(50.0, gt=0, le=90)
        start_azimuth_deg: float = -90.0
        target_m: tuple[float, float, float] = (0.0, 0.45, 0.03)
        table_clearance_m: float = Field(0.008, ge=0)

    def __init__(self, config: Config, ctx: ComponentContext) -> None:
        super().__init__(config, ctx)
        self.config: UniformViews.Config = config

    def next_view(
        self, cloud: PointCloud | None, shape: ShapeEstimate | None, views_taken: int
    ) -> Viewpoint | None:
        if views_taken >= self.config.views:
            return None
        return uniform_view(cloud, views_taken, self.config.views, self.config)
