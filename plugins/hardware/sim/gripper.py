"""Simulated two-finger gripper: force-limited position servos on the two finger slides."""

from __future__ import annotations

import numpy as np
from pydantic import Field
from vistac.component import Component, ComponentConfig, ComponentContext
from vistac.plugins.hardware.sim.arm import find_world
from vistac.types import GripperState


class SimGripper(Component):
    """Implements the ``Gripper`` protocol. ``open`` and ``close`` return at once.

    The fingers are ``moving`` while either slides faster than ``still_speed_mps``; an object
    is detected when they have stopped closing with the pads more than ``contact_width_m``
    apart (they stalled on something).
    """

    kind = "gripper"

    class Config(ComponentConfig):
        still_speed_mps: float = Field(default=0.005, gt=0.0)
        contact_width_m: float = Field(default=0.004, gt=0.0)

    def __init__(self, config: Config, ctx: ComponentContext) -> None:
        super().__init__(config, ctx)
        self.world = find_world(ctx, "sim.gripper")

    def _command_travel(self, travel_m: float) -> None:
        self.world.data.ctrl[self.world.index.finger_actuators] = travel_m

    def open(self) -> None:
        self._command_travel(self.world.geometry.max_finger_travel_m)

    def close(self) -> None:
        self._command_travel(0.0)

    def stop(self) -> None:
        """Hold the fingers where they are."""
        data, index = self.world.data, self.world.index
        self._command_travel(float(np.mean(data.qpos[index.finger_qpos])))

    def state(self) -> GripperState:
        data, index = self.world.data, self.world.index
        width_m = float(np.sum(data.qpos[index.finger_qpos]))
        moving = bool(np.any(np.abs(data.qvel[index.finger_dof]) > self.config.still_speed_mps))
        closing = bool(np.all(data.ctrl[index.finger_actuators] == 0.0))
        detected = closing and not moving and width_m > self.config.contact_width_m
        return GripperState(
            width_m=width_m, object_detected=detected, moving=moving, timestamp_s=self.world.time_s
        )
