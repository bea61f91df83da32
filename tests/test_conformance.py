"""Every shipped component passes the conformance suite of its kind."""

from __future__ import annotations

from pathlib import Path

import pytest
from conftest import SKILLS
from vistac.pluginmanager import Plugins
from vistac.testing import build_components, check_component, check_component_class
from vistac.types import ArmState

SIM = {
    "world": {"plugin": "sim.mujoco", "with": {"object": str(SKILLS / "objects/rect1.yaml")}},
    "arm": {"plugin": "sim.arm"},
    "gripper": {"plugin": "sim.gripper"},
    "camera": {"plugin": "sim.depth_camera", "with": {"width": 80, "height": 60}},
    "tactile": {"plugin": "sim.tactile"},
    "views": {"plugin": "shape.uniform_views"},
    "affordances": {"plugin": "actions.outline"},
    "planner": {"plugin": "actions.random"},
    "executor": {"plugin": "actions.cartesian"},
}


def test_every_registered_component_class(plugins: Plugins) -> None:
    for entry in plugins.registry.entries():
        if entry.plugin != "fixtures_plugin" and entry.kind != "behaviour":
            cls = plugins.registry.load(entry.name)
            if entry.name != "sim.mujoco":  # needs an object file
                check_component_class(cls)


@pytest.mark.parametrize("role", [r for r in SIM if r != "executor"])
def test_sim_component_conforms(role: str, plugins: Plugins, tmp_path: Path) -> None:
    ctx = build_components(SIM, tmp_path, plugins=plugins)
    check_component(ctx.component(role), advance=ctx.clock.advance)


def test_conformance_catches_a_speeding_arm(plugins: Plugins, tmp_path: Path) -> None:
    components = {**SIM, "arm": {"plugin": "sim.arm", "with": {"max_speed_mps": 0.025}}}
    ctx = build_components(components, tmp_path, plugins=plugins)
    arm = ctx.component("arm")
    honest_state = arm.state

    def speeding_state() -> ArmState:  # an arm whose cap does not hold: the check must notice
        state = honest_state()
        return ArmState(state.pose, state.twist * 3, state.timestamp_s)

    arm.state = speeding_state
    with pytest.raises(AssertionError, match="above the cap"):
        check_component(arm, advance=ctx.clock.advance)
