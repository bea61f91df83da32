"""Mirror images of recorded interactions (``vistac.plugins.filters.data.mirrored``) and the
training option that uses them (``mirror`` in a training preset)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from simctx import box_object, sim_setup
from test_sim_physics import DT_S, execute
from vistac.objects import ObjectSpec
from vistac.plugins.filters import train as train_module
from vistac.plugins.filters.data import (
    Trajectory,
    central_twist,
    mirrored,
    process_inputs,
    true_states,
)
from vistac.plugins.filters.mirror import reflect_scene
from vistac.plugins.filters.state import StateLayout
from vistac.types import Push


def _recorded_push(tmp_path: Path, spec: dict[str, Any], push: Push) -> Trajectory:
    """The push carried out in the simulated world, recorded as a training trajectory."""
    ctx = sim_setup(tmp_path, spec)
    world, arm = ctx.find("world"), ctx.find("arm")
    poses, tcp = [world.link_poses()], [np.r_[arm.state().pose[[0, 1, 3]], 0.0, 0.0, 0.0]]
    original_step = world.step

    def step(dt_s: float) -> None:
        original_step(dt_s)
        state = arm.state()
        poses.append(world.link_poses())
        tcp.append(np.r_[state.pose[[0, 1, 3]], state.twist[[0, 1, 3]]])

    world.step = step
    execute(ctx, push)
    poses_array = np.unwrap(np.array(poses), axis=0)
    object_spec = ObjectSpec.model_validate(spec)
    link = object_spec.links[0]
    return Trajectory(
        source=str(tmp_path), spec=object_spec, kind="push", pd_rad=push.pd_rad, link=0,
        dt_s=DT_S, poses=poses_array, twists=central_twist(poses_array, DT_S),
        tcp=np.array(tcp), force_n=np.zeros((len(poses), 2)), depth_m=None, camera_pose=None,
        intrinsics=None,
        parameters={"m_0": link.mass_kg, "f_0": link.friction, "com_x_0": link.com_m[0],
                    "com_y_0": link.com_m[1]},
    )  # fmt: skip


def test_the_mirror_of_a_simulated_push_is_the_push_of_the_mirrored_object(
    tmp_path: Path,
) -> None:
    """Known answer from the simulator: a box with its CoM off centre, turned and off the push
    line, pushed along +y through x = 0, and its mirror image across that line (x and the CoM's
    y negated, turned by pi - theta) pushed the same way. The mirror of the first recording is
    the second within 0.1 mm and 0.01 degrees (1e-6 m and 0.001 degrees measured), while the
    box moves 9 cm and turns by 25 degrees."""
    push = Push(cp_m=np.array([0.0, 0.405]), pd_rad=math.pi / 2, speed_mps=0.02)
    original = box_object(pose=[0.012, 0.45, 0.3], link={"com_m": [0.01, 0.02]})
    image = box_object(pose=[-0.012, 0.45, math.pi - 0.3], link={"com_m": [0.01, -0.02]})
    recorded = _recorded_push(tmp_path / "original", original, push)
    expected = _recorded_push(tmp_path / "image", image, push)
    reflected = mirrored(recorded)
    moved_m = np.linalg.norm(recorded.poses[-1, 0, :2] - recorded.poses[0, 0, :2])
    turned_rad = abs(recorded.poses[-1, 0, 2] - recorded.poses[0, 0, 2])
    assert moved_m > 0.05 and turned_rad > math.radians(20)
    assert reflected.parameters["com_y_0"] == pytest.approx(-0.02)
    assert reflected.reflected and reflected.pd_rad == recorded.pd_rad
    steps = min(len(reflected.poses), len(expected.poses))
    error = reflected.poses[:steps] - expected.poses[:steps]
    assert np.abs(error[..., :2]).max() < 1e-4
    turn_error = (error[..., 2] + math.pi) % (2 * math.pi) - math.pi
    assert np.abs(turn_error).max() < math.radians(0.01)
    tcp_error = reflected.tcp[:steps, :2] - expected.tcp[:steps, :2]
    assert np.abs(tcp_error).max() < 1e-4


def _two_link_trajectory(kind: str) -> Trajectory:
    """A synthetic trajectory of a two-link object pushed at 30 degrees."""
    link = {"footprint": "rect2", "height_m": 0.05, "mass_kg": 0.6, "friction": 0.3,
            "com_m": [0.01, -0.015]}  # fmt: skip
    spec: dict[str, Any] = {"name": "pair", "type": kind, "pose": [0.02, 0.45, 0.4],
                            "links": [link, {**link, "com_m": [-0.02, 0.012]}]}  # fmt: skip
    if kind == "articulated":
        spec["joint"] = {"friction_nm": 0.2}
    rng = np.random.default_rng(0)
    steps = 6
    poses = np.array([[0.02, 0.45, 0.4], [0.12, 0.49, 0.5]]) + rng.normal(0, 0.01, (steps, 2, 3))
    tcp = np.column_stack([np.linspace(-0.1, -0.08, steps), np.linspace(0.40, 0.41, steps),
                           rng.normal(0, 0.1, (steps, 4))])  # fmt: skip
    return Trajectory(
        source="synthetic", spec=ObjectSpec.model_validate(spec), kind="push",
        pd_rad=math.radians(30), link=0, dt_s=DT_S, poses=poses,
        twists=central_twist(poses, DT_S), tcp=tcp, force_n=rng.normal(0, 1, (steps, 2)),
        depth_m=None, camera_pose=None, intrinsics=None,
        parameters={"m_0": 0.6, "f_0": 0.3, "com_x_0": 0.01, "com_y_0": -0.015, "m_1": 0.6,
                    "f_1": 0.3, "com_x_1": -0.02, "com_y_1": 0.012, "f_j_0": 0.2},
    )  # fmt: skip


@pytest.mark.parametrize("kind", ["heterogeneous", "articulated"])
def test_the_mirrored_states_and_inputs_are_those_the_filter_reflects(kind: str) -> None:
    """The filter's states and process inputs of a mirrored trajectory at its first step are
    ``reflect_scene`` of the original's (the reflection the models use for mirror-averaged
    predictions, about the line through the TCP along the push); the mirror of the mirror is
    the original."""
    trajectory = _two_link_trajectory(kind)
    layout = StateLayout(2)
    reflected = mirrored(trajectory)
    states, inputs = true_states(trajectory, layout)[None, :1], process_inputs([trajectory])[0]
    want_states, want_inputs = reflect_scene(states, inputs)  # states [1 object, 1 point, n]
    got_states = true_states(reflected, layout)[None, :1]
    got_inputs = process_inputs([reflected])[0]
    torch.testing.assert_close(got_states, want_states)
    torch.testing.assert_close(got_inputs.link_offset, want_inputs.link_offset)
    torch.testing.assert_close(got_inputs.tcp, want_inputs.tcp)
    torch.testing.assert_close(got_inputs.pd_rad, want_inputs.pd_rad)
    force = trajectory.force_n[0]
    reflected_force = reflected.force_n[0]
    line = np.array([math.cos(trajectory.pd_rad), math.sin(trajectory.pd_rad)])
    assert reflected_force @ line == pytest.approx(force @ line)  # along the line: kept
    normal = np.array([-line[1], line[0]])
    assert reflected_force @ normal == pytest.approx(-(force @ normal))  # across it: negated
    twice = mirrored(reflected)
    assert not twice.reflected
    for name in ("poses", "twists", "tcp", "force_n"):
        np.testing.assert_allclose(getattr(twice, name), getattr(trajectory, name), atol=1e-12)
    assert twice.parameters == pytest.approx(trajectory.parameters)


def test_mirror_training_reflects_about_half_the_windows_and_validates_on_none(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """With ``mirror`` the rollout batches hold reflected and unreflected windows (chosen at
    random), the validation batches only unreflected ones; without it none is reflected."""
    seen: dict[bool, list[bool]] = {True: [], False: []}
    original_loss = train_module.rollout_loss

    def spy(model: Any, windows: list[Trajectory], *args: Any) -> torch.Tensor:
        seen[torch.is_grad_enabled()].extend(w.reflected for w in windows)
        return original_loss(model, windows, *args)

    monkeypatch.setattr(train_module, "rollout_loss", spy)
    windows = {
        "train": [_two_link_trajectory("articulated") for _ in range(24)],
        "val": [_two_link_trajectory("articulated") for _ in range(4)],
    }
    for mirror in (True, False):
        seen[True].clear()
        config = train_module.TrainConfig(
            hidden=8, epochs=1, filter_epochs=0, batch_size=4, mirror=mirror, rollout_steps=3
        )
        rng = np.random.default_rng(0)
        train_module._train_model(
            "gnn", "push", None, windows, config, tmp_path / str(mirror), rng  # type: ignore[arg-type]
        )
        assert len(seen[True]) == 24
        assert (0 < sum(seen[True]) < 24) if mirror else not any(seen[True])
    assert seen[False] and not any(seen[False])
