"""Registers the standard tree nodes. Imports nothing heavy."""

from __future__ import annotations

from vistac import hookimpl
from vistac.registry import Registry

_NODES = {
    "look": "look:Look",
    "choose_action": "interaction:ChooseAction",
    "execute_action": "interaction:ExecuteAction",
    "update_belief": "belief:UpdateBelief",
    "belief_converged": "belief:BeliefConverged",
    "stop": "stop:Stop",
}


@hookimpl
def vistac_register(registry: Registry) -> None:
    for name, target in _NODES.items():
        registry.add("behaviour", name, f"vistac.behaviours.{target}")
