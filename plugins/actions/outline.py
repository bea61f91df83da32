"""``actions.outline``: push and pull candidates from the outline of the observed cloud.

Needs no shape model: the object is the part of the cloud above the table plane (z = 0), its
outline the 2D convex hull of those points. Pushes start on the outline and go inwards along
the edge normal perturbed by U(-jitter, jitter); pulls grasp across the narrowest chord
through a point of the object and move along a direction drawn around ``pull_towards_rad``.
"""

from __future__ import annotations

import logging
from typing import Literal

import numpy as np
from pydantic import Field
from scipy.spatial import ConvexHull, QhullError

from vistac.component import Component, ComponentConfig, ComponentContext
from vistac.errors import DataError
from vistac.protocols import Scene
from vistac.types import Action, FloatArray, Pull, Push

log = logging.getLogger(__name__)

MIN_OBJECT_POINTS = 20
CHORD_DIRECTIONS = 36


class OutlineSampler(Component):
    """Samples pushes on, and pulls across, the convex outline of the observed object."""

    kind = "action_sampler"

    class Config(ComponentConfig):
        samples: int = Field(32, gt=0, description="candidates per call")
        interactions: list[Literal["push", "pull"]] = Field(default_factory=lambda: ["push", "pull"],
                                                            min_length=1)
        speed_mps: float = Field(0.02, gt=0, le=0.25)
        duration_s: float = Field(5.0, gt=0)
        table_clearance_m: float = Field(0.008, ge=0, description="points this far above z=0 are object")
        jitter_deg: float = Field(5.0, ge=0, le=45, description="push direction noise around the normal")
        max_grasp_width_m: float = Field(0.12, gt=0, description="widest chord the gripper can close on")
        pull_towards_rad: float = Field(-np.pi / 2, description="mean pull direction (-y: towards the robot)")
        pull_spread_rad: float = Field(np.pi / 3, ge=0, description="pull direction ~ U(+-spread)")

    def __init__(self, config: Config, ctx: ComponentContext) -> None:
        super().__init__(config, ctx)
        self.config: OutlineSampler.Config = config

    def sample(self, scene: Scene, rng: np.random.Generator) -> list[Action]:
        hull_xy = self.outline(scene.cloud.points_m)
        kinds = rng.choice(self.config.interactions, size=self.config.samples)
        actions: list[Action] = []
        for kind in kinds:
            action = self._push(hull_xy, rng) if kind == "push" else self._pull(hull_xy, rng)
            if action is not None:
                actions.append(action)
        return actions

    def outline(self, points_m: FloatArray) -> FloatArray:
        """Counter-clockwise convex outline [K, 2] of the points above the table."""
        above = points_m[points_m[:, 2] > self.config.table_clearance_m, :2]
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
        weights = rng.dirichlet(np.ones(len(hull_xy)))
        inside = weights @ hull_xy
        centre, axis_rad, width_m = narrowest_chord(hull_xy, inside)
        if width_m > self.config.max_grasp_width_m:
            return None
        pd = self.config.pull_towards_rad + rng.uniform(-1, 1) * self.config.pull_spread_rad
        return Pull(centre, float(pd), self.config.speed_mps, axis_rad, self.config.duration_s)


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


def narrowest_chord(hull_xy: FloatArray, point: FloatArray) -> tuple[FloatArray, float, float]:
    """The shortest chord of a convex polygon [K, 2] through ``point`` [2], over
    CHORD_DIRECTIONS directions: (chord midpoint [2], direction rad, length m)."""
    angles = np.linspace(0.0, np.pi, CHORD_DIRECTIONS, endpoint=False)
    directions = np.stack([np.cos(angles), np.sin(angles)], axis=1)  # [D, 2]
    starts, edges = hull_xy, np.roll(hull_xy, -1, axis=0) - hull_xy  # [K, 2]
    # Solve point + t d = start + u e for every direction/edge pair.
    cross = directions[:, None, 0] * edges[None, :, 1] - directions[:, None, 1] * edges[None, :, 0]
    offset = starts[None] - point[None, None]  # [1, K, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (offset[..., 0] * edges[None, :, 1] - offset[..., 1] * edges[None, :, 0]) / cross
        u = (offset[..., 0] * directions[:, None, 1] - offset[..., 1] * directions[:, None, 0]) / cross
    hit = (np.abs(cross) > 1e-12) & (u >= 0) & (u <= 1)
    t_max = np.where(hit, t, -np.inf).max(axis=1)
    t_min = np.where(hit, t, np.inf).min(axis=1)
    lengths = t_max - t_min
    best = int(np.argmin(lengths))
    midpoint = point + directions[best] * 0.5 * (t_max[best] + t_min[best])
    return midpoint, float(angles[best]), float(lengths[best])
