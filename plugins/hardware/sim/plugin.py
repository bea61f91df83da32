"""Registers the simulated (MuJoCo) devices. Imports nothing heavy."""

from __future__ import annotations

from vistac import hookimpl
from vistac.registry import Registry

_PACKAGE = "vistac.plugins.hardware.sim"


@hookimpl
def vistac_register(registry: Registry) -> None:
    registry.add("world", "sim.mujoco", f"{_PACKAGE}.world:MujocoWorld")
    registry.add("arm", "sim.arm", f"{_PACKAGE}.arm:SimArm")
    registry.add("gripper", "sim.gripper", f"{_PACKAGE}.gripper:SimGripper")
    registry.add("camera", "sim.depth_camera", f"{_PACKAGE}.camera:SimDepthCamera")
    registry.add("tactile", "sim.tactile", f"{_PACKAGE}.tactile:SimTactile")
    registry.add("touch_probe", "sim.touch_probe", f"{_PACKAGE}.touch_probe:SimTouchProbe")
    registry.add("shape_estimator", "sim.true_shape", f"{_PACKAGE}.true_shape:TrueShape")
    registry.add("process_model", "sim.physics", f"{_PACKAGE}.physics_model:PhysicsProcessModel")
