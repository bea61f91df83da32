"""Registers the shape-perception components. Imports nothing heavy."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from vistac import hookimpl
from vistac.registry import Registry

if TYPE_CHECKING:
    from vistac.run import RunInfo


@hookimpl
def vistac_register(registry: Registry) -> None:
    registry.add("view_planner", "shape.uniform_views", "vistac.plugins.shape.views:UniformViews")
    registry.add("shape_estimator", "shape.ems", "vistac.plugins.shape.ems:EMSEstimator")
    registry.add("view_planner", "shape.entropy_nbv", "vistac.plugins.shape.nbv:EntropyNBV")
    registry.add("view_planner", "shape.random_views", "vistac.plugins.shape.nbv:RandomViews")
    registry.add(
        "cloud_processor",
        "shape.open3d_cloud",
        "vistac.plugins.shape.preprocess:Open3dCloudProcessor",
    )


@hookimpl
def vistac_skill_end(run: RunInfo, status: str, summary: dict[str, Any]) -> None:
    """Add ``shape_errors`` (Chamfer distance per link, m) when the true object is known."""
    truth = summary.get("ground_truth")
    if "shape" in summary and isinstance(truth, dict) and "object" in truth:
        from vistac.plugins.shape.evaluation import shape_errors

        summary["shape_errors"] = shape_errors(summary["shape"], truth)
