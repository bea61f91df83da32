"""Registers the shape-perception components. Imports nothing heavy."""

from __future__ import annotations

from vistac import hookimpl
from vistac.registry import Registry


@hookimpl
def vistac_register(registry: Registry) -> None:
    registry.add("view_planner", "shape.uniform_views", "vistac.plugins.shape.views:UniformViews")
    registry.add("shape_estimator", "shape.ems", "vistac.plugins.shape.ems:EMSEstimator")
