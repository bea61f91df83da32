"""Mirror symmetry of planar pushing: a scene reflected about the line of the push moves as
the reflection of the scene's motion (the table is isotropic). A learned process model need
not honour that; averaging its prediction with the reflected prediction of the reflected
scene does, and cancels the part of its error that breaks the symmetry.

The reflection is about the line through the TCP along the push (or pull) direction pd, in
the world frame: a point p goes to ``o + F (p - o)`` with ``F = [[cos 2a, sin 2a], [sin 2a,
-cos 2a]]``, ``a = pd``; an angle theta to ``2a - theta``; a rate to its negative. In a link's
own frame, which the reflection turns into a left-handed one, the CoM's y flips sign, and so
do the y and angle of each link's initial pose relative to link 0 (``link_offset``).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import torch
from torch import Tensor
from vistac.plugins.filters.nets import layout_of, wrap
from vistac.plugins.filters.state import Prediction, ProcessInput

Forward = Callable[[Tensor, ProcessInput, float], Prediction]


def _reflect_xy(xy: Tensor, cos2: Tensor, sin2: Tensor) -> Tensor:
    """Vectors [..., 2] reflected by F (cos2, sin2 broadcast to [...])."""
    x, y = xy.unbind(-1)
    return torch.stack([cos2 * x + sin2 * y, sin2 * x - cos2 * y], -1)


def reflect_poses(pose: Tensor, origin: Tensor, pd_rad: Tensor) -> Tensor:
    """Link poses [..., C, L, 6] (x, y, theta, vx, vy, omega) reflected about the line through
    origin [..., 2] along pd_rad [...]."""
    angle = pd_rad[..., None, None]
    cos2, sin2 = torch.cos(2.0 * angle), torch.sin(2.0 * angle)
    centre = origin[..., None, None, :]
    xy = centre + _reflect_xy(pose[..., :2] - centre, cos2, sin2)
    theta = 2.0 * angle - pose[..., 2]
    velocity = _reflect_xy(pose[..., 3:5], cos2, sin2)
    return torch.cat([xy, theta.unsqueeze(-1), velocity, -pose[..., 5:6]], -1)


def reflect_scene(states: Tensor, inputs: ProcessInput) -> tuple[Tensor, ProcessInput]:
    """States [..., C, n] and inputs reflected about the line through the TCP along pd."""
    layout = layout_of(states)
    origin, pd_rad = inputs.tcp[..., :2], inputs.pd_rad
    pose = reflect_poses(layout.link_pose(states), origin, pd_rad)
    parameters = layout.link_parameters(states) * states.new_tensor([1.0, 1.0, 1.0, -1.0])
    joints = layout.joint_friction(states)
    reflected = torch.cat([pose.flatten(-2), parameters.flatten(-2), joints], -1)
    tcp_pose = reflect_poses(inputs.tcp[..., None, None, :], origin, pd_rad)[..., 0, 0, :]
    offset = inputs.link_offset * inputs.link_offset.new_tensor([1.0, -1.0, -1.0])
    hinge = inputs.hinge_m
    if hinge is not None:
        hinge = hinge * hinge.new_tensor([1.0, -1.0])
    return reflected, ProcessInput(
        tcp_pose, inputs.pd_rad, inputs.is_pull, inputs.link, inputs.link_size_m, offset, hinge
    )


def mirror_averaged(
    forward: Forward, states: Tensor, inputs: ProcessInput, dt_s: float
) -> Prediction:
    """``forward``'s prediction of states [..., C, n] averaged with the reflection of its
    prediction of the reflected scene (one call on both, stacked in front). The process
    variance is the direct prediction's."""
    mirrored_states, mirrored_inputs = reflect_scene(states, inputs)
    stacked = {
        field.name: torch.stack([getattr(inputs, field.name), getattr(mirrored_inputs, field.name)])
        for field in dataclasses.fields(ProcessInput)
        if getattr(inputs, field.name) is not None
    }
    both = forward(torch.stack([states, mirrored_states]), ProcessInput(**stacked), dt_s)
    n_links = layout_of(states).n_links
    direct = both.pose[0].unflatten(-1, (n_links, 6))
    back = reflect_poses(both.pose[1].unflatten(-1, (n_links, 6)), inputs.tcp[..., :2],
                         inputs.pd_rad)  # fmt: skip
    mean = 0.5 * (direct + back)
    theta = direct[..., 2] + 0.5 * wrap(back[..., 2] - direct[..., 2])
    pose = torch.cat([mean[..., :2], theta.unsqueeze(-1), mean[..., 3:]], -1).flatten(-2)
    angle = inputs.pd_rad[..., None]
    force_back = _reflect_xy(both.force_n[1], torch.cos(2.0 * angle), torch.sin(2.0 * angle))
    return Prediction(pose, 0.5 * (both.force_n[0] + force_back), both.process_var[0])
