"""Learned process models of the dual filter: the causal graph network and the feed-forward
baseline (pure torch ``nn.Module``s, float64).

Both take ``forward(states [..., C, n], inputs: ProcessInput, dt_s) -> Prediction`` and work in
the *reference frame* of the action: origin at the gripper TCP, x axis along the push or pull
direction ``pd_rad``. Every feature is expressed in that frame (translation and rotation
invariant) and normalised by fixed scales, and every output is rotated back to the world:

- link node [NODE_DIM]: motion slots (x, y, theta, vx, vy, omega of the link frame relative to
  the reference frame, / ``SIZE_SCALE_M``, ``SIZE_SCALE_M``, 1, ``SPEED_SCALE_MPS``,
  ``SPEED_SCALE_MPS``, ``RATE_SCALE_RADPS``), cos/sin of the relative theta, parameters
  (m / ``MASS_SCALE_KG``, f / ``FRICTION_SCALE``, com_x, com_y / ``SIZE_SCALE_M``), half
  extents (a1, a2) / ``SIZE_SCALE_M``, is_pull, node type one-hot (link, robot, table);
- robot node: the same layout with the TCP as the body (zero position, its yaw and twist),
  zero parameters and size;
- table node: the type one-hot only.

The network's output per link is a normalised delta (dx, dy, dtheta, dvx, dvy, domega) in the
reference frame; :func:`integrate` scales it (dx, dy by ``SPEED_SCALE_MPS * dt_s``, dtheta by
``RATE_SCALE_RADPS * dt_s``, the twist changes by the speed scales), rotates it to the world and
adds it to the current pose and twist.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import torch
from torch import Tensor, nn
from vistac.plugins.filters.state import DTYPE, Prediction, ProcessInput, StateLayout

SIZE_SCALE_M = 0.05
SPEED_SCALE_MPS = 0.025
RATE_SCALE_RADPS = 0.5
MASS_SCALE_KG = 1.0
FRICTION_SCALE = 0.3
JOINT_FRICTION_SCALE_NM = 0.5
FORCE_SCALE_N = 2.0

MOTION_DIM = 6
NODE_DIM = 18
"""motion 6, cos/sin 2, parameters 4, size 2, is_pull 1, type 3."""
EDGE_DIM = 6
"""value (support: f_l, joint: f_j, robot: is_pull), type one-hot 3 (robot, joint, support),
geometry 2 (joint: hinge minus receiver position, reference frame / SIZE_SCALE_M)."""
LINK_FEATURE_DIM = 14
ROBOT_FEATURE_DIM = 9

_LINK, _ROBOT, _TABLE = 0, 1, 2
_EDGE_ROBOT, _EDGE_JOINT, _EDGE_SUPPORT = 1, 2, 3
_INITIAL_STD = (0.001, 0.001, 0.01, 0.005, 0.005, 0.05)
"""Initial learned process noise std per field: m, m, rad, m/s, m/s, rad/s."""
_OUTPUT_INIT_SCALE = 0.1


# ---------------------------------------------------------------------------------------------
# Geometry and features shared by both nets


def layout_of(states: Tensor) -> StateLayout:
    """The layout of states [..., n] with n = 11 L - 1; ValueError for any other n."""
    n = states.shape[-1]
    if n < 10 or (n + 1) % 11:
        raise ValueError(f"a state has 11 L - 1 entries (10, 21, 32, ...), got {n}")
    return StateLayout((n + 1) // 11)


def wrap(angle_rad: Tensor) -> Tensor:
    """Angle wrapped into (-pi, pi] (differentiable)."""
    return torch.atan2(torch.sin(angle_rad), torch.cos(angle_rad))


def rotate(xy: Tensor, angle_rad: Tensor) -> Tensor:
    """Rotate vectors xy [..., 2] by angle_rad [...] (broadcast)."""
    c, s = torch.cos(angle_rad), torch.sin(angle_rad)
    return torch.stack([c * xy[..., 0] - s * xy[..., 1], s * xy[..., 0] + c * xy[..., 1]], -1)


def perp(xy: Tensor) -> Tensor:
    """[..., 2] rotated by +90 degrees: omega x r = omega * perp(r)."""
    return torch.stack([-xy[..., 1], xy[..., 0]], -1)


def hinge_points(pose: Tensor, inputs: ProcessInput) -> Tensor:
    """World position of each joint for the current link poses.

    Joint k joins links k and k + 1; it lies midway between link k's +x side centre and link
    k + 1's -x side centre (footprint boxes from ``link_size_m``), placed with the initial
    relative pose ``link_offset``. pose: [..., C, L, 6]. Returns [..., C, L - 1, 2].
    """
    offset = inputs.link_offset.unsqueeze(-3)  # [..., 1, L, 3]
    size = inputs.link_size_m.unsqueeze(-3)  # [..., 1, L, 2]
    parent, child = offset[..., :-1, :], offset[..., 1:, :]
    rel_xy = rotate(child[..., :2] - parent[..., :2], -parent[..., 2])
    rel_theta = child[..., 2] - parent[..., 2]
    zero = torch.zeros_like(rel_theta)
    parent_side = torch.stack([size[..., :-1, 0], zero], -1)
    child_side = rel_xy + rotate(torch.stack([-size[..., 1:, 0], zero], -1), rel_theta)
    hinge_in_parent = 0.5 * (parent_side + child_side)
    return pose[..., :-1, :2] + rotate(hinge_in_parent, pose[..., :-1, 2])


def _frame(inputs: ProcessInput) -> tuple[Tensor, Tensor]:
    """Reference frame broadcast over C: origin [..., 1, 2] (m), angle [..., 1] (rad)."""
    return inputs.tcp[..., :2].unsqueeze(-2), inputs.pd_rad.unsqueeze(-1)


def link_features(states: Tensor, inputs: ProcessInput) -> Tensor:
    """Per-link features in the reference frame: [..., C, L, LINK_FEATURE_DIM]."""
    layout = layout_of(states)
    pose = layout.link_pose(states)
    params = layout.link_parameters(states)
    origin, angle = _frame(inputs)
    angle_l = angle.unsqueeze(-1)  # [..., 1, 1]
    xy = rotate(pose[..., :2] - origin.unsqueeze(-2), -angle_l)
    theta = wrap(pose[..., 2] - angle_l)
    velocity = rotate(pose[..., 3:5], -angle_l)
    size = inputs.link_size_m.unsqueeze(-3).expand(*pose.shape[:-1], 2)
    scales = pose.new_tensor([MASS_SCALE_KG, FRICTION_SCALE, SIZE_SCALE_M, SIZE_SCALE_M])
    return torch.cat(
        [
            xy / SIZE_SCALE_M,
            theta.unsqueeze(-1),
            velocity / SPEED_SCALE_MPS,
            pose[..., 5:6] / RATE_SCALE_RADPS,
            torch.stack([torch.cos(theta), torch.sin(theta)], -1),
            params / scales,
            size / SIZE_SCALE_M,
        ],
        -1,
    )


def robot_features(inputs: ProcessInput) -> Tensor:
    """Robot features in the reference frame: [..., ROBOT_FEATURE_DIM] = (0, 0, yaw, vx, vy,
    wz, cos yaw, sin yaw, is_pull), normalised like the link motion slots."""
    tcp = inputs.tcp
    yaw = wrap(tcp[..., 2] - inputs.pd_rad)
    velocity = rotate(tcp[..., 3:5], -inputs.pd_rad)
    zero = torch.zeros_like(yaw)
    return torch.stack(
        [
            zero,
            zero,
            yaw,
            velocity[..., 0] / SPEED_SCALE_MPS,
            velocity[..., 1] / SPEED_SCALE_MPS,
            tcp[..., 5] / RATE_SCALE_RADPS,
            torch.cos(yaw),
            torch.sin(yaw),
            inputs.is_pull.to(tcp.dtype),
        ],
        -1,
    )


def integrate(states: Tensor, delta: Tensor, inputs: ProcessInput, dt_s: float) -> Tensor:
    """Apply normalised reference-frame deltas [..., C, L, 6] to the current poses.

    Returns the next time-varying block [..., C, 6 L] (world frame).
    """
    layout = layout_of(states)
    pose = layout.link_pose(states)
    angle = _frame(inputs)[1].unsqueeze(-1)
    xy = pose[..., :2] + rotate(delta[..., :2], angle) * (SPEED_SCALE_MPS * dt_s)
    theta = pose[..., 2:3] + delta[..., 2:3] * (RATE_SCALE_RADPS * dt_s)
    velocity = pose[..., 3:5] + rotate(delta[..., 3:5], angle) * SPEED_SCALE_MPS
    omega = pose[..., 5:6] + delta[..., 5:6] * RATE_SCALE_RADPS
    return torch.cat([xy, theta, velocity, omega], -1).flatten(-2)


def force_to_world(force: Tensor, inputs: ProcessInput) -> Tensor:
    """Normalised reference-frame force [..., C, 2] -> world force (N)."""
    return rotate(force, _frame(inputs)[1]) * FORCE_SCALE_N


def mlp(n_in: int, hidden: int, n_out: int) -> nn.Sequential:
    """Three linear layers with SiLU between them (float64); the last layer starts small so a
    fresh net outputs small values."""
    layers = nn.Sequential(
        nn.Linear(n_in, hidden, dtype=DTYPE),
        nn.SiLU(),
        nn.Linear(hidden, hidden, dtype=DTYPE),
        nn.SiLU(),
        nn.Linear(hidden, n_out, dtype=DTYPE),
    )
    with torch.no_grad():
        last = layers[-1]
        assert isinstance(last, nn.Linear)
        last.weight.mul_(_OUTPUT_INIT_SCALE)
        last.bias.zero_()
    return layers


class LearnedNoise(nn.Module):
    """Diagonal process noise: one log-variance per field (x, y, theta, vx, vy, omega), shared
    by all links."""

    def __init__(self) -> None:
        super().__init__()
        initial = torch.tensor(_INITIAL_STD, dtype=DTYPE)
        self.log_var = nn.Parameter(2.0 * torch.log(initial))

    def forward(self, batch_shape: torch.Size, n_links: int) -> Tensor:
        """Returns [*batch_shape, 6 L] variances (m², rad², (m/s)², (rad/s)²)."""
        return torch.exp(self.log_var).repeat(n_links).expand(*batch_shape, 6 * n_links)


# ---------------------------------------------------------------------------------------------
# Graph network


def _node(features: Tensor, node_type: int) -> Tensor:
    """Append the node type one-hot (link, robot, table) to features [..., NODE_DIM - 3]."""
    one_hot = features.new_zeros(*features.shape[:-1], 3)
    one_hot[..., node_type] = 1.0
    return torch.cat([features, one_hot], -1)


def _edge(value: Tensor, kind: int, geometry: Tensor | None = None) -> Tensor:
    """Static edge features [..., EDGE_DIM] from value [...] and geometry [..., 2]."""
    one_hot = value.new_zeros(*value.shape, 3)
    one_hot[..., kind - 1] = 1.0
    if geometry is None:
        geometry = value.new_zeros(*value.shape, 2)
    return torch.cat([value.unsqueeze(-1), one_hot, geometry], -1)


@dataclass(frozen=True)
class _EffectRows:
    """One effect phase: the messages from the children of the links at one depth."""

    updated: Tensor
    """Rows of the links with any child [n C]."""
    receivers: Tensor
    """Rows of the links with a child on side +1, then of those with one on side -1."""
    slots: Tensor
    """Where each of ``receivers`` is in ``updated``."""
    side_sizes: list[int]
    """How many of ``receivers`` belong to each side."""
    senders: Tensor
    """Rows of those children, both sides in that order."""
    edges: Tensor
    """Rows of the joint edges from the children in ``GraphProcessNet._joint_edges``."""


class _Chain:
    """The link chain seen from the acted link of each batch element, as rows of the link
    nodes flattened to [B C L, ...]: batch element b, sigma point c and link l at row
    ``(b C + c) L + l``. Every message-passing phase gathers only the rows it updates; all
    rows are worked out once per (acted links, L, C), see ``chain_of``."""

    def __init__(self, acted: tuple[int, ...], n_links: int, n_points: int) -> None:
        self.n_links, self.n_points = n_links, n_points
        self.n_rows = len(acted) * n_points * n_links
        acted_links = torch.tensor(acted, dtype=torch.int64)
        link = torch.arange(n_links)
        self._depth = (link - acted_links[:, None]).abs()  # [B, L]
        self._toward = torch.sign(acted_links[:, None] - link)  # [B, L]: the parent's side
        self.acted_rows = self._rows(torch.arange(len(acted)), acted_links)
        """[B C]: rows of the acted links, in the order (b C + c) of the robot rows."""
        self.cause = [self._cause_rows(depth) for depth in range(1, n_links)]
        """Per depth 1, 2, ...: rows of the links there, of their parents, of the joint edges
        to the parents in ``GraphProcessNet._joint_edges``, each [n C]."""
        self.effect = [self._effect_rows(depth) for depth in reversed(range(n_links - 1))]
        """Per depth L - 2, ..., 0: the effect phase's rows."""

    def _rows(self, batch: Tensor, link: Tensor, offset: Tensor | int = 0) -> Tensor:
        """Rows of the links (batch[i], link[i]) (plus offset[i]) for every sigma point,
        i-major: [n] -> [n C] int64."""
        first = (batch * self.n_points)[:, None] + torch.arange(self.n_points)
        return (first * self.n_links + (link + offset)[:, None]).reshape(-1)

    def _cause_rows(self, depth: int) -> tuple[Tensor, Tensor, Tensor]:
        batch, link = (self._depth == depth).nonzero(as_tuple=True)
        side = self._toward[batch, link]
        edge = self._rows(batch, link, (side < 0).to(torch.int64) * self.n_rows)
        return self._rows(batch, link), self._rows(batch, link + side), edge

    def _effect_rows(self, depth: int) -> _EffectRows:
        receivers, senders, edges = [], [], []
        link = torch.arange(self.n_links)
        has_child = torch.zeros_like(self._depth, dtype=torch.bool)
        for side in (1, -1):
            inside = (link + side >= 0) & (link + side < self.n_links)
            with_child = inside & (self._toward != side)  # the neighbour is farther away
            has_child |= with_child
            batch, at = ((self._depth == depth) & with_child).nonzero(as_tuple=True)
            receivers.append(self._rows(batch, at))
            senders.append(self._rows(batch, at + side))
            edges.append(self._rows(batch, at, int(side < 0) * self.n_rows))
        batch, at = ((self._depth == depth) & has_child).nonzero(as_tuple=True)
        updated = self._rows(batch, at)
        slot = torch.full((self.n_rows,), -1, dtype=torch.int64)
        slot[updated] = torch.arange(len(updated))
        return _EffectRows(
            updated=updated,
            receivers=torch.cat(receivers),
            slots=slot[torch.cat(receivers)],
            side_sizes=[len(rows) for rows in receivers],
            senders=torch.cat(senders),
            edges=torch.cat(edges),
        )


@functools.lru_cache(maxsize=32)
def chain_of(acted: tuple[int, ...], n_links: int, n_points: int) -> _Chain:
    """The (cached) chain rows for the acted link of each batch element (CPU tensors)."""
    return _Chain(acted, n_links, n_points)


class GraphProcessNet(nn.Module):
    """Causal graph network (paper 1, III-F2, Algorithm 1) for any number of links.

    Nodes: the L links, the robot and the table. Directed edges: robot -> acted link (cause),
    acted link -> robot (effect), both directions of every joint, table -> each link (support).
    ``f_e`` (edge message) and ``f_n`` (residual node update) are 3-layer MLPs shared by all
    edges and nodes; ``tac_net`` maps the effect message towards the robot to the tactile force.
    The chain is visited breadth-first from the acted link (``inputs.link``), which may differ
    across the batch. The nodes of all batch elements and sigma points are rows of one matrix,
    and each phase runs the MLPs once on just the rows it updates.
    """

    def __init__(self, hidden: int = 64) -> None:
        super().__init__()
        self.hidden = hidden
        self.f_e = mlp(2 * NODE_DIM + EDGE_DIM, hidden, hidden)
        self.f_n = mlp(NODE_DIM + hidden, hidden, NODE_DIM)
        self.tac_net = mlp(hidden, hidden, 2)
        self.noise = LearnedNoise()

    def _message(self, sender: Tensor, receiver: Tensor, edge: Tensor) -> Tensor:
        return self.f_e(torch.cat([sender, receiver, edge], -1))

    def _update(self, node: Tensor, message: Tensor) -> Tensor:
        return node + self.f_n(torch.cat([node, message], -1))

    def forward(self, states: Tensor, inputs: ProcessInput, dt_s: float) -> Prediction:
        """states [..., C, n] -> Prediction (pose [..., C, 6 L], force_n [..., C, 2],
        process_var [..., 6 L])."""
        layout = layout_of(states)
        n_links, (*batch, n_points, _) = layout.n_links, states.shape
        acted = inputs.link.to(torch.int64).expand(batch).reshape(-1)
        chain = chain_of(tuple(acted.tolist()), n_links, n_points)
        links = self._link_nodes(states, inputs).reshape(-1, NODE_DIM)  # [B C L, D]
        robot = self._robot_node(inputs).unsqueeze(-2).expand(*batch, n_points, NODE_DIM)
        robot = robot.reshape(-1, NODE_DIM)  # [B C, D]
        is_pull = inputs.is_pull.to(states.dtype).expand(batch).unsqueeze(-1)
        robot_edge = _edge(is_pull.expand(*batch, n_points), _EDGE_ROBOT).reshape(-1, EDGE_DIM)
        friction = layout.link_parameters(states)[..., 1].reshape(-1) / FRICTION_SCALE
        table = _node(links.new_zeros(NODE_DIM - 3), _TABLE).expand_as(links)
        support = self._message(table, links, _edge(friction, _EDGE_SUPPORT))  # [B C L, H]

        joint_edges = self._joint_edges(states, inputs)
        nodes = self._propagate_cause(links, robot, support, robot_edge, joint_edges, chain)
        nodes = self._propagate_effect(nodes, joint_edges, chain)
        to_robot = self._message(nodes[chain.acted_rows], robot, robot_edge)
        force = force_to_world(self.tac_net(to_robot).reshape(*batch, n_points, 2), inputs)
        delta = (nodes - links)[:, :MOTION_DIM].reshape(*batch, n_points, n_links, MOTION_DIM)
        return Prediction(
            pose=integrate(states, delta, inputs, dt_s),
            force_n=force,
            process_var=self.noise(inputs.tcp.shape[:-1], n_links),
        )

    @staticmethod
    def _joint_edges(states: Tensor, inputs: ProcessInput) -> Tensor:
        """Static features of the joint edges towards each link: [2 B C L, EDGE_DIM], the
        joint on side +1 of every link (joint l) in the first B C L rows, the one on side -1
        (joint l - 1) in the rest; rows without such a joint hold finite filler."""
        layout = layout_of(states)
        pose = layout.link_pose(states)
        hinges = hinge_points(pose, inputs)  # [..., C, L - 1, 2]
        friction = layout.joint_friction(states) / JOINT_FRICTION_SCALE_NM  # [..., C, L - 1]
        no_friction = friction.new_zeros(*pose.shape[:-2], 1)  # filler beyond the chain's ends
        no_hinge = no_friction.unsqueeze(-1).expand(*no_friction.shape, 2)
        hinge = torch.stack([torch.cat([hinges, no_hinge], -2), torch.cat([no_hinge, hinges], -2)])
        value = torch.stack(
            [torch.cat([friction, no_friction], -1), torch.cat([no_friction, friction], -1)]
        )
        geometry = rotate(hinge - pose[..., :2], -inputs.pd_rad[..., None, None]) / SIZE_SCALE_M
        return _edge(value, _EDGE_JOINT, geometry).reshape(-1, EDGE_DIM)

    def _propagate_cause(
        self,
        links: Tensor,
        robot: Tensor,
        support: Tensor,
        robot_edge: Tensor,
        joint_edges: Tensor,
        chain: _Chain,
    ) -> Tensor:
        """Breadth-first from the robot: the links at depth d are updated from their parent's
        (already updated) features plus their support message. links [B C L, D]."""
        nodes = links
        acted = chain.acted_rows
        cause = self._message(robot, nodes[acted], robot_edge)
        nodes = nodes.index_copy(0, acted, self._update(nodes[acted], cause + support[acted]))
        for receivers, senders, edges in chain.cause:
            cause = self._message(nodes[senders], nodes[receivers], joint_edges[edges])
            updated = self._update(nodes[receivers], cause + support[receivers])
            nodes = nodes.index_copy(0, receivers, updated)
        return nodes

    def _propagate_effect(self, nodes: Tensor, joint_edges: Tensor, chain: _Chain) -> Tensor:
        """Back from the deepest links: every link with children is updated by the sum of the
        messages from its children (the neighbours farther from the robot)."""
        for phase in chain.effect:
            senders, receivers = nodes[phase.senders], nodes[phase.receivers]
            messages = self._message(senders, receivers, joint_edges[phase.edges])
            message = nodes.new_zeros(len(phase.updated), self.hidden)
            sides = zip(
                phase.slots.split(phase.side_sizes), messages.split(phase.side_sizes),
                strict=True,
            )  # fmt: skip
            for slots, part in sides:  # side +1, then side -1: a link's children in order
                message.index_add_(0, slots, part)
            rows = phase.updated
            nodes = nodes.index_copy(0, rows, self._update(nodes[rows], message))
        return nodes

    def _link_nodes(self, states: Tensor, inputs: ProcessInput) -> Tensor:
        """[..., C, L, NODE_DIM]: link features, is_pull, type."""
        features = link_features(states, inputs)
        is_pull = inputs.is_pull.to(states.dtype)[..., None, None, None]
        return _node(torch.cat([features, is_pull.expand(*features.shape[:-1], 1)], -1), _LINK)

    def _robot_node(self, inputs: ProcessInput) -> Tensor:
        """[..., NODE_DIM]: motion 6, cos/sin 2, zero parameters 4 and size 2, is_pull, type."""
        robot = robot_features(inputs)
        zeros = robot.new_zeros(*robot.shape[:-1], 6)
        return _node(torch.cat([robot[..., :8], zeros, robot[..., 8:9]], -1), _ROBOT)


# ---------------------------------------------------------------------------------------------
# Feed-forward baseline


class FeedForwardProcessNet(nn.Module):
    """The baseline: one 3-layer MLP over the concatenated features of a fixed number of links.

    Input per sigma point: the link features [14 L], robot features [9], joint frictions / scale
    [L - 1], joint positions relative to the TCP in the reference frame / SIZE_SCALE_M
    [2 (L - 1)] and the acted link one-hot [L]. Output: the normalised deltas [6 L] and the
    normalised force [2]. Process noise as in :class:`GraphProcessNet`.
    """

    def __init__(self, n_links: int, hidden: int = 64) -> None:
        super().__init__()
        if n_links < 1:
            raise ValueError(f"n_links must be >= 1, got {n_links}")
        self.n_links = n_links
        self.hidden = hidden
        n_in = (LINK_FEATURE_DIM + 1) * n_links + ROBOT_FEATURE_DIM + 3 * (n_links - 1)
        self.f = mlp(n_in, hidden, MOTION_DIM * n_links + 2)
        self.noise = LearnedNoise()

    def forward(self, states: Tensor, inputs: ProcessInput, dt_s: float) -> Prediction:
        """states [..., C, 11 L - 1] -> Prediction (pose [..., C, 6 L], force_n [..., C, 2],
        process_var [..., 6 L]). ValueError for another link count."""
        expected = StateLayout(self.n_links)
        if states.shape[-1] != expected.size:
            raise ValueError(
                f"FeedForwardProcessNet was built for n_links={self.n_links} (state size "
                f"{expected.size}), got state size {states.shape[-1]}"
            )
        links = link_features(states, inputs)
        pose = expected.link_pose(states)
        origin, angle = _frame(inputs)
        hinges = rotate(hinge_points(pose, inputs) - origin.unsqueeze(-2), -angle.unsqueeze(-1))
        batch = links.shape[:-2]
        robot = robot_features(inputs).unsqueeze(-2).expand(*batch, ROBOT_FEATURE_DIM)
        acted = nn.functional.one_hot(inputs.link.to(torch.int64), self.n_links).to(states.dtype)
        features = torch.cat(
            [
                links.flatten(-2),
                robot,
                expected.joint_friction(states) / JOINT_FRICTION_SCALE_NM,
                (hinges / SIZE_SCALE_M).flatten(-2),
                acted.unsqueeze(-2).expand(*batch, self.n_links),
            ],
            -1,
        )
        out = self.f(features)
        delta = out[..., :-2].unflatten(-1, (self.n_links, MOTION_DIM))
        return Prediction(
            pose=integrate(states, delta, inputs, dt_s),
            force_n=force_to_world(out[..., -2:], inputs),
            process_var=self.noise(inputs.tcp.shape[:-1], self.n_links),
        )
