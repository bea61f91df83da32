"""Which pushes turn an object's hinge (``vistac objects hinges``).

While its hinge holds, a hinged pair moves as one rigid body, and a push shows of it what it
shows of a welded pair: the pair's friction load and where that load is centred, and of the
joint's friction only a bound. Whether an object's hinge can be made to turn at all is found
in the simulated world: the object is pushed from rest at its true parameters
(:class:`~vistac.plugins.filters.information.PushReplay`), square to the chain at
``POINTS`` points along each link's side, from both sides, and each push's largest turn of
the hinge (link 1's yaw less link 0's, from its first value) is kept.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from vistac.errors import ConfigError
from vistac.objects import ObjectSpec, link_frames
from vistac.plugins.actions.executor import CartesianExecutor
from vistac.plugins.filters.information import PushReplay, RecordedPush

FloatArray = NDArray[np.float64]

POINTS = (-0.8, -0.4, 0.0, 0.4, 0.8)
"""Where along each link the pushes go: fractions of the footprint's half length (link x)."""
SPEED_MPS = 0.02
DURATION_S = 5.0
STEP_S = 1.0 / 15.0
"""Control step of the replayed pushes (the skills' filter rate)."""


@dataclass(frozen=True)
class SquarePush:
    """One push square to the chain and what it did."""

    link: int
    """The link pushed."""
    along: float
    """Where along it (a fraction of its half length, link x)."""
    side: float
    """+1: pushed from the link's +y side towards -y; -1 the other way."""
    turn_rad: float
    """The hinge's largest turn from its first angle."""
    moved_m: float
    """The farthest any link's origin moved."""


def square_push(spec: ObjectSpec, link: int, along: float, side: float) -> RecordedPush:
    """The push of ``link`` at ``along`` from its ``side``, the object at rest at its pose:
    the gripper starts clear of the footprint (standoff and pad offset of the executor's
    defaults beyond its widest point) at the executor's finger height, and moves square to
    the chain at ``SPEED_MPS`` for ``DURATION_S``."""
    executor = CartesianExecutor.Config()
    frames = link_frames(spec)
    x_m, y_m, theta_rad = frames[link]
    polygon = spec.links[link].polygon()
    clear_m = np.abs(polygon[:, 1]).max() + executor.standoff_m + executor.pusher_offset_m
    local = np.array([along * np.abs(polygon[:, 0]).max(), side * clear_m])
    turn = np.array([[math.cos(theta_rad), -math.sin(theta_rad)],
                     [math.sin(theta_rad), math.cos(theta_rad)]])  # fmt: skip
    pd_rad = theta_rad - side * math.pi / 2
    time_s = np.arange(round(DURATION_S / STEP_S) + 1) * STEP_S
    xy = np.array([x_m, y_m]) + turn @ local
    path = xy + np.outer(time_s * SPEED_MPS, [math.cos(pd_rad), math.sin(pd_rad)])
    arm = np.column_stack([path, np.full(len(time_s), executor.finger_height_m),
                           np.full(len(time_s), pd_rad)])  # fmt: skip
    return RecordedPush(spec, time_s, arm, np.repeat(frames[None], len(time_s), 0), pd_rad)


def hinge_turns(spec: ObjectSpec, joint_friction_nm: float | None = None) -> list[SquarePush]:
    """Every square push of a hinged pair (:data:`POINTS` on each link, both sides) and the
    largest turn of its hinge, at the true parameters or with the joint's friction set to
    ``joint_friction_nm``. ConfigError for an object without a hinge."""
    if spec.joint is None or len(spec.links) != 2:
        raise ConfigError(f"{spec.name} ({spec.type}) has no hinge; give articulated objects")
    replay = PushReplay(spec)
    values = replay.truth.copy()
    if joint_friction_nm is not None:
        values[replay.names.index("f_j_0")] = joint_friction_nm
    pushes = []
    for link in range(2):
        for along in POINTS:
            for side in (1.0, -1.0):
                poses, _ = replay.run(square_push(spec, link, along, side), values)
                bend = np.unwrap(poses[:, 1, 2] - poses[:, 0, 2])
                moved = np.linalg.norm(poses[-1, :, :2] - poses[0, :, :2], axis=1).max()
                turn = float(np.abs(bend - bend[0]).max())
                pushes.append(SquarePush(link, along, side, turn, float(moved)))
    return pushes


def hinges_markdown(
    results: dict[str, tuple[float, list[SquarePush]]], threshold_rad: float
) -> list[str]:
    """A table: per object (name -> (joint friction N m, its pushes)), how many pushes turned
    the hinge farther than ``threshold_rad``, the largest turn and the median distance moved."""
    degrees = math.degrees(threshold_rad)
    lines = [
        f"| object | joint friction (N m) | pushes turning it > {degrees:g} deg | largest turn "
        "(deg) | by a push of | median moved (cm) |",
        "|---|---:|---:|---:|---|---:|",
    ]
    for name, (friction_nm, pushes) in results.items():
        turned = sum(push.turn_rad > threshold_rad for push in pushes)
        top = max(pushes, key=lambda push: push.turn_rad)
        moved_cm = 100 * float(np.median([push.moved_m for push in pushes]))
        where = f"link {top.link} at {top.along:+.1f}, from {'+y' if top.side > 0 else '-y'}"
        lines.append(f"| {name} | {friction_nm:.3f} | {turned} of {len(pushes)} | "
                     f"{math.degrees(top.turn_rad):.1f} | {where} | {moved_cm:.1f} |")  # fmt: skip
    return lines
