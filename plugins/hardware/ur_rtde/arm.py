"""The UR arm through ``ur_rtde`` (RTDEControlInterface + RTDEReceiveInterface).

Same protocol, config fields and workspace semantics as ``sim.arm``: velocity streaming
(``speedL``) capped at ``max_speed_mps``, motion that would leave the workspace box refused
(``SafetyError``), TCP pointing down with yaw about world z (world = robot base frame).

Safety, checked before every command:

- connection and freshness. The library's getters keep returning the last value after the
  connection drops, and ``isConnected`` lags, so the age of the latest RTDE sample must be
  under ``max_data_age_s``. Its age is measured on the local ``time.monotonic`` clock (the one
  ``WallClock`` uses) through the offset between that clock and the RTDE ``timestamp``, so
  data that stopped during an idle gap counts as old. Stale data or a lost connection raises
  ``HardwareError`` and marks the arm disconnected until ``reconnect()``.
- protective, safeguard and emergency stops, safety faults and violations, and any safety mode
  but normal or reduced: motion is refused with ``SafetyError`` until a person clears it on
  the pendant (or the dashboard's ``unlock protective stop``); the plugin never clears it.
  ``speedL`` reports success during a protective stop, so the safety bits are read before
  each command rather than trusting the return value.
- ``stop()`` sends ``speedStop`` and ``stopL`` (which ends an asynchronous ``moveL``) whenever
  the interfaces exist, also after a stale read marked the arm disconnected.
- near the workspace walls each velocity component towards a wall is limited so that the arm
  can stop within the remaining distance (``lookahead_s`` of reaction, then
  ``acceleration_mps2``).
- connecting: ``probe_controller`` first checks, with timeouts, that the controller streams
  RTDE data, because the library's constructors hold the GIL while they wait (forever for a
  controller that accepts connections but sends nothing) and no deadline can stop them.
- every library call runs with a deadline (``command_timeout_s``): ``moveL`` on a dropped
  connection would otherwise block for minutes. A move is stopped when it has come no closer
  to its target for ``move_timeout_margin_s``: how fast the controller's ``moveL`` turns the
  tool is its own choice, so no deadline is computed from the distance.
- an RTDE watchdog (``watchdog_min_hz``) makes the controller stop the arm when commands stop
  arriving; while the arm is idle a background thread keeps it fed.
"""

from __future__ import annotations

import contextlib
import ctypes
import logging
import threading
import time
from typing import Any

import numpy as np
from pydantic import Field
from vistac.component import Component, ComponentContext
from vistac.errors import HardwareError, SafetyError
from vistac.plugins.hardware.deadline import call_with_deadline
from vistac.plugins.hardware.limits import AXES, ArmLimits, leaving_workspace
from vistac.plugins.hardware.ur_rtde.frames import arm_pose, tcp_pose
from vistac.plugins.hardware.ur_rtde.probe import probe_controller
from vistac.types import ArmState, FloatArray

log = logging.getLogger(__name__)

_BOUNDARY_TOLERANCE_M = 1e-4
_ARRIVED_M = 2e-4
_ARRIVED_RAD = 2e-3
_PROGRESS_M = 2e-4
_PROGRESS_RAD = 5e-3
"""Least approach to a move's target that counts as progress (above the TCP pose's noise)."""
_CLOCK_DRIFT = 1e-3
"""How fast (s/s) the RTDE clock offset may grow: follows a controller clock running slow."""
_MOVE_POLL_S = 0.01
_DISCONNECT_TIMEOUT_S = 2.0
_NORMAL_OR_REDUCED_BITS = (1 << 0) | (1 << 1)
_SAFETY_STOPS = (  # RTDE safety_status_bits that refuse motion, as the RTDE guide numbers them
    (2, "a protective stop"),
    (5, "a system emergency stop"),
    (6, "a robot emergency stop"),
    (7, "an emergency stop"),
    (4, "a safeguard stop"),
    (9, "a safety fault"),
    (8, "a safety violation"),
    (10, "a stop due to safety"),
)
RECEIVE_VARIABLES = [
    "timestamp",
    "actual_TCP_pose",
    "actual_TCP_speed",
    "actual_TCP_force",
    "robot_mode",
    "safety_mode",
    "safety_status_bits",
    "robot_status_bits",
    "runtime_state",
]


class URArm(Component):
    """Implements the ``Arm`` protocol on a Universal Robots arm over RTDE."""

    kind = "arm"

    class Config(ArmLimits):
        host: str = "192.168.1.10"
        """The controller's IP address."""
        frequency_hz: float = Field(default=-1.0, description="RTDE rate; -1: the controller's")
        acceleration_mps2: float = Field(default=0.5, gt=0.0, le=2.0)
        stop_deceleration_mps2: float = Field(default=2.0, gt=0.0, le=10.0)
        lookahead_s: float = Field(default=0.1, gt=0.0, le=1.0)
        """Reaction time near the walls (at least the control period): velocity components
        are limited so that the TCP, moving this long and then braking, stays in the box."""
        max_data_age_s: float = Field(default=0.1, gt=0.0)
        """Older RTDE data means the connection is lost."""
        command_timeout_s: float = Field(default=0.3, gt=0.0)
        connect_timeout_s: float = Field(default=10.0, gt=0.0)
        move_timeout_margin_s: float = Field(default=2.0, gt=0.0)
        """A move that comes no closer to its target (by 0.2 mm, or 0.3 deg of yaw) for this
        long is stopped."""
        watchdog_min_hz: float = Field(default=2.0, gt=0.0)
        """RTDE watchdog: the controller stops the arm without input this often."""
        upload_script: bool = True
        """Upload ur_rtde's control script (False: an ExternalControl/custom program runs)."""

    def __init__(self, config: Config, ctx: ComponentContext) -> None:
        super().__init__(config, ctx)
        self.max_speed_mps = config.max_speed_mps
        self._low = np.asarray(config.workspace_min_m, dtype=np.float64)
        self._high = np.asarray(config.workspace_max_m, dtype=np.float64)
        self._control: Any = None
        self._receive: Any = None
        self._lock = threading.Lock()
        """Held while a command runs on the current control interface."""
        self._connected = False
        self._streaming = False
        self._closed = threading.Event()
        self._clock_offset_s = np.inf
        self._offset_at_s = 0.0
        self.connect()
        threading.Thread(target=self._feed_watchdog, name="ur_rtde-watchdog", daemon=True).start()

    # --- connection ----------------------------------------------------------------------
    def connect(self) -> None:
        """Open the RTDE interfaces (uploads the control script); HardwareError on failure."""
        import rtde_control
        import rtde_receive

        config = self.config
        flags = rtde_control.RTDEControlInterface.Flags
        mask = int(flags.FLAG_UPLOAD_SCRIPT) if config.upload_script else 0

        def open_interfaces() -> tuple[Any, Any]:
            receive = rtde_receive.RTDEReceiveInterface(
                config.host, config.frequency_hz, RECEIVE_VARIABLES
            )
            control = rtde_control.RTDEControlInterface(config.host, config.frequency_hz, mask)
            return receive, control

        probe_controller(config.host, config.connect_timeout_s)
        self._lock = threading.Lock()  # a command stuck on abandoned interfaces holds the old
        what = f"connecting to the UR controller at {config.host}"
        self._receive, self._control = call_with_deadline(
            open_interfaces, config.connect_timeout_s, what
        )
        self._connected = True
        self._clock_offset_s, self._offset_at_s = np.inf, time.monotonic()
        self._check_fresh()
        self._call(lambda c: c.setWatchdog(config.watchdog_min_hz), "setWatchdog")
        self._streaming = False
        log.info("connected to the UR controller at %s", config.host)

    def reconnect(self) -> None:
        """Drop the old interfaces (never waiting on them) and connect again."""
        self._connected = False
        self._abandon()
        self.connect()

    @property
    def connected(self) -> bool:
        return self._connected

    def _abandon(self) -> None:
        """Disconnect the current interfaces, each with a deadline, while no command runs on
        them. A command still blocked after ``_DISCONNECT_TIMEOUT_S`` leaves both connected
        (``_keep_alive``) and the controller's watchdog stops the arm: disconnecting either
        interface under a blocked ``moveL`` made ur_rtde crash the process."""
        locked = self._lock.acquire(timeout=_DISCONNECT_TIMEOUT_S)
        try:
            old = [i for i in (self._control, self._receive) if i is not None]
            self._control = self._receive = None
            if old and not locked:
                log.warning(
                    "UR arm at %s: a command is still blocked; its RTDE interfaces are left "
                    "connected (the controller's watchdog stops the arm)",
                    self.config.host,
                )
            for interface in old:
                if locked:
                    _disconnect(interface)
                else:
                    _keep_alive(interface)
        finally:
            if locked:
                self._lock.release()

    def _lost(self, reason: str) -> HardwareError:
        """Mark the arm disconnected and return the error to raise."""
        if self._connected:
            log.error("UR arm at %s: %s", self.config.host, reason)
        self._connected = False
        return HardwareError(
            f"UR arm at {self.config.host}: {reason}; check the cable and the controller, "
            "then reconnect"
        )

    def _check_fresh(self) -> float:
        """Raise HardwareError unless the connection is up and the latest RTDE sample is
        younger than ``max_data_age_s``; returns when that sample was taken (monotonic s)."""
        if not self._connected or self._receive is None:
            raise self._lost("not connected")
        receive = self._receive
        timestamp_s = call_with_deadline(
            receive.getTimestamp, self.config.command_timeout_s, "RTDE getTimestamp"
        )
        now_s = time.monotonic()
        sampled_s = self._local_time_s(float(timestamp_s), now_s)
        age_s = now_s - sampled_s
        if age_s > self.config.max_data_age_s:
            raise self._lost(
                f"no new RTDE data for {age_s * 1e3:.0f} ms "
                f"(limit {self.config.max_data_age_s * 1e3:.0f} ms)"
            )
        if not receive.isConnected():
            raise self._lost("the RTDE connection closed")
        return sampled_s

    def _local_time_s(self, timestamp_s: float, now_s: float) -> float:
        """Local monotonic time of the RTDE sample stamped ``timestamp_s`` (controller clock).

        The clock offset is the smallest ``now_s - timestamp_s`` seen (the sample that came
        with the least delay), allowed to grow by ``_CLOCK_DRIFT`` per second."""
        drift_s = _CLOCK_DRIFT * (now_s - self._offset_at_s)
        self._clock_offset_s = min(self._clock_offset_s + drift_s, now_s - timestamp_s)
        self._offset_at_s = now_s
        return timestamp_s + self._clock_offset_s

    def _call(self, command: Any, what: str) -> Any:
        """Run ``command(control_interface)`` with a deadline; a timeout disconnects."""
        if not self._connected or self._control is None:
            raise self._lost("not connected")
        try:
            return self._run(self._control, command, what)
        except HardwareError as exc:
            raise self._lost(str(exc)) from exc

    def _run(self, control: Any, command: Any, what: str) -> Any:
        """Run ``command(control)`` alone on the interface within ``command_timeout_s``."""
        deadline_s = self.config.command_timeout_s

        def locked() -> Any:
            if not self._lock.acquire(timeout=deadline_s):
                raise HardwareError(f"{what}: another command to the arm is still blocked")
            try:
                if control is not self._control:  # abandoned while this call waited
                    raise HardwareError(f"{what}: the connection was closed")
                return command(control)
            finally:
                self._lock.release()

        return call_with_deadline(locked, deadline_s, f"{what} on the UR arm")

    # --- safety ------------------------------------------------------------------------------
    def _safety_bits(self) -> int:
        return int(self._receive.getSafetyStatusBits())

    def _refuse_if_stopped(self) -> None:
        bits = self._safety_bits()
        condition = safety_condition(bits)
        if condition is not None:
            self._streaming = False
            raise SafetyError(
                f"UR arm is in {condition}: motion refused. A person must clear it on the "
                "pendant (or the dashboard's 'unlock protective stop') before the skill is run "
                f"again (safety status bits {bits:#x})"
            )

    def _limit_to_workspace(self, velocity_mps: FloatArray, position_m: FloatArray) -> FloatArray:
        """Refuse outward motion at the boundary; limit components that would cross it."""
        reason = leaving_workspace(
            position_m, velocity_mps, self._low, self._high, _BOUNDARY_TOLERANCE_M
        )
        if reason is not None:
            self.stop()
            raise SafetyError(f"arm motion refused: it would leave the workspace ({reason})")
        highest = self._stoppable_speed_mps(self._high - position_m)
        lowest = -self._stoppable_speed_mps(position_m - self._low)
        return np.clip(velocity_mps, lowest, highest)

    def _stoppable_speed_mps(self, distance_m: FloatArray) -> FloatArray:
        """Per axis [3], the speed from which the arm stops within ``distance_m`` (0 where it
        is negative): ``lookahead_s`` at that speed until the next command, then braking at
        ``acceleration_mps2``; solves v t + v^2 / (2 a) = d."""
        reaction_s, acceleration = self.config.lookahead_s, self.config.acceleration_mps2
        distance = np.maximum(distance_m, 0.0)
        return acceleration * (np.sqrt(reaction_s**2 + 2.0 * distance / acceleration) - reaction_s)

    # --- Arm protocol -----------------------------------------------------------------------
    def state(self) -> ArmState:
        """TCP pose and twist; ``timestamp_s`` is when this RTDE sample was taken (local
        monotonic clock)."""
        sampled_s = self._check_fresh()
        receive = self._receive
        pose = np.asarray(receive.getActualTCPPose(), dtype=np.float64)
        speed = np.asarray(receive.getActualTCPSpeed(), dtype=np.float64)
        stopped = safety_condition(self._safety_bits()) is not None
        return ArmState(
            pose=arm_pose(pose),
            twist=np.array([speed[0], speed[1], speed[2], speed[5]]),
            timestamp_s=sampled_s,
            protective_stop=stopped,
        )

    def wrench(self) -> FloatArray:
        """TCP force and torque [6] = (fx, fy, fz N, tx, ty, tz N m), base frame."""
        self._check_fresh()
        return np.asarray(self._receive.getActualTCPForce(), dtype=np.float64)

    def command_velocity(self, twist: FloatArray) -> None:
        """Stream twist [4] = (vx, vy, vz, wz); clamped to the caps, held until the next call."""
        command = np.asarray(twist, dtype=np.float64)
        if command.shape != (4,) or not np.all(np.isfinite(command)):
            self.stop()
            raise SafetyError(f"arm twist must be 4 finite numbers, got {command!r}")
        self._check_fresh()
        self._refuse_if_stopped()
        speed_mps = float(np.linalg.norm(command[:3]))
        if speed_mps > self.max_speed_mps:
            command[:3] *= self.max_speed_mps / speed_mps
        limit = self.config.max_yaw_rate_rad_s
        command[3] = np.clip(command[3], -limit, limit)
        position = np.asarray(self._receive.getActualTCPPose(), dtype=np.float64)[:3]
        command[:3] = self._limit_to_workspace(command[:3], position)
        speed = [command[0], command[1], command[2], 0.0, 0.0, command[3]]
        acceleration = self.config.acceleration_mps2
        self._streaming = bool(np.any(command))
        accepted = self._call(lambda c: c.speedL(speed, acceleration, 0.0), "speedL")
        if not accepted:
            self.stop()
            raise HardwareError("the UR controller refused speedL (is the control script running?)")

    def move_to(self, pose: FloatArray, speed_mps: float | None = None) -> None:
        """Linear move (``moveL``) to pose [4] = (x, y, z, yaw); returns when it is reached.

        The target must be inside the workspace and the speed is capped. The move is started
        asynchronously and supervised here (freshness, protective stop, watchdog) until the
        TCP is within ``_ARRIVED_M`` and ``_ARRIVED_RAD`` (yaw) of the target; when it has come
        no closer for ``move_timeout_margin_s`` the arm is stopped and ``HardwareError`` raised.
        """
        target = np.asarray(pose, dtype=np.float64)
        if target.shape != (4,) or not np.all(np.isfinite(target)):
            raise SafetyError(f"move target must be 4 finite numbers, got {target!r}")
        outside = (target[:3] < self._low) | (target[:3] > self._high)
        if np.any(outside):
            axis = int(np.argmax(outside))
            raise SafetyError(
                f"move target {target[:3].tolist()} is outside the workspace on {AXES[axis]} "
                f"([{self._low[axis]:.3f}, {self._high[axis]:.3f}] m)"
            )
        speed = min(speed_mps or self.max_speed_mps, self.max_speed_mps)
        self._check_fresh()
        self._refuse_if_stopped()
        tcp = tcp_pose(target).tolist()
        acceleration = self.config.acceleration_mps2
        self._streaming = False
        if not self._call(lambda c: c.moveL(tcp, speed, acceleration, True), "moveL"):
            self._refuse_if_stopped()
            raise HardwareError("the UR controller refused moveL (is the control script running?)")
        self._supervise_move(target)

    def _supervise_move(self, target: FloatArray) -> None:
        """Wait until the TCP is at target [4]; stop the arm when it stops approaching it."""
        closest = np.full(2, np.inf)
        progress = np.array([_PROGRESS_M, _PROGRESS_RAD])
        approached_s = time.monotonic()
        while True:
            error = self._move_error(target)
            if error[0] < _ARRIVED_M and error[1] < _ARRIVED_RAD:
                return
            if np.any(error < closest - progress):
                closest, approached_s = np.minimum(closest, error), time.monotonic()
            elif time.monotonic() - approached_s > self.config.move_timeout_margin_s:
                self.stop()
                raise HardwareError(
                    f"moveL did not reach {target.tolist()}: no closer for "
                    f"{self.config.move_timeout_margin_s} s, {error[0] * 1e3:.1f} mm and "
                    f"{np.degrees(error[1]):.1f} deg away"
                )
            time.sleep(_MOVE_POLL_S)

    def _move_error(self, target: FloatArray) -> FloatArray:
        """Supervise a move (fresh data, no protective stop); the TCP's distance to target [4]:
        [2] = (position m, |yaw| rad)."""
        self._check_fresh()
        self._refuse_if_stopped()
        pose = arm_pose(np.asarray(self._receive.getActualTCPPose(), dtype=np.float64))
        yaw_error_rad = (pose[3] - target[3] + np.pi) % (2.0 * np.pi) - np.pi
        return np.array([np.linalg.norm(pose[:3] - target[:3]), abs(yaw_error_rad)])

    def stop(self) -> None:
        """Stop all motion: ``speedStop`` (streamed velocities), then ``stopL`` (a ``moveL``).
        Safe at any time, repeatedly. Tried whenever the interfaces exist, also after the arm
        was marked disconnected (a stale read while the link still works); a failure is
        logged, and the controller's watchdog stops an arm that nobody talks to."""
        self._streaming = False
        control = self._control
        if control is None or not _still_connected(control):
            log.warning("UR arm stop() without a connection: relying on the controller watchdog")
            return
        deceleration = self.config.stop_deceleration_mps2
        for what, command in (
            ("speedStop", lambda c: c.speedStop(deceleration)),
            ("stopL", lambda c: c.stopL(deceleration)),
        ):
            try:
                self._run(control, command, what)
            except HardwareError as exc:
                log.error("UR arm at %s: stop failed: %s", self.config.host, exc)
                self._connected = False

    def close(self) -> None:
        self._closed.set()
        self.stop()
        self._connected = False
        self._abandon()

    def _feed_watchdog(self) -> None:
        """Kick the RTDE watchdog unless velocities are streamed (then the commands feed it:
        a control loop that stops commanding lets the controller stop the arm)."""
        while not self._closed.wait(0.5 / self.config.watchdog_min_hz):
            if self._connected and not self._streaming:
                with contextlib.suppress(HardwareError):  # reported by the next command
                    self._call(lambda c: c.kickWatchdog(), "kickWatchdog")


def safety_condition(bits: int) -> str | None:
    """The condition, named, under which RTDE ``safety_status_bits`` refuse motion, or None."""
    for bit, condition in _SAFETY_STOPS:
        if bits & (1 << bit):
            return condition
    if not bits & _NORMAL_OR_REDUCED_BITS:
        return "neither normal nor reduced safety mode"
    return None


def _still_connected(interface: Any) -> bool:
    """Whether the interface's connection is open (commands on a closed one block while
    ur_rtde tries to reconnect)."""
    try:
        return bool(call_with_deadline(interface.isConnected, 0.1, "RTDE isConnected"))
    except HardwareError:
        return False


def _disconnect(interface: Any) -> None:
    """Disconnect within ``_DISCONNECT_TIMEOUT_S`` unless the connection is closed already
    (ur_rtde's own thread closes a dropped one, and disconnecting it again crashed the
    process), then ``_keep_alive`` the interface."""
    try:
        if call_with_deadline(interface.isConnected, _DISCONNECT_TIMEOUT_S, "RTDE isConnected"):
            call_with_deadline(interface.disconnect, _DISCONNECT_TIMEOUT_S, "RTDE disconnect")
        else:
            log.debug("%s: connection closed already", type(interface).__name__)
    except HardwareError as exc:
        log.warning("%s; leaving the stuck RTDE interface behind", exc)
    _keep_alive(interface)


def _keep_alive(interface: Any) -> None:
    """Keep an abandoned interface alive for the rest of the process: its C++ destructor joins
    the interface's threads, which hangs on one stuck in a call, aborts the process at exit,
    and once crashed the process right after a dropped connection was re-opened. An arm
    reconnects rarely, so the few kept interfaces cost little."""
    ctypes.pythonapi.Py_IncRef(ctypes.py_object(interface))
