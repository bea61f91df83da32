"""``choose_action`` and ``execute_action``: pick a push or pull, then carry it out one control
period per tick while recording the observation stream."""

from __future__ import annotations

import logging
from typing import Any

import numpy as np
from py_trees.common import Status
from pydantic import Field
from vistac.component import ComponentConfig
from vistac.errors import DataError
from vistac.protocols import Episode, Scene, StepObservation
from vistac.tree import SkillBehaviour
from vistac.types import (
    Action,
    FloatArray,
    GaussianBelief,
    PixelWindow,
    ShapeEstimate,
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


class ChooseAction(SkillBehaviour):
    """Sample candidate actions and select one. With a filter in the skill, the belief is
    initialised from the scene the first time. Writes ``action`` (and ``belief``)."""

    reads = ("cloud",)
    optional_reads = ("shape", "belief")
    writes = ("action", "belief")
    role_fields = {"sampler": "action_sampler", "selector": "action_selector", "filter": "filter"}
    optional_roles = ("filter",)

    class Config(ComponentConfig):
        sampler: str = "affordances"
        selector: str = "planner"
        filter: str = "filter"

    @classmethod
    def blackboard_writes(cls, config: Config, roles: dict[str, str]) -> set[str]:
        return {"action"} | ({"belief"} if config.filter in roles else set())

    def update(self) -> Status:
        scene = Scene(self.read("cloud"), self.read("shape"), self.read("belief"))
        filter_ = self.component("filter")
        if filter_ is not None and scene.belief is None:
            belief = filter_.initialise(scene)
            self.write("belief", belief)
            self.run.hook.vistac_belief(run=self.run.info, belief=belief)
            scene = Scene(scene.cloud, scene.shape, belief)
        rng = self.run.rng(f"choose_action/{self.run.episode_count}")
        candidates = self.component("sampler").sample(scene, rng)
        if not candidates:
            raise DataError(
                "choose_action: no reachable push or pull on the observed object: the "
                f"{self.config.sampler!r} component dropped every candidate; check its "
                "workspace and clearance options (a warning above may say which)"
            )
        action = self.component("selector").select(candidates, scene, rng)
        self.write("action", action)
        self.run.hook.vistac_action(
            run=self.run.info, episode=self.run.episode_count, action=action
        )
        return Status.SUCCESS


class ExecuteAction(SkillBehaviour):
    """Carry out ``action`` through the executor, one control period per tick (RUNNING
    until done). During the interaction proper, record per period the tactile forces, the
    arm state, a depth image and, in simulation, the true link poses. Writes ``episode``."""

    reads = ("action",)
    optional_reads = ("shape", "object_cloud", "belief")
    writes = ("episode",)
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

    def initialise(self) -> None:
        self.action: Action = self.read("action")
        self.episode = Episode(self.run.episode_count, self.action)
        self.observing = False
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
        self._finish()
        return Status.SUCCESS

    def terminate(self, new_status: Status) -> None:
        if new_status != Status.SUCCESS and self.run is not None and hasattr(self, "episode"):
            self.component("executor").abort()
            self.component("arm").stop()

    def _depth_window(self) -> PixelWindow | None:
        """The crop of the camera's frame that the per-step depth images cover, or None."""
        camera, shape = self.component("camera"), self.read("shape")
        points = shape.cloud.points_m if shape is not None else None
        if points is None and self.read("object_cloud") is not None:
            points = self.read("object_cloud").points_m
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

    def _finish(self) -> None:
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
