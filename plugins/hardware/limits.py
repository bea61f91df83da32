"""Motion limits shared by every arm plugin (simulated and real): speed caps and the
workspace box, in the world frame (= the robot base frame, DESIGN §5)."""

from __future__ import annotations

from pydantic import Field, model_validator
from vistac.component import ComponentConfig

AXES = ("x", "y", "z")


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
