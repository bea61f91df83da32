"""``look``: take depth views until the view planner is satisfied, fit the shape."""

from __future__ import annotations

import logging

from py_trees.common import Status
from pydantic import Field
from vistac.component import ComponentConfig
from vistac.errors import DataError
from vistac.tree import SkillBehaviour
from vistac.types import PointCloud

log = logging.getLogger(__name__)


class Look(SkillBehaviour):
    """One view per tick: ask the planner for a viewpoint, move the camera there, capture and
    merge the cloud; with a shape estimator, refit after each view. Writes ``cloud`` (the
    merged world-frame cloud, table included), ``views`` (count) and ``shape``."""

    writes = ("cloud", "views", "shape")
    role_fields = {"camera": "camera", "views": "view_planner", "shape": "shape_estimator"}
    optional_roles = ("shape",)

    class Config(ComponentConfig):
        camera: str = "camera"
        views: str = "views"
        shape: str = "shape"
        max_views: int = Field(8, gt=0, description="hard limit on the number of views")

    @classmethod
    def blackboard_writes(cls, config: Config, roles: dict[str, str]) -> set[str]:
        written = {"cloud", "views"}
        return written | ({"shape"} if config.shape in roles else set())

    def initialise(self) -> None:
        self.clouds: list[PointCloud] = []
        self.shape_estimate = None

    def update(self) -> Status:
        camera, planner = self.component("camera"), self.component("views")
        merged = PointCloud.merge(self.clouds) if self.clouds else None
        view = None
        if len(self.clouds) < self.config.max_views:
            view = planner.next_view(merged, self.shape_estimate, len(self.clouds))
        if view is None:
            return self._finish(merged)
        if camera.movable:
            camera.move_to(view)
        rgbd = camera.capture()
        cloud = rgbd.point_cloud()
        self.run.recorder.save_view(rgbd)
        self.clouds.append(cloud)
        log.info(
            "view %d: %d points from (%.2f, %.2f, %.2f)", len(self.clouds), len(cloud), *view.eye_m
        )
        estimator = self.component("shape")
        if estimator is not None:
            self.shape_estimate = estimator.fit(PointCloud.merge(self.clouds))
        return Status.RUNNING

    def _finish(self, merged: PointCloud | None) -> Status:
        if merged is None or len(merged) == 0:
            raise DataError("look: the camera returned no points; check that the object is in view")
        self.run.recorder.save_cloud(merged)
        self.write("cloud", merged)
        self.write("views", len(self.clouds))
        if self.shape_estimate is not None:
            self.write("shape", self.shape_estimate)
        self.run.results["views_taken"] = len(self.clouds)
        return Status.SUCCESS
