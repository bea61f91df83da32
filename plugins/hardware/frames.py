"""Frames shared by the real tactile sensors: from the gripper frame to the world frame.

The gripper frame turns with the TCP yaw about world z: x along the fingers' travel-free
horizontal axis, y along the closing axis, z up. A 2D fingertip force in the world frame
(what the filter uses, as ``sim.tactile`` reports it) is the x, y part of the force rotated by
the arm's current yaw.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from vistac.types import FloatArray


def gripper_to_world_xy(force_gripper_n: FloatArray, yaw_rad: float) -> FloatArray:
    """Forces [P, >=2] in the gripper frame -> world (x, y) [P, 2] for a TCP yaw."""
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    rotation = np.array([[c, -s], [s, c]])
    return np.asarray(force_gripper_n, dtype=np.float64)[:, :2] @ rotation.T


def arm_yaw_rad(arm: Any | None) -> float:
    """The arm's current yaw, or 0 when the skill has no arm."""
    return 0.0 if arm is None else float(arm.state().pose[3])
