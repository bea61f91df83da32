"""Registers the touch components and tree nodes. Imports nothing heavy."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from vistac import hookimpl
from vistac.registry import Registry

if TYPE_CHECKING:
    from vistac.run import RunInfo

_PACKAGE = "vistac.plugins.touch"


@hookimpl
def vistac_register(registry: Registry) -> None:
    registry.add("touch_estimator", "touch.pf", f"{_PACKAGE}.pf:TouchParticleFilter")
    registry.add("touch_estimator", "touch.gpis", f"{_PACKAGE}.gpis:GpisSurface")
    registry.add("touch_explorer", "touch.dhd", f"{_PACKAGE}.explore:DhdExplorer")
    registry.add("touch_explorer", "touch.rrt", f"{_PACKAGE}.explore:RrtExplorer")
    registry.add("behaviour", "explore_touch", f"{_PACKAGE}.behaviours:ExploreTouch")
    registry.add("behaviour", "recognised", f"{_PACKAGE}.behaviours:Recognised")
    registry.add("behaviour", "learn_shape", f"{_PACKAGE}.learning:LearnShape")


@hookimpl
def vistac_skill_end(run: RunInfo, status: str, summary: dict[str, Any]) -> None:
    """Add ``touch_errors`` (class right, pose error, steps) when the probe knew the truth, and
    the learned shape's reconstruction error (TWD, m) with its Poisson peer."""
    if isinstance(summary.get("touch"), dict) and isinstance(summary.get("touch_truth"), dict):
        from vistac.plugins.touch.evaluation import touch_errors

        summary["touch_errors"] = touch_errors(summary["touch"], summary["touch_truth"])
    if "learned_shape" in summary:
        from vistac.plugins.touch.learning import add_learning_metrics

        add_learning_metrics(summary, run.skill_path.parent)
