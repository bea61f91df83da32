"""``plan_push`` and ``goal_reached``: push an object to a goal pose (paper 1, IV-B5).

The goal is (x_m, y_m, theta_rad): where the centre of link 0 should end, and how far the
object should have turned from its orientation when ``plan_push`` first ran (an absolute yaw
means little for a fitted superquadric, whose axes may be any of its symmetries). In
simulation the summary's ``goal_push`` also gets the true final error: the true position of
the body point that the belief tracks (the fitted centre when planning began) and the true
turn since then.
"""

from __future__ import annotations

import logging
import math
from typing import Any

import numpy as np
from py_trees.common import Status
from pydantic import Field
from vistac.behaviours.belief import initial_belief, record_belief
from vistac.behaviours.interaction import BLOCKED_KEY, blocked_points, episode_rng
from vistac.component import ComponentConfig
from vistac.errors import ConfigError, DataError
from vistac.plugins.actions.icem import wrap_angle
from vistac.protocols import Scene
from vistac.tree import SkillBehaviour
from vistac.types import FloatArray, GaussianBelief

log = logging.getLogger(__name__)


def link0_pose(belief: GaussianBelief) -> FloatArray:
    """(x_m, y_m, theta_rad) of link 0 in the belief: [3]."""
    index = {name: i for i, name in enumerate(belief.names)}
    try:
        return np.array([belief.mean[index[name]] for name in ("x_0", "y_0", "theta_0")])
    except KeyError:
        raise DataError("goal pushing needs a belief over the link poses (filters.dual)") from None


_LOOK_STD_FIELD = Field(
    0.002, gt=0, description="correct the believed link positions with the centres of the "
    "last look's fit, trusted to this std (m); null: use the belief alone, which drifts with "
    "the process model's errors")


def located_belief(behaviour: SkillBehaviour, std_m: float | None) -> GaussianBelief:
    """The blackboard's belief with its link positions corrected by the last look's fit
    (``observe_positions`` of the filter, which uses each fit once), written back."""
    belief, shape = behaviour.read("belief"), behaviour.read("shape")
    if std_m is None or shape is None:
        return belief
    filter_ = behaviour.component("filter")
    if not callable(getattr(filter_, "observe_positions", None)):
        raise ConfigError(
            f"{type(filter_).__name__} cannot take a look as a position measurement; use "
            "filters.dual or set look_std_m: null"
        )
    belief = filter_.observe_positions(shape, std_m)
    behaviour.write("belief", belief)
    record_belief(behaviour.run.results, belief)
    return belief


class PlanPush(SkillBehaviour):
    """Plan the next push towards ``goal`` with the controller; writes ``action``, ``goal``
    (absolute, in belief coordinates) and ``belief``: initialised the first time, later
    located by the last look (:func:`located_belief`)."""

    reads = ("cloud",)
    optional_reads = ("shape", "belief", BLOCKED_KEY)
    writes = ("action", "goal", "belief")
    role_fields = {"controller": "controller", "filter": "filter"}

    class Config(ComponentConfig):
        controller: str = "controller"
        filter: str = "filter"
        goal: tuple[float, float, float] = Field(
            description="x_m, y_m of link 0's centre and its turn theta_rad from the start"
        )
        look_std_m: float | None = _LOOK_STD_FIELD

    def setup(self, **kwargs: Any) -> None:
        """Refuse a goal the controller cannot bring the object to before anything moves
        (the controller's ``check_goal``, where it has one)."""
        check_goal = getattr(self.component("controller"), "check_goal", None)
        if callable(check_goal):
            check_goal(self.config.goal)

    def update(self) -> Status:
        belief, blocked = self.read("belief"), blocked_points(self)
        scene = Scene(self.read("cloud"), self.read("shape"), belief, blocked)
        if belief is None:
            belief = initial_belief(self, scene, "filter")
        else:
            belief = located_belief(self, self.config.look_std_m)
        scene = Scene(scene.cloud, scene.shape, belief, blocked)
        record = self.run.results.get("goal_push")
        if record is None:
            record = self._start_record(belief)
        x, y, turn = self.config.goal
        goal = np.array([x, y, record["start_belief_pose"][2] + turn])
        rng = episode_rng(self, "plan_push", blocked)
        action = self.component("controller").plan(scene, goal, rng)
        self.write("goal", goal)
        self.write("action", action)
        cost_m = getattr(self.component("controller"), "last_cost", math.nan)
        record["planned_cost_m"].append(float(cost_m))
        self.run.hook.vistac_action(
            run=self.run.info, episode=self.run.episode_count, action=action
        )
        return Status.SUCCESS

    def _start_record(self, belief: GaussianBelief) -> dict[str, Any]:
        start = link0_pose(belief)
        record: dict[str, Any] = {
            "goal": list(self.config.goal),
            "start_belief_pose": start.tolist(),
            "planned_cost_m": [],
        }
        world = self.run.world_if_built()
        truth = world.ground_truth_poses() if world is not None else None
        if truth is not None:  # for evaluation only
            true_pose = np.asarray(truth, dtype=np.float64)[0]
            record["start_true_pose"] = true_pose.tolist()
            offset = _rotate(start[:2] - true_pose[:2], -true_pose[2])
            record["tracked_point_in_link_m"] = offset.tolist()
        self.run.results["goal_push"] = record
        return record


def _rotate(vector: FloatArray, angle_rad: float) -> FloatArray:
    cos, sin = math.cos(angle_rad), math.sin(angle_rad)
    return np.array([cos * vector[0] - sin * vector[1], sin * vector[0] + cos * vector[1]])


class GoalReached(SkillBehaviour):
    """Condition: SUCCESS when link 0's believed position is within ``tolerance_m`` of the
    goal (and its turn within ``tolerance_rad`` when that is set). Updates the summary's
    ``goal_push`` with the believed and, in simulation, the true errors."""

    reads = ("belief", "goal")
    optional_reads = ("shape",)
    writes = ("belief",)
    role_fields = {"filter": "filter"}

    class Config(ComponentConfig):
        filter: str = "filter"
        tolerance_m: float = Field(0.01, gt=0)
        tolerance_rad: float | None = Field(None, gt=0, description="None: position only")
        look_std_m: float | None = _LOOK_STD_FIELD

    def update(self) -> Status:
        belief = located_belief(self, self.config.look_std_m)
        pose, goal = link0_pose(belief), np.asarray(self.read("goal"))
        position_error_m = float(np.linalg.norm(pose[:2] - goal[:2]))
        turn_error_rad = abs(float(wrap_angle(pose[2] - goal[2])))
        record = self.run.results["goal_push"]
        record.update(believed_error_m=position_error_m, believed_turn_error_rad=turn_error_rad)
        self._true_errors(record, goal)
        reached = position_error_m <= self.config.tolerance_m and (
            self.config.tolerance_rad is None or turn_error_rad <= self.config.tolerance_rad
        )
        record["reached"] = reached
        self.feedback_message = f"{position_error_m * 1e3:.1f} mm from the goal"
        return Status.SUCCESS if reached else Status.FAILURE

    def _true_errors(self, record: dict[str, Any], goal: FloatArray) -> None:
        world = self.run.world_if_built()
        truth = world.ground_truth_poses() if world is not None else None
        if truth is None or "start_true_pose" not in record:
            return
        true_pose = np.asarray(truth, dtype=np.float64)[0]
        point = true_pose[:2] + _rotate(np.asarray(record["tracked_point_in_link_m"]), true_pose[2])
        turn = float(wrap_angle(true_pose[2] - record["start_true_pose"][2]))
        goal_turn = float(wrap_angle(goal[2] - record["start_belief_pose"][2]))
        record["true_final_xy"] = point.tolist()
        record["true_error_m"] = float(np.linalg.norm(point - goal[:2]))
        record["true_turn_error_rad"] = abs(float(wrap_angle(np.asarray(turn - goal_turn))))
