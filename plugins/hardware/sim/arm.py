"""Simulated Cartesian arm: velocity streaming to the gripper's four ``intvelocity`` servos.

A command holds until the next one. The servo targets are integrated by MuJoCo inside the
physics step (no Python per step), so the TCP target moves at exactly the commanded, capped
speed.

Workspace. The servo targets are limited to the workspace box (the actuators' ``actrange``),
so the arm stops at the boundary: a velocity component that would carry the TCP further out is
held at the limit while the other components continue. A command that points out of the box
from a pose already on its boundary is refused: the arm is stopped and ``SafetyError`` names
the limit.
"""

from __future__ import annotations

import logging

import numpy as np
from vistac.component import Component, ComponentContext
from vistac.errors import PluginError, SafetyError
from vistac.plugins.hardware.limits import ArmLimits, leaving_workspace
from vistac.plugins.hardware.sim.world import MujocoWorld
from vistac.types import ArmState, FloatArray

log = logging.getLogger(__name__)

_BOUNDARY_TOLERANCE_M = 1e-6


def find_world(ctx: ComponentContext, user: str) -> MujocoWorld:
    """The skill's MuJoCo world, or a PluginError naming the component that needs it."""
    world = ctx.find("world")
    if not isinstance(world, MujocoWorld):
        raise PluginError(f"{user} needs the 'sim.mujoco' world, found {type(world).__name__}")
    return world


class SimArm(Component):
    """Implements the ``Arm`` protocol on the simulated gripper."""

    kind = "arm"

    class Config(ArmLimits):
        pass

    def __init__(self, config: Config, ctx: ComponentContext) -> None:
        super().__init__(config, ctx)
        self.world = find_world(ctx, "sim.arm")
        self.max_speed_mps = config.max_speed_mps
        self._low = np.asarray(config.workspace_min_m, dtype=np.float64)
        self._high = np.asarray(config.workspace_max_m, dtype=np.float64)
        model, index = self.world.model, self.world.index
        self._act = model.actuator_actadr[index.arm_actuators]
        model.actuator_actrange[index.arm_actuators[:3]] = np.column_stack([self._low, self._high])
        start = self._target()[:3]
        if np.any(start < self._low) or np.any(start > self._high):
            raise SafetyError(f"gripper start {start.tolist()} is outside the arm workspace")

    def _target(self) -> FloatArray:
        return np.array(self.world.data.act[self._act])

    def state(self) -> ArmState:
        data, index = self.world.data, self.world.index
        return ArmState(
            pose=np.array(data.qpos[index.arm_qpos]),
            twist=np.array(data.qvel[index.arm_dof]),
            timestamp_s=self.world.time_s,
        )

    def command_velocity(self, twist: FloatArray) -> None:
        """Stream twist [4] = (vx, vy, vz, wz); clamped to the caps, held until the next call."""
        command = np.asarray(twist, dtype=np.float64)
        if command.shape != (4,) or not np.all(np.isfinite(command)):
            self.stop()
            raise SafetyError(f"arm twist must be 4 finite numbers, got {command!r}")
        speed_mps = float(np.linalg.norm(command[:3]))
        if speed_mps > self.max_speed_mps:
            command[:3] *= self.max_speed_mps / speed_mps
        command[3] = np.clip(
            command[3], -self.config.max_yaw_rate_rad_s, self.config.max_yaw_rate_rad_s
        )
        self._refuse_leaving(command[:3])
        self.world.data.ctrl[self.world.index.arm_actuators] = command

    def _refuse_leaving(self, velocity_mps: FloatArray) -> None:
        target = self._target()[:3]
        reason = leaving_workspace(target, velocity_mps, self._low, self._high,
                                   _BOUNDARY_TOLERANCE_M)
        if reason is not None:
            self.stop()
            raise SafetyError(f"arm motion refused: it would leave the workspace ({reason})")

    def stop(self) -> None:
        """Zero the velocity and hold the current pose."""
        data, index = self.world.data, self.world.index
        data.ctrl[index.arm_actuators] = 0.0
        pose = np.array(data.qpos[index.arm_qpos])
        pose[:3] = np.clip(pose[:3], self._low, self._high)
        data.act[self._act] = pose
