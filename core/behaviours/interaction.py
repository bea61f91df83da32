"""``choose_action`` and ``execute_action``: pick a push or pull, then carry it out one control
period per tick while recording the observation stream."""

from __future__ import annotations

import logging
from typing import Any

import numpy as np
from py_trees.common import Status
from pydantic import BaseModel, ConfigDict, Field
from vistac.behaviours.belief import initial_belief
from vistac.component import ComponentConfig
from vistac.errors import ConfigError, DataError
from vistac.protocols import Episode, Scene, StepObservation
from vistac.tree import SkillBehaviour
from vistac.types import (
    Action,
    FloatArray,
    GaussianBelief,
    PixelWindow,
    ShapeEstimate,
    Viewpoint,
    action_point,
)

log = logging.getLogger(__name__)


def object_region(
    points_m: FloatArray, fitted: ShapeEstimate | None, belief: GaussianBelief | None,
    margin_m: float,
) -> FloatArray:
    """Table region [2, 2] = (min, max) of (x, y) in m that holds the object now, widened by
    ``margin_m``. From the object's points [N, 3] alone: their extent (the object has not
    moved since they were seen). With the shape fitted to them and a belief: a square of the
    largest link radius around each link's believed position (the object may have moved)."""
    xy = points_m[:, :2]
    names = list(belief.names) if belief is not None else []
    links = range(len(fitted.links)) if fitted is not None else range(0)
    if fitted is None or not all(f"x_{k}" in names and f"y_{k}" in names for k in links):
        return np.stack([xy.min(axis=0) - margin_m, xy.max(axis=0) + margin_m])
    assert belief is not None
    origins = np.asarray(fitted.initial_poses)[:, :2]  # [L, 2] where the shape was fitted
    radius_m = float(np.min(np.linalg.norm(xy[:, None] - origins[None], axis=-1), axis=1).max())
    centres = np.array([[belief.mean[names.index(f"{a}_{link}")] for a in "xy"] for link in links])
    pad_m = radius_m + margin_m
    return np.stack([centres.min(axis=0) - pad_m, centres.max(axis=0) + pad_m])


def action_region(action: Action, region_xy_m: FloatArray, top_m: float) -> FloatArray:
    """Corners [8, 3] (world, m) of the box over the table region [2, 2] = (min, max) of
    (x, y) swept by ``action``'s full travel along its direction, up to ``top_m``."""
    travel_m = action.speed_mps * action.duration_s
    shift = travel_m * np.array([np.cos(action.pd_rad), np.sin(action.pd_rad)])
    lo = np.minimum(region_xy_m[0], region_xy_m[0] + shift)
    hi = np.maximum(region_xy_m[1], region_xy_m[1] + shift)
    return np.array(
        [[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (0.0, top_m)]
    )


BLOCKED_KEY = "blocked_xy_m"
"""Blackboard: the action points [K, 2] (world, m) of the actions whose way down was blocked
since the last interaction (``Scene.blocked_xy_m``)."""


def blocked_points(behaviour: SkillBehaviour) -> FloatArray:
    """The blocked action points [K, 2] on the blackboard (none yet: [0, 2])."""
    return np.asarray(behaviour.read(BLOCKED_KEY, np.zeros((0, 2))), dtype=np.float64)


def episode_rng(behaviour: SkillBehaviour, stream: str, blocked: FloatArray) -> np.random.Generator:
    """The run's generator for ``stream`` at this episode; a fresh one for each retry after
    an action was blocked (blocked [K, 2], as :func:`blocked_points`)."""
    assert behaviour.run is not None
    retry = f"/retry{len(blocked)}" if len(blocked) else ""
    return behaviour.run.rng(f"{stream}/{behaviour.run.episode_count}{retry}")


class ChooseAction(SkillBehaviour):
    """Sample candidate actions and select one. With a filter in the skill, the belief is
    initialised from the scene the first time. Candidates within ``avoid_blocked_m`` of an
    action whose way down was blocked since the last interaction are dropped. Writes
    ``action`` (and ``belief``)."""

    reads = ("cloud",)
    optional_reads = ("shape", "belief", BLOCKED_KEY)
    writes = ("action", "belief")
    role_fields = {"sampler": "action_sampler", "selector": "action_selector", "filter": "filter"}
    optional_roles = ("filter",)

    class Config(ComponentConfig):
        sampler: str = "affordances"
        selector: str = "planner"
        filter: str = "filter"
        avoid_blocked_m: float = Field(
            0.02, ge=0, description="candidates whose contact or grasp point lies this near "
            "that of an action blocked on its way down (since the last interaction) are dropped",
        )

    @classmethod
    def blackboard_writes(cls, config: Config, roles: dict[str, str]) -> set[str]:
        return {"action"} | ({"belief"} if config.filter in roles else set())

    def update(self) -> Status:
        blocked = blocked_points(self)
        scene = Scene(self.read("cloud"), self.read("shape"), self.read("belief"), blocked)
        filter_ = self.component("filter")
        if filter_ is not None and scene.belief is None:
            belief = initial_belief(self, scene, "filter")
            scene = Scene(scene.cloud, scene.shape, belief, blocked)
        rng = episode_rng(self, "choose_action", blocked)
        candidates = self.component("sampler").sample(scene, rng)
        if not candidates:
            raise DataError(
                "choose_action: no reachable push or pull on the observed object: the "
                f"{self.config.sampler!r} component dropped every candidate; check its "
                "workspace and clearance options (a warning above may say which)"
            )
        candidates = self._away_from(blocked, candidates)
        action = self.component("selector").select(candidates, scene, rng)
        self._check_filterable(action.kind)
        self.write("action", action)
        self.run.hook.vistac_action(
            run=self.run.info, episode=self.run.episode_count, action=action
        )
        return Status.SUCCESS

    def _check_filterable(self, kind: str) -> None:
        """Refuse, before the robot moves, an action whose kind the filter cannot update
        from (its ``interactions``; a filter without them takes any)."""
        kinds = getattr(self.component("filter"), "interactions", None)
        if kinds is not None and kind not in kinds:
            raise ConfigError(
                f"choose_action: the filter's process model predicts only "
                f"{' and '.join(kinds)} interactions, and the chosen action is a {kind}; "
                f"offer only {', '.join(kinds)} in components.{self.config.sampler}.with."
                "interactions, or choose another process model"
            )

    def _away_from(self, blocked: FloatArray, candidates: list[Action]) -> list[Action]:
        """The candidates farther than ``avoid_blocked_m`` from every blocked point [K, 2]."""
        if not len(blocked):
            return candidates
        points = np.array([action_point(action) for action in candidates])
        gaps_m = np.linalg.norm(points[:, None] - blocked[None], axis=-1).min(axis=1)
        far = gaps_m > self.config.avoid_blocked_m
        kept = [action for action, keep in zip(candidates, far, strict=True) if keep]
        if not kept:
            raise DataError(
                f"choose_action: every candidate lies within avoid_blocked_m "
                f"({self.config.avoid_blocked_m} m) of the {len(blocked)} action(s) whose way "
                "down was blocked; the object's believed pose or shape is off. Look again, or "
                "lower avoid_blocked_m"
            )
        log.info("choose_action: %d of %d candidates kept away from %d blocked spot(s)",
                 len(kept), len(candidates), len(blocked))  # fmt: skip
        return kept


class InteractionView(BaseModel):
    """Where a movable camera watches an interaction from: on the hemisphere around the
    segmented object's centroid."""

    model_config = ConfigDict(extra="forbid")

    azimuth_deg: float = Field(default=180.0, description="from world +x; 180: from the -x side")
    elevation_deg: float = Field(
        default=70.0, gt=0, le=90, description="70: the least tracking error of the views measured "
        "(docs/results.md); the training pushes were recorded from 50"
    )
    radius_m: float = Field(default=0.5, gt=0)

    def viewpoint(self, points_m: FloatArray) -> Viewpoint:
        """The view of the object points [N, 3]."""
        target_m = np.asarray(points_m, dtype=np.float64).mean(axis=0)
        return Viewpoint.on_hemisphere(
            target_m, self.radius_m, np.radians(self.azimuth_deg), np.radians(self.elevation_deg)
        )


class ExecuteAction(SkillBehaviour):
    """Carry out ``action`` through the executor, one control period per tick (RUNNING
    until done). During the interaction proper, record per period the tactile forces, the
    arm state, a depth image and, in simulation, the true link poses. Writes ``episode``.
    An action the executor backed off from before the interaction (its way down blocked,
    ``blocked_at_m``) records no episode: ``episode`` is None, the summary's
    ``blocked_actions`` lists it and its point joins ``blocked_xy_m`` until the next
    interaction."""

    reads = ("action",)
    optional_reads = ("shape", "object_cloud", "belief", BLOCKED_KEY)
    writes = ("episode", BLOCKED_KEY)
    role_fields = {"executor": "executor", "arm": "arm", "tactile": "tactile", "camera": "camera"}
    optional_roles = ("camera",)

    class Config(ComponentConfig):
        executor: str = "executor"
        arm: str = "arm"
        tactile: str = "tactile"
        camera: str = "camera"
        depth_width: int = Field(64, gt=0, description="width of the per-step depth image")
        depth_height: int = Field(64, gt=0)
        record_depth: bool = True
        depth_margin_m: float | None = Field(
            0.03, gt=0, description="the per-step depth image shows only the object, where the "
            "action can move it and this margin around it: a crop of the full frame, so the "
            "object fills more pixels; None: the whole frame",
        )
        max_sensor_age_s: float = Field(
            0.2, gt=0, description="older tactile/arm data stops the arm"
        )
        view: InteractionView | None = Field(
            InteractionView(), description="a movable camera watches the "
            "interaction from this view of the object; null: from where the last look left it",
        )

    def initialise(self) -> None:
        self.action: Action = self.read("action")
        self.episode = Episode(self.run.episode_count, self.action)
        self.observing = False
        self._move_camera()
        self.window = self._depth_window()
        self.component("executor").start(self.action)
        point = action_point(self.action)
        log.info(
            "episode %d: %s at (%.3f, %.3f) m towards %.0f deg",
            self.episode.index,
            self.action.kind,
            point[0],
            point[1],
            np.degrees(self.action.pd_rad),
        )

    def update(self) -> Status:
        if self.observing:
            self._record_step()
        phase, self.observing = self.component("executor").step(self.run.period_s)
        if phase != "done":
            return Status.RUNNING
        blocked_at_m = getattr(self.component("executor"), "blocked_at_m", None)
        if blocked_at_m is None:
            self._finish()
        else:
            self._drop(np.asarray(blocked_at_m, dtype=np.float64))
        return Status.SUCCESS

    def terminate(self, new_status: Status) -> None:
        if new_status != Status.SUCCESS and self.run is not None and hasattr(self, "episode"):
            self.component("executor").abort()
            self.component("arm").stop()

    def _object_points(self) -> FloatArray | None:
        """The fitted shape's cloud, else the segmented object cloud [N, 3], else None."""
        shape, cloud = self.read("shape"), self.read("object_cloud")
        if shape is not None:
            return np.asarray(shape.cloud.points_m)
        return np.asarray(cloud.points_m) if cloud is not None else None

    def _move_camera(self) -> None:
        """Move a movable camera to ``view`` of the object, if one is set and the object has
        been seen."""
        camera, points = self.component("camera"), self._object_points()
        if self.config.view is None or camera is None or not camera.movable or points is None:
            return
        camera.move_to(self.config.view.viewpoint(points))

    def _depth_window(self) -> PixelWindow | None:
        """The crop of the camera's frame that the per-step depth images cover, or None."""
        camera, shape = self.component("camera"), self.read("shape")
        points = self._object_points()
        margin_m = self.config.depth_margin_m
        if camera is None or points is None or margin_m is None or not self.config.record_depth:
            return None
        region = object_region(points, shape, self.read("belief"), margin_m)
        top_m = max(float(points[:, 2].max()), 0.0)
        frame = camera.capture()
        window = frame.intrinsics.window_of(
            frame.world_from_camera, action_region(self.action, region, top_m)
        )
        if window is None:
            log.warning("the object is out of the camera's view: depth images show the frame")
        return window

    def _record_step(self) -> None:
        tactile = self.component("tactile").read()
        arm_state = self.component("arm").state()
        self.run.check_fresh("tactile", tactile.timestamp_s, self.config.max_sensor_age_s)
        self.run.check_fresh("arm", arm_state.timestamp_s, self.config.max_sensor_age_s)
        camera = self.component("camera")
        depth = None
        if camera is not None and self.config.record_depth:
            width, height = self.config.depth_width, self.config.depth_height
            # Without a window, a camera written before windows existed still works.
            window = {"window": self.window} if self.window is not None else {}
            depth = camera.capture(width, height, **window)
        world = self.run.world_if_built()
        poses = world.ground_truth_poses() if world is not None else None
        step = StepObservation(self.run.time_s, tactile, arm_state, depth, poses)
        self.episode.steps.append(step)
        self.run.hook.vistac_observation(
            run=self.run.info,
            episode=self.episode.index,
            step=len(self.episode.steps) - 1,
            observation=step,
        )

    def _drop(self, blocked_at_m: FloatArray) -> None:
        """The executor backed off at blocked_at_m [3]: no episode; remember the spot."""
        point = action_point(self.action)
        self.write(BLOCKED_KEY, np.vstack([blocked_points(self), point]))
        self.write("episode", None)
        self.run.results.setdefault("blocked_actions", []).append(
            {
                "episode": self.episode.index,
                "kind": self.action.kind,
                "point_m": point.tolist(),
                "pd_rad": float(self.action.pd_rad),
                "blocked_at_m": blocked_at_m.tolist(),
            }
        )
        log.warning(
            "episode %d: the %s at (%.3f, %.3f) m was not carried out, its way down blocked "
            "at %.3f m height (the object's believed pose or shape is off); choosing another",
            self.episode.index, self.action.kind, *point, blocked_at_m[2],
        )  # fmt: skip

    def _finish(self) -> None:
        self.write(BLOCKED_KEY, np.zeros((0, 2)))
        world = self.run.world_if_built()
        truth = world.ground_truth() if world is not None else None
        path = self.run.recorder.save_episode(self.episode, truth)
        self.run.episode_count += 1
        self.write("episode", self.episode)
        self.run.hook.vistac_episode_end(run=self.run.info, episode=self.episode)
        line: dict[str, Any] = self.run.recorder.episodes[-1]
        moved = line.get("object_displacement_m")
        log.info(
            "episode %d done: %d steps%s -> %s",
            self.episode.index,
            len(self.episode.steps),
            f", object moved {max(moved) * 100:.1f} cm" if moved else "",
            path,
        )
