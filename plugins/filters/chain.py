"""Quasi-static pushing and pulling of a chain of links (welded or hinged), batched torch.

The analytical model of two or more links. Each link l slides on the table with the
ellipsoidal limit surface of :mod:`vistac.plugins.filters.analytical` about its CoM
(``f_max = f m g``, characteristic length ``c`` of its footprint box), so moving with twist
(v, omega) at its CoM dissipates ``P_l = f_max sqrt(|v|² + c² omega²)``; hinge k dissipates
``tau_k |omega_(k+1) - omega_k|`` with the joint friction ``tau_k = f_j_k`` (N m; a welded pair
is a hinge that never slips, ``f_j = 1``, paper 1 IV-A).

Minimum power. A quasi-static motion with the hinges held together and the pushed point moving
with the pusher is the one that dissipates the least power (Peshkin and Sanderson 1988; the
friction of a hinge is a convex, degree-one dissipation like the links'). The unknowns are
``z = (v_0, omega_0, delta_1 .. delta_(L-1))``: link 0's twist and each hinge's rate
``delta_k = omega_k - omega_(k-1)``; every twist is linear in z (:func:`chain_twist_map`).
The problem ``min sum_l P_l + sum_k tau_k |delta_k|`` subject to linear equality constraints
``A z = a`` is solved by Newton's method on the KKT system with a line search
(:func:`solve_chain`). Each norm and |delta| is smoothed by ``eta`` relative to the motion's
scale (:data:`SMOOTHING`): a hinge whose friction holds turns at about eta of the motion's
rate instead of not at all, and a link at rest is held by the part of its static friction
its smoothed wrench gives (:func:`friction_wrench`). Without the smoothing a held hinge's
fixed sign makes the problem unbounded and a link at rest stalls Newton's method.

Contact. A push constrains the contact point on the touched link (the link whose footprint
box the pad is nearest, :func:`vistac.plugins.filters.analytical.pad_contact`): sticking, it
moves with the pusher (two rows), and the pusher's force balances every link's friction
(hinges are internal). Outside the friction cone (coefficient mu_r) the contact slips: the
force lies on a cone edge ``d = n ± mu_r t``, which minimum power gives as the motion
minimising the power with ``d . v_contact = 1`` (one row), rescaled so that the contact's
normal speed is the pusher's. Both edges are solved; the one whose slip runs the way its
friction pulls is taken (if both or neither, the side the sticking force left the cone by;
a hinged chain, unlike one body, can have a sticking force that pulls; an edge whose motion
would move the contact point faster than MAX_SLIP_SPEEDUP times the pusher is not taken,
and the contact sticks). The flat pad's line
contact moves the contact point along the pad as in
:func:`vistac.plugins.filters.analytical.line_contact`, about the whole chain's centre of
friction ``sum_l f_max_l c_l / sum_l f_max_l``. A pull moves the grasped link's point
between the fingers with the gripper (two rows) and its rate with the gripper's (a third
row), or, with a grasp friction ``tau_g``, lets it turn between the fingers, dissipating
``tau_g |omega_k - omega_gripper|`` as one more hinge (:func:`pull_motion`). The finger force
is minus the sum of the links' friction forces.

For one link this is Lynch's solution (:func:`vistac.plugins.filters.analytical.
quasi_static_push` gives the same twist; ``tests/test_filters_chain.py``).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor
from vistac.plugins.filters.analytical import (
    Pressure,
    PushSettings,
    characteristic_length,
    line_contact,
    pad_contact,
)
from vistac.plugins.filters.nets import perp, rotate
from vistac.plugins.filters.state import GRAVITY_MPS2, ProcessInput, StateLayout

NEWTON_STEPS = 30
"""Newton iterations at most."""
NEWTON_TOLERANCE = 1e-8
"""A point of a batch is solved once its full Newton step is at most this in every entry of
z (about unit scale: the motion scaled to unit speed); quadratic convergence leaves it much
closer than that to the minimum. A point is also left where it is once the line search takes
no step: every later iteration would repeat that one."""
STEP_SIZES = (*(0.5**k for k in range(0, 16, 2)), 0.0)
"""Line search: the step of these fractions of the Newton step that lowers the power most
(0: none does, stay)."""
SMOOTHING = 1e-3
"""eta: each link's norm is sqrt(|.|² + eta²), the motion scaled to unit speed. A link
slower than about eta (at rest while the hinge turns) is held by part of its static
friction, as its smoothed wrench says; Newton's method converges there only with a smooth
enough norm (1e-6 stalled on links at rest)."""
MAX_SLIP_SPEEDUP = 5.0
"""A slipping contact whose point would move faster than this many times the pusher (an
edge nearly along the contact's motion, met by a degenerate chain of sigma points: one
such step threw a belief kilometres away) is taken as sticking instead."""
_TINY = 1e-12
_ARM_M = 0.05
"""A link's size (m), turning a rate into a speed: for a pull's scale and the hinges'
smoothing."""


class ChainProblem(NamedTuple):
    """A minimum-power problem over z [..., n] (n = 3 + L - 1), batch shape [...].

    twist_map: [..., L, 3, n] (v_x, v_y, omega of each link's CoM) = twist_map @ z;
    char_length_m: [..., L] each link's c; f_max_n: [..., L]; joint_friction_nm: [..., L - 1];
    rows: [..., 3, n] constraint rows A; target: [..., 3] a; used: [..., 3] bool, which rows
    constrain (unused rows are ignored).
    """

    twist_map: Tensor
    char_length_m: Tensor
    f_max_n: Tensor
    joint_friction_nm: Tensor
    rows: Tensor
    target: Tensor
    used: Tensor
    grasp_row: Tensor | None = None
    """[..., n]: the grasped link's rate, for a grasp that lets the link turn between the
    fingers (a hinge to the gripper); None: no such grasp."""
    grasp_rate: Tensor | None = None
    """[...]: the gripper's rate, in z's units."""
    grasp_friction_nm: Tensor | None = None
    """[...]: the torque the grasp holds before the link turns in it."""


_CHAIN = ChainProblem._fields[:7]
"""The fields of a chain and its constraints (a push has no grasp)."""


def chain_twist_map(com_m: Tensor, joints_m: Tensor) -> Tensor:
    """The map [..., L, 3, n] from z to each link's twist at its CoM.

    com_m: [..., L, 2] world CoMs; joints_m: [..., L - 1, 2] world hinge points. Hinge k
    joins links k and k + 1 and moves with both: ``v_(k+1) = v_k + omega_k perp(J_k - c_k) -
    omega_(k+1) perp(J_k - c_(k+1))``; ``omega_(k+1) = omega_k + delta_(k+1)``.
    """
    n_links = com_m.shape[-2]
    n = 3 + n_links - 1
    eye = torch.eye(n, dtype=com_m.dtype).expand(*com_m.shape[:-2], n, n)
    velocity, omega = eye[..., :2, :], eye[..., 2, :]
    maps = [torch.cat([velocity, omega.unsqueeze(-2)], -2)]
    for k in range(n_links - 1):
        joint = joints_m[..., k, :]
        next_omega = omega + eye[..., 3 + k, :]
        lever_k = perp(joint - com_m[..., k, :]).unsqueeze(-1)
        lever_next = perp(joint - com_m[..., k + 1, :]).unsqueeze(-1)
        velocity = velocity + lever_k * omega.unsqueeze(-2) - lever_next * next_omega.unsqueeze(-2)
        omega = next_omega
        maps.append(torch.cat([velocity, omega.unsqueeze(-2)], -2))
    return torch.stack(maps, -3)


def point_velocity_rows(twist_map: Tensor, com_m: Tensor, point_m: Tensor) -> Tensor:
    """Rows [..., 2, n] giving the velocity of a world point [..., 2] on a link whose map is
    twist_map [..., 3, n] and CoM com_m [..., 2]."""
    lever = perp(point_m - com_m).unsqueeze(-1)
    return twist_map[..., :2, :] + lever * twist_map[..., 2:3, :]


def link_twists(problem: ChainProblem, z: Tensor) -> Tensor:
    """Twists [..., L, 3] (v_x, v_y, omega at each CoM) of z [..., n]."""
    return (problem.twist_map @ z[..., None, :, None])[..., 0]


def _scaled(problem: ChainProblem, z: Tensor) -> Tensor:
    """(v_x, v_y, c omega) of each link [..., L, 3]: the limit surface's unit ball."""
    twist = link_twists(problem, z)
    return torch.cat([twist[..., :2], problem.char_length_m.unsqueeze(-1) * twist[..., 2:]], -1)


def _turns(problem: ChainProblem, z: Tensor, eta: float) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The rotational dissipations of z [..., n]: each hinge's rate delta_k and, with a turning
    grasp, the grasped link's rate relative to the gripper. Returns (rows [..., m, n] giving
    each rate from z, the rates [..., m], their magnitudes smoothed by eta / 5 cm, the
    frictions [..., m] in N m)."""
    n_joints = problem.joint_friction_nm.shape[-1]
    rows = torch.eye(z.shape[-1], dtype=z.dtype)[3 : 3 + n_joints].expand(*z.shape[:-1], -1, -1)
    offset, friction = torch.zeros_like(z[..., 3:]), problem.joint_friction_nm
    row, rate, held = problem.grasp_row, problem.grasp_rate, problem.grasp_friction_nm
    if row is not None and rate is not None and held is not None:
        rows = torch.cat([rows, row.unsqueeze(-2).expand(*z.shape[:-1], 1, -1)], -2)
        offset = torch.cat([offset, rate.unsqueeze(-1).expand_as(z[..., :1])], -1)
        friction = torch.cat([friction, held.unsqueeze(-1)], -1)
    turn = (rows @ z.unsqueeze(-1))[..., 0] - offset
    return rows, turn, torch.sqrt(turn * turn + (eta / _ARM_M) ** 2), friction


def power(problem: ChainProblem, z: Tensor, eta: float = SMOOTHING) -> Tensor:
    """The smoothed dissipated power [...] of z [..., n] (each link's norm smoothed by eta,
    each hinge's and the grasp's rate by eta / 5 cm)."""
    _, turn, _, friction = _turns(problem, z, eta)
    return _dissipation(problem, _scaled(problem, z), turn, friction, eta)


def _dissipation(
    problem: ChainProblem, scaled: Tensor, turn: Tensor, friction: Tensor, eta: float
) -> Tensor:
    """The smoothed power [...] of links moving with ``_scaled`` twists [..., L, 3] and of
    rates turn [..., m] against friction [..., m] (see ``_turns``)."""
    norm = torch.sqrt((scaled * scaled).sum(-1) + eta * eta)
    magnitude = torch.sqrt(turn * turn + (eta / _ARM_M) ** 2)
    return (problem.f_max_n * norm).sum(-1) + (friction * magnitude).sum(-1)


def _powers_along(
    problem: ChainProblem, z: Tensor, step: Tensor, fractions: Tensor, eta: float
) -> Tensor:
    """The power [S, B] of z + f step (z, step [B, n]) for each of fractions [S]: the twists
    and the rates are linear in z, so each is worked out for z and for the step once."""
    rows, turn, _, friction = _turns(problem, z, eta)
    along = fractions.reshape(-1, 1, 1)
    scaled = _scaled(problem, z) + along.unsqueeze(-1) * _scaled(problem, step)
    turns = turn + along * (rows @ step.unsqueeze(-1))[..., 0]
    return _dissipation(problem, scaled, turns, friction, eta)


def _gradient_hessian(problem: ChainProblem, z: Tensor, eta: float) -> tuple[Tensor, Tensor]:
    """Gradient [..., n] and Hessian [..., n, n] of :func:`power`."""
    c = problem.char_length_m.unsqueeze(-1).unsqueeze(-1)
    scaled_map = torch.cat([problem.twist_map[..., :2, :], c * problem.twist_map[..., 2:, :]], -2)
    scaled = (scaled_map @ z[..., None, :, None])[..., 0]  # [..., L, 3]
    norm = torch.sqrt((scaled * scaled).sum(-1) + eta * eta)  # [..., L]
    unit = scaled / norm.unsqueeze(-1)
    weight = problem.f_max_n.unsqueeze(-1)
    gradient = (scaled_map.transpose(-1, -2) @ (weight * unit).unsqueeze(-1))[..., 0].sum(-2)
    eye = torch.eye(3, dtype=z.dtype)
    curvature = (eye - unit.unsqueeze(-1) * unit.unsqueeze(-2)) * (
        problem.f_max_n / norm
    )[..., None, None]
    hessian = (scaled_map.transpose(-1, -2) @ curvature @ scaled_map).sum(-3)
    rows, turn, magnitude, friction = _turns(problem, z, eta)
    slope = friction * turn / magnitude
    bend = friction * (1.0 - (turn / magnitude) ** 2) / magnitude
    gradient = gradient + (rows.transpose(-1, -2) @ slope.unsqueeze(-1))[..., 0]
    hessian = hessian + rows.transpose(-1, -2) @ (bend.unsqueeze(-1) * rows)
    return gradient, hessian


_POINT_DIMS = (3, 1, 1, 1, 2, 1, 1, 1, 0, 0)
"""The dimensions of each ChainProblem field after its batch dimensions."""


def _points(problem: ChainProblem) -> tuple[ChainProblem, tuple[int, ...]]:
    """The problem with every field broadcast to the batch shape and flattened to one point
    per row [B, ...], and the batch shape."""
    present = [
        (index, field, field.shape[field.dim() - dims :])
        for index, (field, dims) in enumerate(zip(problem, _POINT_DIMS, strict=True))
        if field is not None
    ]
    batch = torch.broadcast_shapes(*(f.shape[: f.dim() - len(per)] for _, f, per in present))
    flat: list[Tensor | None] = [None] * len(problem)
    for index, field, per in present:
        flat[index] = field.expand(*batch, *per).reshape(math.prod(batch), *per)
    return ChainProblem._make(flat), tuple(batch)


def _take(problem: ChainProblem, index: Tensor) -> ChainProblem:
    """The points ``index`` [k] of a flattened problem (see ``_points``)."""
    return ChainProblem._make(None if field is None else field[index] for field in problem)


class _Constraints(NamedTuple):
    """The equality constraints of flattened points as the KKT system takes them: rows
    [B, 3, n] (unused ones zero), target [B, 3] (unused ones zero) and unused [B, 3, 3] (the
    identity on the unused rows, so that the system stays regular)."""

    rows: Tensor
    target: Tensor
    unused: Tensor

    @classmethod
    def of(cls, points: ChainProblem) -> _Constraints:
        used = points.used
        rows = torch.where(used.unsqueeze(-1), points.rows, 0.0)
        return cls(
            rows, torch.where(used, points.target, 0.0), torch.diag_embed((~used).to(rows.dtype))
        )

    def take(self, index: Tensor) -> _Constraints:
        return _Constraints(*(field[index] for field in self))

    def newton_step(self, z: Tensor, gradient: Tensor, hessian: Tensor) -> Tensor:
        """The step [B, n] from z [B, n] that solves the KKT system of the quadratic model
        (gradient [B, n], hessian [B, n, n]) and the constraints."""
        residual = self.target - (self.rows @ z.unsqueeze(-1))[..., 0]
        upper = torch.cat([hessian, self.rows.transpose(-1, -2)], -1)
        kkt = torch.cat([upper, torch.cat([self.rows, self.unused], -1)], -2)
        return torch.linalg.solve(kkt, torch.cat([-gradient, residual], -1))[..., : z.shape[-1]]


def solve_chain(problem: ChainProblem, eta: float = SMOOTHING) -> Tensor:
    """The minimum-power z [..., n] with A z = a (see the module docstring): Newton's method
    on the KKT system from the feasible point nearest 0, each step the one of STEP_SIZES that
    lowers the power most, until every point of the batch is solved (NEWTON_TOLERANCE, at
    most NEWTON_STEPS steps). A solved point leaves the batch, so its result does not depend
    on the other points, and the iterations that only a few points need cost little."""
    points, batch = _points(problem)
    constraints = _Constraints.of(points)
    n = constraints.rows.shape[-1]
    fractions = torch.tensor(STEP_SIZES, dtype=constraints.rows.dtype)
    zero = torch.zeros_like(constraints.rows[:, 0, :])
    z = constraints.newton_step(zero, zero, torch.diag_embed(torch.ones_like(zero)))
    active, moving = torch.arange(len(z)), z
    for _ in range(NEWTON_STEPS):
        gradient, hessian = _gradient_hessian(points, moving, eta)
        hessian = hessian + _TINY * torch.eye(n, dtype=z.dtype)
        step = constraints.newton_step(moving, gradient, hessian)
        best = _powers_along(points, moving, step, fractions, eta).argmin(0)
        moving = moving + fractions[best].unsqueeze(-1) * step  # the last fraction 0: stay
        solved = (best == len(STEP_SIZES) - 1) | (step.abs().amax(-1) <= NEWTON_TOLERANCE)
        if bool(solved.any()):
            z = z.index_copy(0, active, moving)
            left = torch.nonzero(~solved)[:, 0]
            active, moving = active[left], moving[left]
            points, constraints = _take(points, left), constraints.take(left)
            if not len(active):
                break
    return z.index_copy(0, active, moving).reshape(*batch, n)


def friction_wrench(problem: ChainProblem, z: Tensor, eta: float = SMOOTHING) -> Tensor:
    """The table friction's resistance [..., L, 3] (force x, y in N, moment in N m) to each
    link's motion z [..., n] (scaled to about unit speed): the point of its limit surface
    for the twist, of the smoothed norm, so that a link at rest gets the static friction that
    holds it."""
    scaled = _scaled(problem, z)
    norm = torch.sqrt((scaled * scaled).sum(-1, keepdim=True) + eta * eta)
    unit = scaled / norm
    f_max = problem.f_max_n.unsqueeze(-1)
    moment = f_max * problem.char_length_m.unsqueeze(-1) * unit[..., 2:]
    return torch.cat([f_max * unit[..., :2], moment], -1)


def facing_hinge_offsets(inputs: ProcessInput) -> Tensor:
    """Position of each hinge k in the frame of link k: [..., L - 1, 2] (m).

    Midway between the point of link k's footprint box nearest link k + 1's centre and the
    point of link k + 1's box nearest link k's centre, placed with the initial relative pose
    ``link_offset``: the middle of the facing sides for boxes side by side, whichever of its
    symmetric axes a fitted box's frame took; ``hinge_m`` where given.
    """
    if inputs.hinge_m is not None:
        return inputs.hinge_m
    offset, size = inputs.link_offset, inputs.link_size_m
    parent, child = offset[..., :-1, :], offset[..., 1:, :]
    parent_size, child_size = size[..., :-1, :], size[..., 1:, :]
    rel_xy = rotate(child[..., :2] - parent[..., :2], -parent[..., 2])
    rel_theta = child[..., 2] - parent[..., 2]
    parent_near = torch.maximum(torch.minimum(rel_xy, parent_size), -parent_size)
    parent_in_child = rotate(-rel_xy, -rel_theta)
    child_near = torch.maximum(torch.minimum(parent_in_child, child_size), -child_size)
    return 0.5 * (parent_near + rel_xy + rotate(child_near, rel_theta))


def _pick(values: Tensor, index: Tensor) -> Tensor:
    """values [..., C, L, *rest] at link index [..., C] -> [..., C, *rest]."""
    rest = values.shape[index.dim() + 1 :]
    gather_index = index.reshape(*index.shape, 1, *([1] * len(rest)))
    gather_index = gather_index.expand(*index.shape, 1, *rest)
    return values.gather(index.dim(), gather_index).squeeze(index.dim())


def _constraints(rows: Tensor, target: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Rows [..., r, n] and target [..., r] padded to three rows, and the used mask [..., 3]."""
    missing = 3 - rows.shape[-2]
    rows = torch.cat([rows, rows.new_zeros(*rows.shape[:-2], missing, rows.shape[-1])], -2)
    target = torch.cat([target, target.new_zeros(*target.shape[:-1], missing)], -1)
    used = (torch.arange(3) < 3 - missing).expand_as(target)
    return rows, target, used


class Motion(NamedTuple):
    """A chain's quasi-static motion: z [..., n] (m/s, rad/s) and the friction wrench
    [..., L, 3] of each link (:func:`friction_wrench`); their forces sum to the force of the
    pusher or gripper on the chain."""

    z: Tensor
    wrench: Tensor


def push_motion(
    links: ChainProblem, contact_rows: Tensor, normal: Tensor, velocity_mps: Tensor, mu: float
) -> Motion:
    """The quasi-static motion of a push (see the module docstring).

    links: the chain (its constraint fields are replaced); contact_rows: [..., 2, n] velocity
    of the contact point; normal: [..., 2] unit, into the link; velocity_mps: [..., 2] the
    pusher's, moving into the link; mu: pusher friction coefficient.
    """
    speed = velocity_mps.norm(dim=-1, keepdim=True) + _TINY
    stick = solve_chain(links._replace(**_fields(contact_rows, velocity_mps / speed)))
    wrench = friction_wrench(links, stick)
    force = wrench[..., :2].sum(-2)
    tangent = perp(normal)
    normal_force, tangent_force = (force * normal).sum(-1), (force * tangent).sum(-1)
    slipping = tangent_force.abs() > mu * normal_force
    if not bool(slipping.any()):
        return Motion(stick * speed, wrench)
    # Both cone edges at once ([2, ...]); the slip must run the way its friction pulls.
    side = torch.tensor([1.0, -1.0], dtype=stick.dtype).reshape(2, *([1] * normal.dim()))
    edge = normal + side * mu * tangent
    edge_row = edge.unsqueeze(-2) @ contact_rows
    both = ChainProblem(
        *(getattr(links, name).expand(2, *getattr(links, name).shape) for name in _CHAIN)
    )
    slide = solve_chain(both._replace(**_fields(edge_row, torch.ones_like(edge[..., :1]))))
    contact_velocity = (contact_rows @ slide.unsqueeze(-1))[..., 0]
    wanted = (velocity_mps * normal).sum(-1)
    scale = (wanted / (contact_velocity * normal).sum(-1).clamp(min=_TINY)).unsqueeze(-1)
    slip = ((velocity_mps - contact_velocity * scale) * tangent).sum(-1)
    bounded = (contact_velocity * scale).norm(dim=-1) <= MAX_SLIP_SPEEDUP * speed[..., 0]
    consistent = (slip * side[..., 0] > 0.0) & bounded  # [2, ...]
    by_force = (tangent_force < 0.0).long()  # the edge the sticking force left by
    choice = torch.where(consistent[0] ^ consistent[1], consistent[1].long(), by_force)
    z_slide = _choose(slide * scale, choice)
    wrench_slide = _choose(friction_wrench(both, slide).flatten(-2), choice).unflatten(-1, (-1, 3))
    slipping = (slipping & _choose(bounded.unsqueeze(-1), choice)[..., 0]).unsqueeze(-1)
    return Motion(
        torch.where(slipping, z_slide, stick * speed),
        torch.where(slipping.unsqueeze(-1), wrench_slide, wrench),
    )


def _choose(values: Tensor, choice: Tensor) -> Tensor:
    """values [2, ..., k] at the first index choice [...] (0 or 1) -> [..., k]."""
    index = choice.reshape(1, *choice.shape, 1).expand(1, *values.shape[1:])
    return values.gather(0, index)[0]


def pull_motion(
    links: ChainProblem,
    held_map: Tensor,
    grasp_rows: Tensor,
    twist: Tensor,
    grasp_friction_nm: float | None,
) -> Motion:
    """The motion of the chain when the gripper, moving with twist [..., 3] (v_x, v_y at the
    grasp point, omega), holds one link: held_map [..., 3, n] is that link's map and
    grasp_rows [..., 2, n] give the velocity of its point between the fingers. A rigid grasp
    (grasp_friction_nm None) moves the link with the gripper; otherwise the link may turn
    between the fingers, a hinge to the gripper with that friction."""
    scale = twist[..., :2].norm(dim=-1, keepdim=True) + twist[..., 2:].abs() * _ARM_M + _TINY
    unit = twist / scale
    if grasp_friction_nm is None:
        rows = torch.cat([grasp_rows, held_map[..., 2:, :]], -2)
        problem = links._replace(**_fields(rows, unit))
    else:
        problem = links._replace(
            **_fields(grasp_rows, unit[..., :2]),
            grasp_row=held_map[..., 2, :],
            grasp_rate=unit[..., 2],
            grasp_friction_nm=torch.full_like(unit[..., 2], grasp_friction_nm),
        )
    z = solve_chain(problem)
    return Motion(z * scale, friction_wrench(links, z))


def _fields(rows: Tensor, target: Tensor) -> dict[str, Tensor]:
    padded_rows, padded_target, used = _constraints(rows, target)
    return {"rows": padded_rows, "target": padded_target, "used": used}


def chain_links(
    states: Tensor, inputs: ProcessInput, pressure: Pressure = "uniform"
) -> tuple[ChainProblem, Tensor]:
    """The chain of states [..., C, 11 L - 1] (no constraints yet; each link's limit surface
    under the ``pressure`` model) and its world CoMs [..., C, L, 2]."""
    layout = StateLayout((states.shape[-1] + 1) // 11)
    pose, params = layout.link_pose(states), layout.link_parameters(states)
    theta, com_link = pose[..., 2], params[..., 2:]
    com = pose[..., :2] + rotate(com_link, theta)
    hinges = rotate(facing_hinge_offsets(inputs).unsqueeze(-3), theta[..., :-1])
    twist_map = chain_twist_map(com, pose[..., :-1, :2] + hinges)
    none = twist_map.new_zeros(*twist_map.shape[:-3], 3, twist_map.shape[-1])
    links = ChainProblem(
        twist_map=twist_map,
        char_length_m=characteristic_length(pressure)(
            inputs.link_size_m.unsqueeze(-3), com_link
        ),
        f_max_n=(params[..., 0] * params[..., 1]).clamp(min=0.0) * GRAVITY_MPS2 + _TINY,
        joint_friction_nm=layout.joint_friction(states).clamp(min=0.0),
        rows=none,
        target=none[..., 0],
        used=none[..., 0].bool(),
    )
    return links, com


class _Contact(NamedTuple):
    """The pad's contact with its nearest link, world frame (batch [..., C])."""

    rows: Tensor  # [..., C, 2, n] velocity of the contact point
    normal: Tensor  # [..., C, 2] into the link
    velocity_mps: Tensor  # [..., C, 2] the pad's
    active: Tensor  # bool [..., C]: touching and moving into the link


def _push_contact(
    links: ChainProblem, pose: Tensor, com_m: Tensor, inputs: ProcessInput, settings: PushSettings
) -> _Contact:
    """The pad's contact (:func:`pad_contact`) on the link whose box it is nearest, its point
    moved along the flat pad about the chain's centre of friction (:func:`line_contact`)."""
    half = inputs.link_size_m.unsqueeze(-3).expand_as(com_m)
    pad = pad_contact(
        inputs.tcp[..., None, None, :], inputs.pd_rad[..., None, None], pose[..., :3], half,
        settings,
    )
    link = pad.gap_m.argmin(-1)
    link_pose = _pick(pose, link)
    weight = links.f_max_n.unsqueeze(-1)
    centre = (weight * com_m).sum(-2) / weight.sum(-2)
    normal = _pick(pad.normal, link)
    point = line_contact(
        _pick(pad.point_m, link),
        normal,
        _pick(pad.velocity_mps, link),
        rotate(centre - link_pose[..., :2], -link_pose[..., 2]),
        _pick(half, link),
        settings.pad_half_width_m,
    )
    point_world = link_pose[..., :2] + rotate(point, link_pose[..., 2])
    normal = rotate(normal, link_pose[..., 2])
    velocity = rotate(_pick(pad.velocity_mps, link), link_pose[..., 2])
    rows = point_velocity_rows(_pick(links.twist_map, link), _pick(com_m, link), point_world)
    touching = _pick(pad.gap_m, link) <= settings.contact_margin_m
    into = (velocity * normal).sum(-1) > 0.0
    return _Contact(rows, normal, velocity, touching & into)


def chain_step(
    states: Tensor, inputs: ProcessInput, dt_s: float, settings: PushSettings
) -> tuple[Tensor, Tensor]:
    """One step of a chain of L >= 1 links pushed or pulled quasi-statically.

    states: [..., C, 11 L - 1]. Returns (next time-varying block [..., C, 6 L], force of the
    object on the fingers [..., C, 2]), world frame. Each link's CoM moves by v dt and the link
    turns by omega dt about it.
    """
    layout = StateLayout((states.shape[-1] + 1) // 11)
    pose, com_link = layout.link_pose(states), layout.link_parameters(states)[..., 2:]
    links, com = chain_links(states, inputs, settings.pressure)
    pulling = (inputs.is_pull > 0.5).unsqueeze(-1).expand_as(com[..., 0, 0])
    z = torch.zeros_like(links.rows[..., 0, :])
    wrench = torch.zeros_like(links.twist_map[..., 0])
    if bool((~pulling).any()):
        contact = _push_contact(links, pose, com, inputs, settings)
        push = push_motion(
            links, contact.rows, contact.normal, contact.velocity_mps, settings.pusher_friction
        )
        pushed = contact.active & ~pulling
        z = torch.where(pushed.unsqueeze(-1), push.z, z)
        wrench = torch.where(pushed[..., None, None], push.wrench, wrench)
    if bool(pulling.any()):
        held = inputs.link.unsqueeze(-1).expand_as(pulling)
        held_map = _pick(links.twist_map, held)
        tcp = inputs.tcp.unsqueeze(-2).expand(*pulling.shape, 6)
        grasp_rows = point_velocity_rows(held_map, _pick(com, held), tcp[..., :2])
        gripper = tcp[..., 3:]  # the TCP's velocity (between the fingers) and rate
        pull = pull_motion(links, held_map, grasp_rows, gripper, settings.grasp_friction_nm)
        z = torch.where(pulling.unsqueeze(-1), pull.z, z)
        wrench = torch.where(pulling[..., None, None], pull.wrench, wrench)

    twist = link_twists(links, z)
    force = -wrench[..., :2].sum(-2)
    theta = pose[..., 2]
    next_theta = theta + twist[..., 2] * dt_s
    com_offset = rotate(com_link, next_theta)
    next_xy = com + twist[..., :2] * dt_s - com_offset
    origin_velocity = twist[..., :2] - twist[..., 2:] * perp(com_offset)
    next_pose = torch.cat([next_xy, next_theta.unsqueeze(-1), origin_velocity, twist[..., 2:]], -1)
    return next_pose.flatten(-2), force
