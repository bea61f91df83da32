"""``sim.touch_probe``: a static object at a 6D pose and a probe that moves in a straight line
until it touches it (ray casting on the object's mesh).

The object is a library class, a novel variant or a mesh file, placed at a random pose drawn
from the skill's seed (uniform orientation, position uniform in a cube around
``workspace_centre_m``) unless ``position_m``/``rotation_xyz_deg`` fix it. Contacts come back
with Gaussian noise on the point and the normal. The true class and pose are exposed by
``ground_truth()`` for evaluation only.
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np
from pydantic import Field, ValidationInfo, field_validator
from scipy.spatial.transform import Rotation
from vistac.component import Component, ComponentConfig, ComponentContext
from vistac.errors import DataError
from vistac.types import FloatArray

log = logging.getLogger(__name__)


class SimTouchProbe(Component):
    """A point probe touching a static simulated object."""

    kind = "touch_probe"

    class Config(ComponentConfig):
        object: str = Field("mug", description="library class, novel variant or mesh file path")
        workspace_centre_m: tuple[float, float, float] = (0.0, 0.5, 0.3)
        position_range_m: float = Field(
            0.05, ge=0.0, description="random object position: +- this around the centre"
        )
        position_m: tuple[float, float, float] | None = Field(
            None, description="fixed object position (world, m) instead of a random one"
        )
        rotation_xyz_deg: tuple[float, float, float] | None = Field(
            None, description="fixed extrinsic x-y-z Euler angles instead of a random rotation"
        )
        point_noise_m: float = Field(0.001, ge=0.0, description="contact point noise std")
        normal_noise_rad: float = Field(0.03, ge=0.0, description="normal direction noise std")

        @field_validator("object")
        @classmethod
        def _a_shape_there_is(cls, value: str, info: ValidationInfo) -> str:
            """In a skill, a library name or a mesh file that exists, checked before anything
            is built (a relative path is taken from the skill's folder, as the probe takes
            it); without a skill's folder the probe's build checks it."""
            from vistac.plugins.touch.library import require_shape_in_skill

            return require_shape_in_skill(value, (info.context or {}).get("skill_dir"))

    def __init__(self, config: Config, ctx: ComponentContext) -> None:
        from vistac.plugins.touch.library import resolve_shape

        super().__init__(config, ctx)
        self.mesh = resolve_shape(config.object, ctx.skill_dir)
        self._rng = ctx.rng("touch_probe")
        self.world_from_object = self._pose(ctx.rng("touch_object_pose"))
        self._world_mesh = self.mesh.transformed(self.world_from_object)
        self._sdf = self._world_mesh.sdf()
        self.touches = 0
        self.contacts = 0

    def _pose(self, rng: np.random.Generator) -> FloatArray:
        config = self.config
        pose = np.eye(4)
        if config.rotation_xyz_deg is not None:
            pose[:3, :3] = Rotation.from_euler(
                "xyz", config.rotation_xyz_deg, degrees=True
            ).as_matrix()
        else:
            pose[:3, :3] = Rotation.random(random_state=rng).as_matrix()
        if config.position_m is not None:
            pose[:3, 3] = config.position_m
        else:
            offset = rng.uniform(-config.position_range_m, config.position_range_m, 3)
            pose[:3, 3] = np.asarray(config.workspace_centre_m) + offset
        return pose

    def probe(
        self, start_m: FloatArray, target_m: FloatArray
    ) -> tuple[FloatArray, FloatArray] | None:
        """Move from ``start_m`` [3] to ``target_m`` [3]; the first contact (noisy point [3],
        unit outward normal [3]) or None when the probe reaches the target untouched."""
        start, target = (
            np.asarray(start_m, dtype=np.float64),
            np.asarray(target_m, dtype=np.float64),
        )
        if start.shape != (3,) or target.shape != (3,) or not np.all(np.isfinite([start, target])):
            raise DataError("a touch needs finite 3D start and target points")
        length_m = float(np.linalg.norm(target - start))
        if length_m < 1e-9:
            raise DataError("a touch needs a target different from its start")
        inside, _ = self._sdf(start[None])
        if inside[0] < 0.0:
            raise DataError(
                f"the probe path starts inside the object at {np.round(start, 3).tolist()} m; "
                "start every touch outside the object (e.g. outside the workspace box)"
            )
        direction = (target - start) / length_m
        hit_m, normals = self._sdf.cast(start[None], direction[None])
        self.touches += 1
        if not hit_m[0] <= length_m:
            return None
        self.contacts += 1
        return self._noisy(start + hit_m[0] * direction, normals[0])

    def _noisy(self, point: FloatArray, normal: FloatArray) -> tuple[FloatArray, FloatArray]:
        point = point + self._rng.normal(0.0, self.config.point_noise_m, 3)
        tilt = Rotation.from_rotvec(self._rng.normal(0.0, self.config.normal_noise_rad, 3))
        normal = tilt.apply(normal)
        return point, normal / np.linalg.norm(normal)

    def ground_truth(self) -> dict[str, Any]:
        """For evaluation only: the object's class/source name and its [4, 4] pose."""
        return {
            "object": self.config.object,
            "class": self.mesh.name,
            "world_from_object": self.world_from_object.tolist(),
            "touches": self.touches,
            "contacts": self.contacts,
        }
