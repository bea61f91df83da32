"""A generic CAN force/tactile sensor through python-can (any interface: socketcan, pcan,
virtual, ...).

Each pad publishes its force on its own arbitration ID as ``axes`` signed 16-bit integers
(fx, fy[, fz], gripper frame, ``byte_order``); force_n = count * ``scale_n_per_count`` +
``offset_n``. Frames with an unknown ID belong to other devices and are ignored; a frame of a
pad's ID that is too short, or an error frame, is malformed: counted, logged, skipped.
"""

from __future__ import annotations

from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from vistac.component import ComponentConfig, ComponentContext
from vistac.errors import HardwareError
from vistac.plugins.hardware.streaming import StreamingTactile


class PadSignal(BaseModel):
    """Where one pad's force is on the bus and how to scale it."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    arbitration_id: int = Field(ge=0, le=0x1FFFFFFF)
    axes: Literal[2, 3] = 2
    scale_n_per_count: float = 0.001
    offset_n: tuple[float, float, float] = (0.0, 0.0, 0.0)


class CanForceSensor(StreamingTactile):
    """Implements the ``Tactile`` protocol for pads that publish on a CAN bus."""

    class Config(ComponentConfig):
        interface: str = "socketcan"
        channel: str = "can0"
        bitrate: int | None = Field(default=None, gt=0)
        pads: tuple[PadSignal, ...] = (
            PadSignal(arbitration_id=0x101),
            PadSignal(arbitration_id=0x102),
        )
        byte_order: Literal["little", "big"] = "little"
        first_data_timeout_s: float = Field(default=2.0, gt=0.0)

    def __init__(self, config: Config, ctx: ComponentContext) -> None:
        ids = [pad.arbitration_id for pad in config.pads]
        if len(set(ids)) != len(ids) or not ids:
            raise HardwareError(f"can.force_sensor: pad arbitration IDs must be distinct: {ids}")
        super().__init__(config, ctx, len(config.pads), f"CAN sensor on {config.channel}")
        import can

        options: dict[str, Any] = {"interface": config.interface, "channel": config.channel}
        if config.bitrate is not None:
            options["bitrate"] = config.bitrate
        try:
            self.bus = can.Bus(**options)
        except (can.CanError, OSError, ValueError, ImportError) as exc:
            raise HardwareError(
                f"can.force_sensor: cannot open {config.interface} bus {config.channel}: {exc}"
            ) from exc
        self._pad_of = {pad.arbitration_id: index for index, pad in enumerate(config.pads)}
        self._dtype = np.dtype("<i2" if config.byte_order == "little" else ">i2")
        self.start(config.first_data_timeout_s)

    def _run(self) -> None:
        while not self._stopping.is_set():
            message = self.bus.recv(timeout=0.05)
            if message is not None:
                self._decode(message)

    def _decode(self, message: Any) -> None:
        if message.is_error_frame:
            self.count_malformed("error frame")
            return
        pad = self._pad_of.get(message.arbitration_id)
        if pad is None:
            return
        signal = self.config.pads[pad]
        needed = 2 * signal.axes
        if message.dlc < needed or len(message.data) < needed:
            self.count_malformed(f"ID {message.arbitration_id:#x}: {message.dlc} bytes < {needed}")
            return
        counts = np.frombuffer(bytes(message.data[:needed]), dtype=self._dtype)
        force = np.zeros(3)
        force[: signal.axes] = counts * signal.scale_n_per_count
        self.publish(pad, force + np.asarray(signal.offset_n))

    def close(self) -> None:
        super().close()
        self.bus.shutdown()
