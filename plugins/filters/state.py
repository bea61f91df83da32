"""The dual filter's state layout and the inputs every process model receives.

The joint state of an object with L links has ``n = 11 L - 1`` entries (paper 1, III-F):

- the time-varying block, 6 per link, link-major: ``x_l, y_l, theta_l`` (world frame, m and
  rad) and ``vx_l, vy_l, omega_l`` (m/s, rad/s);
- the time-invariant block: per link ``m_l`` (kg), ``f_l`` (table friction coefficient),
  ``com_x_l, com_y_l`` (CoM offset from the link frame's origin, link frame, m); then one
  ``f_j_k`` (joint friction, N m) per joint, ``L - 1`` of them. Heterogeneous (welded) objects
  keep the joint entries too, so every two-link object has the same state.

All filter and model code is torch, float64, and takes an optional leading batch dimension:
states are ``[..., C, n]`` for C sigma points.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

POSE_FIELDS: tuple[str, ...] = ("x", "y", "theta", "vx", "vy", "omega")
LINK_PARAMETER_FIELDS: tuple[str, ...] = ("m", "f", "com_x", "com_y")
DTYPE = torch.float64
GRAVITY_MPS2 = 9.81


@dataclass(frozen=True)
class StateLayout:
    """Indices and names of the joint state of an object with ``n_links`` links."""

    n_links: int

    def __post_init__(self) -> None:
        if self.n_links < 1:
            raise ValueError(f"an object has at least one link, got n_links={self.n_links}")

    @property
    def size(self) -> int:
        """n = 11 L - 1."""
        return 11 * self.n_links - 1

    @property
    def n_pose(self) -> int:
        """Size of the time-varying block, 6 L."""
        return 6 * self.n_links

    @property
    def n_joints(self) -> int:
        return self.n_links - 1

    @property
    def pose_slice(self) -> slice:
        return slice(0, self.n_pose)

    @property
    def parameter_slice(self) -> slice:
        return slice(self.n_pose, self.size)

    @property
    def names(self) -> tuple[str, ...]:
        pose = [f"{field}_{link}" for link in range(self.n_links) for field in POSE_FIELDS]
        params = [
            f"{field}_{link}" for link in range(self.n_links) for field in LINK_PARAMETER_FIELDS
        ]
        joints = [f"f_j_{joint}" for joint in range(self.n_joints)]
        return tuple(pose + params + joints)

    def index(self, name: str) -> int:
        return self.names.index(name)

    @property
    def bounded_below(self) -> tuple[int, ...]:
        """Rows of the parameter block that are never negative: each link's m and f, and every
        f_j."""
        links = [4 * link + field for link in range(self.n_links) for field in (0, 1)]
        joints = range(4 * self.n_links, 4 * self.n_links + self.n_joints)
        return (*links, *joints)

    def link_pose(self, states: Tensor) -> Tensor:
        """[..., n] -> [..., L, 6] = (x, y, theta, vx, vy, omega) per link."""
        return states[..., self.pose_slice].reshape(*states.shape[:-1], self.n_links, 6)

    def at_rest(self, states: Tensor) -> Tensor:
        """[..., n] -> a copy with every link's twist (vx, vy, omega) zero."""
        links = self.link_pose(states)
        pose = torch.cat([links[..., :3], torch.zeros_like(links[..., 3:])], -1).flatten(-2)
        return torch.cat([pose, states[..., self.parameter_slice]], -1)

    def link_parameters(self, states: Tensor) -> Tensor:
        """[..., n] -> [..., L, 4] = (m, f, com_x, com_y) per link."""
        start = self.n_pose
        block = states[..., start : start + 4 * self.n_links]
        return block.reshape(*states.shape[:-1], self.n_links, 4)

    def joint_friction(self, states: Tensor) -> Tensor:
        """[..., n] -> [..., L - 1]."""
        return states[..., self.size - self.n_joints : self.size]


@dataclass(frozen=True)
class ProcessInput:
    """What a process model knows about the robot at one control step (batch shape ``[...]``,
    the same as the states' leading dimensions without C).

    tcp: [..., 6] = (x_m, y_m, yaw_rad, vx_mps, vy_mps, wz_radps) of the gripper at the step
    start; pd_rad: [...] push or pull direction; is_pull: [...] 1.0 for a pull, 0.0 for a push;
    link: [...] int64 index of the link the robot acts on; link_size_m: [..., L, 2] half
    extents (a1, a2) of each link's fitted footprint in its frame; link_offset: [..., L, 3]
    initial pose of each link relative to link 0 (x_m, y_m, theta_rad); hinge_m: [..., L - 1,
    2] or None, each joint k in the frame of link k (m), None: the model puts it where the
    link boxes place it (``nets.hinge_offsets``, ``chain.facing_hinge_offsets``).
    """

    tcp: Tensor
    pd_rad: Tensor
    is_pull: Tensor
    link: Tensor
    link_size_m: Tensor
    link_offset: Tensor
    hinge_m: Tensor | None = None

    def map(self, function: Callable[[Tensor], Tensor]) -> ProcessInput:
        """These inputs with ``function`` applied to every tensor (a None hinge stays)."""
        hinge = None if self.hinge_m is None else function(self.hinge_m)
        return ProcessInput(
            function(self.tcp), function(self.pd_rad), function(self.is_pull),
            function(self.link), function(self.link_size_m), function(self.link_offset), hinge,
        )  # fmt: skip


@dataclass(frozen=True)
class Prediction:
    """A process model's output for C sigma points.

    pose: [..., C, 6 L] next time-varying block; force_n: [..., C, 2] predicted total contact
    force of the object on the fingers (world x, y, N), the tactile observation; process_var:
    [..., 6 L] or [..., C, 6 L] diagonal process noise variance (learned or fixed).
    """

    pose: Tensor
    force_n: Tensor
    process_var: Tensor
