"""``example.rigid_push``: a process model written from scratch, for any number of links.

The simplest physics that still tells the dual filter something: while the gripper touches
the object, every link slides along with the gripper as one rigid body (no rotation), and the
fingers feel the table's friction on all links, ``g sum(m_l f_l)``, against the motion. Out
of contact nothing moves and the fingers feel nothing. The filter can then learn the total
friction load ``m f`` from the finger force, and nothing about the CoM (which this model
never uses): a baseline to compare a learned model against.

State layout, inputs and outputs: ``vistac.plugins.filters.state`` (states ``[..., C, n]``
with ``n = 11 L - 1``, torch float64). ``check_component`` checks what the filter relies on.
"""

from __future__ import annotations

import torch
from pydantic import Field
from torch import Tensor
from vistac.component import Component, ComponentConfig, ComponentContext
from vistac.plugins.filters.state import (
    DTYPE,
    GRAVITY_MPS2,
    Prediction,
    ProcessInput,
    StateLayout,
)


class RigidPush(Component):
    """Every link moves with the gripper while it is within ``contact_m`` of the acted link."""

    kind = "process_model"
    n_links = None  # any number of links

    class Config(ComponentConfig):
        contact_m: float = Field(0.02, gt=0, description="TCP to acted-link centre, minus "
                                 "the link's half extent, below which the object is pushed")
        position_std_m: float = Field(0.002, gt=0)
        theta_std_rad: float = Field(0.02, gt=0)
        speed_std_mps: float = Field(0.005, gt=0)
        rate_std_radps: float = Field(0.05, gt=0)

    config: Config

    def __init__(self, config: Config, ctx: ComponentContext) -> None:
        super().__init__(config, ctx)
        std = [config.position_std_m] * 2 + [config.theta_std_rad]
        std += [config.speed_std_mps] * 2 + [config.rate_std_radps]
        self.var = torch.tensor(std, dtype=DTYPE) ** 2

    def predict(self, states: Tensor, inputs: ProcessInput, dt_s: float) -> Prediction:
        """states [..., C, n] -> Prediction (pose [..., C, 6 L], force_n [..., C, 2],
        process_var [..., 6 L])."""
        layout = StateLayout((states.shape[-1] + 1) // 11)
        pose = layout.link_pose(states)  # [..., C, L, 6]
        velocity = inputs.tcp[..., 3:5].unsqueeze(-2).unsqueeze(-2)  # [..., 1, 1, 2]
        moving = self._touching(pose, inputs).unsqueeze(-1).unsqueeze(-1)  # [..., C, 1, 1]
        link_velocity = torch.where(moving, velocity, torch.zeros_like(velocity))
        link_velocity = link_velocity.expand(*pose.shape[:-1], 2)
        twist = torch.cat([link_velocity, torch.zeros_like(pose[..., 5:])], -1)
        position = pose[..., :3] + dt_s * twist
        params = layout.link_parameters(states)
        load_n = GRAVITY_MPS2 * (params[..., 0] * params[..., 1]).clamp_min(0.0).sum(-1)
        heading = torch.stack([torch.cos(inputs.pd_rad), torch.sin(inputs.pd_rad)], -1)
        force = -load_n.unsqueeze(-1) * heading.unsqueeze(-2) * moving[..., 0, 0, None]
        variance = self.var.repeat(layout.n_links).expand(*inputs.tcp.shape[:-1], -1)
        return Prediction(torch.cat([position, twist], -1).flatten(-2), force, variance)

    def _touching(self, pose: Tensor, inputs: ProcessInput) -> Tensor:
        """Whether the TCP is near the acted link at each point: [..., C] bool."""
        index = inputs.link.reshape(*inputs.link.shape, 1, 1, 1).expand(*pose.shape[:-2], 1, 2)
        centre = pose[..., :2].gather(-2, index)[..., 0, :]  # [..., C, 2]
        reach_m = inputs.link_size_m.amax(-1).gather(-1, inputs.link.unsqueeze(-1))  # [..., 1]
        gap_m = (centre - inputs.tcp[..., :2].unsqueeze(-2)).norm(dim=-1) - reach_m
        return gap_m < self.config.contact_m
