"""``actions.outline``: push and pull candidates from the outline of the observed cloud.

Needs no shape model: the object is the largest connected cluster (on a 2D grid) of the
points between the table plane (z = 0) and ``max_object_height_m`` (which leaves out a
gripper hovering in view), and its outline is the 2D convex hull of that cluster. Pushes
start on the outline and go inwards along the edge normal perturbed by U(-jitter, jitter);
pulls grasp across the outline where the chord fits the gripper, then move along a direction
drawn around ``pull_towards_rad``.
"""

from __future__ import annotations

import logging
from typing import Literal

import numpy as np
from pydantic import Field
from scipy import ndimage
from scipy.spatial import ConvexHull, QhullError
from vistac.component import Component, ComponentConfig, ComponentContext
from vistac.errors import DataError
from vistac.protocols import Scene
from vistac.types import Action, FloatArray, Pull, Push, action_point

log = logging.getLogger(__name__)

MIN_OBJECT_POINTS = 20
PULL_ATTEMPTS = 8


Workspace = tuple[tuple[float, float], tuple[float, float]]
"""((x min, x max), (y min, y max)) in metres."""


class OutlineSampler(Component):
    """Samples pushes on, and pulls across, the convex outline of the observed object."""

    kind = "action_sampler"

    class Config(ComponentConfig):
        samples: int = Field(32, gt=0, description="candidates per call")
        interactions: list[Literal["push", "pull"]] = Field(default=["push", "pull"], min_length=1)
        speed_mps: float = Field(0.02, gt=0, le=0.25)
        duration_s: float = Field(5.0, gt=0)
        table_clearance_m: float = Field(
            0.008, ge=0, description="points this far above z=0 are object"
        )
        max_object_height_m: float = Field(
            0.1, gt=0, description="points higher up are not the object"
        )
        cluster_cell_m: float = Field(0.01, gt=0, description="grid cell for connected clusters")
        jitter_deg: float = Field(
            5.0, ge=0, le=45, description="push direction noise around the normal"
        )
        max_grasp_width_m: float = Field(
            0.12, gt=0, description="widest object the gripper can close on"
        )
        finger_half_width_m: float = Field(
            0.03, ge=0, description="keeps grasps off the outline's ends"
        )
        workspace_xy_m: Workspace = (
            (-0.45, 0.45),
            (0.2, 0.8),
        )
        """((x min, x max), (y min, y max)): the gripper's path must stay inside."""
        object_margin_m: float | None = Field(
            None, ge=0, description="drop pushes and pulls that would leave any part of the "
            "object's outline less than this inside the workspace, or nearer its edge than it "
            "is where it is that near already (the object moves about as far as the gripper), "
            "so that later interactions can still get behind it; null: no check",
        )  # fmt: skip
        pull_towards_rad: float = Field(
            -np.pi / 2, description="mean pull direction (-y: towards the robot)"
        )
        pull_spread_rad: float = Field(np.pi / 3, ge=0, description="pull direction ~ U(+-spread)")
        push_towards_rad: float | None = Field(
            None, description="keep pushes heading within push_spread_rad of this; None: any"
        )
        push_spread_rad: float = Field(
            np.pi / 6, gt=0, le=np.pi, description="see push_towards_rad"
        )

    def __init__(self, config: Config, ctx: ComponentContext) -> None:
        super().__init__(config, ctx)
        self.config: OutlineSampler.Config = config

    def sample(self, scene: Scene, rng: np.random.Generator) -> list[Action]:
        # The segmented object cloud of the shape estimate when there is one (no clutter).
        cloud = scene.shape.cloud if scene.shape is not None else scene.cloud
        hull_xy = self.outline(cloud.points_m)
        kinds = rng.choice(self.config.interactions, size=self.config.samples)
        actions: list[Action] = []
        for kind in kinds:
            action = self._push(hull_xy, rng) if kind == "push" else self._pull(hull_xy, rng)
            if action is not None and self._reachable(action, hull_xy):
                actions.append(action)
        return actions

    def _reachable(self, action: Action, outline_xy: FloatArray) -> bool:
        """Whether the interaction's start and end points lie in the workspace, a push heads
        where ``push_towards_rad`` allows, and the interaction, moving the object's outline
        outline_xy [K, 2] as far as the gripper, leaves all of it ``object_margin_m`` inside
        the workspace (or, where part of it is nearer the edge already, no nearer than
        before)."""
        towards = self.config.push_towards_rad
        if isinstance(action, Push) and towards is not None:
            off_rad = np.angle(np.exp(1j * (action.pd_rad - towards)))
            if abs(off_rad) > self.config.push_spread_rad:
                return False
        start = action_point(action)
        travel = np.array([np.cos(action.pd_rad), np.sin(action.pd_rad)]) * (
            action.speed_mps * action.duration_s
        )
        if not in_workspace(np.stack([start, start + travel]), self.config.workspace_xy_m):
            return False
        margin = self.config.object_margin_m
        if margin is None:
            return True
        after = depth_inside(outline_xy + travel, self.config.workspace_xy_m)
        return after >= min(margin, depth_inside(outline_xy, self.config.workspace_xy_m))

    def outline(self, points_m: FloatArray) -> FloatArray:
        """Counter-clockwise convex outline [K, 2] of the points above the table."""
        height = points_m[:, 2]
        keep = (height > self.config.table_clearance_m) & (height < self.config.max_object_height_m)
        above = largest_cluster(points_m[keep, :2], self.config.cluster_cell_m)
        if len(above) < MIN_OBJECT_POINTS:
            raise DataError(
                f"actions.outline: only {len(above)} points above the table "
                f"(need {MIN_OBJECT_POINTS}); is the object in view?"
            )
        try:
            hull = ConvexHull(above)
        except QhullError as exc:
            raise DataError(f"actions.outline: the object points are degenerate ({exc})") from None
        return above[hull.vertices]

    def _push(self, hull_xy: FloatArray, rng: np.random.Generator) -> Push:
        point, outward = point_on_outline(hull_xy, rng.uniform())
        jitter = np.radians(rng.uniform(-self.config.jitter_deg, self.config.jitter_deg))
        inward_rad = float(np.arctan2(-outward[1], -outward[0]) + jitter)
        return Push(point, inward_rad, self.config.speed_mps, self.config.duration_s)

    def _pull(self, hull_xy: FloatArray, rng: np.random.Generator) -> Pull | None:
        """Fingers close along a random direction at a random offset across it (kept
        ``finger_half_width_m`` from the outline's ends, so either link of a two-link object
        may be grasped); the chord there must fit the gripper. None after a few misses."""
        for _ in range(PULL_ATTEMPTS):
            axis_rad = float(rng.uniform(0.0, np.pi))
            across = np.array([-np.sin(axis_rad), np.cos(axis_rad)])
            offsets = hull_xy @ across
            margin = min(self.config.finger_half_width_m, 0.4 * np.ptp(offsets))
            offset = rng.uniform(offsets.min() + margin, offsets.max() - margin)
            centroid = hull_xy.mean(axis=0)
            midpoint, width_m = chord(
                hull_xy, centroid + (offset - centroid @ across) * across, axis_rad
            )
            if width_m <= self.config.max_grasp_width_m:
                pd = self.config.pull_towards_rad + rng.uniform(-1, 1) * self.config.pull_spread_rad
                return Pull(
                    midpoint, float(pd), self.config.speed_mps, axis_rad, self.config.duration_s
                )
        return None


def in_workspace(points_xy: FloatArray, workspace_xy_m: Workspace) -> bool:
    """Whether every point [N, 2] lies in the workspace."""
    return depth_inside(points_xy, workspace_xy_m) >= 0.0


def depth_inside(points_xy: FloatArray, workspace_xy_m: Workspace) -> float:
    """Distance (m) of the point [2] or points [N, 2] inside the workspace's nearest edge
    (negative outside): the smallest over the points."""
    (x_min, x_max), (y_min, y_max) = workspace_xy_m
    x, y = np.asarray(points_xy, dtype=np.float64).reshape(-1, 2).T
    return float(np.min([x - x_min, x_max - x, y - y_min, y_max - y]))


def chord(hull_xy: FloatArray, point: FloatArray, angle_rad: float) -> tuple[FloatArray, float]:
    """The chord of a convex polygon [K, 2] through ``point`` [2] along ``angle_rad``:
    (midpoint [2], length m)."""
    direction = np.array([np.cos(angle_rad), np.sin(angle_rad)])
    edges = np.roll(hull_xy, -1, axis=0) - hull_xy
    offset = hull_xy - point
    cross = direction[0] * edges[:, 1] - direction[1] * edges[:, 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (offset[:, 0] * edges[:, 1] - offset[:, 1] * edges[:, 0]) / cross
        u = (offset[:, 0] * direction[1] - offset[:, 1] * direction[0]) / cross
    hit = (np.abs(cross) > 1e-12) & (u >= 0) & (u <= 1)
    t_max, t_min = t[hit].max(), t[hit].min()
    return point + direction * 0.5 * (t_max + t_min), float(t_max - t_min)


def largest_cluster(points_xy: FloatArray, cell_m: float) -> FloatArray:
    """The points [K, 2] of the largest 8-connected cluster of occupied grid cells."""
    if len(points_xy) == 0:
        return points_xy
    cells = np.floor((points_xy - points_xy.min(axis=0)) / cell_m).astype(int)
    grid = np.zeros(cells.max(axis=0) + 1, dtype=bool)
    grid[cells[:, 0], cells[:, 1]] = True
    labels, _ = ndimage.label(grid, structure=np.ones((3, 3)))
    point_labels = labels[cells[:, 0], cells[:, 1]]
    biggest = np.bincount(point_labels)[1:].argmax() + 1
    return points_xy[point_labels == biggest]


def point_on_outline(hull_xy: FloatArray, fraction: float) -> tuple[FloatArray, FloatArray]:
    """The point at ``fraction`` of the perimeter of a counter-clockwise polygon [K, 2] and
    the outward unit normal of its edge: ([2], [2])."""
    edges = np.roll(hull_xy, -1, axis=0) - hull_xy
    lengths = np.linalg.norm(edges, axis=1)
    cumulative = np.concatenate([[0.0], np.cumsum(lengths)])
    s = fraction * cumulative[-1]
    i = int(np.clip(np.searchsorted(cumulative, s, side="right") - 1, 0, len(edges) - 1))
    point = hull_xy[i] + edges[i] * (s - cumulative[i]) / lengths[i]
    outward = np.array([edges[i, 1], -edges[i, 0]]) / lengths[i]
    return point, outward
