"""Process models of the dual filter: conformance of the GNN, feed-forward and analytical
models, link-count generality, checkpoints, and the quasi-static pushing physics checked
against known answers and an independent numerical solution."""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from pydantic import ValidationError
from scipy.optimize import least_squares, minimize, root
from simctx import TestContext
from torch import Tensor
from vistac.errors import ConfigError, DataError
from vistac.plugins.filters import chain, nets
from vistac.plugins.filters.analytical import (
    characteristic_length_m,
    linear_pressure_length_m,
    quasi_static_push,
)
from vistac.plugins.filters.mirror import mirror_averaged, reflect_poses, reflect_scene
from vistac.plugins.filters.models import (
    AnalyticalProcessModel,
    FFProcessModel,
    GNNProcessModel,
    sidecar_path,
)
from vistac.plugins.filters.nets import GraphProcessNet, rotate
from vistac.plugins.filters.state import DTYPE, Prediction, ProcessInput, StateLayout

HALF_M = 0.045
GAP_M = 0.004
SPEED_MPS = 0.025
DT_S = 0.05
C = 7


def scenario(
    batch: tuple[int, ...],
    n_links: int,
    count: int = C,
    link: int = 0,
    is_pull: float = 0.0,
    seed: int = 0,
) -> tuple[Tensor, ProcessInput]:
    """A chain of square links along +x at y = 0.45, pushed along +x on link 0's -x side near
    its middle; sigma points scattered around the nominal state. states: [*batch, count, n]."""
    layout = StateLayout(n_links)
    offset = torch.zeros(n_links, 3, dtype=DTYPE)
    offset[:, 0] = torch.arange(n_links, dtype=DTYPE) * (2 * HALF_M + GAP_M)
    pose = torch.zeros(n_links, 6, dtype=DTYPE)
    pose[:, :3] = offset + torch.tensor([0.0, 0.45, 0.0], dtype=DTYPE)
    params = torch.tensor([[0.8, 0.3, 0.005, -0.004]], dtype=DTYPE).expand(n_links, 4)
    mean = torch.cat([pose.flatten(), params.flatten(), torch.full((n_links - 1,), 0.2)])
    spread = torch.cat(
        [
            torch.tensor([0.002, 0.002, 0.02, 0.002, 0.002, 0.01]).repeat(n_links),
            torch.tensor([0.1, 0.03, 0.003, 0.003]).repeat(n_links),
            torch.full((n_links - 1,), 0.05),
        ]
    ).to(DTYPE)
    generator = torch.Generator().manual_seed(seed)
    noise = torch.randn(*batch, count, layout.size, generator=generator, dtype=DTYPE)
    states = mean + spread * noise
    tcp = torch.tensor([-HALF_M - 0.009, 0.46, 0.0, SPEED_MPS, 0.0, 0.0], dtype=DTYPE)
    inputs = ProcessInput(
        tcp=tcp.expand(*batch, 6),
        pd_rad=torch.zeros(batch, dtype=DTYPE),
        is_pull=torch.full(batch, is_pull, dtype=DTYPE),
        link=torch.full(batch, link, dtype=torch.int64),
        link_size_m=torch.full((*batch, n_links, 2), HALF_M, dtype=DTYPE),
        link_offset=offset.expand(*batch, n_links, 3),
    )
    return states, inputs


def build(cls: type, tmp_path: Path, seed: int = 0, **options: Any) -> Any:
    return TestContext(tmp_path, seed).add(cls, **options)


MODELS: dict[str, tuple[Callable[[Path], Any], int]] = {
    "gnn": (lambda tmp: build(GNNProcessModel, tmp, hidden=32), 2),
    "ff": (lambda tmp: build(FFProcessModel, tmp, hidden=32, n_links=2), 2),
    "analytical": (lambda tmp: build(AnalyticalProcessModel, tmp), 2),
    "analytical_linear_pressure": (
        lambda tmp: build(AnalyticalProcessModel, tmp, pressure="linear"), 2
    ),
}


# ---------------------------------------------------------------------------------------------
# Conformance


def parts(prediction: Prediction) -> tuple[Tensor, Tensor, Tensor]:
    return prediction.pose, prediction.force_n, prediction.process_var


def check_prediction(prediction: Prediction, batch: tuple[int, ...], n_links: int) -> None:
    assert prediction.pose.shape == (*batch, C, 6 * n_links)
    assert prediction.force_n.shape == (*batch, C, 2)
    assert prediction.process_var.shape in {(*batch, 6 * n_links), (*batch, C, 6 * n_links)}
    for value in parts(prediction):
        assert value.dtype == DTYPE
        assert torch.isfinite(value).all()
    assert (prediction.process_var > 0).all()


@pytest.mark.parametrize("name", MODELS)
@pytest.mark.parametrize("batch", [(), (2,)])
def test_process_model_conformance(name: str, batch: tuple[int, ...], tmp_path: Path) -> None:
    factory, n_links = MODELS[name]
    model = factory(tmp_path)
    assert model.kind == "process_model"
    assert model.n_links in (None, n_links)
    states, inputs = scenario(batch, n_links)
    before = states.clone()

    prediction = model.predict(states, inputs, DT_S)

    check_prediction(prediction, batch, n_links)
    assert torch.equal(states, before), "predict must not change the states"
    again = model.predict(states, inputs, DT_S)
    for first, second in zip(parts(prediction), parts(again), strict=True):
        assert torch.equal(first, second)


@pytest.mark.parametrize("name", MODELS)
def test_process_model_is_differentiable(name: str, tmp_path: Path) -> None:
    factory, n_links = MODELS[name]
    model = factory(tmp_path)
    states, inputs = scenario((2,), n_links)
    states.requires_grad_(True)
    prediction = model.predict(states, inputs, DT_S)
    loss = sum(value.square().sum() for value in parts(prediction))
    assert isinstance(loss, Tensor)
    loss.backward()
    assert states.grad is not None and torch.isfinite(states.grad).all()
    assert states.grad.abs().sum() > 0
    if hasattr(model, "net"):
        for key, parameter in model.net.named_parameters():
            assert parameter.grad is not None, key
            assert torch.isfinite(parameter.grad).all(), key
            assert parameter.grad.abs().sum() > 0, key


def test_gnn_runs_on_one_two_and_three_links(tmp_path: Path) -> None:
    model = build(GNNProcessModel, tmp_path, hidden=32)
    for n_links in (1, 2, 3):
        for link in range(n_links):
            states, inputs = scenario((2,), n_links, link=link)
            check_prediction(model.predict(states, inputs, DT_S), (2,), n_links)


def test_gnn_pose_only_prediction_equals_the_full_one_without_the_force(tmp_path: Path) -> None:
    model = build(GNNProcessModel, tmp_path, hidden=32)
    states, inputs = scenario((2,), 2, link=1)
    full, pose_only = model.predict(states, inputs, DT_S), model.predict_pose(states, inputs, DT_S)
    check_prediction(pose_only, (2,), 2)
    assert torch.equal(pose_only.pose, full.pose)
    assert torch.equal(pose_only.process_var, full.process_var)
    assert not pose_only.force_n.any() and full.force_n.abs().sum() > 0


def test_gnn_force_vanishes_without_friction_load(tmp_path: Path) -> None:
    """The GNN's tactile force is the links' friction loads g m f times their node vectors:
    frictionless or massless links push back with nothing, whatever the net's weights."""
    model = build(GNNProcessModel, tmp_path, hidden=32)
    states, inputs = scenario((2,), 2, link=1)
    params = StateLayout(2).link_parameters(states)  # a view into states
    assert model.predict(states, inputs, DT_S).force_n.abs().min() > 0
    params[..., 1] = 0.0
    assert not model.predict(states, inputs, DT_S).force_n.any()
    params[..., 1], params[..., 0] = 0.3, 0.0
    assert not model.predict(states, inputs, DT_S).force_n.any()


def reference_graph_step(
    net: GraphProcessNet, states: Tensor, inputs: ProcessInput
) -> Prediction:
    """Algorithm 1 written link by link for one batch element (states [C, n]): the cause
    pass breadth-first from the robot, the effect pass back from the deepest links, then the
    force as the links' friction loads times ``tac_net`` of their nodes."""
    layout = StateLayout((states.shape[-1] + 1) // 11)
    n_links, acted = layout.n_links, int(inputs.link)
    links = net._link_nodes(states, inputs)  # [C, L, D]
    robot = net._robot_node(inputs).expand(states.shape[0], -1)
    pose = layout.link_pose(states)
    hinges = nets.hinge_points(pose, inputs)  # [C, L - 1, 2]

    def joint_edge(joint: int, receiver: int) -> Tensor:
        geometry = hinges[:, joint] - pose[:, receiver, :2]
        geometry = rotate(geometry, -inputs.pd_rad) / nets.SIZE_SCALE_M
        value = layout.joint_friction(states)[:, joint] / nets.JOINT_FRICTION_SCALE_NM
        return nets._edge(value, nets._EDGE_JOINT, geometry)

    robot_edge = nets._edge(inputs.is_pull.expand(states.shape[0]), nets._EDGE_ROBOT)
    table = nets._node(links.new_zeros(nets.NODE_DIM - 3), nets._TABLE).expand_as(robot)
    friction = layout.link_parameters(states)[..., 1] / nets.FRICTION_SCALE
    nodes = list(links.unbind(-2))
    support = [
        net._message(table, nodes[link], nets._edge(friction[:, link], nets._EDGE_SUPPORT))
        for link in range(n_links)
    ]
    by_depth = sorted(range(n_links), key=lambda link: abs(link - acted))
    for link in by_depth:
        parent = link + (acted > link) - (acted < link)
        sender, edge = (robot, robot_edge) if link == acted else (
            nodes[parent], joint_edge(min(link, parent), link)
        )  # fmt: skip
        cause = net._message(sender, nodes[link], edge)
        nodes[link] = net._update(nodes[link], cause + support[link])
    for link in reversed(by_depth):
        children = [
            child for child in (link + 1, link - 1)
            if 0 <= child < n_links and abs(child - acted) == abs(link - acted) + 1
        ]  # fmt: skip
        if children:
            message = torch.zeros(states.shape[0], net.hidden, dtype=DTYPE)
            for child in children:
                edge = joint_edge(min(link, child), link)
                message = message + net._message(nodes[child], nodes[link], edge)
            nodes[link] = net._update(nodes[link], message)
    params = layout.link_parameters(states)  # the friction load g m f of each link
    load_n = 9.81 * params[..., 0] * params[..., 1] / nets.FORCE_SCALE_N  # [C, L]
    force = sum(load_n[:, link, None] * net.tac_net(nodes[link]) for link in range(n_links))
    delta = torch.stack(nodes, -2)[..., : nets.MOTION_DIM] - links[..., : nets.MOTION_DIM]
    return Prediction(
        pose=nets.integrate(states, delta, inputs, DT_S),
        force_n=nets.force_to_world(force, inputs),
        process_var=net.noise(inputs.tcp.shape[:-1], n_links),
    )


@pytest.mark.parametrize("n_links", [1, 2, 3, 4])
def test_gnn_equals_the_link_by_link_reference(n_links: int) -> None:
    """The batched message passing (only the rows each phase updates) against Algorithm 1
    link by link, with a different acted link in each batch element, and its gradients."""
    torch.manual_seed(n_links)
    net = GraphProcessNet(hidden=16)
    acted = torch.arange(n_links).repeat(2)[: max(2, n_links)]
    states, inputs = scenario((len(acted),), n_links)
    inputs = ProcessInput(
        tcp=inputs.tcp, pd_rad=torch.linspace(-0.5, 0.5, len(acted), dtype=DTYPE),
        is_pull=(acted % 2).to(DTYPE), link=acted, link_size_m=inputs.link_size_m,
        link_offset=inputs.link_offset,
    )  # fmt: skip
    states.requires_grad_(True)
    batched = parts(net(states, inputs, DT_S))
    gradient = torch.autograd.grad(sum(part.square().sum() for part in batched), states)[0]
    for b in range(len(acted)):
        one = inputs.map(lambda tensor, b=b: tensor[b])
        reference = parts(reference_graph_step(net, states[b], one))
        for got, want in zip(batched, reference, strict=True):
            torch.testing.assert_close(got[b], want, rtol=1e-12, atol=1e-12)
        reference_loss = sum(part.square().sum() for part in reference)
        want_gradient = torch.autograd.grad(reference_loss, states)[0][b]
        torch.testing.assert_close(gradient[b], want_gradient, rtol=1e-10, atol=1e-12)


def test_gnn_is_translation_and_rotation_invariant() -> None:
    torch.manual_seed(0)
    net = GraphProcessNet(hidden=16)
    states, inputs = scenario((), 3, link=1)
    shift, angle = torch.tensor([0.3, -0.2], dtype=DTYPE), torch.tensor(0.7, dtype=DTYPE)

    def move(pose: Tensor) -> Tensor:
        """Rigidly move [..., 6 L] poses (or the [6] TCP) by (shift, angle)."""
        moved = pose.unflatten(-1, (-1, 6)).clone()
        moved[..., :2] = rotate(moved[..., :2], angle) + shift
        moved[..., 2] = moved[..., 2] + angle
        moved[..., 3:5] = rotate(moved[..., 3:5], angle)
        return moved.flatten(-2)

    layout = StateLayout(3)
    moved_states = torch.cat([move(states[..., layout.pose_slice]), states[..., 18:]], -1)
    moved_inputs = ProcessInput(
        tcp=move(inputs.tcp),
        pd_rad=inputs.pd_rad + angle,
        is_pull=inputs.is_pull,
        link=inputs.link,
        link_size_m=inputs.link_size_m,
        link_offset=inputs.link_offset,
    )
    original = net(states, inputs, DT_S)
    moved = net(moved_states, moved_inputs, DT_S)
    torch.testing.assert_close(moved.pose, move(original.pose))
    torch.testing.assert_close(moved.force_n, rotate(original.force_n, angle))


@pytest.mark.parametrize(
    ("local_xy_m", "gap_m"),
    [
        ((0.01, -0.005), 0.0),  # inside the footprint
        ((-0.05, 0.0), 0.01),  # 1 cm behind the -x side
        ((0.0, 0.022), 0.002),  # 2 mm beside the +y side
        ((0.046, -0.028), 0.01),  # off a corner: hypot(6 mm, 8 mm)
        ((0.2, 0.0), nets.GAP_CAP_M),  # far: capped
    ],
)
def test_link_features_give_the_tcp_gap_to_each_footprint(
    local_xy_m: tuple[float, float], gap_m: float
) -> None:
    """The gap feature is the TCP's distance to the link's footprint box (half extents
    40 x 20 mm), whatever the link's pose and the push direction."""
    link_pose = torch.tensor([0.1, 0.4, 0.7], dtype=DTYPE)
    tcp_xy = link_pose[:2] + rotate(torch.tensor(local_xy_m, dtype=DTYPE), link_pose[2])
    states = torch.cat([link_pose, torch.tensor([0, 0, 0, 0.8, 0.3, 0, 0])]).to(DTYPE)[None]
    inputs = ProcessInput(
        tcp=torch.cat([tcp_xy, torch.tensor([0.3, 0.02, 0.0, 0.0], dtype=DTYPE)]),
        pd_rad=torch.tensor(-1.2, dtype=DTYPE),
        is_pull=torch.tensor(0.0, dtype=DTYPE),
        link=torch.tensor(0),
        link_size_m=torch.tensor([[0.04, 0.02]], dtype=DTYPE),
        link_offset=torch.zeros(1, 3, dtype=DTYPE),
    )
    features = nets.link_features(states, inputs)
    assert features.shape == (1, 1, nets.LINK_FEATURE_DIM)
    got_m = float(features[0, 0, -1]) * nets.SIZE_SCALE_M
    assert got_m == pytest.approx(gap_m, abs=1e-12)


def test_link_features_give_the_com_in_the_reference_frame() -> None:
    """The CoM feature is the world CoM (link pose plus the link-frame CoM turned by the
    link's yaw) relative to the TCP, in the frame of the push direction: a link at yaw 90 deg
    with its CoM 20 mm along its own x, pushed along world +y from 50 mm behind its centre,
    has the CoM 70 mm ahead on the push line (x) and on the line (y = 0)."""
    link_pose = torch.tensor([0.1, 0.4, math.pi / 2], dtype=DTYPE)
    states = torch.cat([link_pose, torch.tensor([0, 0, 0, 0.8, 0.3, 0.02, 0.0])]).to(DTYPE)
    inputs = ProcessInput(
        tcp=torch.tensor([0.1, 0.35, 0.0, 0.0, 0.02, 0.0], dtype=DTYPE),
        pd_rad=torch.tensor(math.pi / 2, dtype=DTYPE),
        is_pull=torch.tensor(0.0, dtype=DTYPE),
        link=torch.tensor(0),
        link_size_m=torch.tensor([[0.04, 0.02]], dtype=DTYPE),
        link_offset=torch.zeros(1, 3, dtype=DTYPE),
    )
    features = nets.link_features(states[None], inputs)
    com_m = features[0, 0, 12:14] * nets.SIZE_SCALE_M
    torch.testing.assert_close(com_m, torch.tensor([0.07, 0.0], dtype=DTYPE))
    states[9] = 0.01  # and 10 mm along the link's y (world -x): 10 mm left of the line (+y)
    com_m = nets.link_features(states[None], inputs)[0, 0, 12:14] * nets.SIZE_SCALE_M
    torch.testing.assert_close(com_m, torch.tensor([0.07, 0.01], dtype=DTYPE))


def test_ff_rejects_another_link_count(tmp_path: Path) -> None:
    model = build(FFProcessModel, tmp_path, n_links=2)
    states, inputs = scenario((), 3)
    with pytest.raises(ValueError, match=r"n_links=2 \(state size 21\), got state size 32"):
        model.predict(states, inputs, DT_S)


def test_ff_with_a_checkpoint_per_link_count_predicts_with_the_states_count(
    tmp_path: Path,
) -> None:
    """`checkpoints`: one net per link count; the states' link count picks the net, so an
    object fitted with 1 or 2 links is filtered by that count's FF (the fit decides, not the
    skill); another count is refused, naming the counts there are."""
    singles = {n: build(FFProcessModel, tmp_path, seed=n, hidden=16, n_links=n) for n in (1, 2)}
    for n, single in singles.items():
        single.save_checkpoint(tmp_path / f"ff{n}.pt")
    both = build(FFProcessModel, tmp_path, hidden=16, checkpoints={1: "ff1.pt", 2: "ff2.pt"})
    assert both.n_links == (1, 2)
    for n, single in singles.items():
        states, inputs = scenario((), n)
        expected, got = single.predict(states, inputs, DT_S), both.predict(states, inputs, DT_S)
        for first, second in zip(parts(expected), parts(got), strict=True):
            assert torch.equal(first, second)
    states, inputs = scenario((), 3)
    with pytest.raises(ValueError, match=r"no feed-forward net for 3 link\(s\); .* 1, 2 link"):
        both.predict(states, inputs, DT_S)
    with pytest.raises(ConfigError, match="one net per link count"):
        both.save_checkpoint(tmp_path / "both.pt")


def test_ff_checkpoints_are_checked_per_link_count(tmp_path: Path) -> None:
    build(FFProcessModel, tmp_path, hidden=16, n_links=1).save_checkpoint(tmp_path / "ff1.pt")
    match = r"`checkpoints` 2: .*ff1\.pt does not match .*n_links: saved 1, configured 2"
    with pytest.raises(DataError, match=match):
        build(FFProcessModel, tmp_path, hidden=16, checkpoints={2: "ff1.pt"})
    with pytest.raises(ConfigError, match=r"gone\.pt"):
        build(FFProcessModel, tmp_path, hidden=16, checkpoints={1: "gone.pt"})
    for options, why in [
        ({"checkpoints": {1: "ff1.pt"}, "n_links": 1}, "drop `n_links`"),
        ({"checkpoints": {1: "ff1.pt"}, "checkpoint": "ff1.pt"}, "drop `checkpoint`"),
        ({"checkpoints": {}}, "`checkpoints` is empty"),
        ({"checkpoints": {9: "ff1.pt"}}, "less than or equal to 8"),
    ]:
        with pytest.raises(ValidationError, match=why):
            build(FFProcessModel, tmp_path, hidden=16, **options)


# ---------------------------------------------------------------------------------------------
# Checkpoints


@pytest.mark.parametrize(
    ("cls", "options"), [(GNNProcessModel, {"hidden": 64}), (FFProcessModel, {"n_links": 2})]
)
def test_checkpoint_round_trip(cls: type, options: dict[str, Any], tmp_path: Path) -> None:
    trained = build(cls, tmp_path, seed=1, **options)
    trained.save_checkpoint(tmp_path / "model.pt")
    assert (tmp_path / "model.pt").stat().st_size < 2_000_000
    assert sidecar_path(tmp_path / "model.pt").is_file()

    loaded = build(cls, tmp_path, seed=2, checkpoint="model.pt", **options)
    fresh = build(cls, tmp_path, seed=2, **options)
    states, inputs = scenario((), 2)
    expected = trained.predict(states, inputs, DT_S)
    got = loaded.predict(states, inputs, DT_S)
    for first, second in zip(parts(expected), parts(got), strict=True):
        assert torch.equal(first, second)
    assert not torch.equal(expected.pose, fresh.predict(states, inputs, DT_S).pose)


def test_missing_checkpoint_is_a_config_error(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"gone\.pt.*vistac train"):
        build(GNNProcessModel, tmp_path, checkpoint="gone.pt")


@pytest.mark.parametrize("damage", ["truncated", "garbage"])
def test_corrupted_checkpoint_is_a_data_error(damage: str, tmp_path: Path) -> None:
    build(GNNProcessModel, tmp_path).save_checkpoint(tmp_path / "broken.pt")
    data = (tmp_path / "broken.pt").read_bytes()
    damaged = data[: len(data) // 2] if damage == "truncated" else b"not a checkpoint\n" * 9
    (tmp_path / "broken.pt").write_bytes(damaged)
    with pytest.raises(DataError, match=r"broken\.pt is not a readable.*vistac train"):
        build(GNNProcessModel, tmp_path, checkpoint="broken.pt")


@pytest.mark.parametrize(
    "sidecar",
    ["", "[1]", '{"model": "filters.gnn"}', '{"model": "filters.gnn", "architecture": [32]}'],
)
def test_a_damaged_sidecar_is_a_data_error(sidecar: str, tmp_path: Path) -> None:
    build(GNNProcessModel, tmp_path).save_checkpoint(tmp_path / "model.pt")
    sidecar_path(tmp_path / "model.pt").write_text(sidecar)
    with pytest.raises(DataError, match=r"model\.pt\.json: unreadable checkpoint sidecar"):
        build(GNNProcessModel, tmp_path, checkpoint="model.pt")


def test_checkpoint_of_another_architecture_is_a_data_error(tmp_path: Path) -> None:
    build(GNNProcessModel, tmp_path, hidden=32).save_checkpoint(tmp_path / "small.pt")
    with pytest.raises(DataError, match=r"small\.pt.*hidden: saved 32, configured 64"):
        build(GNNProcessModel, tmp_path, hidden=64, checkpoint="small.pt")
    # Without the sidecar the weights' shapes tell.
    sidecar_path(tmp_path / "small.pt").unlink()
    with pytest.raises(DataError, match=r"small\.pt does not fit.*shape: f_e\.0\.weight"):
        build(GNNProcessModel, tmp_path, hidden=64, checkpoint="small.pt")


def test_checkpoint_with_foreign_keys_is_a_data_error(tmp_path: Path) -> None:
    torch.save({"layer.weight": torch.zeros(3)}, tmp_path / "other.pt")
    with pytest.raises(DataError, match=r"other\.pt.*missing: .*unexpected: layer\.weight"):
        build(FFProcessModel, tmp_path, checkpoint="other.pt")


def test_checkpoint_of_another_model_is_a_data_error(tmp_path: Path) -> None:
    build(GNNProcessModel, tmp_path).save_checkpoint(tmp_path / "gnn.pt")
    with pytest.raises(DataError, match=r"gnn\.pt was saved by 'filters\.gnn'"):
        build(FFProcessModel, tmp_path, checkpoint="gnn.pt")


# ---------------------------------------------------------------------------------------------
# Analytical model: known answers


def single_push(
    tcp_y_m: float, com: tuple[float, float] = (0.0, 0.0), **options: Any
) -> Prediction:
    """One noiseless sigma point: link 0 at the origin, pushed along +x on its -x side by the
    analytical model of ``options``."""
    states = torch.tensor([[0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.8, 0.3, *com]], dtype=DTYPE)
    inputs = ProcessInput(
        tcp=torch.tensor([-HALF_M - 0.01, tcp_y_m, 0.0, SPEED_MPS, 0.0, 0.0], dtype=DTYPE),
        pd_rad=torch.tensor(0.0, dtype=DTYPE),
        is_pull=torch.tensor(0.0, dtype=DTYPE),
        link=torch.tensor(0),
        link_size_m=torch.full((1, 2), HALF_M, dtype=DTYPE),
        link_offset=torch.zeros(1, 3, dtype=DTYPE),
    )
    config = AnalyticalProcessModel.Config(**options)
    model = AnalyticalProcessModel(config, TestContext(Path(".")))
    return model.predict(states, inputs, DT_S)


def test_push_through_the_com_translates_at_pusher_speed() -> None:
    prediction = single_push(0.0)
    expected = torch.tensor([SPEED_MPS * DT_S, 0.0, 0.0, SPEED_MPS, 0.0, 0.0], dtype=DTYPE)
    torch.testing.assert_close(prediction.pose[0], expected, rtol=0, atol=1e-12)
    friction_n = 0.3 * 0.8 * 9.81
    torch.testing.assert_close(
        prediction.force_n[0], torch.tensor([-friction_n, 0.0], dtype=DTYPE), rtol=0, atol=1e-9
    )


def test_offset_push_turns_the_link_away_from_the_pusher() -> None:
    above = single_push(0.02).pose[0]
    below = single_push(-0.02).pose[0]
    assert above[5] < 0 < below[5], "a push above the CoM turns clockwise"
    assert 0 < above[0] < SPEED_MPS * DT_S
    torch.testing.assert_close(above[5], -below[5])


def test_push_through_offset_com_turns_the_link() -> None:
    """The CoM's line of pushing misses the 24 mm wide pad: the link turns about its end."""
    prediction = single_push(0.0, com=(0.0, -0.02))
    assert prediction.pose[0, 5] < 0


def test_flat_pad_pushes_a_nearby_com_straight() -> None:
    """The CoM's line of pushing meets the pad: the pressure centre moves there, no turn."""
    prediction = single_push(0.0, com=(0.0, -0.01))
    torch.testing.assert_close(prediction.pose[0, 5], torch.tensor(0.0, dtype=DTYPE))


def test_linear_pressure_under_an_offset_com_turns_the_link_more() -> None:
    """The pressure gathers under an offset CoM, so the link turns about it more easily; with a
    centred CoM both pressures give nearly the same push."""
    pressures = ("uniform", "linear")
    centred = [single_push(0.02, pressure=p).pose[0, 5] for p in pressures]
    torch.testing.assert_close(centred[0], centred[1], rtol=0.02, atol=0.0)
    offset = [single_push(0.03, (0.0, -0.025), pressure=p).pose[0, 5] for p in pressures]
    assert offset[1] < offset[0] < 0


def test_line_contact_point() -> None:
    from vistac.plugins.filters.analytical import line_contact

    point = torch.tensor([-0.05, 0.0], dtype=DTYPE)
    normal = torch.tensor([1.0, 0.0], dtype=DTYPE)
    u = torch.tensor([0.02, 0.0], dtype=DTYPE)
    half = torch.tensor([0.05, 0.05], dtype=DTYPE)

    def contact(com_y: float, width: float = 0.012) -> Tensor:
        com = torch.tensor([0.0, com_y], dtype=DTYPE)
        return line_contact(point, normal, u, com, half, width)

    torch.testing.assert_close(contact(0.005), torch.tensor([-0.05, 0.005], dtype=DTYPE))
    torch.testing.assert_close(contact(-0.03), torch.tensor([-0.05, -0.012], dtype=DTYPE))
    torch.testing.assert_close(contact(0.03, 0.0), point)
    edge = line_contact(
        torch.tensor([-0.05, 0.045], dtype=DTYPE), normal, u,
        torch.tensor([0.0, 0.049], dtype=DTYPE), half, 0.012,
    )  # fmt: skip
    torch.testing.assert_close(edge, torch.tensor([-0.05, 0.049], dtype=DTYPE))


def test_no_motion_without_contact() -> None:
    prediction = single_push(0.1)
    torch.testing.assert_close(prediction.pose[0], torch.zeros(6, dtype=DTYPE))
    torch.testing.assert_close(prediction.force_n[0], torch.zeros(2, dtype=DTYPE))


def test_pull_moves_the_link_with_the_gripper(tmp_path: Path) -> None:
    states, inputs = scenario((), 1, is_pull=1.0)
    rigid = build(AnalyticalProcessModel, tmp_path, grasp_friction_nm=None)
    prediction = rigid.predict(states, inputs, DT_S)
    moved = prediction.pose - states[..., :6]
    torch.testing.assert_close(moved[:, 0], torch.full((C,), SPEED_MPS * DT_S, dtype=DTYPE))
    torch.testing.assert_close(moved[:, 1:3], torch.zeros(C, 2, dtype=DTYPE))
    friction_n = (states[:, 6] * states[:, 7] * 9.81).unsqueeze(-1)
    torch.testing.assert_close(prediction.force_n[:, 0:1], -friction_n)


def test_characteristic_length_of_a_centred_square() -> None:
    """Mean distance from the centre of a unit square: (sqrt 2 + asinh 1) / 6 (~0.3826)."""
    c = characteristic_length_m(torch.tensor([0.5, 0.5], dtype=DTYPE), torch.zeros(2, dtype=DTYPE))
    assert float(c) == pytest.approx((math.sqrt(2) + math.asinh(1.0)) / 6.0, rel=1e-12)


def test_characteristic_length_matches_sampling() -> None:
    rng = np.random.default_rng(3)
    half, com = np.array([0.06, 0.03]), np.array([0.02, -0.01])
    points = rng.uniform(-half, half, size=(400_000, 2))
    sampled = np.linalg.norm(points - com, axis=1).mean()
    c = characteristic_length_m(torch.tensor(half), torch.tensor(com))
    assert float(c) == pytest.approx(sampled, rel=3e-3)


def _linear_pressure_length_by_root(half: np.ndarray, com: np.ndarray) -> float:
    """c under p = max(0, 1 + g . u) with g from scipy's root finder on a dense grid."""
    ticks = (np.arange(400) + 0.5) / 200.0 - 1.0
    unit = np.stack(np.meshgrid(ticks, ticks, indexing="ij"), -1).reshape(-1, 2)

    def pressure(g: np.ndarray) -> np.ndarray:
        return np.maximum(0.0, 1.0 + unit @ g)

    def centre_error(g: np.ndarray) -> np.ndarray:
        p = pressure(g)
        return (p[:, None] * unit).sum(0) / p.sum() - com / half

    g = root(centre_error, 3.0 * com / half).x
    p = pressure(g)
    return float((p * np.linalg.norm((unit - com / half) * half, axis=1)).sum() / p.sum())


@pytest.mark.parametrize(
    ("com", "lift_off"),
    [((0.0, 0.0), False), ((0.01, -0.004), False), ((0.03, 0.012), True), ((-0.04, 0.02), True)],
)
def test_linear_pressure_length_matches_an_independent_solution(
    com: tuple[float, float], lift_off: bool
) -> None:
    """Centred: the uniform pressure's c; off centre the pressure follows the CoM, with part of
    the footprint lifting off beyond |cx|/a + |cy|/b = 1/3."""
    half = np.array([0.06, 0.03])
    assert (np.abs(np.array(com) / half).sum() > 1.0 / 3.0) == lift_off
    c = float(linear_pressure_length_m(torch.tensor(half), torch.tensor(com, dtype=DTYPE)))
    assert c == pytest.approx(_linear_pressure_length_by_root(half, np.array(com)), rel=0.02)
    if com == (0.0, 0.0):
        uniform = characteristic_length_m(torch.tensor(half), torch.tensor(com, dtype=DTYPE))
        assert c == pytest.approx(float(uniform), rel=0.01)


# ---------------------------------------------------------------------------------------------
# Analytical model: agreement with an independent solution


def _cross(a: np.ndarray, b: np.ndarray) -> float:
    return float(a[0] * b[1] - a[1] * b[0])


def independent_push(
    p: np.ndarray, n: np.ndarray, u: np.ndarray, f_max: float, c: float, mu: float
) -> tuple[np.ndarray, bool]:
    """Quasi-static push solved from first principles with scipy. Returns (twist [3], sticking).

    Sticking: among the twists whose contact point moves with the pusher, the one dissipating
    the least power on the ellipsoidal limit surface (``D² = f_max² |v|² + m_max² omega²``),
    valid when the wrench normal to the limit surface is a force inside the friction cone.
    Slipping: the twist whose limit-surface wrench is a point force at the contact on a friction
    cone edge, with the contact's normal velocity equal to the pusher's; the edge is the one
    whose tangential force points along the pusher's sliding relative to the object.
    """
    m_max = c * f_max
    t = np.array([-n[1], n[0]])

    def twist_for(omega: float) -> np.ndarray:
        velocity = u - omega * np.array([-p[1], p[0]])
        return np.array([*velocity, omega])

    def power_sq(x: np.ndarray) -> tuple[float, np.ndarray]:
        """Normalised D² and its derivative in omega = x * SPEED_MPS / c."""
        omega = float(x[0]) * SPEED_MPS / c
        twist = twist_for(omega)
        value = (twist[0] ** 2 + twist[1] ** 2 + (c * twist[2]) ** 2) / SPEED_MPS**2
        d_velocity = -np.array([-p[1], p[0]]) * SPEED_MPS / c
        d_value = 2 * (twist[:2] @ d_velocity + c * twist[2] * SPEED_MPS) / SPEED_MPS**2
        return value, np.array([d_value])

    x = minimize(power_sq, np.zeros(1), jac=True, method="BFGS", options={"gtol": 1e-14}).x
    stick = twist_for(float(x[0]) * SPEED_MPS / c)
    force = f_max**2 * stick[:2]
    assert m_max**2 * stick[2] == pytest.approx(_cross(p, force), rel=1e-6, abs=1e-12)
    if abs(force @ t) <= mu * (force @ n):
        return stick, True

    consistent = []
    for side in (1.0, -1.0):
        edge = n + side * mu * t

        def residual(twist: np.ndarray, edge: np.ndarray = edge) -> np.ndarray:
            contact_velocity = twist[:2] + twist[2] * np.array([-p[1], p[0]])
            return np.array(
                [
                    (contact_velocity - u) @ n / SPEED_MPS,
                    _cross(twist[:2], edge) / SPEED_MPS,
                    (c**2 * twist[2] - _cross(p, twist[:2])) / (c * SPEED_MPS),
                ]
            )

        twist = least_squares(residual, np.array([*u, 0.0]), xtol=1e-15, ftol=1e-15).x
        sliding = (u - twist[:2] - twist[2] * np.array([-p[1], p[0]])) @ t
        if twist[:2] @ edge > 0 and sliding * side > 0:
            consistent.append(twist)
    assert len(consistent) == 1
    return consistent[0], False


def random_push(rng: np.random.Generator) -> dict[str, Any]:
    half = rng.uniform(0.03, 0.07, size=2)
    com = rng.uniform(-0.3, 0.3, size=2) * half
    contact = np.array([-half[0], rng.uniform(-0.95, 0.95) * half[1]])
    angle = rng.uniform(-math.pi, math.pi)
    turn = np.array([[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]])
    beta = rng.uniform(-1.3, 1.3)
    return {
        "p": turn @ (contact - com),
        "n": turn @ np.array([1.0, 0.0]),
        "u": turn @ (SPEED_MPS * np.array([math.cos(beta), math.sin(beta)])),
        "f_max": rng.uniform(0.5, 5.0),
        "c": float(characteristic_length_m(torch.tensor(half), torch.tensor(com))),
        "mu": rng.uniform(0.1, 1.0),
    }


def test_quasi_static_push_agrees_with_an_independent_solution() -> None:
    rng = np.random.default_rng(7)
    cases = [random_push(rng) for _ in range(60)]
    result = quasi_static_push(
        *(torch.tensor(np.array([case[key] for case in cases])) for key in "pnu"),
        *(torch.tensor([case[key] for case in cases]) for key in ("f_max", "c", "mu")),
    )
    kinds = set()
    for i, case in enumerate(cases):
        twist, sticking = independent_push(**case)
        kinds.add(sticking)
        assert bool(result.sticking[i]) == sticking, i
        # Relative to the natural scales: pusher speed, speed / c, f_max.
        speed_error = np.abs(result.velocity_mps[i].numpy() - twist[:2]).max() / SPEED_MPS
        rate_error = abs(float(result.omega_radps[i]) - twist[2]) * case["c"] / SPEED_MPS
        f_max, m_max = case["f_max"], case["f_max"] * case["c"]
        force = f_max**2 * twist[:2] / math.hypot(f_max * math.hypot(*twist[:2]), m_max * twist[2])
        force_error = np.abs(result.force_n[i].numpy() - force).max() / f_max
        assert max(speed_error, rate_error, force_error) < 1e-6, (i, sticking)
    assert kinds == {True, False}, "the random cases must cover sticking and slipping"


def test_pusher_moving_away_does_not_push() -> None:
    result = quasi_static_push(
        torch.tensor([-0.04, 0.01], dtype=DTYPE),
        torch.tensor([1.0, 0.0], dtype=DTYPE),
        torch.tensor([-0.02, 0.01], dtype=DTYPE),
        torch.tensor(2.0, dtype=DTYPE),
        torch.tensor(0.03, dtype=DTYPE),
        0.5,
    )
    assert float(result.velocity_mps.abs().sum()) == 0.0
    assert float(result.force_n.abs().sum()) == 0.0


# ---------------------------------------------------------------------------------------------
# Mirror averaging


def test_the_reflection_about_the_push_line_is_an_involution_with_known_images() -> None:
    states, inputs = scenario((2,), 2)
    inputs = ProcessInput(inputs.tcp, torch.full((2,), 0.4, dtype=DTYPE), inputs.is_pull,
                          inputs.link, inputs.link_size_m, inputs.link_offset)  # fmt: skip
    mirrored, mirrored_inputs = reflect_scene(states, inputs)
    back, back_inputs = reflect_scene(mirrored, mirrored_inputs)
    torch.testing.assert_close(back, states, rtol=0, atol=1e-15)
    torch.testing.assert_close(back_inputs.tcp, inputs.tcp, rtol=0, atol=1e-15)
    # pd 0.4 rad through the TCP: a point on the line stays, one off it lands across it.
    layout, tcp = StateLayout(2), inputs.tcp[0, :2]
    along = torch.tensor([math.cos(0.4), math.sin(0.4)], dtype=DTYPE)
    across = torch.tensor([-math.sin(0.4), math.cos(0.4)], dtype=DTYPE)
    pose = torch.zeros(1, 1, 6, dtype=DTYPE)
    pose[0, 0, :3] = torch.cat([tcp + 0.1 * along + 0.02 * across, torch.tensor([0.4 + 0.3])])
    pose[0, 0, 3:] = torch.cat([0.01 * across, torch.tensor([0.2])])
    image = reflect_poses(pose, tcp, torch.tensor(0.4, dtype=DTYPE))[0, 0]
    torch.testing.assert_close(image[:2], tcp + 0.1 * along - 0.02 * across)
    torch.testing.assert_close(image[2], torch.tensor(0.4 - 0.3, dtype=DTYPE))
    torch.testing.assert_close(image[3:5], -0.01 * across)
    assert float(image[5]) == pytest.approx(-0.2)
    com_y = [layout.index(f"com_y_{link}") for link in range(2)]
    torch.testing.assert_close(mirrored[..., com_y], -states[..., com_y])
    torch.testing.assert_close(mirrored_inputs.link_offset[..., 1:], -inputs.link_offset[..., 1:])


@pytest.mark.parametrize("name", ["gnn", "ff"])
def test_mirror_averaged_predictions_are_mirror_symmetric(name: str, tmp_path: Path) -> None:
    """With ``mirror_average`` the prediction of the reflected scene is the reflection of the
    prediction (a plain net's is not); the force is reflected too."""
    states, inputs = scenario((), 2)
    inputs = ProcessInput(inputs.tcp, torch.tensor(0.3, dtype=DTYPE), inputs.is_pull,
                          inputs.link, inputs.link_size_m, inputs.link_offset)  # fmt: skip
    mirrored, mirrored_inputs = reflect_scene(states, inputs)
    cls, options = (GNNProcessModel, {}) if name == "gnn" else (FFProcessModel, {"n_links": 2})
    angle = inputs.pd_rad.unsqueeze(-1)

    @torch.no_grad()
    def asymmetry(model: Any) -> tuple[float, float]:
        direct = model.predict(states, inputs, DT_S)
        other = model.predict(mirrored, mirrored_inputs, DT_S)
        back = reflect_poses(other.pose.unflatten(-1, (2, 6)), inputs.tcp[:2], inputs.pd_rad)
        force = rotate(other.force_n * torch.tensor([1.0, -1.0], dtype=DTYPE), 2 * angle)
        return (float((back.flatten(-2) - direct.pose).abs().max()),
                float((force - direct.force_n).abs().max()))  # fmt: skip

    plain = asymmetry(build(cls, tmp_path / "plain", hidden=16, **options))
    averaged = asymmetry(build(cls, tmp_path / "mirror", hidden=16, mirror_average=True, **options))
    assert plain[0] > 1e-4 and plain[1] > 1e-4
    assert averaged[0] < 1e-12 and averaged[1] < 1e-12


# ---------------------------------------------------------------------------------------------
# Joints given to the models (ProcessInput.hinge_m, ``filters.dual`` ``joints_from``)


def with_hinge(inputs: ProcessInput, hinge_m: Tensor) -> ProcessInput:
    return ProcessInput(inputs.tcp, inputs.pd_rad, inputs.is_pull, inputs.link,
                        inputs.link_size_m, inputs.link_offset, hinge_m)  # fmt: skip


@pytest.mark.parametrize("name", ["gnn", "ff", "analytical"])
def test_a_given_joint_replaces_the_one_the_model_places_and_nothing_else(
    tmp_path: Path, name: str
) -> None:
    """Given where the model itself puts the joint, a model predicts exactly as without; given
    a joint 3 cm to the side, otherwise. The learned models take it from the link boxes as in
    training (``nets.hinge_offsets``), the analytical chain from the facing sides."""
    model = MODELS[name][0](tmp_path)
    states, inputs = scenario((2,), 2)
    if name == "analytical":
        own = chain.facing_hinge_offsets(inputs)
    else:
        own = nets.hinge_offsets(inputs)[..., 0, :, :]
    plain = model.predict(states, inputs, DT_S)
    same = model.predict(states, with_hinge(inputs, own), DT_S)
    torch.testing.assert_close(same.pose, plain.pose, rtol=0, atol=0)
    torch.testing.assert_close(same.force_n, plain.force_n, rtol=0, atol=0)
    aside = model.predict(states, with_hinge(inputs, own + own.new_tensor([0.0, 0.03])), DT_S)
    moved = float((aside.pose - plain.pose).detach().abs().max())  # an untrained net's: small
    assert moved > (1e-4 if name == "analytical" else 1e-9), moved


def test_the_gnn_reuses_its_input_parts_only_while_the_joint_is_the_same(tmp_path: Path) -> None:
    model = MODELS["gnn"][0](tmp_path)
    states, inputs = scenario((2,), 2)
    first = with_hinge(inputs, nets.hinge_offsets(inputs)[..., 0, :, :])
    second = with_hinge(inputs, first.hinge_m + 0.02)  # type: ignore[operator]
    with torch.no_grad():  # parts are reused, as in a look-ahead, while the inputs are equal
        before, moved, again = (model.net(states, given, DT_S, reuse_inputs=True).pose
                                for given in (first, second, first))  # fmt: skip
    assert float((moved - before).abs().max()) > 1e-9
    torch.testing.assert_close(again, before, rtol=0, atol=0)


def test_the_reflection_mirrors_a_given_joint_and_mirror_averaging_takes_it(
    tmp_path: Path,
) -> None:
    states, inputs = scenario((2,), 2)
    hinge = torch.tensor([[0.03, 0.01]], dtype=DTYPE).expand(2, 1, 2)
    _, mirrored = reflect_scene(states, with_hinge(inputs, hinge))
    assert mirrored.hinge_m is not None
    torch.testing.assert_close(mirrored.hinge_m, hinge * hinge.new_tensor([1.0, -1.0]))
    _, plain = reflect_scene(states, inputs)
    assert plain.hinge_m is None
    model = MODELS["gnn"][0](tmp_path)
    averaged = mirror_averaged(model.predict, states, with_hinge(inputs, hinge), DT_S)
    without = mirror_averaged(model.predict, states, inputs, DT_S)
    assert float((averaged.pose - without.pose).detach().abs().max()) > 1e-9
