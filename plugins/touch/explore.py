"""Where to touch next (paper 2, III-I and III-J).

``touch.dhd``: the target is the point of the estimated surface farthest from every contact so
far (eq. 42) -- or, when the estimate carries a GPIS ``surface_variance``, the most uncertain
surface point (eq. 39-41) -- approached along its estimated normal from outside the workspace
sphere; after a miss, contact enforcement moves the target towards the nearest contact.
``touch.gpis`` publishes the variance from its first contacts, before the object is judged
novel, where III-I keeps the farthest point until then: on touch_learn.yaml's armchair the
paper's rule aimed at the pose-offset MLE chair's far side, missed about 200 times in a row
and stopped at 300 touches (two-way distance 0.092 m), against 108 touches and 0.036 m.
``touch.rrt``: the baseline -- extend from the contact nearest to a random workspace point by a
fixed step. Both stop when the directed Hausdorff distance from the estimated surface to the
contacts falls below ``dhd_threshold_m`` (eq. 44-45).

The estimate dict (from the touch estimators) may contain: ``contacts`` [[x, y, z], ...],
``mle_surface_m`` / ``mle_surface_normals`` ([S, 3] arrays: the MLE shape's surface samples in
the world frame), ``surface_points_m`` / ``surface_normals`` ([S, 3]: a reconstructed surface,
which then replaces the MLE surface) and ``surface_variance`` (points [N, 3] -> variance [N]).
"""

from __future__ import annotations

import logging
from abc import ABC, abstractmethod
from typing import Any

import numpy as np
from pydantic import Field
from vistac.component import Component, ComponentConfig, ComponentContext
from vistac.plugins.touch.metrics import nearest_distances
from vistac.types import FloatArray

log = logging.getLogger(__name__)

Touch = tuple[FloatArray, FloatArray]


class ExplorerConfig(ComponentConfig):
    workspace_centre_m: tuple[float, float, float] = (0.0, 0.5, 0.3)
    workspace_half_extent_m: float = Field(
        0.2, gt=0, description="the object lies inside the cube of this half size"
    )
    dhd_threshold_m: float = Field(0.03, gt=0, description="stop below this coverage DHD")
    min_contacts: int = Field(8, ge=1, description="never stop with fewer contacts")
    overshoot_m: float = Field(0.03, ge=0, description="the probe goes this far past a target")
    enforce_attempts: int = Field(2, ge=0, description="local retries after a missed target")


class _Explorer(Component, ABC):
    """Shared parts: first touches, the approach from outside and the termination test."""

    kind = "touch_explorer"
    Config = ExplorerConfig

    def __init__(self, config: ExplorerConfig, ctx: ComponentContext) -> None:
        super().__init__(config, ctx)
        self.centre = np.asarray(config.workspace_centre_m, dtype=np.float64)
        self.outside_m = 2.0 * np.sqrt(3.0) * config.workspace_half_extent_m
        self.last_dhd_m: float | None = None
        self._pending: tuple[FloatArray, FloatArray, int] | None = None
        self._contact_count = 0
        self._missed: list[FloatArray] = []

    def next_touch(self, estimate: dict[str, Any], rng: np.random.Generator) -> Touch | None:
        """(start [3], target [3]) of the next touch, or None when the surface is covered."""
        contacts = np.asarray(estimate.get("contacts") or np.zeros((0, 3)), dtype=np.float64)
        missed_last = self._pending is not None and not self._reached(contacts)
        self._contact_count = len(contacts)
        surface, normals = self._surface(estimate)
        if surface is None or len(contacts) == 0:
            self.last_dhd_m = None
            return self._blind_touch(rng)
        reachable = self._away_from_misses(surface)
        if not reachable.any():
            log.info("every estimated surface point is next to a target the probe could not "
                     "reach; nothing left to touch, exploration stops")  # fmt: skip
            self.last_dhd_m = 0.0
            return None
        self.last_dhd_m = float(nearest_distances(surface[reachable], contacts).max(initial=0.0))
        if self.last_dhd_m < self.config.dhd_threshold_m and (
            len(contacts) >= self.config.min_contacts
        ):
            return None
        if missed_last and self._pending is not None:
            self._missed.append(self._pending[0])
            retry = self._enforce(contacts)
            if retry is not None:
                return retry
        target, normal = self._choose(estimate, surface, normals, contacts, rng)
        self._pending = (target, normal, 0)
        return self._approach(target, normal)

    def _reached(self, contacts: FloatArray) -> bool:
        """Whether the last touch made contact near its target (within ``dhd_threshold_m``)."""
        if len(contacts) == self._contact_count or self._pending is None:
            return False
        return bool(np.linalg.norm(contacts[-1] - self._pending[0]) <= self.config.dhd_threshold_m)

    def _surface(self, estimate: dict[str, Any]) -> tuple[FloatArray | None, FloatArray | None]:
        for points_key, normals_key in (
            ("surface_points_m", "surface_normals"),
            ("mle_surface_m", "mle_surface_normals"),
        ):
            points = estimate.get(points_key)
            if points is not None and len(points):
                normals = estimate.get(normals_key)
                if normals is None:
                    normals = self._radial(np.asarray(points))
                return np.asarray(points, dtype=np.float64), np.asarray(normals, dtype=np.float64)
        return None, None

    def _radial(self, points: FloatArray) -> FloatArray:
        away = points - self.centre
        return np.asarray(away / np.maximum(np.linalg.norm(away, axis=1, keepdims=True), 1e-9))

    def _blind_touch(self, rng: np.random.Generator) -> Touch:
        """Before there is an estimate: through the workspace from a random direction."""
        direction = rng.normal(size=3)
        direction /= np.linalg.norm(direction)
        aim = self.centre + rng.uniform(-0.5, 0.5, 3) * self.config.workspace_half_extent_m
        self._pending = None
        return aim + self.outside_m * direction, aim - self.outside_m * direction

    def _approach(self, target: FloatArray, normal: FloatArray) -> Touch:
        """Start outside the workspace sphere on the target's normal, end past the target."""
        normal = normal / np.linalg.norm(normal)
        return target + self.outside_m * normal, target - self.config.overshoot_m * normal

    def _enforce(self, contacts: FloatArray) -> Touch | None:
        """Contact enforcement (III-I2): move the missed target a third of the way to the
        nearest contact and approach again, at most ``enforce_attempts`` times."""
        assert self._pending is not None
        target, normal, attempts = self._pending
        if attempts >= self.config.enforce_attempts:
            return None
        nearest = contacts[np.argmin(np.linalg.norm(contacts - target, axis=1))]
        target = target + (nearest - target) / 3.0
        self._pending = (target, normal, attempts + 1)
        return self._approach(target, normal)

    def _away_from_misses(self, surface: FloatArray) -> Any:
        """Mask [S] of surface points not next to a target that could not be reached (no
        contact near it after contact enforcement); these are left out of target selection
        and of the termination test."""
        if not self._missed:
            return np.ones(len(surface), dtype=bool)
        return nearest_distances(surface, np.array(self._missed)) > self.config.dhd_threshold_m / 2

    @abstractmethod
    def _choose(
        self,
        estimate: dict[str, Any],
        surface: FloatArray,
        normals: FloatArray,
        contacts: FloatArray,
        rng: np.random.Generator,
    ) -> tuple[FloatArray, FloatArray]:
        """The next target point [3] and the normal [3] to approach it along."""


class DhdExplorer(_Explorer):
    """``touch.dhd``: the surface point farthest from the contacts (eq. 42), or the most
    uncertain one when the estimate has a ``surface_variance``."""

    def _choose(
        self,
        estimate: dict[str, Any],
        surface: FloatArray,
        normals: FloatArray,
        contacts: FloatArray,
        rng: np.random.Generator,
    ) -> tuple[FloatArray, FloatArray]:
        variance = estimate.get("surface_variance")
        if callable(variance):
            score = np.asarray(variance(surface), dtype=np.float64)
        else:
            score = nearest_distances(surface, contacts)
        score = np.where(self._away_from_misses(surface), score, -np.inf)
        best = (
            int(np.argmax(score)) if np.isfinite(score).any() else int(rng.integers(len(surface)))
        )
        return surface[best], normals[best]


class RrtConfig(ExplorerConfig):
    step_m: float = Field(0.03, gt=0, description="RRT extension length")


class RrtExplorer(_Explorer):
    """``touch.rrt``: extend from the contact nearest to a random workspace point."""

    Config = RrtConfig

    def __init__(self, config: RrtConfig, ctx: ComponentContext) -> None:
        super().__init__(config, ctx)
        self._normals: FloatArray = np.zeros((0, 3))

    def next_touch(self, estimate: dict[str, Any], rng: np.random.Generator) -> Touch | None:
        self._normals = np.asarray(estimate.get("normals") or np.zeros((0, 3)), dtype=np.float64)
        return super().next_touch(estimate, rng)

    def _choose(
        self,
        estimate: dict[str, Any],
        surface: FloatArray,
        normals: FloatArray,
        contacts: FloatArray,
        rng: np.random.Generator,
    ) -> tuple[FloatArray, FloatArray]:
        half = self.config.workspace_half_extent_m
        sample = self.centre + rng.uniform(-half, half, 3)
        nearest = int(np.argmin(np.linalg.norm(contacts - sample, axis=1)))
        direction = sample - contacts[nearest]
        direction /= max(float(np.linalg.norm(direction)), 1e-9)
        normal = self._normals[nearest] if len(self._normals) > nearest else direction
        target = contacts[nearest] + self.config.step_m * direction
        return target, normal
