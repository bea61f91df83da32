"""Executes a push or a pull with any ``Arm`` and ``Gripper`` (simulated or real).

An action is a list of phases, each stepped once per control period:

- push: ``lift`` to the approach height, ``close`` the fingers, ``approach`` above the
  pre-contact point (``standoff_m`` behind the contact point along -pd, the closing axis along
  pd so that the leading pad faces the push), ``descend`` to finger height, ``push`` along pd
  at the action's speed for ``duration_s`` (the observed interaction), ``back_off`` along -pd
  by ``back_off_m`` at finger height (a pad still pressed on the object would drag its face
  up as it rises and can tip it over), ``retreat`` upwards.
- pull: ``lift``, ``open``, ``approach`` above the grasp point with the fingers closing along
  ``grasp_axis_rad``, ``descend``, ``grasp`` (close until the fingers stall), ``pull`` along pd
  for ``duration_s`` (observed), ``release`` and ``retreat``.

Moves use a proportional velocity command towards the waypoint, capped at the arm's speed,
and end within ``tolerance_m`` / ``yaw_tolerance_rad``. Yaw targets are taken modulo pi (the
two fingers are symmetric), nearest to the current yaw. A move that over ``stall_s`` gets less
than half as far as it was commanded is blocked (the fingers on the object, say): the arm
stops at once and the action fails with a HardwareError saying where.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

import numpy as np
from pydantic import Field
from vistac.component import Component, ComponentConfig, ComponentContext
from vistac.errors import HardwareError, PluginError
from vistac.protocols import Arm, Gripper
from vistac.types import Action, FloatArray, Pull, Push

log = logging.getLogger(__name__)

_GRIPPER_SETTLE_S = 0.15
_MIN_COMMANDED_M = 0.002
"""The stall check skips windows in which less than this was commanded (at the waypoint)."""
_YAW_M_PER_RAD = 0.05
"""Yaw counted as distance in the stall check (a turn in place is progress)."""
_RECOVERABLE_MOVES = ("approach", "descend")
"""Moves before the fingers are meant to touch anything: blocked, the arm can back off."""


def _move_metric(position_m: FloatArray, yaw_rad: float) -> float:
    """A position [3] and yaw as one distance (m) for the stall check."""
    return float(np.linalg.norm(position_m)) + _YAW_M_PER_RAD * abs(yaw_rad)


@dataclass
class _StallWindow:
    """Progress of a move since ``start_s``: the distance to the waypoint then and the
    distance commanded since (both as :func:`_move_metric`)."""

    start_s: float
    start_distance_m: float
    commanded_m: float = 0.0


def _wrap(angle_rad: float, period_rad: float = 2.0 * math.pi) -> float:
    """``angle_rad`` wrapped into [-period/2, period/2)."""
    return (angle_rad + 0.5 * period_rad) % period_rad - 0.5 * period_rad


@dataclass
class _Phase:
    """One step of an action. ``enter`` runs once, then per period ``finished`` is checked
    before ``command``; ``interaction`` marks the observed part."""

    name: str
    enter: Callable[[], None]
    finished: Callable[[float], bool]
    command: Callable[[], None]
    timeout_s: float
    interaction: bool = False


class CartesianExecutor(Component):
    """Implements the ``Executor`` protocol using only the Arm and Gripper protocols."""

    kind = "executor"

    class Config(ComponentConfig):
        standoff_m: float = Field(default=0.01, ge=0.0)
        """Gap between the pushing pad and the contact point before the push starts."""
        pusher_offset_m: float = Field(default=0.01, ge=0.0)
        """Distance from the TCP to the leading pad face with the fingers closed."""
        back_off_m: float = Field(default=0.02, ge=0.0)
        """After a push, how far the pad backs away from the object along -pd before it
        rises: lifting a pad that still presses on the object drags the object's face up
        (the pads grip), which turned tall objects over in the simulated world."""
        approach_height_m: float = Field(default=0.1, gt=0.0)
        finger_height_m: float = Field(default=0.02, gt=0.0)
        tolerance_m: float = Field(default=0.002, gt=0.0)
        yaw_tolerance_rad: float = Field(default=0.02, gt=0.0)
        gain_per_s: float = Field(default=3.0, gt=0.0)
        max_yaw_rate_rad_s: float = Field(default=0.5, gt=0.0)
        move_timeout_s: float = Field(default=60.0, gt=0.0)
        stall_s: float = Field(default=0.5, gt=0.0)
        """A move that gets less than half as much nearer its waypoint as it was commanded
        to move over this long is blocked: the arm stops (for example on a descent onto the
        object when the believed pose is off), then ``on_blocked_descent`` says what next."""
        on_blocked_descent: Literal["lift", "fail"] = "lift"
        """A blocked ``approach`` or ``descend`` (the object where the fingers were to come
        down: its believed pose or shape is off): ``lift`` the arm back to the approach
        height, park it and end the action without an interaction (``blocked_at_m``), so
        that the skill can choose another; or ``fail`` the action, the arm stopped."""
        gripper_timeout_s: float = Field(default=5.0, gt=0.0)
        park_pose: tuple[float, float, float, float] | None = (0.0, 0.25, 0.12, 0.0)
        """Where the TCP waits after an action (x, y, z m, yaw rad), out of the cameras'
        way; None stays above the object."""

    def __init__(self, config: Config, ctx: ComponentContext) -> None:
        super().__init__(config, ctx)
        arm, gripper = ctx.find("arm"), ctx.find("gripper")
        if not isinstance(arm, Arm) or not isinstance(gripper, Gripper):
            raise PluginError("the cartesian executor needs an 'arm' and a 'gripper' component")
        self.arm: Arm = arm
        self.gripper: Gripper = gripper
        self._phases: list[_Phase] = []
        self._index = 0
        self._entered = False
        self._elapsed_s = 0.0
        self._target = np.zeros(4)
        self._stall_window: _StallWindow | None = None
        self._dt_s = 0.0
        self.blocked_at_m: FloatArray | None = None
        """Where (x, y, z, m) the TCP stopped when the last action's approach or descent
        was blocked and the arm backed off (``on_blocked_descent: lift``); else None."""

    # -- Executor protocol ----------------------------------------------------------------

    def start(self, action: Action) -> None:
        self._phases = (
            self._push_phases(action) if isinstance(action, Push) else self._pull_phases(action)
        )
        self._index, self._entered = 0, False
        self.blocked_at_m = None
        log.debug("executing %s: %s", action.kind, [p.name for p in self._phases])

    def step(self, dt_s: float) -> tuple[str, bool]:
        self._dt_s = dt_s
        while self._index < len(self._phases):
            phase = self._phases[self._index]
            if not self._entered:
                phase.enter()
                self._entered, self._elapsed_s = True, 0.0
            if phase.finished(self._elapsed_s):
                self._index, self._entered = self._index + 1, False
                continue
            if self._elapsed_s > phase.timeout_s:
                self.abort()
                raise HardwareError(
                    f"executor: phase {phase.name!r} timed out after {phase.timeout_s} s"
                )
            phase.command()
            self._elapsed_s += dt_s
            return phase.name, phase.interaction
        self.arm.stop()
        return "done", False

    def abort(self) -> None:
        self.arm.stop()
        self.gripper.stop()
        self._index = len(self._phases)

    # -- phase lists ----------------------------------------------------------------------

    def _push_phases(self, push: Push) -> list[_Phase]:
        direction = np.array([math.cos(push.pd_rad), math.sin(push.pd_rad)])
        back_m = self.config.standoff_m + self.config.pusher_offset_m
        pre_xy = push.cp_m - back_m * direction
        back_off = self.config.back_off_m * direction
        return [
            self._move_phase("lift", lambda pose: (pose[0], pose[1], self._safe_z, pose[3])),
            self._gripper_phase("close", self.gripper.close),
            self._move_phase("approach", lambda pose: (*pre_xy, self._safe_z, push.pd_rad)),
            self._move_phase("descend", lambda pose: (*pre_xy, self._finger_z, pose[3])),
            self._interact_phase("push", direction, push.speed_mps, push.duration_s),
            self._move_phase("back_off", lambda pose: (*(pose[:2] - back_off), *pose[2:])),
            *self._retreat_phases(),
        ]

    def _pull_phases(self, pull: Pull) -> list[_Phase]:
        direction = np.array([math.cos(pull.pd_rad), math.sin(pull.pd_rad)])
        grasp_xy = pull.gp_m
        return [
            self._move_phase("lift", lambda pose: (pose[0], pose[1], self._safe_z, pose[3])),
            self._gripper_phase("open", self.gripper.open),
            self._move_phase(
                "approach", lambda pose: (*grasp_xy, self._safe_z, pull.grasp_axis_rad)
            ),
            self._move_phase("descend", lambda pose: (*grasp_xy, self._finger_z, pose[3])),
            self._gripper_phase("grasp", self.gripper.close, check_grasp=True),
            self._interact_phase("pull", direction, pull.speed_mps, pull.duration_s),
            self._gripper_phase("release", self.gripper.open),
            *self._retreat_phases(),
        ]

    def _retreat_phases(self) -> list[_Phase]:
        """Straight up to the approach height, then to the park pose."""
        up = self._move_phase("retreat", lambda pose: (pose[0], pose[1], self._safe_z, pose[3]))
        return [up, *self._park_phases()]

    def _park_phases(self) -> list[_Phase]:
        park = self.config.park_pose
        if park is None:
            return []
        return [
            self._move_phase("park_over", lambda pose: (park[0], park[1], self._safe_z, park[3])),
            self._move_phase("park", lambda pose: park),
        ]

    @property
    def _safe_z(self) -> float:
        return self.config.approach_height_m

    @property
    def _finger_z(self) -> float:
        return self.config.finger_height_m

    # -- phase kinds ----------------------------------------------------------------------

    def _move_phase(self, name: str, target: Callable[[FloatArray], tuple[float, ...]]) -> _Phase:
        """Move to ``target(current pose)`` (x, y, z, yaw; yaw taken modulo pi)."""

        def enter() -> None:
            pose = self.arm.state().pose
            goal = np.array(target(pose), dtype=np.float64)
            goal[3] = pose[3] + _wrap(goal[3] - pose[3], math.pi)
            self._target = goal
            self._stall_window = None

        def command() -> None:
            self._command_towards_target()  # first: the arm's own errors take precedence
            self._check_progress(name)

        return _Phase(name, enter, lambda _: self._at_target(), command, self.config.move_timeout_s)

    def _check_progress(self, name: str) -> None:
        """Raise HardwareError (arm stopped) when, over the last ``stall_s``, the move got
        less than half as much nearer its waypoint as it was commanded to move."""
        error = self._target - self.arm.state().pose
        distance_m = _move_metric(error[:3], _wrap(error[3]))
        window = self._stall_window
        if window is None or self._elapsed_s - window.start_s >= self.config.stall_s:
            if window is not None and window.commanded_m >= _MIN_COMMANDED_M:
                progress_m = window.start_distance_m - distance_m
                if progress_m < 0.5 * window.commanded_m:
                    self._blocked(name, error, progress_m, window.commanded_m)
            self._stall_window = _StallWindow(self._elapsed_s, distance_m)

    def _blocked(self, name: str, error: FloatArray, progress_m: float, commanded_m: float) -> None:
        """Stop the arm; back off (``on_blocked_descent: lift``) or raise HardwareError."""
        self.arm.stop()
        at_m = self._target[:3] - error[:3]
        what = (
            f"the {name!r} move is blocked at ({at_m[0]:.3f}, {at_m[1]:.3f}, {at_m[2]:.3f}) m: "
            f"it got {progress_m * 1e3:.1f} mm nearer its waypoint in {self.config.stall_s} s "
            f"while commanded {commanded_m * 1e3:.1f} mm"
        )
        if name in _RECOVERABLE_MOVES and self.config.on_blocked_descent == "lift":
            log.warning("executor: %s; lifting the arm off, the action is not carried out", what)
            self.blocked_at_m = at_m
            self._phases, self._index, self._entered = self._retreat_phases(), 0, False
            return
        self.abort()
        raise HardwareError(
            f"executor: {what}; the arm is stopped. Is something in the way? (a push whose "
            "start lies on the object: the believed pose is off)"
        )

    def _at_target(self) -> bool:
        error = self._target - self.arm.state().pose
        return bool(
            np.linalg.norm(error[:3]) < self.config.tolerance_m
            and abs(_wrap(error[3])) < self.config.yaw_tolerance_rad
        )

    def _command_towards_target(self) -> None:
        error = self._target - self.arm.state().pose
        velocity = self.config.gain_per_s * error[:3]
        speed = float(np.linalg.norm(velocity))
        if speed > self.arm.max_speed_mps:
            velocity *= self.arm.max_speed_mps / speed
        yaw_rate = float(
            np.clip(
                self.config.gain_per_s * _wrap(error[3]),
                -self.config.max_yaw_rate_rad_s,
                self.config.max_yaw_rate_rad_s,
            )
        )
        self.arm.command_velocity(np.append(velocity, yaw_rate))
        if self._stall_window is not None:
            self._stall_window.commanded_m += _move_metric(velocity, yaw_rate) * self._dt_s

    def _gripper_phase(
        self, name: str, command: Callable[[], None], check_grasp: bool = False
    ) -> _Phase:
        """Stop the arm and send ``command`` once, then hold the arm where it stopped (zero
        velocity: stopping it again every period would re-anchor it wherever the fingers'
        contact forces had nudged it) until the fingers stop."""

        def enter() -> None:
            self.arm.stop()
            command()

        def finished(elapsed_s: float) -> bool:
            state = self.gripper.state()
            if elapsed_s < _GRIPPER_SETTLE_S or state.moving:
                return False
            if check_grasp and not state.object_detected:
                log.warning("grasp: the fingers closed on nothing (width %.4f m)", state.width_m)
            return True

        def hold() -> None:
            self.arm.command_velocity(np.zeros(4))

        return _Phase(name, enter, finished, hold, self.config.gripper_timeout_s)

    def _interact_phase(
        self, name: str, direction: FloatArray, speed_mps: float, duration_s: float
    ) -> _Phase:
        """Move along ``direction`` [2] at ``speed_mps`` for ``duration_s`` (observed)."""
        speed = min(speed_mps, self.arm.max_speed_mps)
        twist = np.array([*(speed * direction), 0.0, 0.0])
        return _Phase(
            name,
            enter=lambda: None,
            finished=lambda elapsed_s: elapsed_s >= duration_s - 1e-9,
            command=lambda: self.arm.command_velocity(twist),
            timeout_s=duration_s + 1.0,
            interaction=True,
        )
