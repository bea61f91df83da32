"""``actions.icem``: goal-driven pushing by iCEM model-predictive control (paper 1, IV-B5).

The improved cross-entropy method of Pinneri et al. (2021) plans a sequence of
``horizon_pushes`` pushes; the first is executed, then the skill looks, updates the belief and
plans again. Each push is three numbers: where on the pushed link's outline it starts (a
fraction of the outline, in the link's frame, so it moves with the object), the offset of its
direction from the inward normal, and its duration. A sequence is scored by rolling it out
with the filter's learned process model (``predict_states`` of ``filters.dual``: the mean
prediction with the belief's parameters); its cost is the mean over the pushes of the
distance of the predicted pose of link 0 to the goal after each push.

iCEM's ingredients: samples are the mean plus the standard deviation times colored noise
(power spectrum 1/f^beta along the push sequence), clipped to the bounds; the population
shrinks by ``population_decay`` per iteration (never below twice the elites); a share of the
elites is kept into the next iteration and, shifted by one push, into the next plan; the
mean is added in the last iteration; the best sequence seen is executed.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
import torch
from pydantic import Field, NonNegativeFloat, model_validator
from scipy.spatial.distance import cdist
from vistac.component import Component, ComponentConfig, ComponentContext
from vistac.errors import ConfigError, DataError
from vistac.plugins.actions.affordances import (
    CLOUD_POINTS_FIELD,
    FINGER_FOOTPRINT_FIELD,
    fingers_blocked,
    inside_any_link,
    link_outline,
)
from vistac.protocols import Scene
from vistac.types import Action, FloatArray, Push, ShapeEstimate, Superquadric

log = logging.getLogger(__name__)

NoiseScaling = Literal["spectrum", "sequence"]
_FRACTION, _OFFSET, _DURATION = 0, 1, 2
_INFEASIBLE_COST = 1e3
_OUTLINE_POINTS = 360
_CACHED_OUTLINES = 8
_JOIN_M = 0.005
"""Fitted links whose outlines come this near are parts of one body (``joined_outline``)."""


def colored_noise(
    beta: float,
    shape: tuple[int, ...],
    length: int,
    rng: np.random.Generator,
    scaling: NoiseScaling = "spectrum",
) -> FloatArray:
    """Noise [*shape, length] whose power spectrum along the last axis falls as 1/f^beta
    (beta = 0: white; 2: smooth, as iCEM uses).

    ``scaling``: "spectrum" divides by the standard deviation the spectrum implies, as
    Pinneri et al.'s reference does: every value is standard normal. "sequence" divides each
    sequence by its own sample std (unit std along the horizon; for one value, whose sample
    std is 0, the spectrum's): for two pushes the values lie exactly 2 apart with heavy tails
    (their mean is Cauchy), so more samples land far from the mean."""
    frequencies = np.fft.rfftfreq(length)
    frequencies[0] = frequencies[1] if length > 1 else 1.0
    amplitude = frequencies ** (-beta / 2.0)
    spectrum = amplitude * (
        rng.standard_normal((*shape, len(frequencies)))
        + 1j * rng.standard_normal((*shape, len(frequencies)))
    )
    power = 4.0 * amplitude**2  # each value's variance from a complex bin, times length^2
    if length % 2 == 0 and length > 1:
        spectrum[..., -1] = spectrum[..., -1].real * math.sqrt(2.0)
        power[-1] = 2.0 * amplitude[-1] ** 2
    spectrum[..., 0] = spectrum[..., 0].real * math.sqrt(2.0)
    power[0] = 2.0 * amplitude[0] ** 2
    signal = np.fft.irfft(spectrum, n=length)
    if scaling == "sequence" and length > 1:
        return np.asarray(signal / signal.std(axis=-1, keepdims=True).clip(1e-12))
    return np.asarray(signal * length / math.sqrt(float(power.sum())))


def wrap_angle(angle_rad: FloatArray) -> FloatArray:
    return np.asarray((angle_rad + np.pi) % (2.0 * np.pi) - np.pi)


class ICEMController(Component):
    """Implements the ``Controller`` protocol: ``plan(scene, goal, rng) -> Push``.

    goal: [3] = (x_m, y_m, theta_rad) of link 0 in the filter's belief coordinates."""

    kind = "controller"

    class Config(ComponentConfig):
        population: int = Field(32, ge=4, description="samples in the first iteration")
        elites: int = Field(5, ge=1)
        iterations: int = Field(3, ge=1)
        horizon_pushes: int = Field(2, ge=1, description="pushes planned ahead")
        noise_beta: float = Field(2.0, ge=0, description="colored-noise exponent")
        noise_scaling: NoiseScaling = Field(
            "sequence",
            description="sequence: each sampled sequence scaled to unit std along the horizon "
            "(a wider search; with skills/goal_push.yaml 1.8 mm lower final error with "
            "estimated parameters, docs/results.md); spectrum: every value standard normal, "
            "as Pinneri et al.'s reference",
        )
        population_decay: float = Field(1.25, ge=1, description="population shrink per iteration")
        keep_elites: float = Field(0.3, ge=0, le=1, description="share of elites carried over")
        momentum: float = Field(0.1, ge=0, lt=1, description="weight of the old mean and std")
        speed_mps: float = Field(0.02, gt=0, le=0.25)
        duration_s: tuple[float, float] = Field(
            (1.0, 4.0),
            description="push duration bounds; the executor starts the pad 10 mm (standoff) "
            "from the object, so at 20 mm/s a push shorter than 0.5 s never touches it, and a "
            "process model learned from pushes that did will still predict it moving",
        )
        max_offset_deg: float = Field(30.0, ge=0, le=80, description="|pd - inward normal|")
        rate_hz: float = Field(5.0, gt=0, description="steps per second of the look-ahead")
        angle_weight_m_per_rad: float = Field(
            0.02, ge=0, description="cost of an angle error, in metres per radian"
        )
        approach_clearance_m: float = Field(
            0.02, ge=0, description="the fingers descend this far behind the contact point "
            "(the executor's standoff_m + pusher_offset_m): there they must be within the "
            "arm's workspace and clear of the object",
        )
        finger_footprint_m: tuple[NonNegativeFloat, NonNegativeFloat] = FINGER_FOOTPRINT_FIELD
        finger_clearance_m: float = Field(
            0.0, ge=0, description="gap kept between every fitted link and the fingers where "
            "they descend (actions.affordances keeps 5 mm, its pushes within 5 deg of the "
            "normal; a push here may turn max_offset_deg from it, and at 30 deg the closed "
            "fingers' corner descends 3 mm from a flat face it pushes)",
        )
        max_cloud_points_under_fingers: int | None = CLOUD_POINTS_FIELD
        avoid_blocked_m: float = Field(
            0.02, ge=0, description="a first push whose contact point lies this near that of "
            "a push blocked on its way down (the scene's blocked_xy_m) is infeasible",
        )

        @model_validator(mode="after")
        def _bounds(self) -> ICEMController.Config:
            low, high = self.duration_s
            if not 0 < low <= high:
                raise ValueError(f"duration_s: need 0 < min <= max, got {self.duration_s}")
            if self.elites > self.population:
                raise ValueError("elites must not exceed population")
            return self

    def __init__(self, config: Config, ctx: ComponentContext) -> None:
        super().__init__(config, ctx)
        self.config: ICEMController.Config = config
        filter_ = ctx.find("filter")
        if filter_ is None or not callable(getattr(filter_, "predict_states", None)):
            raise ConfigError(
                "actions.icem needs a filter component with predict_states (filters.dual) "
                "whose process model predicts the pushes"
            )
        self.filter = filter_
        arm_config = getattr(ctx.find("arm"), "config", None)
        self.workspace_m = (
            np.asarray(getattr(arm_config, "workspace_min_m", (-np.inf,) * 3))[:2],
            np.asarray(getattr(arm_config, "workspace_max_m", (np.inf,) * 3))[:2],
        )
        self._shifted: FloatArray | None = None
        """Elites of the last plan, shifted by one push: [K, H, 3]."""
        self.last_cost: float = math.nan
        self._outlines: dict[int, tuple[Superquadric, FloatArray, FloatArray]] = {}
        """The links of the last shape estimate whose outlines were traced (by id), with
        their points and normals."""

    # -- Controller protocol ----------------------------------------------------------------

    def check_goal(self, goal: Sequence[float]) -> None:
        """ConfigError when the goal's position (x_m, y_m) lies outside the arm's workspace,
        where no push can bring the object."""
        (x_m, y_m), (low, high) = goal[:2], self.workspace_m
        if low[0] <= x_m <= high[0] and low[1] <= y_m <= high[1]:
            return
        raise ConfigError(
            f"goal ({x_m:.3f}, {y_m:.3f}) m lies outside the arm's workspace (x {low[0]:.2f} "
            f"to {high[0]:.2f} m, y {low[1]:.2f} to {high[1]:.2f} m); give a goal within it"
        )

    def plan(self, scene: Scene, goal: FloatArray, rng: np.random.Generator) -> Action:
        if scene.shape is None:
            raise DataError("actions.icem: no shape estimate; run `look` with a shape estimator")
        goal = np.asarray(goal, dtype=np.float64)
        if goal.shape != (3,) or not np.all(np.isfinite(goal)):
            raise ConfigError(f"actions.icem: goal must be 3 finite numbers, got {goal!r}")
        link0 = self.filter.layout.link_pose(self.filter.belief.mean)[0, :3].numpy()
        # A look may split what the belief holds as one link (a triangle fitted as two):
        # the pushes then start on the outline of the fitted links joined together.
        whole = self.filter.layout.n_links == 1 and len(scene.shape.links) > 1
        outline = _OutlineInLink(scene.shape, link0, self._link_outline, whole)
        with torch.inference_mode():  # rollouts only: no autograd bookkeeping at all
            best, cost = self._optimise(outline, goal, rng, self._obstacles(scene))
        self.last_cost = cost
        if cost >= _INFEASIBLE_COST:
            raise DataError(
                "actions.icem: every planned first push would start out of the arm's reach, "
                "bring the fingers down on the object or start where a push was blocked "
                "(approach_clearance_m, finger_clearance_m, max_cloud_points_under_fingers, "
                "avoid_blocked_m); move the goal or the object"
            )
        first = self._pushes(outline, best[None, 0], None)[0][0]
        log.info(
            "icem: push at (%.3f, %.3f) m along %.0f deg for %.1f s, predicted goal distance "
            "%.1f mm", *first.cp_m, math.degrees(first.pd_rad), first.duration_s, cost * 1e3,
        )  # fmt: skip
        return first

    def _link_outline(self, link: Superquadric) -> tuple[FloatArray, FloatArray]:
        """:func:`link_outline` of ``link`` with ``_OUTLINE_POINTS`` points, traced again
        only for the links of a new shape estimate: plans between two looks share them."""
        cached = self._outlines.get(id(link))
        if cached is None or cached[0] is not link:
            if len(self._outlines) >= _CACHED_OUTLINES:
                self._outlines.clear()
            cached = self._outlines[id(link)] = (link, *link_outline(link, _OUTLINE_POINTS))
        return cached[1], cached[2]

    def _obstacles(self, scene: Scene) -> _Obstacles:
        """Where the fingers must not come down, as the last look saw the object, and the
        pushes blocked on their way down since the last interaction."""
        shape = scene.shape
        assert shape is not None
        cloud_xy = np.asarray(shape.cloud.points_m, dtype=np.float64)[:, :2]
        margin_m = 2.0 * self.config.finger_clearance_m
        along_m, across_m = self.config.finger_footprint_m
        return _Obstacles(
            shape, cloud_xy[~inside_any_link(shape.links, cloud_xy)],
            (along_m + margin_m, across_m + margin_m), self.config.max_cloud_points_under_fingers,
            np.asarray(scene.blocked_xy_m, dtype=np.float64).reshape(-1, 2),
            self.config.avoid_blocked_m,
        )  # fmt: skip

    # -- iCEM -------------------------------------------------------------------------------

    def _bounds(self) -> tuple[FloatArray, FloatArray]:
        offset = math.radians(self.config.max_offset_deg)
        low = np.array([0.0, -offset, self.config.duration_s[0]])
        high = np.array([1.0, offset, self.config.duration_s[1]])
        return low, high

    def _optimise(
        self,
        outline: _OutlineInLink,
        goal: FloatArray,
        rng: np.random.Generator,
        obstacles: _Obstacles,
    ) -> tuple[FloatArray, float]:
        """The best push sequence [H, 3] and its cost (m); the first push must keep the
        fingers off the ``obstacles`` (see ``_costs``)."""
        config = self.config
        low, high = self._bounds()
        horizon = config.horizon_pushes
        mean = np.tile(0.5 * (low + high), (horizon, 1))
        std = np.tile(0.5 * (high - low), (horizon, 1))
        elites = self._shifted
        best, best_cost = mean.copy(), math.inf
        for iteration in range(config.iterations):
            count = max(round(config.population / config.population_decay**iteration),
                        2 * config.elites)  # fmt: skip
            noise = colored_noise(
                config.noise_beta, (count, 3), horizon, rng, config.noise_scaling
            ).transpose(0, 2, 1)
            samples = mean + std * noise
            if elites is not None and len(elites):
                kept = elites[: round(config.keep_elites * len(elites))]
                samples = np.concatenate([samples, kept])
            if iteration == config.iterations - 1:
                samples = np.concatenate([samples, mean[None]])
            samples = self._clip(samples, low, high)
            costs = self._costs(outline, samples, goal, obstacles)
            order = np.argsort(costs)
            elites = samples[order[: config.elites]]
            if costs[order[0]] < best_cost:
                best, best_cost = samples[order[0]].copy(), float(costs[order[0]])
            mean = config.momentum * mean + (1 - config.momentum) * elites.mean(0)
            std = config.momentum * std + (1 - config.momentum) * elites.std(0)
        assert elites is not None
        self._shifted = self._shift(elites, low, high)
        return best, best_cost

    @staticmethod
    def _clip(samples: FloatArray, low: FloatArray, high: FloatArray) -> FloatArray:
        """Clip to the bounds; the outline fraction wraps around."""
        clipped = np.clip(samples, low, high)
        clipped[..., _FRACTION] = np.mod(samples[..., _FRACTION], 1.0)
        return clipped

    def _shift(self, elites: FloatArray, low: FloatArray, high: FloatArray) -> FloatArray:
        """Elites [K, H, 3] advanced by one push, the new last push at the bounds' middle."""
        tail = np.broadcast_to(0.5 * (low + high), (len(elites), 1, 3))
        return np.concatenate([elites[:, 1:], tail], axis=1)

    def _costs(
        self,
        outline: _OutlineInLink,
        samples: FloatArray,
        goal: FloatArray,
        obstacles: _Obstacles,
    ) -> FloatArray:
        """Cost [N] (m) of push sequences [N, H, 3]: the mean over the pushes of the distance
        of the predicted link-0 pose to the goal after each (so the first push, the one
        carried out, already heads there), plus a penalty for pushes the arm cannot start.
        The first push, also infeasible where its fingers would come down on the
        ``obstacles`` (the later ones are planned again after the next look), costs at least
        ``_INFEASIBLE_COST`` when infeasible, more than any later push can."""
        states: torch.Tensor | None = None
        costs = np.zeros(len(samples))
        low, high = self.workspace_m
        horizon = samples.shape[1]
        for step in range(horizon):
            pushes, starts = self._pushes(outline, samples[:, step], states)
            infeasible = np.any((starts < low) | (starts > high), axis=1)
            if step == 0:  # the push carried out: after the mean, a penalty of its own
                infeasible = (infeasible | obstacles.blocked(pushes, starts)) * horizon
            costs += infeasible * _INFEASIBLE_COST
            states = self.filter.predict_states(pushes, self.config.rate_hz, states)
            costs += self._goal_distance(states, goal)
        return costs / horizon

    def _goal_distance(self, states: torch.Tensor, goal: FloatArray) -> FloatArray:
        """Distance [N] (m) of link 0 in states [N, n] from the goal, angles weighted."""
        pose = self.filter.layout.link_pose(states)[:, 0, :3].numpy()
        position_m = np.linalg.norm(pose[:, :2] - goal[:2], axis=1)
        angle_m = self.config.angle_weight_m_per_rad * np.abs(wrap_angle(pose[:, 2] - goal[2]))
        return np.asarray(np.hypot(position_m, angle_m))

    def _pushes(
        self, outline: _OutlineInLink, samples: FloatArray, states: torch.Tensor | None
    ) -> tuple[list[Push], FloatArray]:
        """The pushes of samples [N, 3] with link 0 at the states' poses [N, n] (None: the
        belief's), and the gripper start points [N, 2]."""
        if states is None:
            states = self.filter.belief.mean.expand(len(samples), -1)
        pose = self.filter.layout.link_pose(states)[:, 0, :3].numpy()
        points, normals = outline.at(samples[:, _FRACTION], pose)
        pd_rad = np.arctan2(-normals[:, 1], -normals[:, 0]) + samples[:, _OFFSET]
        heading = np.column_stack([np.cos(pd_rad), np.sin(pd_rad)])
        starts = points - self.config.approach_clearance_m * heading
        pushes = [
            Push(point, float(angle), self.config.speed_mps, float(duration), link=0)
            for point, angle, duration in zip(points, pd_rad, samples[:, _DURATION], strict=True)
        ]
        return pushes, starts


@dataclass(frozen=True)
class _Obstacles:
    """The fitted links and the object cloud's points no link covers (what the fit missed),
    cloud_xy [P, 2], found once per plan: the check runs for every sample of every
    iteration. size_m: the finger footprint grown by the clearance. blocked_xy [K, 2]: the
    contact points of pushes blocked on their way down, kept ``avoid_m`` away from."""

    shape: ShapeEstimate
    cloud_xy: FloatArray
    size_m: tuple[float, float]
    max_cloud_points: int | None
    blocked_xy: FloatArray
    avoid_m: float

    def blocked(self, pushes: list[Push], starts_xy: FloatArray) -> FloatArray:
        """Whether the fingers of ``pushes`` descending at starts_xy [N, 2] would come down
        on the object (``fingers_blocked``) or the push starts where one was blocked: bool
        [N]."""
        headings = np.array([push.pd_rad for push in pushes])
        on_object = fingers_blocked(self.shape, self.cloud_xy, starts_xy, headings, self.size_m,
                                    self.max_cloud_points)  # fmt: skip
        if not len(self.blocked_xy):
            return on_object
        points = np.array([push.cp_m for push in pushes])
        gaps_m = np.linalg.norm(points[:, None] - self.blocked_xy[None], axis=-1).min(axis=1)
        return np.asarray(on_object | (gaps_m <= self.avoid_m))


class _OutlineInLink:
    """Link 0's mid-height outline in the belief's link-0 frame, placed at any pose.

    points [P, 2] (m) and outward normals [P, 2], counter-clockwise: the outline of the
    fitted link nearest to the belief's link 0 (traced by ``outline_of``), or with ``whole``
    the outer outline of that link and those joined to it (:func:`joined_outline`: the
    belief holds them as one link), seen from the belief's pose of link 0 ``belief_pose``
    (x_m, y_m, theta_rad), so that at that pose it lies where the fit saw it (the fit's own
    axes, which may be any of its symmetries, do not matter)."""

    def __init__(
        self,
        shape: ShapeEstimate,
        belief_pose: FloatArray,
        outline_of: Callable[[Superquadric], tuple[FloatArray, FloatArray]],
        whole: bool = False,
    ) -> None:
        centres = np.asarray(shape.initial_poses, dtype=np.float64)[:, :2]
        nearest = int(np.linalg.norm(centres - belief_pose[:2], axis=1).argmin())
        if whole:
            points, normals = joined_outline(shape.links, nearest, outline_of)
        else:
            points, normals = outline_of(shape.links[nearest])
        rotation = _rotation(-float(belief_pose[2]))
        self.points = (points - belief_pose[:2]) @ rotation.T
        self.normals = normals @ rotation.T

    def at(self, fraction: FloatArray, poses: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Outline points and normals [N, 2] at fractions [N] with link 0 at poses [N, 3]."""
        index = np.minimum((fraction * len(self.points)).astype(int), len(self.points) - 1)
        cos, sin = np.cos(poses[:, 2]), np.sin(poses[:, 2])
        rotation = np.stack([np.stack([cos, -sin], -1), np.stack([sin, cos], -1)], -2)
        points = poses[:, :2] + np.einsum("nij,nj->ni", rotation, self.points[index])
        normals = np.einsum("nij,nj->ni", rotation, self.normals[index])
        return points, normals


def joined_outline(
    links: Sequence[Superquadric],
    first: int,
    outline_of: Callable[[Superquadric], tuple[FloatArray, FloatArray]] = link_outline,
    join_m: float = _JOIN_M,
) -> tuple[FloatArray, FloatArray]:
    """The outer outline of link ``first`` and of the links joined to it (their outlines
    within ``join_m``, directly or through each other): the points [P, 2] (m) of each one's
    outline (``outline_of``) that lie inside no other of them, with their outward normals
    [P, 2], ordered counter-clockwise about their centroid. A link apart from them (another
    object, say) is left out."""
    outlines = [outline_of(link) for link in links]
    members, grown = [first], True
    while grown:
        grown = False
        for index, (outline_xy, _) in enumerate(outlines):
            if index in members:
                continue
            gap_m = min(cdist(outline_xy, outlines[member][0]).min() for member in members)
            if gap_m <= join_m:
                members.append(index)
                grown = True
    points, normals = [], []
    for index in members:
        others = [links[other] for other in members if other != index]
        outside = ~inside_any_link(others, outlines[index][0])
        points.append(outlines[index][0][outside])
        normals.append(outlines[index][1][outside])
    all_points, all_normals = np.concatenate(points), np.concatenate(normals)
    offset = all_points - all_points.mean(axis=0)
    order = np.argsort(np.arctan2(offset[:, 1], offset[:, 0]), kind="stable")
    return all_points[order], all_normals[order]


def _rotation(theta_rad: float) -> Any:
    cos, sin = math.cos(theta_rad), math.sin(theta_rad)
    return np.array([[cos, -sin], [sin, cos]])
