"""Look-aheads with the learned process models' copies with float32 MLPs (``look_ahead``):
they agree with the float64 prediction, follow the weights, and leave the info-gain choice
unchanged.

Measured on the shipped GNN push checkpoint (hidden 32), a two-link object and the 32 candidates
of the info-gain benchmark, 37 prediction steps of 32 sigma points, against the same look-ahead
with the float64 net: belief means within 1e-9 m, 2e-8 rad, 7e-8 m/s or rad/s, and 6e-7 of
their std for the parameters; covariances within 1.3e-6 of std_i std_j; information gains
within 2.2e-7 relative; the states of ``predict_states`` within 4e-9 m and 7e-8 rad. Only the
MLPs run in float32 (the features and the integration of the predicted change stay float64), so
the error does not grow with the positions' magnitude (~0.5 m). The tolerances below leave a
margin of 45 to 500 over those measurements, and are far below anything that matters to a
choice (1 um, 10 urad).
"""

from __future__ import annotations

import copy
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from simctx import TestContext
from torch import Tensor
from vistac.plugins.filters.component import _LookAheadModel
from vistac.plugins.filters.models import (
    AnalyticalProcessModel,
    FFProcessModel,
    GNNProcessModel,
)
from vistac.plugins.filters.nets import GraphProcessNet
from vistac.plugins.filters.state import DTYPE, ProcessInput, StateLayout
from vistac.testing import build_components, two_box_scene
from vistac.types import Action

pytestmark = pytest.mark.usefixtures("single_thread")

ROOT = Path(__file__).resolve().parents[1]
CHECKPOINT = ROOT / "skills/checkpoints/gnn_push.pt"
POSITION_TOL_M = 1e-6
ANGLE_TOL_RAD = 1e-5
TWIST_TOL = 1e-5
"""m/s and rad/s."""
COVARIANCE_TOL = 1e-4
"""Of std_i std_j (float64), and of std_i for the parameter means."""
GAIN_REL_TOL = 1e-5
HORIZON_S, RATE_HZ, ICEM_RATE_HZ = 2.5, 15.0, 5.0
"""The info-gain look-ahead (37 steps) and the iCEM one."""



@pytest.fixture(scope="module")
def skill(tmp_path_factory: pytest.TempPathFactory) -> Any:
    """The GNN checkpoint, a dual filter initialised on the two boxes, an info-gain planner and
    an affordance sampler (a RunContext)."""
    components = {
        "model": {"plugin": "filters.gnn", "with": {"checkpoint": str(CHECKPOINT), "hidden": 32}},
        "filter": {"plugin": "filters.dual", "with": {"sigma_points": 100}},
        "affordances": {"plugin": "actions.affordances", "with": {"samples": 128}},
        "planner": {"plugin": "actions.info_gain", "with": {"horizon_s": HORIZON_S}},
    }
    ctx = build_components(components, tmp_path_factory.mktemp("skill"))
    ctx.component("filter").initialise(two_box_scene())
    return ctx


def _candidates(skill: Any, seed: int = 0) -> list[Action]:
    sampled: list[Action] = skill.component("affordances").sample(
        two_box_scene(), np.random.default_rng(seed)
    )
    assert len(sampled) >= 32, "too few candidates: sample more"
    return sampled[:32]


@pytest.fixture
def float64_look_ahead(skill: Any, monkeypatch: pytest.MonkeyPatch) -> Callable[[], None]:
    """Call it to make the look-aheads use the float64 net (``predict_pose``) until the test
    ends."""
    model = skill.component("model")
    return lambda: monkeypatch.setattr(model, "look_ahead", lambda: model.predict_pose)


def _check_poses(got: Tensor, want: Tensor, layout: StateLayout) -> None:
    """The poses and twists of states [..., n] agree."""
    difference = layout.link_pose((got - want).abs())
    assert float(difference[..., :2].max()) < POSITION_TOL_M
    assert float(difference[..., 2].max()) < ANGLE_TOL_RAD
    assert float(difference[..., 3:].max()) < TWIST_TOL


def test_belief_look_ahead_agrees_with_float64(
    skill: Any, float64_look_ahead: Callable[[], None]
) -> None:
    filter_ = skill.component("filter")
    candidates = _candidates(skill)
    got = filter_.predict_beliefs(candidates, HORIZON_S, RATE_HZ, 32)
    float64_look_ahead()
    want = filter_.predict_beliefs(candidates, HORIZON_S, RATE_HZ, 32)
    means, covs = (torch.stack([pair[i] for pair in got]) for i in (0, 1))
    want_means, want_covs = (torch.stack([pair[i] for pair in want]) for i in (0, 1))
    assert means.dtype == covs.dtype == DTYPE
    assert not means.is_inference() and not covs.is_inference()
    moved_m = filter_.layout.link_pose(want_means - filter_.belief.mean)[..., :2].abs().max()
    assert float(moved_m) > 0.005  # the candidates move the object
    _check_poses(means, want_means, filter_.layout)
    std = want_covs.diagonal(dim1=-2, dim2=-1).sqrt()
    assert float(((means - want_means).abs() / std).max()) < COVARIANCE_TOL  # parameters too
    scale = std[..., :, None] * std[..., None, :]
    assert float(((covs - want_covs).abs() / scale).max()) < COVARIANCE_TOL


def test_state_look_ahead_agrees_with_float64(
    skill: Any, float64_look_ahead: Callable[[], None]
) -> None:
    filter_ = skill.component("filter")
    candidates = _candidates(skill)
    got = filter_.predict_states(candidates, ICEM_RATE_HZ)
    again = filter_.predict_states(candidates, ICEM_RATE_HZ, got)  # from moved states
    float64_look_ahead()
    want = filter_.predict_states(candidates, ICEM_RATE_HZ)
    assert got.dtype == DTYPE and not got.is_inference()
    _check_poses(got, want, filter_.layout)
    _check_poses(again, filter_.predict_states(candidates, ICEM_RATE_HZ, want), filter_.layout)
    parameters = filter_.layout.parameter_slice
    assert torch.equal(again[:, parameters], filter_.belief.mean[parameters].expand(32, -1))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_info_gain_choice_is_unchanged(
    skill: Any, float64_look_ahead: Callable[[], None], seed: int
) -> None:
    planner, candidates = skill.component("planner"), _candidates(skill, seed)
    gains = planner.gains(candidates)
    chosen = planner.select(candidates, two_box_scene(), np.random.default_rng(0))
    float64_look_ahead()
    want = planner.gains(candidates)
    assert torch.allclose(gains, want, rtol=GAIN_REL_TOL, atol=0.0)
    assert chosen is candidates[int(want.argmax())]
    assert planner.select(candidates, two_box_scene(), np.random.default_rng(0)) is chosen


# -- the float32 copy -------------------------------------------------------------------------


def _inputs(batch: int, n_links: int = 2, pd_rad: float = 0.3, x_m: float = -0.06) -> ProcessInput:
    """Pushes along pd_rad on link 0 of a chain of 90 mm squares at y = 0.45 m."""
    offset = torch.zeros(n_links, 3, dtype=DTYPE)
    offset[:, 0] = torch.arange(n_links, dtype=DTYPE) * 0.094
    tcp = torch.tensor([x_m, 0.45, pd_rad, 0.02, 0.005, 0.0], dtype=DTYPE)
    return ProcessInput(
        tcp=tcp.expand(batch, 6),
        pd_rad=torch.full((batch,), pd_rad, dtype=DTYPE),
        is_pull=torch.zeros(batch, dtype=DTYPE),
        link=torch.zeros(batch, dtype=torch.int64),
        link_size_m=torch.full((batch, n_links, 2), 0.045, dtype=DTYPE),
        link_offset=offset.expand(batch, n_links, 3),
    )


def _states(batch: int, count: int, n_links: int = 2, seed: int = 0) -> Tensor:
    """States [batch, count, n] scattered around the chain at rest."""
    layout = StateLayout(n_links)
    mean = torch.zeros(layout.size, dtype=DTYPE)
    pose = layout.link_pose(mean)
    pose[:, 0] = torch.arange(n_links, dtype=DTYPE) * 0.094
    pose[:, 1] = 0.45
    layout.link_parameters(mean)[:] = torch.tensor([0.8, 0.3, 0.005, -0.004], dtype=DTYPE)
    mean[layout.size - layout.n_joints :] = 0.2
    generator = torch.Generator().manual_seed(seed)
    noise = torch.randn(batch, count, layout.size, generator=generator, dtype=DTYPE)
    return mean + 0.003 * noise


def _check_look_ahead(model: Any, states: Tensor, inputs: ProcessInput) -> None:
    """model.look_ahead() agrees with model.predict with gradients, the float64 net (poses,
    process noise)."""
    with torch.no_grad():
        got = model.look_ahead()(states, inputs, 0.05)
    want = model.predict(states, inputs, 0.05)
    assert want.pose.requires_grad
    want = replace(want, pose=want.pose.detach())
    assert got.pose.dtype == got.process_var.dtype == got.force_n.dtype == DTYPE
    layout = StateLayout(inputs.link_size_m.shape[-2])
    difference = layout.link_pose((got.pose - want.pose).abs())
    assert float(difference[..., :2].max()) < POSITION_TOL_M / 10  # one step
    assert float(difference[..., 2].max()) < ANGLE_TOL_RAD / 10
    assert torch.equal(got.process_var, want.process_var)  # the noise stays float64


def _copy_of(model: Any) -> Any:
    """The net with float32 MLPs behind ``model.look_ahead()``."""
    return model.look_ahead().func


def test_float32_copy_is_made_once_and_leaves_the_net_alone(tmp_path: Path) -> None:
    model = TestContext(tmp_path).add(GNNProcessModel, checkpoint=CHECKPOINT, hidden=32)
    states, inputs = _states(3, 5), _inputs(3)
    before = model.predict(states, inputs, 0.05)
    copy32 = _copy_of(model)
    assert _copy_of(model) is copy32  # the weights did not change
    assert not any(p.requires_grad for p in copy32.parameters())
    assert all(p.dtype == torch.float32 for p in copy32.f_e.parameters())
    assert all(p.dtype == DTYPE and p.requires_grad for p in model.net.parameters())
    after = model.predict(states, inputs, 0.05)
    assert torch.equal(before.pose, after.pose) and torch.equal(before.force_n, after.force_n)
    _check_look_ahead(model, states, inputs)


def test_predict_without_gradients_is_the_float32_copy_with_the_force(tmp_path: Path) -> None:
    """A filter in a skill predicts without gradients: the float32 copy of the look-aheads,
    the finger force included, within their tolerances of the float64 net that training
    differentiates."""
    model = TestContext(tmp_path).add(GNNProcessModel, checkpoint=CHECKPOINT, hidden=32)
    states, inputs = _states(3, 5), _inputs(3)
    want = model.predict(states, inputs, 0.05)
    assert want.pose.requires_grad
    want = replace(want, pose=want.pose.detach(), force_n=want.force_n.detach())
    with torch.no_grad():
        got = model.predict(states, inputs, 0.05)
    assert got.pose.dtype == got.force_n.dtype == DTYPE and not got.pose.requires_grad
    difference = StateLayout(2).link_pose((got.pose - want.pose).abs())
    assert 0 < float(difference[..., :2].max()) < POSITION_TOL_M / 10
    assert float(difference[..., 2].max()) < ANGLE_TOL_RAD / 10
    assert float(want.force_n.abs().max()) > 0.1
    assert 0 < float((got.force_n - want.force_n).abs().max()) < 1e-4  # N
    assert torch.equal(got.process_var, want.process_var)


def test_float32_copy_follows_a_loaded_checkpoint(tmp_path: Path) -> None:
    model = TestContext(tmp_path).add(GNNProcessModel, hidden=32)  # fresh weights
    states, inputs = _states(2, 4), _inputs(2)
    fresh = _copy_of(model)
    _check_look_ahead(model, states, inputs)
    model.net.load_state_dict(torch.load(CHECKPOINT, weights_only=True))
    assert _copy_of(model) is not fresh
    _check_look_ahead(model, states, inputs)


def test_float32_copy_follows_training_and_in_place_changes(tmp_path: Path) -> None:
    model = TestContext(tmp_path).add(GNNProcessModel, checkpoint=CHECKPOINT, hidden=32)
    states, inputs = _states(2, 4), _inputs(2)
    before = _copy_of(model)
    optimizer = torch.optim.Adam(model.net.parameters(), lr=1e-2)
    model.predict(states, inputs, 0.05).pose.square().sum().backward()
    optimizer.step()
    after_step = _copy_of(model)
    assert after_step is not before
    _check_look_ahead(model, states, inputs)
    with torch.no_grad():
        next(model.net.parameters()).data.mul_(1.5)  # bypasses the version counter
    assert _copy_of(model) is not after_step
    _check_look_ahead(model, states, inputs)


def test_ff_look_ahead_agrees_with_float64(tmp_path: Path) -> None:
    model = TestContext(tmp_path).add(FFProcessModel, hidden=32, n_links=2)
    _check_look_ahead(model, _states(3, 5), _inputs(3))


def test_analytical_look_ahead_is_its_prediction(tmp_path: Path) -> None:
    model = TestContext(tmp_path).add(AnalyticalProcessModel)
    assert _LookAheadModel(model).predict == model.predict


def test_reused_input_parts_equal_fresh_ones() -> None:
    """Along a straight push only the TCP position changes and the parts are reused; any
    other change of the inputs makes them anew: either way the prediction is exact."""
    net = copy.deepcopy(GraphProcessNet(32)).float().requires_grad_(False)  # all float32
    states = _states(3, 5, n_links=3)
    changes = [
        _inputs(3, n_links=3),
        _inputs(3, n_links=3, x_m=-0.055),  # the TCP moved on: reused
        _inputs(3, n_links=3, pd_rad=0.1),  # another direction: made anew
    ]
    parts = []
    with torch.inference_mode():
        for inputs in changes:
            reused = net(states, inputs, 0.05, with_force=False, reuse_inputs=True)
            assert net._last_inputs is not None
            parts.append(net._last_inputs[1])
            fresh = net(states, inputs, 0.05, with_force=False)
            assert torch.equal(reused.pose, fresh.pose)
            assert torch.equal(reused.process_var, fresh.process_var)
        moved = net(states[:2], _inputs(2, n_links=3), 0.05, reuse_inputs=True)  # other shape
        assert torch.equal(moved.pose, net(states[:2], _inputs(2, n_links=3), 0.05).pose)
    assert parts[1] is parts[0] and parts[2] is not parts[1]
