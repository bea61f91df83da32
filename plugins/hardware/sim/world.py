"""The MuJoCo world: table, object and Cartesian gripper (see :mod:`.mjcf` for the model).

Table tilt is simulated by rotating the gravity vector about world x; for objects resting on
the table this is physically the same as tilting the table by that angle (positive tilt raises
the far, +y edge, so a free object slides towards the robot), while the scene geometry and the
camera stay untilted. The gripper is gravity-compensated, so it is unaffected.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import mujoco
import numpy as np
from pydantic import Field, field_validator
from vistac.component import Component, ComponentConfig, ComponentContext, SkillPath
from vistac.errors import ConfigError
from vistac.objects import ObjectSpec, load_object
from vistac.plugins.hardware.sim.mjcf import (
    ARM_JOINTS,
    FINGER_JOINTS,
    PAD_GEOMS,
    GripperGeometry,
    build_mjcf,
    gravity_vector,
)
from vistac.types import FloatArray

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SimIndex:
    """Model addresses the sim devices use (arrays of ints, one entry per joint/geom/body)."""

    arm_qpos: np.ndarray
    arm_dof: np.ndarray
    arm_actuators: np.ndarray
    finger_qpos: np.ndarray
    finger_dof: np.ndarray
    finger_actuators: np.ndarray
    pad_geoms: np.ndarray
    link_bodies: np.ndarray

    @classmethod
    def of(cls, model: mujoco.MjModel, n_links: int) -> SimIndex:
        def ids(kind: mujoco.mjtObj, names: tuple[str, ...]) -> np.ndarray:
            return np.array([mujoco.mj_name2id(model, kind, name) for name in names])

        arm_joints = ids(mujoco.mjtObj.mjOBJ_JOINT, ARM_JOINTS)
        finger_joints = ids(mujoco.mjtObj.mjOBJ_JOINT, FINGER_JOINTS)
        links = tuple(f"link{i}" for i in range(n_links))
        return cls(
            arm_qpos=model.jnt_qposadr[arm_joints],
            arm_dof=model.jnt_dofadr[arm_joints],
            arm_actuators=ids(mujoco.mjtObj.mjOBJ_ACTUATOR, ARM_JOINTS),
            finger_qpos=model.jnt_qposadr[finger_joints],
            finger_dof=model.jnt_dofadr[finger_joints],
            finger_actuators=ids(mujoco.mjtObj.mjOBJ_ACTUATOR, FINGER_JOINTS),
            pad_geoms=ids(mujoco.mjtObj.mjOBJ_GEOM, PAD_GEOMS),
            link_bodies=ids(mujoco.mjtObj.mjOBJ_BODY, links),
        )


def planar_poses(data: mujoco.MjData, bodies: np.ndarray) -> FloatArray:
    """The world frames of ``bodies`` [B] in the table's plane: [B, 3] = (x_m, y_m,
    theta_rad)."""
    rotation = data.xmat[bodies]
    theta = np.arctan2(rotation[:, 3], rotation[:, 0])
    return np.column_stack([data.xpos[bodies, :2], theta])


class MujocoWorld(Component):
    """Simulated world; other ``sim.*`` components use its ``model``, ``data`` and ``index``."""

    kind = "world"
    simulated = True

    class Config(ComponentConfig):
        object: SkillPath
        """Object definition (YAML, see :mod:`vistac.objects`)."""
        timestep_s: float = Field(default=0.002, gt=0.0, le=0.01)
        table_tilt_rad: float | None = Field(default=None, ge=-0.5, le=0.5)
        """Table tilt about world x; None takes the object file's ``table_tilt_rad``."""
        gripper_start: tuple[float, float, float, float] = (0.0, 0.25, 0.12, 0.0)
        """Initial TCP pose (x_m, y_m, z_m, yaw_rad)."""
        gripper_max_opening_m: float = Field(default=0.15, gt=0.02, le=0.3)

        @field_validator("object")
        @classmethod
        def _object_file_is_valid(cls, path: Path) -> Path:
            """Check the object file before anything is built (errors name the file)."""
            if not path.exists():
                raise ValueError(
                    f"{path}: no such file (a relative path is taken from the skill file's "
                    "folder; give an absolute path for a file elsewhere)"
                )
            try:
                load_object(path)
            except ConfigError as exc:
                raise ValueError(str(exc).replace("\n", "; ")) from None
            return path

    def __init__(self, config: Config, ctx: ComponentContext) -> None:
        super().__init__(config, ctx)
        self.spec: ObjectSpec = load_object(config.object)
        self.geometry = GripperGeometry(config.gripper_max_opening_m)
        tilt = self.spec.table_tilt_rad if config.table_tilt_rad is None else config.table_tilt_rad
        xml = build_mjcf(self.spec, self.geometry, config.timestep_s, tilt)
        self.model = mujoco.MjModel.from_xml_string(xml)
        self.data = mujoco.MjData(self.model)
        self.index = SimIndex.of(self.model, len(self.spec.links))
        self._initial_tilt_rad = tilt
        self.reset(ctx.seed)
        log.info("built world for object %r (%s)", self.spec.name, self.spec.type)

    def reset(self, seed: int) -> None:
        """Object at its spec pose, gripper at its start pose and open, time 0.

        The world is deterministic: ``seed`` is accepted for the protocol and not used.
        """
        del seed
        model, data, index = self.model, self.data, self.index
        mujoco.mj_resetData(model, data)
        self._clock_s = 0.0
        self.table_tilt_rad = self._initial_tilt_rad
        start = np.asarray(self.config.gripper_start, dtype=np.float64)
        data.qpos[index.arm_qpos] = start
        data.act[model.actuator_actadr[index.arm_actuators]] = start
        data.qpos[index.finger_qpos] = self.geometry.max_finger_travel_m
        data.ctrl[index.finger_actuators] = self.geometry.max_finger_travel_m
        mujoco.mj_forward(model, data)

    def step(self, dt_s: float) -> None:
        """Advance physics by ``dt_s``: whole timesteps, keeping the simulated time within half
        a timestep of the sum of all ``dt_s`` since ``reset``."""
        if not dt_s > 0:
            raise ValueError(f"dt_s must be > 0, got {dt_s}")
        self._clock_s += dt_s
        steps = round((self._clock_s - self.data.time) / self.model.opt.timestep)
        if steps > 0:
            mujoco.mj_step(self.model, self.data, nstep=steps)

    @property
    def time_s(self) -> float:
        return float(self.data.time)

    @property
    def table_tilt_rad(self) -> float:
        """Current table tilt about world x (settable, e.g. to test change detection)."""
        gravity = self.model.opt.gravity
        return float(np.arctan2(-gravity[1], -gravity[2]))

    @table_tilt_rad.setter
    def table_tilt_rad(self, tilt_rad: float) -> None:
        self.model.opt.gravity[:] = gravity_vector(tilt_rad)

    def link_poses(self) -> FloatArray:
        """Link body frames in the world: [L, 3] = (x_m, y_m, theta_rad)."""
        return planar_poses(self.data, self.index.link_bodies)

    def ground_truth_poses(self) -> FloatArray:
        """True link poses [L, 3] for recording (alias of :meth:`link_poses`)."""
        return self.link_poses()

    def ground_truth(self) -> dict[str, Any]:
        """Object parameters, link poses [L, 3] and tilt. For evaluation and recording only."""
        return {
            "object": self.spec.model_dump(mode="json"),
            "parameters": self.spec.parameters(),
            "link_poses": self.link_poses(),
            "table_tilt_rad": self.table_tilt_rad,
            "time_s": self.time_s,
        }

    def object_center_m(self) -> FloatArray:
        """Mean of the link frames at half the tallest link's height: [3]."""
        centre = self.link_poses()[:, :2].mean(axis=0)
        height = max(link.height_m for link in self.spec.links)
        return np.array([centre[0], centre[1], 0.5 * height])
