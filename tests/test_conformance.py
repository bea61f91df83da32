"""Every shipped component passes the conformance suite of its kind."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from conftest import SKILLS
from torch import Tensor
from vistac.pluginmanager import Plugins
from vistac.plugins.filters.state import Prediction
from vistac.testing import build_components, check_component, check_component_class
from vistac.types import ArmState, PointCloud, ShapeEstimate

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


PROCESS_MODELS = {
    "gnn": {"plugin": "filters.gnn", "with": {"hidden": 16}},
    "gnn shipped": {
        "plugin": "filters.gnn",
        "with": {"checkpoint": str(SKILLS / "checkpoints/gnn_push.pt"), "hidden": 32},
    },
    "gnn mirror_average": {"plugin": "filters.gnn", "with": {"hidden": 16, "mirror_average": True}},
    "ff 1 link": {"plugin": "filters.ff", "with": {"hidden": 16, "n_links": 1}},
    "ff 2 links": {"plugin": "filters.ff", "with": {"hidden": 16, "n_links": 2}},
    "ff shipped, by link count": {
        "plugin": "filters.ff",
        "with": {"hidden": 32, "checkpoints": {
            n: str(SKILLS / f"checkpoints/ff{n}/ff_push.pt") for n in (1, 2)
        }},
    },
    "analytical": {"plugin": "filters.analytical"},
}


@pytest.mark.parametrize("name", PROCESS_MODELS)
def test_shipped_process_models_conform(name: str, plugins: Plugins, tmp_path: Path) -> None:
    ctx = build_components({"model": PROCESS_MODELS[name]}, tmp_path, plugins=plugins)
    check_component(ctx.component("model"))


class _Broken:
    """The analytical model with one promise broken: what the process-model check must catch."""

    kind = "process_model"
    n_links = 1

    def __init__(self, model: Any, flaw: str) -> None:
        self.model, self.flaw = model, flaw

    def predict(self, states: Tensor, inputs: Any, dt_s: float) -> Prediction:
        prediction = self.model.predict(states, inputs, dt_s)
        pose, force, var = prediction.pose, prediction.force_n, prediction.process_var
        if self.flaw == "mutates":
            states[..., 0] += 1e-3
        elif self.flaw == "couples points":  # a point's prediction depends on the others
            pose = pose + states[..., :6].mean(-2, keepdim=True)
        elif self.flaw == "float32":
            force = force.float()
        elif self.flaw == "random":
            pose = pose + 1e-3 * torch.randn_like(pose)
        elif self.flaw == "variance shape":
            var = var[..., :3]
        return Prediction(pose, force, var)


@pytest.mark.parametrize(
    ("flaw", "message"),
    [
        ("mutates", "must not change the states"),
        ("couples points", "may depend on its own state and inputs only"),
        ("float32", "force_n must be float64"),
        ("random", "must give the same pose"),
        ("variance shape", "process_var: expected one of"),
    ],
)
def test_process_model_check_catches_a_broken_model(
    flaw: str, message: str, plugins: Plugins, tmp_path: Path
) -> None:
    ctx = build_components({"model": PROCESS_MODELS["analytical"]}, tmp_path, plugins=plugins)
    with pytest.raises(AssertionError, match=message):
        check_component(_Broken(ctx.component("model"), flaw))


@pytest.mark.parametrize("max_links", [1, 2])
def test_shipped_shape_estimator_conforms(max_links: int, plugins: Plugins, tmp_path: Path) -> None:
    components = {"shape": {"plugin": "shape.ems", "with": {"max_links": max_links}}}
    check_component(build_components(components, tmp_path, plugins=plugins).component("shape"))


class _OffsetEstimator:
    """shape.ems with its estimate moved or malformed: the shape-estimator check must notice."""

    kind = "shape_estimator"

    def __init__(self, estimator: Any, flaw: str) -> None:
        self.estimator, self.flaw = estimator, flaw

    def fit(self, cloud: PointCloud) -> ShapeEstimate:
        estimate = self.estimator.fit(cloud)
        poses = np.array(estimate.initial_poses, dtype=np.float64)
        if self.flaw == "moved":
            poses[:, 0] += 0.03
        elif self.flaw == "poses shape":
            poses = poses[:, :2]
        return replace(estimate, initial_poses=poses)


@pytest.mark.parametrize(
    ("flaw", "message"), [("moved", "from the box's"), ("poses shape", "initial_poses")]
)
def test_shape_estimator_check_catches_a_wrong_fit(
    flaw: str, message: str, plugins: Plugins, tmp_path: Path
) -> None:
    ctx = build_components({"shape": {"plugin": "shape.ems"}}, tmp_path, plugins=plugins)
    with pytest.raises(AssertionError, match=message):
        check_component(_OffsetEstimator(ctx.component("shape"), flaw))
