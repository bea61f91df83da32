"""Conversions between UR TCP poses and vistac's (x, y, z, yaw) arm pose.

A UR pose is [6] = (x, y, z m, rx, ry, rz rotation vector rad) in the robot base frame, which is
vistac's world frame (DESIGN §5). vistac's gripper points down: the tool's z axis along world
-z, rotated by ``yaw`` about world z, i.e. ``R = Rz(yaw) @ Rx(pi)``.
"""

from __future__ import annotations

import math

import numpy as np
from vistac.types import FloatArray

_FLIP_X = np.diag([1.0, -1.0, -1.0])
"""Rx(pi): the tool pointing down."""


def rotvec_to_matrix(rotvec: FloatArray) -> FloatArray:
    """Rodrigues' formula: rotation vector [3] -> rotation matrix [3, 3]."""
    vector = np.asarray(rotvec, dtype=np.float64)
    angle = float(np.linalg.norm(vector))
    if angle < 1e-12:
        return np.eye(3)
    kx, ky, kz = vector / angle
    k = np.array([[0.0, -kz, ky], [kz, 0.0, -kx], [-ky, kx, 0.0]])
    return np.eye(3) + math.sin(angle) * k + (1.0 - math.cos(angle)) * (k @ k)


def matrix_to_rotvec(rotation: FloatArray) -> FloatArray:
    """Rotation matrix [3, 3] -> rotation vector [3] (angle in [0, pi])."""
    cos_angle = float(np.clip((np.trace(rotation) - 1.0) / 2.0, -1.0, 1.0))
    angle = math.acos(cos_angle)
    if angle < 1e-9:
        return np.zeros(3)
    if math.pi - angle < 1e-6:  # axis from the symmetric part
        axis_outer = (rotation + np.eye(3)) / 2.0
        axis = np.sqrt(np.clip(np.diag(axis_outer), 0.0, None))
        column = int(np.argmax(axis))
        axis = axis_outer[:, column] / axis[column]
        return angle * axis / np.linalg.norm(axis)
    axis = np.array(
        [
            rotation[2, 1] - rotation[1, 2],
            rotation[0, 2] - rotation[2, 0],
            rotation[1, 0] - rotation[0, 1],
        ]
    ) / (2.0 * math.sin(angle))
    return angle * axis


def yaw_of(tcp_pose: FloatArray) -> float:
    """Yaw (rad) of a down-pointing tool from a UR pose [6]: the tool x axis in the xy plane."""
    rotation = rotvec_to_matrix(np.asarray(tcp_pose)[3:6])
    return math.atan2(rotation[1, 0], rotation[0, 0])


def arm_pose(tcp_pose: FloatArray) -> FloatArray:
    """UR pose [6] -> vistac pose [4] = (x, y, z, yaw)."""
    pose = np.asarray(tcp_pose, dtype=np.float64)
    return np.array([pose[0], pose[1], pose[2], yaw_of(pose)])


def tcp_pose(arm_pose_4: FloatArray) -> FloatArray:
    """vistac pose [4] = (x, y, z, yaw) -> UR pose [6] with the tool pointing down."""
    x, y, z, yaw = (float(v) for v in arm_pose_4)
    c, s = math.cos(yaw), math.sin(yaw)
    rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return np.concatenate([[x, y, z], matrix_to_rotvec(rz @ _FLIP_X)])
