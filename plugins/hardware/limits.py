"""Motion limits shared by every arm plugin (simulated and real): speed caps and the
workspace box, in the world frame (= the robot base frame, DESIGN §5)."""

from __future__ import annotations

import numpy as np
from pydantic import Field, model_validator
from vistac.component import ComponentConfig
from vistac.types import FloatArray

AXES = ("x", "y", "z")


def leaving_workspace(position_m: FloatArray, velocity_mps: FloatArray, low_m: FloatArray,
                      high_m: FloatArray, tolerance_m: float) -> str | None:
    """Why a move at velocity [3] from position [3] (both world frame) would leave the box
    [low_m, high_m] it is on the boundary of, e.g. ``"x max = 0.300 m"``; None when it does
    not."""
    at_low = (position_m <= low_m + tolerance_m) & (velocity_mps < 0)
    at_high = (position_m >= high_m - tolerance_m) & (velocity_mps > 0)
    if not np.any(at_low | at_high):
        return None
    axis = int(np.argmax(at_low | at_high))
    side, limit = ("min", low_m[axis]) if at_low[axis] else ("max", high_m[axis])
    return f"{AXES[axis]} {side} = {limit:.3f} m"


class ArmLimits(ComponentConfig):
    """Base of an arm's ``Config``: the speed caps and the workspace box."""

    max_speed_mps: float = Field(default=0.025, gt=0.0, le=0.25)
    """Hard cap on the TCP's linear speed (norm of vx, vy, vz)."""
    max_yaw_rate_rad_s: float = Field(default=0.5, gt=0.0, le=3.0)
    workspace_min_m: tuple[float, float, float] = (-0.5, 0.15, 0.015)
    workspace_max_m: tuple[float, float, float] = (0.5, 0.85, 0.5)

    @model_validator(mode="after")
    def _box(self) -> ArmLimits:
        for axis, low, high in zip(AXES, self.workspace_min_m, self.workspace_max_m, strict=True):
            if not low < high:
                raise ValueError(f"workspace {axis}: min {low} must be below max {high}")
        return self
