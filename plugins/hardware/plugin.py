"""Registers the real devices. Imports nothing heavy: ``ur_rtde``, ``serial``, ``can`` and
``cv2`` are imported only when a skill builds the component."""

from __future__ import annotations

from vistac import hookimpl
from vistac.registry import Registry

_PACKAGE = "vistac.plugins.hardware"


@hookimpl
def vistac_register(registry: Registry) -> None:
    registry.add("arm", "ur_rtde.arm", f"{_PACKAGE}.ur_rtde.arm:URArm")
    registry.add("gripper", "robotiq.2f85", f"{_PACKAGE}.robotiq.gripper:Robotiq2F85")
    registry.add("tactile", "contactile.papillarray", f"{_PACKAGE}.contactile.tactile:PapillArray")
    registry.add("tactile", "can.force_sensor", f"{_PACKAGE}.can_bus.tactile:CanForceSensor")
    registry.add("camera", "camera.rgbd", f"{_PACKAGE}.camera.rgbd:RGBDCamera")
    registry.add("camera", "camera.recorded", f"{_PACKAGE}.camera.recorded:RecordedCamera")
