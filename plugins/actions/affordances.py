"""``actions.affordances`` and ``actions.push_pull_rule``: candidates on the fitted superquadrics.

Paper 1, III-E (Monte-Carlo sampling of action affordances): the contact point ``cp`` or grasp
point ``gp`` and the contact normal ``cn`` come from each link's estimated superquadric, and a
push goes along the inward normal plus U(-jitter, jitter). The outline of a link is its
cross-section at mid height (the plane z = its centre's height), traced densely by bisection
along rays from the centre (the tapered and sheared superquadric is star-shaped about it), with
outward normals by finite differences of that closed curve. Pulls close the fingers along the
outline normal where the chord across the link along it fits the gripper, then move along a
direction drawn around ``pull_towards_rad`` as in ``actions.outline``.

``actions.push_pull_rule`` (III-D) picks the interaction from the object instead of the
``interactions`` option: push only for one link; otherwise pull when the object lies beyond
the table edge (its y below ``edge_y_m``), push when it does not.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from typing import Literal

import numpy as np
from pydantic import Field, NonNegativeFloat, model_validator
from vistac.component import ComponentContext
from vistac.errors import DataError
from vistac.plugins.actions.outline import OutlineSampler, chord, point_on_outline
from vistac.plugins.shape.superquadric import inside_outside, to_superquadric_frame
from vistac.protocols import Scene
from vistac.types import Action, FloatArray, Pull, Push, ShapeEstimate, Superquadric

log = logging.getLogger(__name__)

OUTLINE_POINTS = 720
"""Rays (one per half degree) tracing a link's mid-height outline."""
_BISECTIONS = 40
_MAX_RADIUS_FACTOR = 4.0
"""The bisection searches radii up to this times the longest semi-axis (taper and shear
stretch the footprint by at most 2 + 1)."""

Interaction = Literal["push", "pull"]


FINGER_FOOTPRINT_FIELD = Field(
    (0.02, 0.024), description="(along, across the push) size of the closed fingers about the "
    "TCP: where they descend must be clear of every link",
)
CLOUD_POINTS_FIELD = Field(
    2, ge=0, description="where the fingers descend (grown by finger_clearance_m) at most "
    "this many points of the observed object cloud may lie, or the push or grasp is dropped: "
    "a fit can miss a part of the object (a sharp corner, where two links meet), and fingers "
    "descending onto it are blocked; null: check the fitted links only",
)


def link_outline(link: Superquadric, count: int = OUTLINE_POINTS) -> tuple[FloatArray, FloatArray]:
    """The mid-height cross-section of a superquadric in the world table plane.

    Returns counter-clockwise points [count, 2] (m) with F = 1 (eq. 1-2) and their outward unit
    normals [count, 2] (central differences along the curve).
    """
    centre = link.world_from_sq[:3, 3]
    angles = np.linspace(0.0, 2.0 * np.pi, count, endpoint=False)
    rays = np.column_stack([np.cos(angles), np.sin(angles), np.zeros(count)])
    low = np.zeros(count)
    high = np.full(count, _MAX_RADIUS_FACTOR * float(np.max(link.scale_m)))
    for _ in range(_BISECTIONS):
        middle = 0.5 * (low + high)
        local = to_superquadric_frame(link, centre + middle[:, None] * rays)
        inside = inside_outside(local, link.scale_m, link.exponents, link.taper) < 1.0
        low, high = np.where(inside, middle, low), np.where(inside, high, middle)
    points = centre[:2] + (0.5 * (low + high))[:, None] * rays[:, :2]
    tangent = np.roll(points, -1, axis=0) - np.roll(points, 1, axis=0)
    normals = np.column_stack([tangent[:, 1], -tangent[:, 0]])
    return points, normals / np.linalg.norm(normals, axis=1, keepdims=True)


def inside_link(link: Superquadric, points_xy: FloatArray) -> FloatArray:
    """Whether table-plane points [N, 2] lie inside the link at its mid height: bool [N]."""
    height = np.full((len(points_xy), 1), link.world_from_sq[2, 3])
    local = to_superquadric_frame(link, np.hstack([points_xy, height]))
    return np.asarray(inside_outside(local, link.scale_m, link.exponents, link.taper) < 1.0)


def inside_any_link(links: Sequence[Superquadric], points_xy: FloatArray) -> FloatArray:
    """Whether table-plane points [N, 2] lie inside any of the links (``inside_link``):
    bool [N]."""
    inside = np.zeros(len(points_xy), dtype=bool)
    for link in links:
        inside |= inside_link(link, points_xy)
    return inside


def finger_footprint(
    centre_xy: FloatArray, heading_rad: float | FloatArray, size_m: tuple[float, float],
    per_side: int = 5,
) -> FloatArray:
    """A grid of points [..., per_side**2, 2] over the rectangle of ``size_m`` (along,
    across ``heading_rad`` [...]) centred at ``centre_xy`` [..., 2], its edges included."""
    along, across = np.meshgrid(
        np.linspace(-0.5, 0.5, per_side) * size_m[0], np.linspace(-0.5, 0.5, per_side) * size_m[1]
    )
    heading = np.asarray(heading_rad, dtype=np.float64)[..., None]
    c, s = np.cos(heading), np.sin(heading)
    offsets = np.stack([c * along.ravel() - s * across.ravel(),
                        s * along.ravel() + c * across.ravel()], -1)  # fmt: skip
    return np.asarray(np.asarray(centre_xy)[..., None, :] + offsets, dtype=np.float64)


def in_rectangle(
    points_xy: FloatArray, centre_xy: FloatArray, heading_rad: float | FloatArray,
    size_m: tuple[float, float],
) -> FloatArray:
    """Whether table-plane points [P, 2] lie in the rectangle of ``size_m`` (along, across
    ``heading_rad`` [...]) centred at ``centre_xy`` [..., 2]: bool [..., P]."""
    offset = np.asarray(points_xy, dtype=np.float64) - np.asarray(centre_xy)[..., None, :]
    heading = np.asarray(heading_rad, dtype=np.float64)[..., None]
    c, s = np.cos(heading), np.sin(heading)
    along = offset[..., 0] * c + offset[..., 1] * s
    across = offset[..., 1] * c - offset[..., 0] * s
    return np.asarray((np.abs(along) <= 0.5 * size_m[0]) & (np.abs(across) <= 0.5 * size_m[1]))


def fingers_blocked(
    shape: ShapeEstimate,
    cloud_xy: FloatArray,
    centres_xy: FloatArray,
    headings_rad: FloatArray,
    size_m: tuple[float, float],
    max_cloud_points: int | None,
) -> FloatArray:
    """Whether closed fingers of ``size_m`` (along, across the heading) descending at
    centres_xy [N, 2] with headings_rad [N] would come down on a fitted link of ``shape``,
    or on more than ``max_cloud_points`` points of the observed object cloud_xy [P, 2]
    (None: the links only): bool [N]."""
    footprints = finger_footprint(centres_xy, headings_rad, size_m)  # [N, F, 2]
    on_link = inside_any_link(shape.links, footprints.reshape(-1, 2))
    blocked = on_link.reshape(footprints.shape[:-1]).any(axis=-1)
    if max_cloud_points is not None:
        counts = in_rectangle(cloud_xy, centres_xy, headings_rad, size_m).sum(axis=-1)
        blocked |= counts > max_cloud_points
    return np.asarray(blocked)


class SuperquadricAffordances(OutlineSampler):
    """Samples pushes and pulls on the mid-height outlines of the fitted superquadric links.

    Shares the options of ``actions.outline`` (and its workspace check); its cloud options
    (``table_clearance_m``, ``max_object_height_m``, ``cluster_cell_m``,
    ``finger_half_width_m``) do not apply, since the shape estimate gives the outline.
    """

    class Config(OutlineSampler.Config):
        link: Literal["all"] | int = Field(
            "all", description="the link(s) to act on: 'all' or an index (negative from the end)"
        )
        approach_clearance_m: float = Field(
            0.02, ge=0, description="pre-contact TCP distance behind a push's contact point "
            "(the executor's standoff_m + pusher_offset_m)",
        )  # fmt: skip
        object_margin_m: float | None = Field(
            0.03, ge=0, description="as in actions.outline (there off by default), measured "
            "to the fitted links' outlines: enough for the fingers to come down behind the "
            "object (approach_clearance_m) and push it back from any edge",
        )  # fmt: skip
        finger_footprint_m: tuple[NonNegativeFloat, NonNegativeFloat] = FINGER_FOOTPRINT_FIELD
        finger_clearance_m: float = Field(
            0.005, ge=0, description="gap kept between every fitted link and the fingers "
            "where they descend (and a closing finger's path): the fit's error and the corners "
            "a superquadric rounds off",
        )  # fmt: skip
        max_cloud_points_under_fingers: int | None = CLOUD_POINTS_FIELD
        gripper_opening_m: float = Field(
            0.15, gt=0, description="distance between the pads of the open gripper (sim "
            "0.15, Robotiq 2F-85 0.085): where the open fingers descend for a grasp, each a "
            "pad of half the finger footprint, must be clear of every link",
        )  # fmt: skip

        @model_validator(mode="after")
        def _grasp_fits_opening(self) -> SuperquadricAffordances.Config:
            if self.max_grasp_width_m >= self.gripper_opening_m:
                raise ValueError(
                    f"max_grasp_width_m ({self.max_grasp_width_m} m) must be less than "
                    f"gripper_opening_m ({self.gripper_opening_m} m): the open fingers have to "
                    "pass either side of the object"
                )
            return self

    def __init__(self, config: Config, ctx: ComponentContext) -> None:
        super().__init__(config, ctx)
        self.config: SuperquadricAffordances.Config = config

    def sample(self, scene: Scene, rng: np.random.Generator) -> list[Action]:
        """Up to ``samples`` reachable candidates (fewer where pushes or grasps are dropped)."""
        shape = self._shape(scene)
        return self.candidates(shape, self.interactions(shape), rng)

    def interactions(self, shape: ShapeEstimate) -> list[Interaction]:
        """The interaction kinds to draw from for this object."""
        return list(self.config.interactions)

    def candidates(
        self, shape: ShapeEstimate, kinds: list[Interaction], rng: np.random.Generator
    ) -> list[Action]:
        """``samples`` draws of a kind in ``kinds``, a link and an outline point each."""
        links = self._links(shape)
        outlines = [link_outline(link) for link in shape.links]
        object_outline_xy = np.concatenate([points for points, _ in outlines])
        cloud_xy = np.asarray(shape.cloud.points_m, dtype=np.float64)[:, :2]
        actions: list[Action] = []
        blocked = 0
        for kind, index in zip(
            rng.choice(kinds, size=self.config.samples),
            rng.choice(links, size=self.config.samples), strict=True,
        ):  # fmt: skip
            outline, _ = outlines[int(index)]
            point, outward = point_on_outline(outline, rng.uniform())
            action = (
                self._push(shape, cloud_xy, int(index), point, outward, rng)
                if kind == "push"
                else self._pull(shape, cloud_xy, outline, int(index), point, outward, rng)
            )
            if action is None:
                blocked += 1
            elif self._reachable(action, object_outline_xy):
                actions.append(action)
        log.debug("%d of %d candidates kept", len(actions), self.config.samples)
        if not actions:
            log.warning(
                "actions.affordances: all %d candidates dropped: %d where the fingers would "
                "come down on the object or a grasp is too wide (finger_clearance_m, "
                "max_cloud_points_under_fingers, max_grasp_width_m), %d out of reach "
                "(workspace_xy_m, object_margin_m, push_towards_rad)",
                self.config.samples, blocked, self.config.samples - blocked,
            )  # fmt: skip
        return actions

    def _shape(self, scene: Scene) -> ShapeEstimate:
        if scene.shape is None or not scene.shape.links:
            raise DataError(
                f"{type(self).__name__}: no shape estimate to sample actions on; run `look` "
                "with a shape estimator (e.g. shape.ems) first, or use actions.outline"
            )
        return scene.shape

    def _links(self, shape: ShapeEstimate) -> list[int]:
        count = len(shape.links)
        if self.config.link == "all":
            return list(range(count))
        if not -count <= self.config.link < count:
            raise DataError(
                f"actions.affordances: link {self.config.link} of a {count}-link object"
            )
        return [self.config.link % count]

    def _push(
        self,
        shape: ShapeEstimate,
        cloud_xy: FloatArray,
        index: int,
        point: FloatArray,
        outward: FloatArray,
        rng: np.random.Generator,
    ) -> Push | None:
        """A push at ``point`` [2] along the inward normal plus jitter; None when the
        fingers would descend onto a link (a corner of a neighbouring link, say) or onto the
        observed object cloud_xy [P, 2]."""
        jitter = np.radians(rng.uniform(-self.config.jitter_deg, self.config.jitter_deg))
        pd_rad = float(np.arctan2(-outward[1], -outward[0]) + jitter)
        start = point - self.config.approach_clearance_m * np.array(
            [np.cos(pd_rad), np.sin(pd_rad)]
        )
        size_m = self._with_clearance(*self.config.finger_footprint_m)
        most = self.config.max_cloud_points_under_fingers
        if fingers_blocked(shape, cloud_xy, start[None], np.array([pd_rad]), size_m, most)[0]:
            return None
        return Push(point, pd_rad, self.config.speed_mps, self.config.duration_s, link=index)

    def _pull(
        self,
        shape: ShapeEstimate,
        cloud_xy: FloatArray,
        outline: FloatArray,
        index: int,
        point: FloatArray,
        outward: FloatArray,
        rng: np.random.Generator,
    ) -> Pull | None:
        """A grasp closing along the outline normal at ``point`` [2], or None when the chord
        of the link along it is wider than ``max_grasp_width_m`` or the fingers would meet
        another link (see :meth:`_grasp_blocked`)."""
        axis_rad = float(np.arctan2(outward[1], outward[0]))
        midpoint, width_m = chord(outline, point, axis_rad)
        if width_m > self.config.max_grasp_width_m:
            return None
        if self._grasp_blocked(shape, cloud_xy, index, midpoint, axis_rad, width_m):
            return None
        pd_rad = self.config.pull_towards_rad + rng.uniform(-1, 1) * self.config.pull_spread_rad
        return Pull(
            midpoint, float(pd_rad), self.config.speed_mps, axis_rad, self.config.duration_s,
            link=index,
        )  # fmt: skip

    def _with_clearance(self, along_m: float, across_m: float) -> tuple[float, float]:
        """A footprint size (along, across, m) grown by ``finger_clearance_m`` on every side."""
        margin_m = 2.0 * self.config.finger_clearance_m
        return along_m + margin_m, across_m + margin_m

    def _on_cloud(
        self, cloud_xy: FloatArray, centre_xy: FloatArray, heading_rad: float,
        size_m: tuple[float, float],
    ) -> bool:  # fmt: skip
        """Whether more than ``max_cloud_points_under_fingers`` of the object cloud's points
        cloud_xy [P, 2] lie in a finger's footprint (see ``in_rectangle``)."""
        most = self.config.max_cloud_points_under_fingers
        if most is None:
            return False
        return int(in_rectangle(cloud_xy, centre_xy, heading_rad, size_m).sum()) > most

    def _grasp_blocked(
        self,
        shape: ShapeEstimate,
        cloud_xy: FloatArray,
        index: int,
        midpoint: FloatArray,
        axis_rad: float,
        width_m: float,
    ) -> bool:
        """Whether an open finger would descend onto a link or the object cloud_xy [P, 2],
        or a closing finger would sweep over a link other than the grasped one ``index`` (and
        squeeze both): the grasp has its chord of ``width_m`` centred at ``midpoint`` [2]
        along ``axis_rad``."""
        along_m, across_m = self.config.finger_footprint_m
        pad_m = 0.5 * along_m
        open_m = 0.5 * (self.config.gripper_opening_m + pad_m)  # pad centre, open
        contact_m = 0.5 * (width_m + pad_m)  # pad centre, on the link
        axis = np.array([np.cos(axis_rad), np.sin(axis_rad)])
        pad_size_m = self._with_clearance(pad_m, across_m)
        for side in (-1.0, 1.0):
            pad_centre = midpoint + side * open_m * axis
            if self._on_cloud(cloud_xy, pad_centre, axis_rad, pad_size_m):
                return True
            pad = finger_footprint(pad_centre, axis_rad, pad_size_m)
            sweep = finger_footprint(
                midpoint + side * 0.5 * (open_m + contact_m) * axis, axis_rad,
                self._with_clearance(open_m - contact_m + pad_m, across_m), per_side=9,
            )  # fmt: skip
            for other, link in enumerate(shape.links):
                if inside_link(link, pad if other == index else sweep).any():
                    return True
        return False


class PushPullRule(SuperquadricAffordances):
    """``actions.affordances`` with the interaction chosen by paper 1, III-D (the
    ``interactions`` option is not used): one link is only pushed; an object of more links is
    pulled when its mean link y is below ``edge_y_m`` (near the table edge) and pushed
    otherwise."""

    class Config(SuperquadricAffordances.Config):
        edge_y_m: float = Field(0.3, description="pull objects whose y is below this (m)")

    def __init__(self, config: Config, ctx: ComponentContext) -> None:
        super().__init__(config, ctx)
        self.config: PushPullRule.Config = config

    def interactions(self, shape: ShapeEstimate) -> list[Interaction]:
        y_m = float(np.mean(np.asarray(shape.initial_poses)[:, 1]))
        kind: Interaction = (
            "pull" if len(shape.links) > 1 and y_m < self.config.edge_y_m else "push"
        )
        log.debug("push_pull_rule: %d link(s) at y = %.3f m: %s", len(shape.links), y_m, kind)
        return [kind]
