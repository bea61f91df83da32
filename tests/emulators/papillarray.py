"""A PapillArray stream (``vistac.plugins.hardware.contactile.protocol``) on a pseudo-terminal.

Streams one frame per sensor at ``rate_hz``: nine pillars whose forces add up to the
sensor's global force (``set_force``), minus the offsets taken by the bias command. Test
modes: ``corrupt_every`` (every Nth frame has a broken checksum, plus a burst of garbage
bytes) and ``silent`` (nothing is sent).
"""

from __future__ import annotations

import contextlib
import os
import select
import time

import numpy as np
from vistac.plugins.hardware.contactile import protocol

from emulators.pty import PtyDevice

PILLARS = 9


class PapillArrayPty(PtyDevice):
    def __init__(self, sensors: int = 2, rate_hz: float = 100.0) -> None:
        self.sensors = sensors
        self.period_s = 1.0 / rate_hz
        self.force_n = np.zeros((sensors, 3))
        self.offset_n = np.zeros((sensors, 3))
        self.corrupt_every = 0
        self.bias_commands = 0
        self.frames_sent = 0
        super().__init__()

    def set_force(self, sensor: int, force_n: list[float]) -> None:
        self.force_n[sensor] = force_n

    def frame(self, sensor: int) -> bytes:
        force = self.force_n[sensor] - self.offset_n[sensor]
        pillars = np.zeros((PILLARS, 6))
        pillars[:, 3:] = force / PILLARS
        pillars[:, :3] = force / PILLARS * 0.1  # 0.1 mm per N of displacement
        wrench = np.concatenate([force, np.zeros(3)])
        device_time_us = int(time.monotonic() * 1e6) & 0xFFFFFFFF
        return protocol.encode(protocol.SensorFrame(sensor, device_time_us, pillars, wrench))

    def _run(self) -> None:
        next_s = time.monotonic()
        while not self._stop.is_set():
            next_s += self.period_s
            self._handle_commands(max(0.0, next_s - time.monotonic()))
            if self.silent:
                continue
            for sensor in range(self.sensors):
                data = self.frame(sensor)
                self.frames_sent += 1
                if self.corrupt_every and self.frames_sent % self.corrupt_every == 0:
                    data = b"\x00\x55garbage" + data[:-1] + bytes([data[-1] ^ 0xFF])
                with contextlib.suppress(OSError):
                    os.write(self.master, data)

    def _handle_commands(self, wait_s: float) -> None:
        ready, _, _ = select.select([self.master], [], [], wait_s)
        if not ready:
            return
        with contextlib.suppress(OSError):
            if protocol.BIAS_COMMAND in os.read(self.master, 1024):
                self.bias_commands += 1
                self.offset_n = self.force_n.copy()
