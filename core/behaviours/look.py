"""``look``: take depth views until the view planner is satisfied, fit the shape."""

from __future__ import annotations

import logging
import time
from dataclasses import asdict
from typing import Any

import numpy as np
from py_trees.common import Status
from pydantic import Field
from vistac.component import ComponentConfig
from vistac.errors import DataError
from vistac.tree import SkillBehaviour
from vistac.types import PointCloud, ShapeEstimate, Superquadric, Viewpoint

log = logging.getLogger(__name__)


class Look(SkillBehaviour):
    """One view per tick: ask the planner for a viewpoint, move the camera there, capture,
    register the view onto the previous ones and (with a cloud processor) segment the object;
    with a shape estimator, refit after each view. Writes ``cloud`` (the merged world-frame
    cloud, table included), ``views`` (count), ``object_cloud`` (the segmented object, with
    a cloud processor) and ``shape``; the run summary gets ``shape``
    (per link the fitted superquadric and its parameter std, the views and the time spent)."""

    writes = ("cloud", "views", "object_cloud", "shape")
    role_fields = {
        "camera": "camera",
        "views": "view_planner",
        "shape": "shape_estimator",
        "processor": "cloud_processor",
    }
    optional_roles = ("shape", "processor")

    class Config(ComponentConfig):
        camera: str = "camera"
        views: str = "views"
        shape: str = "shape"
        processor: str = "cloud"
        max_views: int = Field(8, gt=0, description="hard limit on the number of views")

    @classmethod
    def blackboard_writes(cls, config: Config, roles: dict[str, str]) -> set[str]:
        written = {"cloud", "views"} | ({"object_cloud"} if config.processor in roles else set())
        return written | ({"shape"} if config.shape in roles else set())

    def initialise(self) -> None:
        self.clouds: list[PointCloud] = []
        self.merged: PointCloud | None = None
        self.object_cloud: PointCloud | None = None
        # Where an earlier look saw the object: if a few pushes have moved it out of the view
        # planner's first view, the first view is taken again, aimed there.
        self.last_seen: PointCloud | None = self.read("object_cloud")
        self.shape_estimate: ShapeEstimate | None = None
        self.busy_s = 0.0

    def update(self) -> Status:
        start_s = time.perf_counter()
        view = None
        if len(self.clouds) < self.config.max_views:
            view = self.component("views").next_view(
                self.object_cloud, self.shape_estimate, len(self.clouds)
            )
        if view is None:
            self.busy_s += time.perf_counter() - start_s
            return self._finish()
        if self.clouds or self.last_seen is None:
            self._take_view(view)
        else:
            self._take_first_view(view, self.last_seen)
        estimator = self.component("shape")
        if estimator is not None and self.object_cloud is not None:
            self.shape_estimate = estimator.fit(self.object_cloud)
        self.busy_s += time.perf_counter() - start_s
        return Status.RUNNING

    def _take_first_view(self, view: Viewpoint, last_seen: PointCloud) -> None:
        """Take a later look's first ``view``; when it shows no object, take the planner's
        first view again, aimed at ``last_seen`` (the object cloud of the last look)."""
        try:
            self._take_view(view)
        except DataError as error:
            log.info("look: %s; looking where the object was last seen", error)
            self.clouds, self.merged = [], None
            again = self.component("views").next_view(last_seen, None, 0)
            if again is None:
                raise
            self._take_view(again)

    def _take_view(self, view: Viewpoint) -> None:
        camera, processor = self.component("camera"), self.component("processor")
        if camera.movable:
            camera.move_to(view)
        rgbd = camera.capture()
        self.run.recorder.save_view(rgbd)
        cloud = rgbd.point_cloud()
        if processor is not None:
            cloud = processor.register(cloud, self.merged)
        self.clouds.append(cloud)
        self.merged = PointCloud.merge(self.clouds)
        self.object_cloud = processor.segment(self.merged) if processor is not None else self.merged
        log.info(
            "view %d: %d points from (%.2f, %.2f, %.2f)", len(self.clouds), len(cloud), *view.eye_m
        )

    def _finish(self) -> Status:
        merged = self.merged
        if merged is None or self.object_cloud is None or len(self.object_cloud) == 0:
            raise DataError("look: the camera returned no points; check that the object is in view")
        self.run.recorder.save_cloud(merged)
        self.write("cloud", merged)
        self.write("views", len(self.clouds))
        if self.component("processor") is not None:
            self.write("object_cloud", self.object_cloud)
        self.run.results["views_taken"] = len(self.clouds)
        if self.shape_estimate is not None:
            self.write("shape", self.shape_estimate)
            summary = shape_summary(self.shape_estimate, len(self.clouds), self.busy_s)
            world = self.run.world_if_built()
            truth = world.ground_truth_poses() if world is not None else None
            if truth is not None:  # for evaluation only, never read by estimators
                summary["true_link_poses"] = np.asarray(truth).tolist()
            self.run.results["shape"] = summary
        return Status.SUCCESS


def shape_summary(shape: ShapeEstimate, views: int, time_s: float) -> dict[str, Any]:
    """JSON-ready summary of a shape estimate: per link the superquadric's fields, the
    initial pose and the parameter std; the number of views and the time spent (s)."""
    return {"links": shape_links(shape), "views": views, "time_s": time_s,
            "points": len(shape.cloud)}  # fmt: skip


def shape_links(shape: ShapeEstimate) -> list[dict[str, Any]]:
    """Per link the superquadric's fields, the initial pose and the parameter std (JSON-ready;
    ``shape_from_links`` reads them back)."""
    return [
        {
            "superquadric": {
                name: np.asarray(value).tolist() for name, value in asdict(link).items()
            },
            "initial_pose": np.asarray(pose).tolist(),
            "std": np.asarray(std).tolist(),
        }
        for link, pose, std in zip(shape.links, shape.initial_poses, shape.uncertainty, strict=True)
    ]


def shape_from_links(links: list[dict[str, Any]], cloud: PointCloud) -> ShapeEstimate:
    """The ShapeEstimate of ``shape_links`` output, fitted to ``cloud``."""
    superquadrics = [
        {key: np.asarray(value, dtype=np.float64) for key, value in link["superquadric"].items()}
        for link in links
    ]
    return ShapeEstimate(
        tuple(Superquadric(**fields) for fields in superquadrics),
        np.array([link["initial_pose"] for link in links], dtype=np.float64),
        np.array([link["std"] for link in links], dtype=np.float64),
        cloud,
    )
