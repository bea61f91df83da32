"""The joint constraint of the dual filter's pose update (``filters.dual`` ``hinge_std_m``)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from torch import Tensor
from vistac.plugins.filters.component import facing_joints
from vistac.plugins.filters.dual import Belief, DualFilter, HeldJoints, joint_gaps
from vistac.plugins.filters.state import DTYPE, Prediction, ProcessInput, StateLayout

LAYOUT = StateLayout(2)
HALF_M = torch.tensor([[0.05, 0.03], [0.04, 0.03]], dtype=DTYPE)
"""Two boxes' half extents (m)."""
GAP_M = 0.004
"""Between their facing sides."""
HINGES = torch.tensor([[[0.05 + GAP_M / 2, 0.0], [-0.04 - GAP_M / 2, 0.0]]], dtype=DTYPE)
"""[1, 2, 2] the joint of ``side_by_side`` in each box's frame."""

pytestmark = pytest.mark.usefixtures("single_thread")


def side_by_side(theta_rad: float = 0.0) -> Tensor:
    """[2, 3] the boxes along x, turned together by theta_rad about link 0's origin."""
    c, s = math.cos(theta_rad), math.sin(theta_rad)
    distance = 0.05 + GAP_M + 0.04
    return torch.tensor([[0.2, 0.1, theta_rad], [0.2 + c * distance, 0.1 + s * distance,
                                                 theta_rad]], dtype=DTYPE)  # fmt: skip


def box_outline(half_m: Tensor, pose: Tensor, count: int = 400) -> np.ndarray:
    """A box's outline [count, 2] (world, m), points evenly along its sides."""
    a, b = half_m.tolist()
    corners = np.array([[a, b], [-a, b], [-a, -b], [a, -b], [a, b]])
    steps = np.linspace(0.0, 4.0, count, endpoint=False)
    side = steps.astype(int)
    local = corners[side] + (steps - side)[:, None] * (corners[side + 1] - corners[side])
    x, y, theta = pose.tolist()
    c, s = math.cos(theta), math.sin(theta)
    world_x = x + c * local[:, 0] - s * local[:, 1]
    return np.column_stack([world_x, y + s * local[:, 0] + c * local[:, 1]])


def test_facing_joints_lie_midway_across_the_gap_in_both_frames() -> None:
    poses = side_by_side(0.7)
    outlines = [box_outline(HALF_M[k], poses[k]) for k in range(2)]
    joints, nearest_m = facing_joints(outlines, poses.numpy())
    assert nearest_m == pytest.approx([GAP_M], abs=1e-4)
    torch.testing.assert_close(joints, HINGES, rtol=0, atol=2e-4)
    assert float(joint_gaps(pose_blocks(poses), joints).abs().max()) < 1e-12


def test_a_facing_joint_is_a_tip_that_touches_a_side_not_the_middle_of_its_box() -> None:
    """A turned box points a corner at the other box's side, 4 mm from it and 10 mm off
    their centre line: the joint is there, where the links nearly touch."""
    poses = torch.zeros(2, 3, dtype=DTYPE)
    diagonal = float(HALF_M[1].norm())  # the turned box's centre to its corner
    poses[1, 0] = 0.05 + GAP_M + diagonal
    poses[1, 1] = 0.01  # its corner 0.01 m off the x axis
    corner_turn = math.atan2(HALF_M[1, 1], HALF_M[1, 0])
    poses[1, 2] = math.pi - corner_turn  # a corner points at -x
    outlines = [box_outline(HALF_M[k], poses[k], count=4000) for k in range(2)]
    joints, _ = facing_joints(outlines, poses.numpy())
    tip = torch.tensor([0.05 + GAP_M / 2, 0.01], dtype=DTYPE)
    assert float((joints[0, 0] - tip).norm()) < 0.004  # the centre line: 0.01 off


def at_rest(poses: Tensor) -> ProcessInput:
    """The process input of the boxes at poses [2, 3] with the gripper at rest."""
    zero = torch.zeros((), dtype=DTYPE)
    return ProcessInput(tcp=torch.zeros(6, dtype=DTYPE), pd_rad=zero, is_pull=zero,
                        link=torch.zeros((), dtype=torch.int64), link_size_m=HALF_M,
                        link_offset=poses)  # fmt: skip


def pose_blocks(poses: Tensor) -> Tensor:
    """[..., L, 3] link poses -> [..., 6 L] pose blocks at rest."""
    return torch.cat([poses, torch.zeros_like(poses)], -1).flatten(-2)


def test_hinge_gaps_are_zero_when_the_pair_turns_about_its_joint_and_not_otherwise() -> None:
    poses = side_by_side()
    hinges = HINGES
    joint = poses[0, :2] + hinges[0, 0]
    turned = poses.clone()  # the child turned by 0.5 rad about the joint
    arm = poses[1, :2] - joint
    c, s = math.cos(0.5), math.sin(0.5)
    turned[1, :2] = joint + torch.stack([c * arm[0] - s * arm[1], s * arm[0] + c * arm[1]])
    turned[1, 2] += 0.5
    assert float(joint_gaps(pose_blocks(turned), hinges).abs().max()) < 1e-12
    turned[1, 2] += 0.1  # then about its own origin: its end of the joint swings by 0.1 rad
    gap = joint_gaps(pose_blocks(turned), hinges)
    assert float(gap.norm()) == pytest.approx(2 * (0.04 + GAP_M / 2) * math.sin(0.05), rel=1e-9)


class Still:
    """Links stay where they are, with no process noise; no force."""

    def predict(self, states: Tensor, inputs: ProcessInput, dt_s: float) -> Prediction:
        pose = states[..., LAYOUT.pose_slice]
        zeros = torch.zeros(LAYOUT.n_pose, dtype=DTYPE)
        return Prediction(pose, torch.zeros(*states.shape[:-1], 2, dtype=DTYPE), zeros)


class Blind:
    """An observation that every state explains alike: only the joint informs."""

    def expected(self, states: Tensor, force_n: Tensor) -> Tensor:
        return torch.zeros(*states.shape[:-1], 3, dtype=DTYPE)

    def noise_var(self, observation: Tensor) -> Tensor:
        return torch.ones_like(observation)


def test_the_joint_update_is_the_kalman_update_of_the_gap_observed_as_zero() -> None:
    """With the links' yaws known (so the gap is linear in x, y) one step conditions the
    positions on the gap being zero, exactly as a Kalman filter does."""
    poses = side_by_side()
    hinges = HINGES
    pose_var = torch.tensor([4e-6, 9e-6, 1e-14, 1e-6, 1e-6, 1e-6] * 2, dtype=DTYPE)
    start = pose_blocks(poses) + torch.tensor(
        [0.003, -0.002, 0, 0, 0, 0, -0.001, 0.004, 0, 0, 0, 0], dtype=DTYPE
    )
    parameters = torch.tensor([0.9, 0.3, 0, 0, 0.9, 0.3, 0, 0, 0.25], dtype=DTYPE)
    variance = torch.cat([pose_var, torch.full((9,), 1e-2, dtype=DTYPE)])
    belief = Belief(torch.cat([start, parameters]), torch.diag(variance))
    std_m = 0.001
    dual = DualFilter(LAYOUT, Still(), Blind(), sigma_points=60, pose_std_floor=None,
                      joints=HeldJoints(hinges, std_m))  # fmt: skip
    inputs = at_rest(poses)
    posterior = dual.step(belief, inputs, 0.1, torch.zeros(3, dtype=DTYPE),
                          torch.Generator().manual_seed(0))  # fmt: skip

    rows = np.zeros((2, 12))
    rows[0, 0], rows[0, 6], rows[1, 1], rows[1, 7] = 1, -1, 1, -1
    prior_cov = np.diag(pose_var.numpy())
    gap = joint_gaps(start, hinges).numpy()
    gain = prior_cov @ rows.T @ np.linalg.inv(rows @ prior_cov @ rows.T + std_m**2 * np.eye(2))
    mean = start.numpy() - gain @ gap
    cov = prior_cov - gain @ rows @ prior_cov
    np.testing.assert_allclose(posterior.mean[:12].numpy(), mean, rtol=0, atol=1e-9)
    np.testing.assert_allclose(posterior.cov[:12, :12].numpy(), cov, rtol=0, atol=1e-12)
    np.testing.assert_allclose(posterior.mean[12:].numpy(), parameters.numpy(), atol=1e-9)


def test_without_hinges_the_blind_update_leaves_the_pose_alone() -> None:
    """The control of the test above: the same step without the joint changes nothing."""
    poses = side_by_side()
    variance = torch.full((21,), 1e-6, dtype=DTYPE)
    variance[12:] = 1e-2
    mean = torch.cat([pose_blocks(poses) + 0.002, torch.full((9,), 0.5, dtype=DTYPE)])
    dual = DualFilter(LAYOUT, Still(), Blind(), sigma_points=60, pose_std_floor=None)
    generator = torch.Generator().manual_seed(0)
    observation = torch.zeros(3, dtype=DTYPE)
    posterior = dual.step(
        Belief(mean, torch.diag(variance)), at_rest(poses), 0.1, observation, generator
    )
    torch.testing.assert_close(posterior.mean[:12], mean[:12], rtol=0, atol=1e-12)


def test_hinges_of_the_wrong_shape_are_refused() -> None:
    with pytest.raises(ValueError, match=r"joints\.ends_m: expected \[1, 2, 2\]"):
        DualFilter(LAYOUT, Still(), Blind(), joints=HeldJoints(HINGES.repeat(2, 1, 1), 0.002))
    with pytest.raises(ValueError, match=r"joints\.std_m must be > 0"):
        DualFilter(LAYOUT, Still(), Blind(), joints=HeldJoints(HINGES, 0.0))
