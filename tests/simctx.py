"""A minimal component context and builders for the simulated devices (test helpers)."""

from __future__ import annotations

import zlib
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from vistac.component import Component
from vistac.plugins.hardware.sim.arm import SimArm
from vistac.plugins.hardware.sim.camera import SimDepthCamera
from vistac.plugins.hardware.sim.gripper import SimGripper
from vistac.plugins.hardware.sim.tactile import SimTactile
from vistac.plugins.hardware.sim.world import MujocoWorld

PUSH_RATE_HZ = 15.0
"""The skills' control rate: a recorded push's steps."""
PUSH_SPEED_MPS = 0.02
"""A test push's gripper speed."""
GRIPPER_Z_M = 0.02
"""The executor's finger height: the gripper body 20 mm above the table."""


class TestContext:
    """skill_dir, seed, ``rng(stream)`` and ``find(kind)`` over explicitly added components."""

    __test__ = False

    def __init__(self, skill_dir: Path, seed: int = 0) -> None:
        self.skill_dir = skill_dir
        self.seed = seed
        self.components: dict[str, Any] = {}

    def rng(self, stream: str) -> np.random.Generator:
        return np.random.default_rng([self.seed, zlib.crc32(stream.encode())])

    def find(self, kind: str) -> Any:
        """The component of ``kind`` or None (typed Any so tests can use it directly)."""
        return self.components.get(kind)

    def add(self, cls: type[Component], **options: Any) -> Any:
        config = cls.Config.model_validate(options, context={"skill_dir": self.skill_dir})
        component = cls(config, self)
        self.components[cls.kind] = component
        return component


def box_object(**overrides: Any) -> dict[str, Any]:
    """A homogeneous rect1 box (90 x 90 x 50 mm) at (0, 0.45), as an object-file mapping."""
    link = {"footprint": "rect1", "height_m": 0.05, "mass_kg": 0.5, "friction": 0.3}
    link.update(overrides.pop("link", {}))
    spec: dict[str, Any] = {
        "name": "box",
        "type": "homogeneous",
        "links": [link],
        "pose": [0.0, 0.45, 0.0],
    }
    spec.update(overrides)
    return spec


def sim_setup(tmp_path: Path, spec: dict[str, Any], seed: int = 0, **world: Any) -> TestContext:
    """Write ``spec`` to a YAML file and build a world, arm, gripper and tactile sensor."""
    tmp_path.mkdir(parents=True, exist_ok=True)
    (tmp_path / "object.yaml").write_text(yaml.safe_dump(spec), encoding="utf-8")
    ctx = TestContext(tmp_path, seed)
    ctx.add(MujocoWorld, object="object.yaml", **world)
    ctx.add(SimArm)
    ctx.add(SimGripper)
    ctx.add(SimTactile, noise_n=0.0)
    return ctx


def add_camera(ctx: TestContext, **options: Any) -> SimDepthCamera:
    camera: SimDepthCamera = ctx.add(SimDepthCamera, **options)
    return camera
