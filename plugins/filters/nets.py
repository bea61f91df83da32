"""Learned process models of the dual filter: the causal graph network and the feed-forward
baseline (pure torch ``nn.Module``s, float64).

Both take ``forward(states [..., C, n], inputs: ProcessInput, dt_s) -> Prediction`` and work in
the *reference frame* of the action: origin at the gripper TCP, x axis along the push or pull
direction ``pd_rad``. Every feature is expressed in that frame (translation and rotation
invariant) and normalised by fixed scales, and every output is rotated back to the world:

- link node [NODE_DIM]: motion slots (x, y, theta, vx, vy, omega of the link frame relative to
  the reference frame, / ``SIZE_SCALE_M``, ``SIZE_SCALE_M``, 1, ``SPEED_SCALE_MPS``,
  ``SPEED_SCALE_MPS``, ``RATE_SCALE_RADPS``), cos/sin of the relative theta, parameters
  (m / ``MASS_SCALE_KG``, f / ``FRICTION_SCALE``, com_x, com_y / ``SIZE_SCALE_M``), the CoM's
  position in the reference frame / ``SIZE_SCALE_M`` (its offset from the push line is what
  turns the link: the com_x, com_y of the link frame would need a product with the relative
  theta, which small nets do not learn from a few hundred pushes), half
  extents (a1, a2) / ``SIZE_SCALE_M``, the gap from the TCP to the link's footprint box
  (:func:`box_gap_m`, capped at ``GAP_CAP_M``) / ``SIZE_SCALE_M``, is_pull, node type one-hot
  (link, robot, table). The gap tells the nets whether the fingers touch the link: from the
  relative pose and the size alone, small nets learn contact poorly and predict pushes that
  never reach the object moving it;
- robot node: the same layout with the TCP as the body (zero position, its yaw and twist),
  zero parameters, size and gap;
- table node: the type one-hot only.

The network's output per link is a normalised delta (dx, dy, dtheta, dvx, dvy, domega) in the
reference frame; :func:`integrate` scales it (dx, dy by ``SPEED_SCALE_MPS * dt_s``, dtheta by
``RATE_SCALE_RADPS * dt_s``, the twist changes by the speed scales), rotates it to the world and
adds it to the current pose and twist.

The weights are float64. Look-aheads use a copy with float32 MLPs
(``_LearnedProcessModel.look_ahead``) on float64 states: the features and the integration are
worked out in the states' dtype, only the MLPs run in their weights' dtype.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import torch
from torch import Tensor, nn
from vistac.plugins.filters.state import (
    DTYPE,
    GRAVITY_MPS2,
    Prediction,
    ProcessInput,
    StateLayout,
)

SIZE_SCALE_M = 0.05
SPEED_SCALE_MPS = 0.025
RATE_SCALE_RADPS = 0.5
MASS_SCALE_KG = 1.0
FRICTION_SCALE = 0.3
JOINT_FRICTION_SCALE_NM = 0.5
FORCE_SCALE_N = 2.0
GAP_CAP_M = 0.05

MOTION_DIM = 6
NODE_DIM = 21
"""motion 6, cos/sin 2, parameters 4, CoM position 2, size 2, gap 1, is_pull 1, type 3."""
EDGE_DIM = 6
"""value (support: f_l, joint: f_j, robot: is_pull), type one-hot 3 (robot, joint, support),
geometry 2 (joint: hinge minus receiver position, reference frame / SIZE_SCALE_M)."""
LINK_FEATURE_DIM = 17
ROBOT_FEATURE_DIM = 9

_LINK, _ROBOT, _TABLE = 0, 1, 2
_FRICTION_FEATURE = 9
"""The column of f / FRICTION_SCALE in the link features."""
_EDGE_ROBOT, _EDGE_JOINT, _EDGE_SUPPORT = 1, 2, 3
_INITIAL_STD = (0.001, 0.001, 0.01, 0.005, 0.005, 0.05)
"""Initial learned process noise std per field: m, m, rad, m/s, m/s, rad/s."""
_OUTPUT_INIT_SCALE = 0.1
_LINK_FEATURE_SCALES = (
    *(SIZE_SCALE_M, SIZE_SCALE_M, 1.0, SPEED_SCALE_MPS, SPEED_SCALE_MPS, RATE_SCALE_RADPS),
    *(1.0, 1.0, MASS_SCALE_KG, FRICTION_SCALE, SIZE_SCALE_M, SIZE_SCALE_M),
    *(SIZE_SCALE_M, SIZE_SCALE_M, SIZE_SCALE_M, SIZE_SCALE_M, SIZE_SCALE_M),
)
"""What each link feature is divided by (motion, cos/sin, parameters, CoM position, size,
gap)."""
_ROBOT_FEATURE_SCALES = (
    *(1.0, 1.0, 1.0, SPEED_SCALE_MPS, SPEED_SCALE_MPS, RATE_SCALE_RADPS),
    *(1.0, 1.0, 1.0),
)
"""What each robot feature is divided by (motion, cos/sin, is_pull)."""


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


@dataclass(frozen=True)
class Turn:
    """The cosine and sine of rotation angles [...], for :func:`rotate`."""

    cos: Tensor
    sin: Tensor

    @staticmethod
    def of(angle_rad: Tensor) -> Turn:
        return Turn(torch.cos(angle_rad), torch.sin(angle_rad))

    def squeeze(self) -> Turn:
        """Without the last dimension (of size 1)."""
        return Turn(self.cos.squeeze(-1), self.sin.squeeze(-1))


def rotate(xy: Tensor, angle_rad: Tensor | Turn) -> Tensor:
    """Rotate vectors xy [..., 2] by angle_rad [...] (broadcast), or by its Turn."""
    turn = angle_rad if isinstance(angle_rad, Turn) else Turn.of(angle_rad)
    c, s = turn.cos, turn.sin
    x, y = xy.unbind(-1)
    return torch.stack([torch.addcmul(c * x, s, y, value=-1.0), torch.addcmul(s * x, c, y)], -1)


@functools.lru_cache(maxsize=64)
def _constant(values: tuple[float, ...], dtype: torch.dtype, device: torch.device) -> Tensor:
    """The tensor [len(values)] (made once; a normal tensor even when first asked for in
    inference mode, so that autograd can use it later). Never change it in place."""
    with torch.inference_mode(False):
        return torch.tensor(values, dtype=dtype, device=device)


def constant(values: tuple[float, ...], like: Tensor) -> Tensor:
    """``like.new_tensor(values)``, made once per dtype and device."""
    return _constant(values, like.dtype, like.device)


def perp(xy: Tensor) -> Tensor:
    """[..., 2] rotated by +90 degrees: omega x r = omega * perp(r)."""
    return torch.stack([-xy[..., 1], xy[..., 0]], -1)


def hinge_offsets(inputs: ProcessInput) -> Tensor:
    """Position of each joint k in the frame of link k: [..., 1, L - 1, 2] (m).

    Joint k joins links k and k + 1: ``hinge_m`` where given, else midway between link k's +x
    side centre and link k + 1's -x side centre (footprint boxes from ``link_size_m``), placed
    with the initial relative pose ``link_offset``, as the models were trained.
    """
    if inputs.hinge_m is not None:
        return inputs.hinge_m.unsqueeze(-3)
    offset = inputs.link_offset.unsqueeze(-3)  # [..., 1, L, 3]
    size = inputs.link_size_m.unsqueeze(-3)  # [..., 1, L, 2]
    parent, child = offset[..., :-1, :], offset[..., 1:, :]
    rel_xy = rotate(child[..., :2] - parent[..., :2], -parent[..., 2])
    rel_theta = child[..., 2] - parent[..., 2]
    zero = torch.zeros_like(rel_theta)
    parent_side = torch.stack([size[..., :-1, 0], zero], -1)
    child_side = rel_xy + rotate(torch.stack([-size[..., 1:, 0], zero], -1), rel_theta)
    return 0.5 * (parent_side + child_side)


def hinge_points(pose: Tensor, inputs: ProcessInput, offsets: Tensor | None = None) -> Tensor:
    """World position of each joint (see :func:`hinge_offsets`, or ``offsets`` from it) for
    the current link poses [..., C, L, 6]. Returns [..., C, L - 1, 2]."""
    if offsets is None:
        offsets = hinge_offsets(inputs)
    return pose[..., :-1, :2] + rotate(offsets, pose[..., :-1, 2])


def _frame(inputs: ProcessInput) -> tuple[Tensor, Tensor]:
    """Reference frame broadcast over C: origin [..., 1, 2] (m), angle [..., 1] (rad)."""
    return inputs.tcp[..., :2].unsqueeze(-2), inputs.pd_rad.unsqueeze(-1)


def frame_turns(inputs: ProcessInput) -> tuple[Turn, Turn]:
    """The turns [..., 1, 1, 1] into the reference frame (by -pd_rad) and back to the world
    (by +pd_rad), broadcast over C, L and a pair of vectors."""
    angle = inputs.pd_rad[..., None, None, None]
    return Turn.of(-angle), Turn.of(angle)


def box_gap_m(point_m: Tensor, half_extents_m: Tensor) -> Tensor:
    """Distance of points [..., 2] outside an axis-aligned box centred at the origin with
    half extents [..., 2]: [...] (m, 0 inside)."""
    return torch.linalg.vector_norm((point_m.abs() - half_extents_m).clamp(min=0.0), dim=-1)


@dataclass(frozen=True)
class RelativeLinks:
    """The links of states [..., C, n] seen in the reference frame (``relative_links``)."""

    xy_m: Tensor
    """Positions [..., C, L, 2]."""
    velocity_mps: Tensor
    """Velocities [..., C, L, 2]."""
    rate_radps: Tensor
    """Angular rates [..., C, L, 1] (the same in every frame)."""
    theta_rad: Tensor
    """Angles [..., C, L], wrapped into (-pi, pi]..."""
    turn: Turn
    """... and their cosine and sine."""


def relative_links(states: Tensor, inputs: ProcessInput, into: Turn | None = None) -> RelativeLinks:
    """The link poses and velocities of states [..., C, n] in the reference frame. into: the
    first of :func:`frame_turns`."""
    pose = layout_of(states).link_pose(states)
    origin, angle = _frame(inputs)
    angle_l = angle.unsqueeze(-1)  # [..., 1, 1]
    position_velocity = torch.stack([pose[..., :2] - origin.unsqueeze(-2), pose[..., 3:5]], -2)
    xy, velocity = rotate(position_velocity, into or Turn.of(-angle_l.unsqueeze(-1))).unbind(-2)
    turn = Turn.of(pose[..., 2] - angle_l)
    return RelativeLinks(xy, velocity, pose[..., 5:6], torch.atan2(turn.sin, turn.cos), turn)


def link_features(
    states: Tensor,
    inputs: ProcessInput,
    into: Turn | None = None,
    relative: RelativeLinks | None = None,
) -> Tensor:
    """Per-link features in the reference frame: [..., C, L, LINK_FEATURE_DIM]. into: the
    first of :func:`frame_turns`; relative: ``relative_links`` of the same, where known."""
    relative = relative or relative_links(states, inputs, into)
    xy, turn = relative.xy_m, relative.turn
    size = inputs.link_size_m.unsqueeze(-3).expand(*xy.shape)
    parameters = layout_of(states).link_parameters(states)
    # The TCP is the reference frame's origin: in the link's frame it lies at -R(-theta) xy,
    # as far from the footprint box (symmetric about the origin) as R(-theta) xy.
    tcp_mirror = rotate(xy, Turn(turn.cos, -turn.sin))
    features = torch.cat(
        [
            xy,
            relative.theta_rad.unsqueeze(-1),
            relative.velocity_mps,
            relative.rate_radps,
            torch.stack([turn.cos, turn.sin], -1),
            parameters,
            xy + rotate(parameters[..., 2:4], turn),
            size,
            box_gap_m(tcp_mirror, size).clamp(max=GAP_CAP_M).unsqueeze(-1),
        ],
        -1,
    )
    return features / constant(_LINK_FEATURE_SCALES, features)


def robot_features(inputs: ProcessInput) -> Tensor:
    """Robot features in the reference frame: [..., ROBOT_FEATURE_DIM] = (0, 0, yaw, vx, vy,
    wz, cos yaw, sin yaw, is_pull), normalised like the link motion slots."""
    tcp = inputs.tcp
    yaw = wrap(tcp[..., 2] - inputs.pd_rad)
    velocity = rotate(tcp[..., 3:5], -inputs.pd_rad)
    is_pull = inputs.is_pull.to(tcp.dtype)
    features = torch.cat(
        [
            yaw.new_zeros(*yaw.shape, 2),
            yaw.unsqueeze(-1),
            velocity,
            tcp[..., 5:6],
            torch.stack([torch.cos(yaw), torch.sin(yaw), is_pull], -1),
        ],
        -1,
    )
    return features / constant(_ROBOT_FEATURE_SCALES, features)


def integrate(
    states: Tensor, delta: Tensor, inputs: ProcessInput, dt_s: float, back: Turn | None = None
) -> Tensor:
    """Apply normalised reference-frame deltas [..., C, L, 6] to the current poses. back: the
    second of :func:`frame_turns`.

    Returns the next time-varying block [..., C, 6 L] (world frame).
    """
    pose = layout_of(states).link_pose(states)
    planar = delta.unflatten(-1, (2, 3))  # (dx, dy, dtheta), (dvx, dvy, domega)
    turn = back or _frame(inputs)[1][..., None, None]  # [..., 1, 1, 1]
    change = torch.cat([rotate(planar[..., :2], turn), planar[..., 2:]], -1)
    scales = (
        *(SPEED_SCALE_MPS * dt_s, SPEED_SCALE_MPS * dt_s, RATE_SCALE_RADPS * dt_s),
        *(SPEED_SCALE_MPS, SPEED_SCALE_MPS, RATE_SCALE_RADPS),
    )
    return (pose + change.flatten(-2) * constant(scales, delta)).flatten(-2)


def friction_load(states: Tensor) -> Tensor:
    """Each link's friction load ``g m f`` / ``FORCE_SCALE_N``: [..., n] -> [..., L]."""
    params = layout_of(states).link_parameters(states)
    return params[..., 0] * params[..., 1] * (GRAVITY_MPS2 / FORCE_SCALE_N)


def force_to_world(force: Tensor, inputs: ProcessInput) -> Tensor:
    """Normalised reference-frame force [..., C, 2] -> world force (N)."""
    return rotate(force, _frame(inputs)[1]) * FORCE_SCALE_N


class MLP(nn.Sequential):
    """Linear layers with SiLU between them, on rows [..., n_in] -> [..., n_out] (``forward``)
    or on the concatenation of several inputs (``rows``). A SiLU works in place: it only ever
    gets the fresh output of the layer before."""

    FEATURE_MAJOR_MIN_ROWS = 256
    """From this many rows on, ``rows`` multiplies feature-major (see there)..."""
    FEATURE_MAJOR_MIN_ROWS_FLOAT32 = 4096
    """... and from this many in float32, where the BLAS does the row-major products about
    as fast up to there (hidden 32, one thread)."""

    def __init__(self, *layers: nn.Module) -> None:
        super().__init__(*layers)
        self._frozen: list[tuple[Tensor, Tensor]] | None = None

    @property
    def dtype(self) -> torch.dtype:
        """The weights' dtype, which the inputs must have (float64; float32 in a copy made
        for look-aheads, see ``_LearnedProcessModel.look_ahead``)."""
        return self._linear_layers()[0][0].dtype

    def freeze(self) -> None:
        """Keep the layers' (transposed weight, bias) from now on: for a copy whose weights
        never change again (the float32 copy for look-aheads, made after its ``float()``),
        it saves an operation per layer and call."""
        self._frozen = self._linear_layers()

    def _linear_layers(self) -> list[tuple[Tensor, Tensor]]:
        """(weight [n_in, n_out] (a transposed view), bias [n_out]) of every linear layer;
        a SiLU follows each but the last."""
        if self._frozen is not None:
            return self._frozen
        layers: list[tuple[Tensor, Tensor]] = []
        for layer in self._modules.values():
            if isinstance(layer, nn.Linear):
                weight, bias = layer._parameters["weight"], layer._parameters["bias"]
                assert weight is not None and bias is not None
                layers.append((weight.t(), bias))
        return layers

    def rows(self, *inputs: Tensor) -> Tensor:
        """The layers on the concatenation of ``inputs`` (rows [n, d_i], or [d_i] for the same
        values in every row; the d_i add up to n_in) -> [n, n_out].

        With many rows, the layers run feature-major: the first multiplies each input by its
        block of weight columns (a constant one goes into the bias), so nothing is
        concatenated, and every product is ``W x^T`` with the rows contiguous, for a few
        dozen features and thousands of rows the order the BLAS does fastest. With fewer
        rows, where the cost per call dominates, the concatenated rows go through the layers
        as usual, each layer one ``addmm``.
        """
        n_rows = max(part.shape[0] if part.dim() == 2 else 0 for part in inputs)
        layers = self._linear_layers()
        if n_rows >= self._feature_major_min_rows(inputs[0].dtype):
            return self._feature_major(inputs, layers).t()
        parts = [part if part.dim() == 2 else part.expand(n_rows, -1) for part in inputs]
        hidden = torch.cat(parts, -1) if len(parts) > 1 else parts[0]
        for index, (weight_t, bias) in enumerate(layers):
            hidden = torch.addmm(bias, hidden, weight_t)
            if index < len(layers) - 1:
                hidden = nn.functional.silu(hidden, inplace=True)
        return hidden

    @staticmethod
    def _feature_major(inputs: tuple[Tensor, ...], layers: list[tuple[Tensor, Tensor]]) -> Tensor:
        """The layers on ``inputs`` (see ``rows``), feature-major: -> [n_out, n]."""
        blocks = layers[0][0].t().split([part.shape[-1] for part in inputs], 1)
        bias: Tensor = layers[0][1]
        for part, weight in zip(inputs, blocks, strict=True):
            if part.dim() == 1:
                bias = torch.addmv(bias, weight, part)
        (part, weight), *others = [
            (part, weight) for part, weight in zip(inputs, blocks, strict=True) if part.dim() == 2
        ]
        hidden = torch.addmm(bias.unsqueeze(-1), weight, part.t())
        for part, weight in others:
            hidden = hidden.addmm_(weight, part.t())
        for weight_t, bias in layers[1:]:
            hidden = nn.functional.silu(hidden, inplace=True)
            hidden = torch.addmm(bias.unsqueeze(-1), weight_t.t(), hidden)
        return hidden

    def _feature_major_min_rows(self, dtype: torch.dtype) -> int:
        if dtype == torch.float32:
            return self.FEATURE_MAJOR_MIN_ROWS_FLOAT32
        return self.FEATURE_MAJOR_MIN_ROWS

    def forward(self, features: Tensor) -> Tensor:
        output = self.rows(features.reshape(-1, features.shape[-1]))
        return output.reshape(*features.shape[:-1], output.shape[-1])


def mlp(n_in: int, hidden: int, n_out: int) -> MLP:
    """Three linear layers with SiLU between them (float64); the last layer starts small so a
    fresh net outputs small values."""
    layers = MLP(
        nn.Linear(n_in, hidden, dtype=DTYPE),
        nn.SiLU(inplace=True),
        nn.Linear(hidden, hidden, dtype=DTYPE),
        nn.SiLU(inplace=True),
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


def _one_hot(index: int, like: Tensor, zeros: int = 0) -> Tensor:
    """(0, 0, 0) with a 1 at index, then ``zeros`` more zeros: [3 + zeros], like's dtype."""
    return constant(tuple(float(i == index) for i in range(3 + zeros)), like)


def _node(features: Tensor, node_type: int) -> Tensor:
    """Append the node type one-hot (link, robot, table) to features [..., NODE_DIM - 3]."""
    one_hot = _one_hot(node_type, features).expand(*features.shape[:-1], 3)
    return torch.cat([features, one_hot], -1)


def _edge(value: Tensor, kind: int, geometry: Tensor | None = None) -> Tensor:
    """Static edge features [..., EDGE_DIM] from value [...] and geometry [..., 2] (zeros for
    None)."""
    if geometry is None:
        rest = _one_hot(kind - 1, value, zeros=2).expand(*value.shape, EDGE_DIM - 1)
        return torch.cat([value.unsqueeze(-1), rest], -1)
    one_hot = _one_hot(kind - 1, value).expand(*value.shape, 3)
    return torch.cat([value.unsqueeze(-1), one_hot, geometry], -1)


@dataclass(frozen=True)
class _EffectRows:
    """One effect phase: the messages from the children of the links at one depth."""

    updated: Tensor
    """Rows of the links with any child [n C], in the order they first appear in
    ``receivers``."""
    receivers: Tensor
    """Rows of the links with a child on side +1, then of those with one on side -1."""
    slots: Tensor | None
    """Where each of ``receivers`` is in ``updated`` (side +1 first: summed in that order);
    None where every link has one child, so that ``receivers`` is ``updated``."""
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
        self.n_joint_rows = len(acted) * n_points * (n_links - 1)
        acted_links = torch.tensor(acted, dtype=torch.int64)
        link = torch.arange(n_links)
        self._depth = (link - acted_links[:, None]).abs()  # [B, L]
        self._toward = torch.sign(acted_links[:, None] - link)  # [B, L]: the parent's side
        self.acted_rows = self._rows(torch.arange(len(acted)), acted_links)
        """[B C]: rows of the acted links, in the order (b C + c) of the robot rows."""
        self.cause = [self._cause_rows(depth) for depth in range(1, n_links)]
        """Per depth 1, 2, ...: rows of the links there, of their parents, of the edges to them
        from their parents (``joint_rows``), each [n C]."""
        self.effect = [self._effect_rows(depth) for depth in reversed(range(n_links - 1))]
        """Per depth L - 2, ..., 0: the effect phase's rows."""

    def _rows(self, batch: Tensor, link: Tensor, offset: Tensor | int = 0) -> Tensor:
        """Rows of the links (batch[i], link[i]) (plus offset[i]) for every sigma point,
        i-major: [n] -> [n C] int64."""
        first = (batch * self.n_points)[:, None] + torch.arange(self.n_points)
        return (first * self.n_links + (link + offset)[:, None]).reshape(-1)

    def joint_rows(self, batch: Tensor, link: Tensor, side: Tensor | int) -> Tensor:
        """Rows in ``GraphProcessNet._joint_edges`` of the edges towards the links (batch[i],
        link[i]) across their joint on side[i] (+1 or -1), for every sigma point: [n C]."""
        second = (torch.as_tensor(side) < 0).to(torch.int64)  # the joint's second link
        first = (batch * self.n_points)[:, None] + torch.arange(self.n_points)
        joint = link - second + second * self.n_joint_rows
        return (first * (self.n_links - 1) + joint[:, None]).reshape(-1)

    def _cause_rows(self, depth: int) -> tuple[Tensor, Tensor, Tensor]:
        batch, link = (self._depth == depth).nonzero(as_tuple=True)
        side = self._toward[batch, link]
        edge = self.joint_rows(batch, link, side)
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
            edges.append(self.joint_rows(batch, at, side))
        rows = torch.cat(receivers)
        updated = torch.tensor(list(dict.fromkeys(rows.tolist())), dtype=torch.int64)
        slot = torch.full((self.n_rows,), -1, dtype=torch.int64)
        slot[updated] = torch.arange(len(updated))
        return _EffectRows(
            updated=updated,
            receivers=rows,
            slots=None if len(updated) == len(rows) else slot[rows],
            senders=torch.cat(senders),
            edges=torch.cat(edges),
        )


@functools.lru_cache(maxsize=32)
def chain_of(acted: tuple[int, ...], n_links: int, n_points: int) -> _Chain:
    """The (cached) chain rows for the acted link of each batch element (CPU tensors; normal
    ones even when first asked for in inference mode, so that autograd can use them later)."""
    with torch.inference_mode(False):
        return _Chain(acted, n_links, n_points)


def _link_tail(inputs: ProcessInput, dtype: torch.dtype) -> Tensor:
    """The last features of the link nodes: [..., 1, 1, 4] = is_pull, the link one-hot."""
    is_pull = inputs.is_pull.to(dtype)[..., None, None, None]
    return _node(is_pull, _LINK)


@dataclass(frozen=True)
class _InputParts:
    """What :class:`GraphProcessNet` takes from the inputs alone, apart from the TCP position
    (which only the link features use): the same at every step of a straight look-ahead."""

    chain: _Chain
    robot: Tensor
    """Robot nodes [B C, D] (the MLPs' dtype)."""
    robot_edge: Tensor
    """The edges robot -> acted link [B C, EDGE_DIM] (the MLPs' dtype)."""
    table: Tensor
    """The table node [D] (the MLPs' dtype)."""
    hinge_offsets: Tensor
    """Each joint in the frame of its first link [..., 1, L - 1, 2] (:func:`hinge_offsets`)."""
    into: Turn
    """Into the reference frame and ..."""
    back: Turn
    """... back to the world [..., 1, 1, 1] (:func:`frame_turns`)."""
    link_tail: Tensor
    """The last features of each link node [..., 1, 1, 4]: is_pull and the type one-hot."""
    process_var: Tensor
    """[..., 6 L] (the states' dtype)."""


@dataclass(frozen=True)
class _InputKey:
    """What :class:`_InputParts` are made from: the states' shape and dtype, the weights'
    dtype, and every input but the TCP position (tensors)."""

    shape: tuple[torch.Size, torch.dtype, torch.dtype]
    tensors: tuple[Tensor, ...]

    @staticmethod
    def of(states: Tensor, inputs: ProcessInput, weights: torch.dtype) -> _InputKey:
        fields = (inputs.pd_rad, inputs.is_pull, inputs.link, inputs.link_size_m)
        hinge = () if inputs.hinge_m is None else (inputs.hinge_m,)
        tensors = (inputs.tcp[..., 2:], *fields, inputs.link_offset, *hinge)
        return _InputKey((states.shape, states.dtype, weights), tensors)

    def copy(self) -> _InputKey:
        """A key that later in-place changes of the inputs do not alter."""
        return _InputKey(self.shape, tuple(tensor.clone() for tensor in self.tensors))

    def equals(self, other: _InputKey) -> bool:
        return self.shape == other.shape and all(
            a.shape == b.shape and torch.equal(a, b)
            for a, b in zip(self.tensors, other.tensors, strict=True)
        )


class GraphProcessNet(nn.Module):
    """Causal graph network (paper 1, III-F2, Algorithm 1) for any number of links.

    Nodes: the L links, the robot and the table. Directed edges: robot -> acted link (cause),
    both directions of every joint, table -> each link (support). ``f_e`` (edge message) and
    ``f_n`` (residual node update) are 3-layer MLPs shared by all edges and nodes.

    The tactile force: where paper 1 maps the effect message towards the robot to it, here
    ``tac_net`` maps each updated link node to a vector that scales the link's friction load
    ``g m f``, and the force is their sum. In a quasi-static push the fingers balance
    the table's friction on the links, so the force is about ``g sum(m f)`` (the median
    within 15 % in the generated pushes), and the product m f is what the force tells the
    filter; read off the message, the product had to be learned, and was learned poorly.
    The chain is visited breadth-first from the acted link (``inputs.link``), which may differ
    across the batch. The nodes of all batch elements and sigma points are rows of one matrix,
    updated in place phase by phase; each phase runs the MLPs (``MLP.rows``: no concatenated
    inputs and feature-major products for many rows) on just the rows it updates.
    """

    def __init__(self, hidden: int = 64) -> None:
        super().__init__()
        self.hidden = hidden
        self.f_e = mlp(2 * NODE_DIM + EDGE_DIM, hidden, hidden)
        self.f_n = mlp(NODE_DIM + hidden, hidden, NODE_DIM)
        self.tac_net = mlp(NODE_DIM, hidden, 2)
        self.noise = LearnedNoise()
        self._last_inputs: tuple[_InputKey, _InputParts] | None = None
        """The key and parts of the last call with ``reuse_inputs``."""

    def _message(self, sender: Tensor, receiver: Tensor, edge: Tensor) -> Tensor:
        """f_e of sender, receiver [n, D] (or [D] for all) and edge [n, EDGE_DIM] -> [n, H]."""
        return self.f_e.rows(sender, receiver, edge)

    def _update(self, node: Tensor, message: Tensor) -> Tensor:
        """The residual update of node [n, D] by message [n, H] -> [n, D]."""
        return node + self.f_n.rows(node, message)

    def forward(
        self,
        states: Tensor,
        inputs: ProcessInput,
        dt_s: float,
        with_force: bool = True,
        reuse_inputs: bool = False,
    ) -> Prediction:
        """states [..., C, n] -> Prediction (pose [..., C, 6 L], force_n [..., C, 2] (zero
        without ``with_force``), process_var [..., 6 L]), in the states' dtype.

        The features, and the integration of the predicted change, are worked out in the
        states' dtype, the MLPs run in their weights' (a copy for look-aheads has float32
        MLPs and takes float64 states). ``reuse_inputs`` (without gradients only): reuse what
        the last call took from the inputs alone (:class:`_InputParts`) while those inputs
        are equal, as at every step of a straight look-ahead."""
        parts = self._input_parts(states, inputs, reuse_inputs and not torch.is_grad_enabled())
        layout, weights = layout_of(states), self.f_e.dtype
        relative = relative_links(states, inputs, parts.into)
        links = self._link_nodes(states, inputs, parts, relative).reshape(-1, NODE_DIM)
        links = links.to(weights)
        support_edges = _edge(links[:, _FRICTION_FEATURE], _EDGE_SUPPORT)  # [B C L, EDGE_DIM]
        joint_edges = self._joint_edges(states, relative, parts).to(weights)
        nodes = links.clone()  # updated in place, phase by phase
        self._propagate_cause(nodes, parts, support_edges, joint_edges)
        self._propagate_effect(nodes, joint_edges, parts.chain)
        delta = nodes[:, :MOTION_DIM] - links[:, :MOTION_DIM]
        delta = delta.reshape(*states.shape[:-1], layout.n_links, MOTION_DIM).to(states.dtype)
        force = states.new_zeros(*states.shape[:-1], 2)
        if with_force:
            force = self._force(nodes, states, inputs)
        return Prediction(
            pose=integrate(states, delta, inputs, dt_s, parts.back),
            force_n=force,
            process_var=parts.process_var,
        )

    def _force(self, nodes: Tensor, states: Tensor, inputs: ProcessInput) -> Tensor:
        """The tactile force (world, N) [..., C, 2] from the updated nodes [B C L, D]: the sum
        over the links of their friction load ``g m f`` times ``tac_net`` of their node (a
        vector in the reference frame, about minus the link's sliding direction)."""
        per_link = self.tac_net.rows(nodes).to(states.dtype)  # [B C L, 2]
        per_link = per_link.reshape(*states.shape[:-1], -1, 2)
        force = (friction_load(states).unsqueeze(-1) * per_link).sum(-2)
        return force_to_world(force, inputs)

    def _input_parts(self, states: Tensor, inputs: ProcessInput, reuse: bool) -> _InputParts:
        """What the graph takes from the inputs alone; with ``reuse``, the last call's while
        the inputs it depends on, the states' shape and the dtypes are the same."""
        if not reuse:
            return self._make_input_parts(states, inputs)
        key = _InputKey.of(states, inputs, self.f_e.dtype)
        if self._last_inputs is None or not self._last_inputs[0].equals(key):
            self._last_inputs = (key.copy(), self._make_input_parts(states, inputs))
        return self._last_inputs[1]

    def _make_input_parts(self, states: Tensor, inputs: ProcessInput) -> _InputParts:
        n_links, (*batch, n_points, _) = layout_of(states).n_links, states.shape
        weights = self.f_e.dtype
        acted = inputs.link.to(torch.int64).expand(batch).reshape(-1)
        robot = self._robot_node(inputs).unsqueeze(-2).expand(*batch, n_points, NODE_DIM)
        is_pull = inputs.is_pull.to(weights).expand(batch).unsqueeze(-1)
        robot_edge = _edge(is_pull.expand(*batch, n_points), _EDGE_ROBOT)
        into, back = frame_turns(inputs)
        return _InputParts(
            chain=chain_of(tuple(acted.tolist()), n_links, n_points),
            robot=robot.reshape(-1, NODE_DIM).to(weights),
            robot_edge=robot_edge.reshape(-1, EDGE_DIM),
            table=_node(robot.new_zeros(NODE_DIM - 3, dtype=weights), _TABLE),
            hinge_offsets=hinge_offsets(inputs),
            into=into,
            back=back,
            link_tail=_link_tail(inputs, states.dtype),
            process_var=self.noise(inputs.tcp.shape[:-1], n_links).to(states.dtype),
        )

    @staticmethod
    def _joint_edges(states: Tensor, relative: RelativeLinks, parts: _InputParts) -> Tensor:
        """Static features of the edges across each joint k towards its two links:
        [2 B C (L - 1), EDGE_DIM], towards link k in the first B C (L - 1) rows, towards link
        k + 1 in the rest (see ``_Chain.joint_rows``). Their geometry, the joint's position
        from the receiving link in the reference frame, from the links there (``relative``)."""
        turn, xy = relative.turn, relative.xy_m
        from_first = rotate(parts.hinge_offsets, Turn(turn.cos[..., :-1], turn.sin[..., :-1]))
        from_second = from_first + (xy[..., :-1, :] - xy[..., 1:, :])
        geometry = torch.stack([from_first, from_second]) / SIZE_SCALE_M  # [2, ..., C, L - 1, 2]
        friction = layout_of(states).joint_friction(states) / JOINT_FRICTION_SCALE_NM
        edges = _edge(friction.expand(geometry.shape[:-1]), _EDGE_JOINT, geometry)
        return edges.reshape(-1, EDGE_DIM)

    def _propagate_cause(
        self, nodes: Tensor, parts: _InputParts, support_edges: Tensor, joint_edges: Tensor
    ) -> None:
        """Breadth-first from the robot: the links at depth d are updated from their parent's
        (already updated) features plus their support message. nodes [B C L, D], in place.

        Every link is updated once here, so it gets all its messages at its first features:
        the table's support messages to every link and the robot's to the acted links are
        one batch of ``f_e``."""
        chain, n_rows = parts.chain, nodes.shape[0]
        acted = nodes.index_select(0, chain.acted_rows)
        messages = self._message(
            torch.cat([parts.table.expand(n_rows, -1), parts.robot]),
            torch.cat([nodes, acted]),
            torch.cat([support_edges, parts.robot_edge]),
        )
        support, robot = messages[:n_rows], messages[n_rows:]
        message = robot + support.index_select(0, chain.acted_rows)
        nodes.index_copy_(0, chain.acted_rows, self._update(acted, message))
        for receivers, senders, edges in chain.cause:
            node, sender = nodes.index_select(0, receivers), nodes.index_select(0, senders)
            message = self._message(sender, node, joint_edges.index_select(0, edges))
            message = message + support.index_select(0, receivers)
            nodes.index_copy_(0, receivers, self._update(node, message))

    def _propagate_effect(self, nodes: Tensor, joint_edges: Tensor, chain: _Chain) -> None:
        """Back from the deepest links: every link with children is updated by the sum of the
        messages from its children (the neighbours farther from the robot). nodes [B C L, D],
        in place."""
        for phase in chain.effect:
            node = nodes.index_select(0, phase.receivers)
            sender = nodes.index_select(0, phase.senders)
            message = self._message(sender, node, joint_edges.index_select(0, phase.edges))
            if phase.slots is not None:  # a link with two children: the sum of their messages
                node = nodes.index_select(0, phase.updated)
                summed = message.new_zeros(len(phase.updated), self.hidden)
                message = summed.index_add_(0, phase.slots, message)  # side +1 first
            nodes.index_copy_(0, phase.updated, self._update(node, message))

    def _link_nodes(
        self,
        states: Tensor,
        inputs: ProcessInput,
        parts: _InputParts | None = None,
        relative: RelativeLinks | None = None,
    ) -> Tensor:
        """[..., C, L, NODE_DIM]: link features, is_pull, type (the latter and the turn into
        the reference frame from ``parts``, the links there from ``relative``, where
        given)."""
        if parts is None:
            into, tail = None, _link_tail(inputs, states.dtype)
        else:
            into, tail = parts.into, parts.link_tail
        features = link_features(states, inputs, into, relative)
        return torch.cat([features, tail.expand(*features.shape[:-1], 4)], -1)

    def _robot_node(self, inputs: ProcessInput) -> Tensor:
        """[..., NODE_DIM]: motion 6, cos/sin 2, zero parameters 4, CoM position 2, size 2 and
        gap 1, is_pull, type."""
        robot = robot_features(inputs)
        zeros = robot.new_zeros(*robot.shape[:-1], 9)
        return _node(torch.cat([robot[..., :8], zeros, robot[..., 8:9]], -1), _ROBOT)


# ---------------------------------------------------------------------------------------------
# Feed-forward baseline


class FeedForwardProcessNet(nn.Module):
    """The baseline: one 3-layer MLP over the concatenated features of a fixed number of links.

    Input per sigma point: the link features [17 L], robot features [9], joint frictions / scale
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
        out = self.f(features.to(self.f.dtype)).to(states.dtype)
        delta = out[..., :-2].unflatten(-1, (self.n_links, MOTION_DIM))
        return Prediction(
            pose=integrate(states, delta, inputs, dt_s),
            force_n=force_to_world(out[..., -2:], inputs),
            process_var=self.noise(inputs.tcp.shape[:-1], self.n_links).to(states.dtype),
        )


class FeedForwardByLinks(nn.Module):
    """One :class:`FeedForwardProcessNet` per link count; each prediction goes to the net of
    the states' link count, so the shape fit, not the skill, decides which net runs."""

    def __init__(self, link_counts: tuple[int, ...], hidden: int = 64) -> None:
        super().__init__()
        self.nets = nn.ModuleDict({str(n): FeedForwardProcessNet(n, hidden) for n in link_counts})

    def net(self, n_links: int) -> FeedForwardProcessNet:
        """The net for ``n_links`` links; ValueError when there is none."""
        if str(n_links) not in self.nets:
            raise ValueError(
                f"no feed-forward net for {n_links} link(s); there are nets for "
                f"{', '.join(self.nets)} link(s)"
            )
        net = self.nets[str(n_links)]
        assert isinstance(net, FeedForwardProcessNet)
        return net

    def forward(self, states: Tensor, inputs: ProcessInput, dt_s: float) -> Prediction:
        """states [..., C, 11 L - 1] -> the Prediction of the net for L links."""
        prediction: Prediction = self.net(layout_of(states).n_links)(states, inputs, dt_s)
        return prediction
