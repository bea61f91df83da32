"""Quasi-static pushing of one homogeneous link (Lynch, Maekawa and Tanie 1992), batched torch.

Limit surface. The table friction of a link of mass m and friction coefficient f is
approximated by the ellipsoid ``(fx² + fy²) / f_max² + M² / m_max² = 1`` about the CoM with
``f_max = f m g`` and ``m_max = c f_max``. The characteristic length ``c`` is the mean distance
of a footprint point from the CoM, weighted by the pressure on the table: uniform over the
fitted footprint box (half extents a1, a2; exact, :func:`characteristic_length_m`) or linear
with its centre under the CoM, as a rigid link presses an elastic table
(:func:`linear_pressure_length_m`; uniform pressure puts its centre at the box's centre, not
under an offset CoM). A twist (v, omega) at the CoM is produced by the wrench normal to the
ellipsoid, so with ``q = perp(contact)`` (omega x r = omega q) a point force F at the contact
gives ``v = k F, omega = k (q . F) / c²`` for some k >= 0.

Contact. The pusher moves with velocity u at the contact (inward normal n, friction
coefficient mu_r). Sticking: the contact point moves with the pusher, ``k A F = u`` with
``A = I + q q^T / c²``; valid while F lies inside the friction cone (equivalently, u inside the
motion cone). Otherwise the contact slips and F lies on the cone edge ``n ± mu_r t`` on the side
where the sticking force left the cone (A is positive definite, so it maps cone sides onto
motion-cone sides), with k set by the normal constraint ``n . v_contact = n . u``. A pusher
moving out of the surface (``u . n <= 0``) does not move the object.

The force of the pusher is the point of the limit surface for the resulting twist
(:func:`limit_surface_force`); the tactile force is its negative.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal, NamedTuple

import torch
from torch import Tensor
from vistac.plugins.filters.nets import box_gap_m, perp, rotate
from vistac.plugins.filters.state import GRAVITY_MPS2, Prediction, ProcessInput, StateLayout

_TINY = 1e-12
Pressure = Literal["uniform", "linear"]


class PushSolution(NamedTuple):
    """Quasi-static motion of a pushed object (all vectors in the frame of the inputs).

    velocity_mps: [..., 2] CoM velocity; omega_radps: [...]; force_n: [..., 2] force of the
    pusher on the object; sticking: [...] bool (False also when there is no push).
    """

    velocity_mps: Tensor
    omega_radps: Tensor
    force_n: Tensor
    sticking: Tensor


def _dot(a: Tensor, b: Tensor) -> Tensor:
    return (a * b).sum(-1)


def _corner_integral(a_m: Tensor, b_m: Tensor) -> Tensor:
    """∫0^a ∫0^b sqrt(x² + y²) dy dx (m³) for a, b >= 0."""
    a, b = a_m.clamp(min=_TINY), b_m.clamp(min=_TINY)
    d = torch.sqrt(a * a + b * b)
    return (2.0 * a * b * d + a**3 * torch.asinh(b / a) + b**3 * torch.asinh(a / b)) / 6.0


def characteristic_length_m(half_extents_m: Tensor, com_m: Tensor) -> Tensor:
    """Mean distance from the CoM of a point of the footprint box under uniform pressure.

    half_extents_m: [..., 2] (a1, a2); com_m: [..., 2] CoM in the box frame (inside the box).
    Returns c [...] (m): the box is split at the CoM into four rectangles with a corner there.
    """
    a1, a2 = half_extents_m[..., 0], half_extents_m[..., 1]
    cx, cy = com_m[..., 0], com_m[..., 1]
    total = sum(
        _corner_integral(a1 + sx * cx, a2 + sy * cy) for sx in (-1.0, 1.0) for sy in (-1.0, 1.0)
    )
    return total / (4.0 * a1 * a2)


_QUADRATURE = 12
"""Midpoints per axis of the footprint box in :func:`linear_pressure_length_m`."""
_PRESSURE_ITERATIONS = 6
_MAX_CENTRE = 0.8
"""The pressure's centre is kept within this fraction of the box's half extents (a CoM
nearer a side than the quadrature resolves); distances are still taken from the CoM."""
_RIDGE = 1e-3


def linear_pressure_length_m(half_extents_m: Tensor, com_m: Tensor) -> Tensor:
    """Mean distance from the CoM of a footprint point weighted by a linear pressure.

    A rigid link on an elastic table presses it with ``p = max(0, 1 + g . u)`` (u: the point
    in box units, -1..1), and the pressure's centre lies under the CoM; g is found by Newton's
    method from ``g = 3 com / a``, exact where no part lifts off. A CoM off the centre puts
    the pressure near it, so the link turns about it more easily than under uniform pressure.
    half_extents_m: [..., 2]; com_m: [..., 2] in the box frame (inside). Returns c [...] (m).
    """
    ticks = (torch.arange(_QUADRATURE, dtype=com_m.dtype) + 0.5) * (2.0 / _QUADRATURE) - 1.0
    unit = torch.stack(torch.meshgrid(ticks, ticks, indexing="ij"), -1).reshape(-1, 2)  # [Q, 2]
    half = half_extents_m.clamp(min=_TINY)
    target = (com_m / half).clamp(-_MAX_CENTRE, _MAX_CENTRE)
    slope = 3.0 * target
    for _ in range(_PRESSURE_ITERATIONS):  # Newton on centre(slope) = target
        raw = 1.0 + _dot(unit, slope.unsqueeze(-2))  # [..., Q]
        pressure, active = raw.clamp(min=0.0), (raw > 0.0).to(raw.dtype)
        total = pressure.sum(-1)[..., None]  # [..., 1]
        centre = (pressure.unsqueeze(-1) * unit).sum(-2) / total
        moment = torch.einsum("...q,qi,qj->...ij", active, unit, unit)
        spread = (active.unsqueeze(-1) * unit).sum(-2)  # [..., 2]
        jacobian = (moment - centre.unsqueeze(-1) * spread.unsqueeze(-2)) / total[..., None]
        jacobian = jacobian + _RIDGE * torch.eye(2, dtype=raw.dtype)
        step = torch.linalg.solve(jacobian, (target - centre).unsqueeze(-1))[..., 0]
        slope = slope + step
    pressure = (1.0 + _dot(unit, slope.unsqueeze(-2))).clamp(min=0.0)
    distance = torch.linalg.norm(unit * half.unsqueeze(-2) - com_m.unsqueeze(-2), dim=-1)
    return (pressure * distance).sum(-1) / pressure.sum(-1).clamp(min=_TINY)


def characteristic_length(pressure: Pressure) -> Callable[[Tensor, Tensor], Tensor]:
    """The characteristic length of the limit surface under a ``pressure`` model."""
    return linear_pressure_length_m if pressure == "linear" else characteristic_length_m


def limit_surface_force(
    velocity_mps: Tensor, omega_radps: Tensor, f_max_n: Tensor, c_m: Tensor
) -> Tensor:
    """Force [..., 2] of the wrench on the ellipsoidal limit surface that moves the object with
    CoM twist (velocity [..., 2], omega [...]): ``f_max v / sqrt(|v|² + c² omega²)``; zero for
    a still object."""
    norm_sq = _dot(velocity_mps, velocity_mps) + (c_m * omega_radps) ** 2
    moving = norm_sq > _TINY**2
    scale = f_max_n / torch.sqrt(torch.where(moving, norm_sq, torch.ones_like(norm_sq)))
    return torch.where(moving.unsqueeze(-1), scale.unsqueeze(-1) * velocity_mps, 0.0)


def quasi_static_push(
    contact_m: Tensor,
    normal: Tensor,
    pusher_velocity_mps: Tensor,
    f_max_n: Tensor,
    c_m: Tensor,
    pusher_friction: float | Tensor,
) -> PushSolution:
    """Object twist at the CoM for a point push (see the module docstring).

    contact_m: [..., 2] contact point relative to the CoM; normal: [..., 2] unit normal into
    the object; pusher_velocity_mps: [..., 2]; f_max_n: [...] = f m g; c_m: [...] limit-surface
    characteristic length (m_max = c f_max); pusher_friction: mu_r (scalar or [...]).
    """
    mu = torch.as_tensor(pusher_friction, dtype=contact_m.dtype)
    q = perp(contact_m)
    tangent = perp(normal)
    c_sq = (c_m * c_m).unsqueeze(-1)
    u = pusher_velocity_mps
    # Sticking: v = k F = A^-1 u (Sherman-Morrison).
    stick_v = u - q * _dot(q, u).unsqueeze(-1) / (c_sq + _dot(q, q).unsqueeze(-1))
    normal_part, tangent_part = _dot(stick_v, normal), _dot(stick_v, tangent)
    sticking = tangent_part.abs() <= mu * normal_part
    side = torch.where(tangent_part >= 0.0, 1.0, -1.0).to(u.dtype)
    edge = normal + (side * mu).unsqueeze(-1) * tangent
    edge_normal_speed = _dot(normal, edge) + _dot(q, normal) * _dot(q, edge) / c_sq[..., 0]
    k = _dot(u, normal) / edge_normal_speed.clamp(min=_TINY)
    velocity = torch.where(sticking.unsqueeze(-1), stick_v, k.unsqueeze(-1) * edge)
    pushing = _dot(u, normal) > 0.0
    velocity = torch.where(pushing.unsqueeze(-1), velocity, 0.0)
    omega = _dot(q, velocity) / c_sq[..., 0]
    return PushSolution(
        velocity_mps=velocity,
        omega_radps=omega,
        force_n=limit_surface_force(velocity, omega, f_max_n, c_m),
        sticking=sticking & pushing,
    )


def line_contact(
    point_m: Tensor,
    normal: Tensor,
    pusher_velocity_mps: Tensor,
    com_m: Tensor,
    half_extents_m: Tensor,
    pad_half_width_m: float,
) -> Tensor:
    """Resultant contact point of a flat pad pressed against a box side (box frame).

    The pad touches the side along the segment ``point + s t`` (``t = perp(normal)``) with
    ``|s| <= pad_half_width_m``, cut to the side's extent. Its pressure resultant can act anywhere
    on that segment, so the object translates without turning when the line through the CoM
    along the pusher velocity meets the segment, at ``s* = -cross(point - com, u) /
    cross(t, u)``; otherwise it turns about the segment's end nearest that line. Returns the
    point ``point + clamp(s*) t`` [..., 2] for the point-contact solution (a line contact of
    width 0 gives ``point``). Lynch's point model alone turns offset pushes about twice as fast
    as the simulator's flat pad does.
    """
    if pad_half_width_m <= 0.0:
        return point_m
    tangent = perp(normal)
    relative = point_m - com_m
    u = pusher_velocity_mps
    cross_tu = tangent[..., 0] * u[..., 1] - tangent[..., 1] * u[..., 0]
    cross_pu = relative[..., 0] * u[..., 1] - relative[..., 1] * u[..., 0]
    safe = torch.where(cross_tu.abs() > _TINY, cross_tu, torch.full_like(cross_tu, _TINY))
    target = -cross_pu / safe
    along = _dot(point_m, tangent)
    side_half_m = _dot(half_extents_m, tangent.abs())
    low = torch.maximum(torch.full_like(along, -pad_half_width_m), -side_half_m - along)
    high = torch.minimum(torch.full_like(along, pad_half_width_m), side_half_m - along)
    high = torch.maximum(high, low)
    s = torch.minimum(torch.maximum(target, low), high)
    return point_m + s.unsqueeze(-1) * tangent


def box_contact(point_m: Tensor, half_extents_m: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Where a point touches an axis-aligned box centred at the origin.

    point_m: [..., 2]; half_extents_m: [..., 2]. Returns (contact point on the side the point
    is most outside of [..., 2], inward unit normal of that side [..., 2], distance of the point
    outside the box [...] (0 inside)).
    """
    excess = point_m.abs() - half_extents_m
    outside = box_gap_m(point_m, half_extents_m)
    on_x = excess[..., 0] >= excess[..., 1]
    sign = torch.where(point_m >= 0.0, 1.0, -1.0).to(point_m.dtype)
    clamped = torch.maximum(torch.minimum(point_m, half_extents_m), -half_extents_m)
    x_side = torch.stack([sign[..., 0] * half_extents_m[..., 0], clamped[..., 1]], -1)
    y_side = torch.stack([clamped[..., 0], sign[..., 1] * half_extents_m[..., 1]], -1)
    zero = torch.zeros_like(sign[..., 0])
    x_normal = torch.stack([-sign[..., 0], zero], -1)
    y_normal = torch.stack([zero, -sign[..., 1]], -1)
    on_x = on_x.unsqueeze(-1)
    return (
        torch.where(on_x, x_side, y_side),
        torch.where(on_x, x_normal, y_normal),
        outside,
    )


@dataclass(frozen=True)
class PushSettings:
    """Fixed quantities of the analytical model."""

    pusher_friction: float
    """mu_r between the finger pad and the object."""
    pusher_offset_m: float
    """Distance from the TCP to the leading pad face along the push direction."""
    contact_margin_m: float
    """The pusher touches the link when its point is at most this far outside the box."""
    pad_half_width_m: float = 0.012
    """Half width of the flat pad face across the push direction (the simulated gripper's pad
    is 24 mm wide, ``PAD_HALF_SIZE_M[1]``); 0 for a point pusher. See :func:`line_contact`."""
    grasp_friction_nm: float | None = None
    """The torque a pull's grasp holds before the link turns between the fingers (N m); None
    for a rigid grasp. See :func:`vistac.plugins.filters.chain.pull_motion`."""
    contact_normal: Literal["push", "box"] = "push"
    """The contact's normal: the push direction (the pad's face, which the action planner sets
    within a few degrees of the surface normal), or the normal of the footprint box's side
    nearest the pad (exact for boxes only; see :func:`pad_contact`)."""
    pressure: Pressure = "uniform"
    """How a link presses on the table: uniformly over its footprint box
    (:func:`characteristic_length_m`) or linearly, centred under the CoM
    (:func:`linear_pressure_length_m`)."""


class PadContact(NamedTuple):
    """Where the pad face meets a link (link frame) and how it moves.

    point_m: [..., 2] the pad point (push normal) or the nearest point on the box side (box
    normal); normal: [..., 2] unit, into the link; gap_m: [...] distance of the pad point
    outside the footprint box (0 inside); velocity_mps: [..., 2] the pad point's velocity.
    """

    point_m: Tensor
    normal: Tensor
    gap_m: Tensor
    velocity_mps: Tensor


def pad_contact(
    tcp: Tensor, pd_rad: Tensor, link_pose: Tensor, half_extents_m: Tensor, settings: PushSettings
) -> PadContact:
    """The pad's contact with links at link_pose [..., 3] (x, y, theta; half extents [..., 2])
    for the gripper tcp [..., 6] pushing along pd_rad [...] (all broadcast).

    The pad face lies ``pusher_offset_m`` ahead of the TCP along the push direction. With the
    push normal the contact is that point with the push direction as normal; with the box
    normal, the point of the box side it is most outside of and that side's normal. The box's
    sides are a poor normal for round or many-sided footprints: on the seed-0 test pushes from
    the true states (``docs/results.md``) the push normal halved the heterogeneous objects'
    one-step force error of the chain model.
    """
    theta = link_pose[..., 2]
    direction = torch.stack([torch.cos(pd_rad), torch.sin(pd_rad)], -1)
    pusher = tcp[..., :2] + settings.pusher_offset_m * direction
    velocity = tcp[..., 3:5] + tcp[..., 5:6] * perp(pusher - tcp[..., :2])
    local = rotate(pusher - link_pose[..., :2], -theta)
    point, normal, gap = box_contact(local, half_extents_m)
    if settings.contact_normal == "push":
        point, normal = local.expand_as(point), rotate(direction, -theta).expand_as(normal)
    return PadContact(point, normal, gap, rotate(velocity, -theta))


def analytical_step(
    states: Tensor, inputs: ProcessInput, dt_s: float, settings: PushSettings
) -> tuple[Tensor, Tensor]:
    """One step of a one-link object pushed (quasi-statically) or pulled (rigidly).

    states: [..., C, 10]. Returns (next pose [..., C, 6] of the link frame: x, y, theta and the
    frame origin's velocity vx, vy, omega; force of the object on the fingers [..., C, 2]),
    world frame. Integration: the CoM moves by v dt and the link turns by omega dt about it.
    """
    layout = StateLayout(1)
    pose = layout.link_pose(states)[..., 0, :]
    mass, friction = layout.link_parameters(states)[..., 0, :2].unbind(-1)
    com_link = layout.link_parameters(states)[..., 0, 2:]
    theta = pose[..., 2]
    com_world = pose[..., :2] + rotate(com_link, theta)

    tcp = inputs.tcp.unsqueeze(-2)  # [..., 1, 6]
    pd = inputs.pd_rad.unsqueeze(-1)
    half_extents = inputs.link_size_m[..., 0, :].unsqueeze(-2)
    c = characteristic_length(settings.pressure)(half_extents, com_link)
    f_max = friction * mass * GRAVITY_MPS2

    # Push, in the link frame.
    pad = pad_contact(tcp, pd, pose[..., :3], half_extents, settings)
    point = line_contact(
        pad.point_m, pad.normal, pad.velocity_mps, com_link, half_extents,
        settings.pad_half_width_m,
    )
    push = quasi_static_push(
        point - com_link, pad.normal, pad.velocity_mps, f_max, c, settings.pusher_friction
    )
    touching = (pad.gap_m <= settings.contact_margin_m).unsqueeze(-1)
    push_velocity = torch.where(touching, rotate(push.velocity_mps, theta), 0.0)
    push_omega = torch.where(touching[..., 0], push.omega_radps, 0.0)

    # Pull: the grasped link moves with the gripper.
    pull_omega = tcp[..., 5].expand_as(theta)
    pull_velocity = tcp[..., 3:5] + pull_omega.unsqueeze(-1) * perp(com_world - tcp[..., :2])

    pulling = (inputs.is_pull.unsqueeze(-1) > 0.5).expand_as(theta)
    velocity = torch.where(pulling.unsqueeze(-1), pull_velocity, push_velocity)
    omega = torch.where(pulling, pull_omega, push_omega)
    force = -limit_surface_force(velocity, omega, f_max, c)

    next_theta = theta + omega * dt_s
    com_offset = rotate(com_link, next_theta)
    next_xy = com_world + velocity * dt_s - com_offset
    origin_velocity = velocity - omega.unsqueeze(-1) * perp(com_offset)
    next_pose = torch.cat(
        [next_xy, next_theta.unsqueeze(-1), origin_velocity, omega[..., None]], -1
    )
    return next_pose, force


def analytical_prediction(
    states: Tensor, inputs: ProcessInput, dt_s: float, settings: PushSettings, variance: Tensor
) -> Prediction:
    """:func:`analytical_step` as a Prediction with the fixed process variance [6]."""
    pose, force = analytical_step(states, inputs, dt_s, settings)
    return Prediction(
        pose=pose, force_n=force, process_var=variance.expand(*inputs.tcp.shape[:-1], 6)
    )
