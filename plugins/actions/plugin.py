"""Registers the action components. Imports nothing heavy."""

from __future__ import annotations

from vistac import hookimpl
from vistac.registry import Registry

_PACKAGE = "vistac.plugins.actions"


@hookimpl
def vistac_register(registry: Registry) -> None:
    registry.add("action_sampler", "actions.outline", f"{_PACKAGE}.outline:OutlineSampler")
    registry.add(
        "action_sampler", "actions.affordances", f"{_PACKAGE}.affordances:SuperquadricAffordances"
    )
    registry.add("action_sampler", "actions.push_pull_rule", f"{_PACKAGE}.affordances:PushPullRule")
    registry.add("action_selector", "actions.random", f"{_PACKAGE}.selectors:RandomSelector")
    registry.add("action_selector", "actions.uniform", f"{_PACKAGE}.selectors:UniformSelector")
    registry.add("action_selector", "actions.info_gain", f"{_PACKAGE}.info_gain:InfoGainSelector")
    registry.add("executor", "actions.cartesian", f"{_PACKAGE}.executor:CartesianExecutor")
    registry.add("controller", "actions.icem", f"{_PACKAGE}.icem:ICEMController")
    registry.add("behaviour", "change_detected", f"{_PACKAGE}.change:ChangeDetected")
    registry.add("behaviour", "plan_push", f"{_PACKAGE}.goal:PlanPush")
    registry.add("behaviour", "goal_reached", f"{_PACKAGE}.goal:GoalReached")
