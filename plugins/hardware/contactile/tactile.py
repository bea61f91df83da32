"""Contactile PapillArray pads over their USB serial stream (framing: ``protocol``).

Per sensor, the global force (sensor frame) is rotated into the gripper frame by a fixed
rotation per sensor (``sensor_to_gripper``, rows of a 3x3 matrix), then into the world frame
with the arm's current yaw; the reading is its world (x, y) part, the force the object exerts
on each pad, as ``sim.tactile`` reports it. ``bias`` sends the device's bias command.
"""

from __future__ import annotations

import logging

import numpy as np
from pydantic import Field, field_validator
from vistac.component import ComponentConfig, ComponentContext
from vistac.errors import HardwareError
from vistac.plugins.hardware.contactile import protocol
from vistac.plugins.hardware.streaming import StreamingTactile

log = logging.getLogger(__name__)

Matrix3 = tuple[tuple[float, float, float], tuple[float, float, float], tuple[float, float, float]]
# Pad 0 on the finger at gripper -y, its surface normal (sensor z) facing +y; pad 1 opposite.
_PAD0: Matrix3 = ((1.0, 0.0, 0.0), (0.0, 0.0, 1.0), (0.0, -1.0, 0.0))
_PAD1: Matrix3 = ((-1.0, 0.0, 0.0), (0.0, 0.0, -1.0), (0.0, -1.0, 0.0))


class PapillArray(StreamingTactile):
    """Implements the ``Tactile`` protocol on two (or more) PapillArray sensors."""

    class Config(ComponentConfig):
        port: str = "/dev/ttyACM0"
        baudrate: int = Field(default=921600, gt=0)
        sensors: int = Field(default=2, ge=1, le=8)
        sensor_to_gripper: tuple[Matrix3, ...] = (_PAD0, _PAD1)
        """Per sensor: rotation from the sensor frame to the gripper frame (rows)."""
        first_data_timeout_s: float = Field(default=2.0, gt=0.0)
        read_timeout_s: float = Field(default=0.05, gt=0.0)

        @field_validator("sensor_to_gripper")
        @classmethod
        def _rotations(cls, value: tuple[Matrix3, ...]) -> tuple[Matrix3, ...]:
            for index, rows in enumerate(value):
                matrix = np.asarray(rows)
                if not np.allclose(matrix @ matrix.T, np.eye(3), atol=1e-6) or not np.isclose(
                    np.linalg.det(matrix), 1.0
                ):
                    raise ValueError(f"sensor_to_gripper[{index}] is not a rotation matrix")
            return value

    def __init__(self, config: Config, ctx: ComponentContext) -> None:
        if len(config.sensor_to_gripper) != config.sensors:
            raise HardwareError(
                f"contactile.papillarray: sensor_to_gripper has {len(config.sensor_to_gripper)} "
                f"rotations for {config.sensors} sensors; give one per sensor"
            )
        super().__init__(config, ctx, config.sensors, f"PapillArray on {config.port}")
        import serial

        try:
            self.serial = serial.Serial(
                config.port, config.baudrate, timeout=config.read_timeout_s, write_timeout=0.5
            )
        except (serial.SerialException, OSError) as exc:
            raise HardwareError(f"PapillArray: cannot open {config.port}: {exc}") from exc
        self._rotations = np.asarray(config.sensor_to_gripper, dtype=np.float64)
        self.splitter = protocol.FrameSplitter()
        self.start(config.first_data_timeout_s)

    def _run(self) -> None:
        while not self._stopping.is_set():
            data = self.serial.read(4096) or b""
            before = self.splitter.malformed
            frames = self.splitter.feed(data)
            for _ in range(self.splitter.malformed - before):
                self.count_malformed("bad sync, length or checksum")
            for frame in frames:
                if frame.sensor_id >= len(self._rotations):
                    self.count_malformed(f"unknown sensor id {frame.sensor_id}")
                    continue
                force = self._rotations[frame.sensor_id] @ frame.global_wrench[:3]
                self.publish(frame.sensor_id, force)

    def bias(self) -> None:
        """Send the bias command: the device zeroes its pillars (nothing may touch them)."""
        try:
            self.serial.write(protocol.BIAS_COMMAND)
        except Exception as exc:
            raise HardwareError(f"PapillArray: bias command failed: {exc}") from exc

    def close(self) -> None:
        super().close()
        self.serial.close()
