"""Base of tactile sensors that stream on their own: a reader thread keeps the latest force
per pad with the ``time.monotonic()`` time it arrived (the clock ``WallClock`` runs on).

``read()`` returns the latest forces rotated into the world frame with the arm's current yaw;
its ``timestamp_s`` is the arrival time of the oldest pad's latest sample, so a silent pad
makes the reading stale and ``execute_action`` (``max_sensor_age_s``) stops the arm.
Malformed frames are counted in ``malformed``, logged and skipped; they never raise.
"""

from __future__ import annotations

import logging
import threading
import time

import numpy as np
from vistac.component import Component, ComponentContext
from vistac.errors import HardwareError
from vistac.plugins.hardware.frames import arm_yaw_rad, gripper_to_world_xy
from vistac.types import FloatArray, TactileReading

log = logging.getLogger(__name__)

_LOGGED_MALFORMED = 10


class StreamingTactile(Component):
    """Implements the ``Tactile`` protocol for ``pads`` pads fed by ``_run`` in a thread."""

    kind = "tactile"

    def __init__(self, config: object, ctx: ComponentContext, pads: int, name: str) -> None:
        super().__init__(config, ctx)
        self.name = name
        self.malformed = 0
        self._lock = threading.Lock()
        self._force_gripper_n = np.zeros((pads, 3))
        self._bias_n = np.zeros((pads, 3))
        self._arrived_s = np.full(pads, -np.inf)
        self._stopping = threading.Event()
        self._thread = threading.Thread(target=self._guarded_run, name=name, daemon=True)

    def start(self, first_data_timeout_s: float) -> None:
        """Start the reader and wait until every pad has reported once."""
        self._thread.start()
        deadline = time.monotonic() + first_data_timeout_s
        while not np.all(np.isfinite(self._arrived_s)):
            if time.monotonic() > deadline or not self._thread.is_alive():
                self.close()
                missing = np.flatnonzero(~np.isfinite(self._arrived_s)).tolist()
                raise HardwareError(
                    f"{self.name}: no data from pads {missing} within {first_data_timeout_s} s; "
                    "check the cable, the port/bus and the sensor's configuration"
                )
            time.sleep(0.01)

    def _guarded_run(self) -> None:
        try:
            self._run()
        except Exception as exc:  # the reading goes stale and the arm is stopped
            log.error("%s: reader stopped: %s", self.name, exc)

    def _run(self) -> None:
        raise NotImplementedError

    def publish(self, pad: int, force_gripper_n: FloatArray) -> None:
        """Store pad ``pad``'s latest force [3] (gripper frame, N)."""
        with self._lock:
            self._force_gripper_n[pad] = force_gripper_n
            self._arrived_s[pad] = time.monotonic()

    def count_malformed(self, why: str) -> None:
        self.malformed += 1
        if self.malformed <= _LOGGED_MALFORMED or self.malformed % 100 == 0:
            log.warning(
                "%s: malformed frame skipped (%d so far): %s", self.name, self.malformed, why
            )

    def read(self) -> TactileReading:
        with self._lock:
            force_n = self._force_gripper_n - self._bias_n
            timestamp_s = float(np.min(self._arrived_s))
        world_n = gripper_to_world_xy(force_n, arm_yaw_rad(self.ctx.find("arm")))
        return TactileReading(force_n=world_n, timestamp_s=timestamp_s)

    def bias(self) -> None:
        """Zero the pads in software (the current forces become the offsets)."""
        with self._lock:
            self._bias_n = self._force_gripper_n.copy()

    def close(self) -> None:
        self._stopping.set()
        if self._thread.is_alive():
            self._thread.join(1.0)
