"""``filters.dual``: the dual differentiable filter as a skill component (``Filter`` protocol).

``initialise`` builds the joint belief from the shape estimate (link poses from the fitted
superquadrics, zero twist, a configurable prior over the parameters). ``update`` runs one
filter step per recorded control step of an episode: the process model of the skill
(``filters.gnn``, ``filters.ff`` or ``filters.analytical``) predicts, and the depth image
projected from the segmented initial cloud plus the fingertip force are the observation.
The belief is carried from one interaction to the next.
"""

from __future__ import annotations

import functools
import json
import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, cast

import numpy as np
import torch
from pydantic import BaseModel, ConfigDict, Field, NonNegativeFloat, PositiveFloat
from vistac.component import Component, ComponentConfig, ComponentContext, SkillPath
from vistac.errors import ConfigError, DataError
from vistac.objects import polygon_centroid_covariance, to_link_frame, to_world_xy
from vistac.plugins.actions.affordances import link_outline
from vistac.plugins.actions.executor import CartesianExecutor
from vistac.plugins.filters.data import relative_poses
from vistac.plugins.filters.dual import Belief, DualFilter, HeldJoints
from vistac.plugins.filters.mirror import mirror_averaged
from vistac.plugins.filters.models import load_checkpoint
from vistac.plugins.filters.observation import (
    DepthProjector,
    ObsNoiseNet,
    ProjectionObservationModel,
    observation_vector,
)
from vistac.plugins.filters.rollout import PushEvidence, end_poses, push_update
from vistac.plugins.filters.state import DTYPE, ProcessInput, StateLayout
from vistac.protocols import Episode, Scene, StepObservation
from vistac.types import Action, FloatArray, GaussianBelief, Pull, ShapeEstimate, action_point

log = logging.getLogger(__name__)

PoseStds = tuple[
    NonNegativeFloat, NonNegativeFloat, NonNegativeFloat,
    NonNegativeFloat, NonNegativeFloat, NonNegativeFloat,
]  # fmt: skip
"""(x, y, theta, vx, vy, omega) stds, m, rad, m/s and rad/s."""


class Prior(BaseModel):
    """Initial mean and standard deviation of each parameter family. The defaults are the
    spread of the generated object set (`vistac objects generate`): uniform masses of 0.2-1.6
    kg, frictions of 0.1-0.5, joint frictions of 0-0.5 N m, and CoMs anywhere in the
    footprint (2.8 cm std per axis over the set's links). A prior narrower than the objects
    it meets keeps the estimate from reaching an off-centre CoM and makes the reported
    uncertainty dishonest."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    mass_kg: tuple[float, PositiveFloat] = (0.9, 0.4)
    friction: tuple[float, PositiveFloat] = (0.3, 0.12)
    com_m: tuple[float, PositiveFloat] = Field(
        default=(0.0, 0.028), description="CoM mean and std per axis in each link's frame, "
        "unless com_in_shape"
    )
    com_in_shape: bool = Field(
        default=False, description="each link's CoM uniform over its fitted footprint (the "
        "superquadric's mid-height outline): mean the outline's area centroid, covariance "
        "its area moments about it, in place of com_m (measured no better on the test split)",
    )
    joint_friction_nm: tuple[float, PositiveFloat] = (0.25, 0.15)
    position_m: float = Field(default=0.005, gt=0, description="std of the initial link positions")
    angle_rad: float = Field(default=0.05, gt=0, description="std of the initial link angles")
    velocity_mps: float = Field(
        default=0.002, gt=0, description="std of the initial twist (m/s, rad/s)"
    )


def link_boxes(shape: ShapeEstimate) -> tuple[FloatArray, FloatArray]:
    """(poses [L, 3] = (x, y, theta) of the fitted links, half extents [L, 2] (a1, a2))."""
    sizes = np.array([link.scale_m[:2] for link in shape.links])
    return np.asarray(shape.initial_poses, dtype=np.float64), sizes


LinkFrames = Literal["fitted", "trained"]
"""The frames the process models see the fitted links in (``ModelFrames``)."""
JointsFrom = Literal["boxes", "outlines"]
"""Where the process models put the joints (``filters.dual`` ``joints_from``)."""
AXES_CLEAR = 0.45
"""A fitted outline shows its link's axes where more than this share of its length runs
within ``AXES_BAND_RAD`` of one direction or its perpendicular (``outline_axes``): a box's
about 0.9, a right triangle's legs 0.55-0.6; an ellipse's 0.1-0.11, the tapered
superellipse of the butter footprint's 0.23, a hexagon's fit (a superellipse) up to 0.31."""
AXES_BAND_RAD = np.radians(4.0)


def outline_axes(outline: FloatArray) -> tuple[float, float]:
    """(yaw in [0, pi/2) of the direction that most of a closed outline [K, 2] runs along,
    or across (rad), the share of its length within ``AXES_BAND_RAD`` of it): the straight
    sides of boxes and of a right triangle's legs, whatever axes the fit gave the link."""
    edges = np.roll(outline, -1, axis=0) - outline
    length_m = np.hypot(edges[:, 0], edges[:, 1])
    quarter = np.pi / 2
    angle = np.arctan2(edges[:, 1], edges[:, 0]) % quarter
    # the length within the band about each edge's direction, on the circle of quarter turns
    gap = np.abs((angle[:, None] - angle[None, :] + quarter / 2) % quarter - quarter / 2)
    support = (gap <= AXES_BAND_RAD) @ length_m
    best = int(np.argmax(support))
    near = gap[best] <= AXES_BAND_RAD
    offset = (angle[near] - angle[best] + quarter / 2) % quarter - quarter / 2
    yaw = (angle[best] + np.average(offset, weights=length_m[near])) % quarter
    return float(yaw), float(support[best] / length_m.sum())


def frame_yaws(fitted_rad: FloatArray, outlines: Sequence[FloatArray]) -> FloatArray:
    """The yaws [L] of the links' model frames: where an outline shows its axes
    (``outline_axes``), those nearest the fitted yaws [L] (rad); else the fit's. The training's
    frames of a chain all share the object's yaw, each next link on the +x side: a chain's
    links all take the axes of the link that shows them best, those nearest the direction
    from the first outline's mean point to the last's, or that direction itself where no
    link shows its axes."""
    quarter = np.pi / 2
    axes = [outline_axes(outline) for outline in outlines]

    def nearest(axis_rad: float, to_rad: float) -> float:
        return axis_rad + quarter * round((to_rad - axis_rad) / quarter)

    if len(outlines) == 1:
        axis_rad, clarity = axes[0]
        return np.array([nearest(axis_rad, fitted_rad[0]) if clarity > AXES_CLEAR
                         else fitted_rad[0]])  # fmt: skip
    along = np.mean(outlines[-1], axis=0) - np.mean(outlines[0], axis=0)
    chain_rad = float(np.arctan2(along[1], along[0]))
    axis_rad, clarity = max(axes, key=lambda axis: axis[1])
    yaw = nearest(axis_rad, chain_rad) if clarity > AXES_CLEAR else chain_rad
    return np.full(len(outlines), yaw)


@dataclass(frozen=True)
class ModelFrames:
    """The frames the process models and the belief see the fitted links in (``link_frames``
    of ``filters.dual``), and each link's footprint in its frame.

    ``fitted``: each fitted superquadric's own frame and half extents (a1, a2), whatever
    axes the fit gave the link. ``trained``: the frames the models were trained in
    (:func:`vistac.plugins.filters.data.link_geometry` of the true footprints): each at the
    area centroid of the link's fitted mid-height outline (``link_outline``), turned along
    the outline's own straight sides (``frame_yaws``: a chain's links all share one yaw with
    each next link on the +x side), its half extents the outline's largest |coordinate|
    about that centroid per axis. For a symmetric footprint the two frames share their
    origin; a right triangle's trained frame lies a sixth of each leg from the box centre,
    its half extents a third larger."""

    poses: FloatArray
    """[L, 3] (x m, y m, theta rad) in the world, where the fit put the links."""
    half_extents_m: FloatArray
    """[L, 2]."""
    origin_m: FloatArray
    """[L, 2] each frame's origin in its fitted box's frame."""
    turn_rad: FloatArray
    """[L] each frame's yaw less its fitted box's."""
    box_half_extents_m: FloatArray
    """[L, 2] the fitted boxes' (a1, a2)."""
    footprint_mean_m: FloatArray
    """[L, 2] the outline's area centroid in the link's frame (kept inside the half
    extents)..."""
    footprint_cov_m2: FloatArray
    """... and [L, 2, 2] its second area moments about it over its area: the mean and
    covariance of a CoM uniform over the fitted footprint."""

    @classmethod
    def of(cls, shape: ShapeEstimate, convention: LinkFrames = "fitted") -> ModelFrames:
        """The frames of ``convention``, ``fitted`` or ``trained``."""
        box_poses, box_sizes = link_boxes(shape)
        outlines = [link_outline(link)[0] for link in shape.links]  # world [K, 2] each
        centroids = np.array([polygon_centroid_covariance(o)[0] for o in outlines])
        if convention == "trained":
            poses = np.column_stack([centroids, frame_yaws(box_poses[:, 2], outlines)])
        else:
            poses = box_poses
        means, extents, covariances = [], [], []
        for outline, pose, box_m in zip(outlines, poses, box_sizes, strict=True):
            local = to_link_frame(np.column_stack([outline, np.zeros(len(outline))]), pose)
            mean, covariance = polygon_centroid_covariance(local[:, :2])
            extents.append(np.abs(local[:, :2]).max(axis=0) if convention == "trained" else box_m)
            means.append(np.clip(mean, -extents[-1], extents[-1]))
            covariances.append(covariance)
        origins = np.array([
            to_link_frame(np.array([[*pose[:2], 0.0]]), box)[0, :2]
            for pose, box in zip(poses, box_poses, strict=True)
        ])  # fmt: skip
        return cls(poses, np.array(extents), origins, poses[:, 2] - box_poses[:, 2], box_sizes,
                   np.array(means), np.array(covariances))  # fmt: skip

    def box_poses(self, poses: FloatArray) -> FloatArray:
        """The fitted boxes' poses [..., L, 3] for links whose frames stand at ``poses``
        [..., L, 3]."""
        theta = poses[..., 2] - self.turn_rad
        c, s = np.cos(theta), np.sin(theta)
        x, y = self.origin_m[:, 0], self.origin_m[:, 1]
        return np.stack([poses[..., 0] - (c * x - s * y), poses[..., 1] - (s * x + c * y),
                         theta], -1)  # fmt: skip

    def link_at(self, points_m: FloatArray, poses: FloatArray) -> FloatArray:
        """Index [..., N] of the link whose fitted box is nearest each point [..., N, >=2]
        (``nearest_link``), the links' frames at ``poses`` [..., L, 3]."""
        return nearest_link(points_m, self.box_poses(poses), self.box_half_extents_m)


JOINT_TOLERANCE_M = 0.01
"""Outline points this much farther apart than the links' closest approach still join."""
MAX_JOINT_GAP_M = 0.02
"""Links whose outlines come no nearer than this are not joined (``hinge_std_m``)."""


def facing_joints(
    outlines: Sequence[FloatArray], poses: FloatArray
) -> tuple[torch.Tensor, FloatArray]:
    """Where each link k meets link k + 1, in both links' frames: [L - 1, 2, 2] (m), and how
    near the two outlines come [L - 1] (m).

    outlines: each link's fitted outline [K, 2] (world, ``link_outline``); poses [L, 3]
    (world) of the belief's link frames. The joint is the mean of the two outlines' points
    that lie within ``JOINT_TOLERANCE_M`` of their closest approach: where the links touch or
    nearly so, as a hinge sits in the middle of its gap and a weld along its seam; a
    triangle's tip, not its bounding box's side.
    """
    joints, nearest_m = [], []
    for k in range(len(outlines) - 1):
        first, second = outlines[k], outlines[k + 1]
        apart_m = np.linalg.norm(first[:, None] - second[None], axis=-1)
        near = apart_m <= apart_m.min() + JOINT_TOLERANCE_M
        joint = np.vstack([first[near.any(1)], second[near.any(0)]]).mean(0)
        joints.append([to_link_frame(joint[None], poses[i])[0, :2] for i in (k, k + 1)])
        nearest_m.append(apart_m.min())
    ends = torch.as_tensor(np.reshape(joints, (-1, 2, 2)), dtype=DTYPE)
    return ends, np.asarray(nearest_m)


def com_discrepancy_var(
    shape: ShapeEstimate, layout: StateLayout, discrepancy_m: tuple[float, float]
) -> FloatArray:
    """Variance [n] added to the reported belief's diagonal: ``(a + b |kappa1|)^2`` on each
    link's com_x and com_y (``discrepancy_m`` = (a, b), kappa1 the link's fitted taper), 0
    elsewhere."""
    base_m, per_taper_m = discrepancy_m
    var = np.zeros(layout.size)
    for i, link in enumerate(shape.links):
        std_m = base_m + per_taper_m * abs(float(link.taper[0]))
        for axis in "xy":
            var[layout.index(f"com_{axis}_{i}")] = std_m**2
    return var


def prior_belief(
    pose_twist: FloatArray,
    prior: Prior,
    layout: StateLayout,
    com: tuple[FloatArray, FloatArray] | None = None,
) -> Belief:
    """The initial belief: link poses and twists [L, 6] with the prior's position, angle and
    velocity std, the prior's parameter means and std, no correlations but those of each
    link's CoM where com (mean [L, 2], covariance [L, 2, 2]; ``footprint_com``) replaces the
    prior's ``com_m``."""
    pose_std = [prior.position_m] * 2 + [prior.angle_rad] + [prior.velocity_mps] * 3
    link_mean = [prior.mass_kg[0], prior.friction[0], prior.com_m[0], prior.com_m[0]]
    link_std = [prior.mass_kg[1], prior.friction[1], prior.com_m[1], prior.com_m[1]]
    links, joints = layout.n_links, layout.n_joints
    mean = np.concatenate(
        [np.ravel(pose_twist), np.tile(link_mean, links), [prior.joint_friction_nm[0]] * joints]
    )
    std = np.concatenate(
        [np.tile(pose_std, links), np.tile(link_std, links), [prior.joint_friction_nm[1]] * joints]
    )
    cov = np.diag(std**2)
    for link, (com_mean, com_cov) in enumerate(zip(*com, strict=True) if com else []):
        entries = [layout.index(f"com_{axis}_{link}") for axis in "xy"]
        mean[entries], cov[np.ix_(entries, entries)] = com_mean, com_cov
    return Belief(torch.as_tensor(mean, dtype=DTYPE), torch.as_tensor(cov, dtype=DTYPE))


Correlation = tuple[list[str], FloatArray]
"""Entry names [n] and their correlation matrix [n, n] (``GaussianBelief.correlation_dict``)."""


def load_prior_from(path: Path) -> tuple[dict[str, dict[str, float]], Correlation | None]:
    """The parameters a ``prior_from`` file knows: its ``belief`` (name -> {"mean", "std"})
    and its ``belief_correlation``, None when the file has none (a file of measured values
    may leave it out)."""
    try:
        summary = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError) as error:
        raise ConfigError(
            f"prior_from: cannot read {path}: {error}; give the summary.json of an earlier "
            "run on this object, e.g. `vistac run skills/explore_push.yaml --out DIR`, or a "
            'file of measured values: {"belief": {"m_0": {"mean": 0.8, "std": 0.02}, ...}}'
        ) from None
    if not isinstance(summary, dict):
        summary = {}
    return _summary_belief(summary, path), _summary_correlation(summary, path)


def _summary_belief(summary: dict[str, Any], path: Path) -> dict[str, dict[str, float]]:
    belief = summary.get("belief")
    if not isinstance(belief, dict) or not belief:
        raise ConfigError(
            f"prior_from: {path} has no belief; use the summary.json of a run that "
            "updated a belief (explore_push or explore_pull)"
        )
    return {str(name): _mean_std(entry, f"{path}: belief.{name}") for name, entry in belief.items()}


def _mean_std(entry: Any, where: str) -> dict[str, float]:
    """{"mean", "std"} of one ``prior_from`` entry as floats; ConfigError unless both are
    finite numbers and the std is not negative."""
    try:
        mean, std = float(entry["mean"]), float(entry["std"])
    except (KeyError, TypeError, ValueError):
        mean, std = float("nan"), float("nan")
    if not (np.isfinite(mean) and np.isfinite(std) and std >= 0):
        raise ConfigError(
            f"prior_from: {where} is {entry!r}; give each parameter as "
            '{"mean": <number>, "std": <number >= 0>}, e.g. "m_0": {"mean": 0.8, "std": 0.02}'
        )
    return {"mean": mean, "std": std}


def _summary_correlation(summary: dict[str, Any], path: Path) -> Correlation | None:
    entry = summary.get("belief_correlation")
    if entry is None:
        return None
    try:
        names = [str(name) for name in entry["names"]]
        matrix = np.asarray(entry["matrix"], dtype=np.float64)
    except (KeyError, TypeError, ValueError):
        names, matrix = [], np.empty(0)
    if (
        matrix.shape != (len(names), len(names))
        or len(names) == 0
        or not np.isfinite(matrix).all()
        or np.abs(matrix).max() > 1.0
    ):
        raise ConfigError(
            f"prior_from: {path} has a belief_correlation that is not "
            '{"names": [n names], "matrix": [n x n correlations in -1..1]}; fix it or remove it '
            "(the parameters are then taken as uncorrelated)"
        )
    return names, matrix


def known_parameters(
    belief: Belief,
    layout: StateLayout,
    known: dict[str, dict[str, float]],
    source: Path,
    correlation: Correlation | None = None,
) -> Belief:
    """``belief`` with every parameter's mean and std taken from ``known``, correlated as
    ``correlation`` says (``load_prior_from``; the m and f of a pushed object are
    known mostly through their product, which only their correlation keeps) and else
    uncorrelated, and uncorrelated with the pose."""
    names = layout.names[layout.parameter_slice]
    missing = [name for name in names if name not in known]
    if missing:
        raise ConfigError(
            f"prior_from: {source} has no {', '.join(missing)}; it is from an object with "
            f"another number of links than the {layout.n_links} seen now"
        )
    mean, cov = belief.mean.clone(), belief.cov.clone()
    params = layout.parameter_slice
    std = torch.tensor([max(float(known[name]["std"]), 1e-6) for name in names], dtype=DTYPE)
    mean[params] = torch.tensor([float(known[name]["mean"]) for name in names], dtype=DTYPE)
    cov[params, :] = 0.0
    cov[:, params] = 0.0
    cov[params, params] = std[:, None] * _parameter_correlation(names, correlation) * std
    return Belief(mean, cov)


def _parameter_correlation(names: Sequence[str], correlation: Correlation | None) -> torch.Tensor:
    """The correlation [p, p] of the parameters ``names`` (0 for a pair the file does not
    give), made positive definite (rounding in the file can break that)."""
    result = np.eye(len(names))
    if correlation is not None:
        given, matrix = correlation
        pairs = [(i, given.index(name)) for i, name in enumerate(names) if name in given]
        mine = np.array([i for i, _ in pairs], dtype=np.int64)
        theirs = np.array([j for _, j in pairs], dtype=np.int64)
        result[np.ix_(mine, mine)] = matrix[np.ix_(theirs, theirs)]
        values, vectors = np.linalg.eigh(0.5 * (result + result.T))
        result = (vectors * np.clip(values, 1e-6, None)) @ vectors.T
        scale = np.sqrt(np.diag(result))
        result = result / np.outer(scale, scale)
    return torch.as_tensor(result, dtype=DTYPE)


def position_update(belief: Belief, rows: Sequence[int], measured: torch.Tensor,
                    std_m: float) -> Belief:
    """Kalman update of ``belief`` with a direct measurement [k] of its entries ``rows``
    (k indices) of noise std ``std_m``; Joseph form, so the covariance stays symmetric
    positive definite."""
    n = belief.mean.shape[-1]
    observe = torch.zeros(len(rows), n, dtype=DTYPE)
    observe[torch.arange(len(rows)), torch.as_tensor(list(rows))] = 1.0
    noise = torch.eye(len(rows), dtype=DTYPE) * std_m**2
    innovation_cov = observe @ belief.cov @ observe.T + noise
    gain = torch.linalg.solve(innovation_cov, observe @ belief.cov).T  # [n, k]
    mean = belief.mean + gain @ (measured - observe @ belief.mean)
    keep = torch.eye(n, dtype=DTYPE) - gain @ observe
    cov = keep @ belief.cov @ keep.T + gain @ noise @ gain.T
    return Belief(mean, 0.5 * (cov + cov.T))


def nearest_link(points_m: FloatArray, poses: FloatArray, sizes: FloatArray) -> FloatArray:
    """Index [..., N] of the link whose footprint box (size-normalised) is nearest to each
    point: points_m [..., N, >=2], poses [..., L, 3], sizes [L, 2]."""
    c, s = np.cos(poses[..., None, :, 2]), np.sin(poses[..., None, :, 2])  # [..., 1, L]
    dx = points_m[..., :, None, 0] - poses[..., None, :, 0]  # [..., N, L]
    dy = points_m[..., :, None, 1] - poses[..., None, :, 1]
    local_x, local_y = c * dx + s * dy, -s * dx + c * dy
    score = np.maximum(np.abs(local_x) / sizes[:, 0], np.abs(local_y) / sizes[:, 1])
    return np.asarray(score.argmin(axis=-1))


class _LookAheadModel:
    """The process model as one look-ahead uses it: its ``look_ahead`` prediction where it
    has one (the learned models: float32 MLPs, no finger force, which no look-ahead reads),
    else ``predict`` (``filters.analytical``). Make one per look-ahead: it holds the learned
    model's float32 copy of the weights at the time."""

    def __init__(self, model: Any) -> None:
        self.n_links = model.n_links
        look_ahead = getattr(model, "look_ahead", None)
        self.predict = look_ahead() if look_ahead is not None else model.predict


@dataclass(frozen=True)
class _ActionMotion:
    """The gripper moving along each of B actions: start [B, 2] (m), yaw [B] (rad),
    velocity [B, 2] (m/s), and the ProcessInput fields that stay fixed."""

    start_xy: FloatArray
    yaw_rad: FloatArray
    velocity_mps: FloatArray
    fixed: dict[str, torch.Tensor]

    def inputs(self, elapsed_s: float) -> ProcessInput:
        """The process input ``elapsed_s`` into the actions."""
        xy = self.start_xy + self.velocity_mps * elapsed_s
        tcp = np.column_stack(
            [xy, self.yaw_rad, self.velocity_mps, np.zeros(len(self.yaw_rad))]
        )
        return ProcessInput(tcp=torch.as_tensor(tcp, dtype=DTYPE), **self.fixed)


class DualFilterComponent(Component):
    """Implements the ``Filter`` protocol with :class:`DualFilter` (paper 1, III-F)."""

    kind = "filter"

    class Config(ComponentConfig):
        sigma_points: int = Field(100, ge=2, description="C, Monte-Carlo sigma points")
        liu_west_delta: float = Field(0.97, gt=1 / 3, le=1, description="kernel discount")
        noise_checkpoint: SkillPath | None = Field(
            None, description="ObsNoiseNet state dict from `vistac train`; None: defaults"
        )
        prior: Prior = Prior()
        prior_from: SkillPath | None = Field(
            None,
            description="summary.json of an earlier run on this object: its belief's parameter "
            "means, std and correlation replace the prior (an object whose parameters are "
            "known)",
        )
        depth_size_px: int = Field(64, gt=0, description="side of the observed depth image")
        splat_px: int = Field(1, ge=1, description="pixels each projected point covers")
        min_ess_fraction: float = Field(
            0.8, gt=0, le=1, description="temper the parameter weights to keep this ESS share"
        )
        pose_std_floor: PoseStds = Field(
            (0.006, 0.006, 0.06, 0.0, 0.0, 0.0),
            description="least predicted pose std (m, rad) before the visual update: about "
            "one pixel, so the unscented points render differently",
        )
        estimate_parameters: bool = Field(
            True, description="false: keep the prior parameters (pose tracking only)"
        )
        occlusion_margin_m: float | None = Field(
            0.01, gt=0, description="ignore pixels this much nearer than any projection (gripper)"
        )
        max_link_speed_mps: float = Field(
            0.25, gt=0, description="fastest a link can move (predicted sigma points are "
            "brought back to it; about 10x the push speed)",
        )
        max_link_rate_radps: float = Field(2.5, gt=0, description="fastest a link can turn")
        robot_radius_m: float | None = Field(
            0.06, gt=0, description="only pixels that see above the object's top or within "
            "this distance of the TCP may be ignored as the robot (None: any nearer pixel)",
        )
        evidence_steps: float | None = Field(
            None, ge=1, description="steps of an interaction that count as one independent "
            "observation of the parameters; None: the noise checkpoint's (the process model's "
            "force-error autocorrelation time, measured by `vistac train`) times "
            "evidence_factor",
        )
        evidence_factor: float = Field(
            2.0, ge=1, description="the noise checkpoint's evidence_steps times this: the "
            "depth image's errors (the fitted shape's, the model's turn) persist longer than "
            "the force error it was measured from; 2 was chosen on the validation objects",
        )
        push_load_only: bool = Field(
            True, description="a push shows each link's friction load m f, not m and f apart "
            "(quasi-static): the process model sees the sigma points' m and f at the belief "
            "mean's ratio m / f, so the belief does not wander along m f = const; false for "
            "pushes fast enough that inertia shows",
        )
        tactile_std: tuple[PositiveFloat, NonNegativeFloat] | None = Field(
            None, description="[a N, b]: the fingertip force's noise std a + b |force| in "
            "place of the noise checkpoint's learned one (about 0.74 N whatever the force, so "
            "a light object's pushes tell little); null: the learned one. [0.05, 0.2] brought "
            "the friction load m f of 3 of 4 homogeneous test objects nearer the truth, but "
            "the overall NRMSE rose (README)",
        )
        contact_force_n: NonNegativeFloat | None = Field(
            0.2, description="a measured fingertip force weaker than this (N) is no evidence "
            "on the parameters: without contact it is zero whatever they are, and what the "
            "points' forces disagree on then is the model's contact onset (the shipped GNN "
            "predicts about 2 N in the steps before the finger touches); null: every force "
            "counts",
        )
        between_episodes_std_m: float = Field(
            0.002, ge=0, description="pose std added between interactions (m, and rad / 10)"
        )
        hinge_std_m: PositiveFloat | None = Field(
            None, description="hold each link k and link k + 1 together where their fitted "
            "outlines meet at the first look (``facing_joints``; a joint fixed in both links' "
            "frames): the pose update also observes the gap between the joint's two ends as "
            "zero with this std (m), which holds for welded and hinged links alike. 0.002 took "
            "20-55 % off the tracked turn error on the two-link test objects but brought no "
            "estimate nearer (docs/results.md). None: each link tracked on its own (paper 1)",
        )
        joints_from: JointsFrom = Field(
            "boxes", description="where the process models put the joint of each link k and "
            "link k + 1: by the fitted link boxes, as in training (boxes: the middle of link "
            "k's +x side and link k + 1's -x side for the learned models, of the facing sides "
            "for filters.analytical), or where the fitted outlines meet at the first look "
            "(outlines: ``facing_joints``, the same joints hinge_std_m holds)",
        )
        link_frames: LinkFrames = Field(
            "fitted", description="the frames the process model and the belief see the "
            "fitted links in: each superquadric's own (fitted), or those the models were "
            "trained in, at each footprint's centroid and, for a chain, along it (trained; "
            "see ModelFrames). Measured: trained is better on articulated objects, worse on "
            "single triangles and no better overall (docs/results.md)",
        )
        com_discrepancy_m: tuple[NonNegativeFloat, NonNegativeFloat] = Field(
            (0.0, 0.0), description="[a m, b m]: the reported belief (not the filter's own) "
            "adds a model-discrepancy std of a + b |kappa1| to each link's com_x and com_y, "
            "kappa1 the fitted link's taper. The process models see a link as its bounding "
            "box, so their CoM is the one that moves a box like the link: on a triangle it "
            "settles confidently off the true CoM. The shipped push skills' [0.010, 0.011] "
            "was measured on training objects (docs/results.md)",
        )
        push_evidence: PushEvidence = Field(
            PushEvidence(), description="after each interaction, score the parameters by the "
            "process model's open-loop rollout of the whole interaction against the tracked "
            "end pose (vistac.plugins.filters.rollout)",
        )

        def evidence_scale(self, measured_steps: float | None) -> float:
            """1 / the steps of an interaction that count as one independent observation:
            ``evidence_steps``, else ``measured_steps`` (a noise checkpoint's) times
            ``evidence_factor``; 1 when neither is known."""
            if self.evidence_steps is not None:
                return 1.0 / self.evidence_steps
            if measured_steps is None:
                return 1.0
            return 1.0 / max(measured_steps * self.evidence_factor, 1.0)

        def observation_model(
            self, layout: StateLayout, projector: DepthProjector, noise_net: ObsNoiseNet
        ) -> ProjectionObservationModel:
            """The observation model of these settings."""
            return ProjectionObservationModel(
                layout, projector, noise_net, occlusion_margin_m=self.occlusion_margin_m,
                robot_radius_m=self.robot_radius_m, tactile_std=self.tactile_std,
                contact_force_n=self.contact_force_n,
            )  # fmt: skip

        def dual_filter(
            self,
            layout: StateLayout,
            model: Any,
            observation: ProjectionObservationModel,
            measured_steps: float | None,
            sigma_points: int | None = None,
            joint_ends_m: torch.Tensor | None = None,
        ) -> DualFilter:
            """The DualFilter of these settings (``sigma_points`` overrides the config's;
            the joints [L - 1, 2, 2] of ``facing_joints`` are held with ``hinge_std_m``)."""
            joints = None
            if joint_ends_m is not None and self.hinge_std_m is not None:
                joints = HeldJoints(joint_ends_m, self.hinge_std_m)
            return DualFilter(
                layout, model, observation, sigma_points or self.sigma_points,
                self.liu_west_delta, min_ess_fraction=self.min_ess_fraction,
                pose_std_floor=self.pose_std_floor,
                evidence_scale=self.evidence_scale(measured_steps),
                twist_bound=(self.max_link_speed_mps, self.max_link_rate_radps),
                push_load_only=self.push_load_only,
                joints=joints,
            )  # fmt: skip

    def __init__(self, config: Config, ctx: ComponentContext) -> None:
        super().__init__(config, ctx)
        self.config: DualFilterComponent.Config = config
        self.model = ctx.find("process_model")
        if self.model is None:
            raise ConfigError(
                "filters.dual needs a process_model component in the skill "
                "(filters.gnn, filters.ff or filters.analytical)"
            )
        with torch.random.fork_rng(devices=[]):  # the same initial weights for the same seed
            torch.manual_seed(ctx.seed)
            self.noise_net = ObsNoiseNet(height_px=config.depth_size_px,
                                         width_px=config.depth_size_px)
        if config.noise_checkpoint is not None:
            load_checkpoint(self.noise_net, config.noise_checkpoint, "filters.dual", {})
        self.noise_net.to(DTYPE)
        known: tuple[dict[str, dict[str, float]] | None, Correlation | None] = (None, None)
        if config.prior_from is not None:  # read before anything moves
            known = load_prior_from(config.prior_from)
        self.known, self.known_correlation = known
        """The ``prior_from`` belief and its correlation."""
        self.generator = torch.Generator().manual_seed(int(ctx.rng("filter").integers(2**31)))
        self.layout: StateLayout | None = None
        self.belief: Belief | None = None
        self.prior: Belief | None = None
        self.shape: ShapeEstimate | None = None
        self.frames: ModelFrames | None = None
        self.joint_ends_m: torch.Tensor | None = None
        """[L - 1, 2, 2]: each joint in its two links' frames, from the first look; None
        unless ``hinge_std_m`` or ``joints_from: outlines``."""
        self._reported_var: FloatArray = np.zeros(0)
        self._observed_shape: ShapeEstimate | None = None
        self.history: list[dict[str, Any]] = []

    # -- Filter protocol ------------------------------------------------------------------

    def initialise(self, scene: Scene) -> GaussianBelief:
        if scene.shape is None:
            raise DataError("filters.dual: no shape estimate; run `look` with a shape estimator")
        self.shape = self._observed_shape = scene.shape
        self.frames = ModelFrames.of(scene.shape, self.config.link_frames)
        poses = self.frames.poses
        self.layout = StateLayout(len(poses))
        joints_wanted = self.config.hinge_std_m is not None or self.config.joints_from != "boxes"
        if joints_wanted and len(poses) > 1:
            self.joint_ends_m = self._joints(scene.shape, poses)
        self._reported_var = com_discrepancy_var(
            scene.shape, self.layout, self.config.com_discrepancy_m
        )
        handled = self.model.n_links
        counts = handled if isinstance(handled, tuple) else (handled,)
        if handled is not None and self.layout.n_links not in counts:
            raise ConfigError(
                f"the process model handles {' or '.join(map(str, counts))} link(s) but the object "
                f"was fitted with {self.layout.n_links}; use filters.gnn or a model trained "
                "for this many links"
            )
        if self.config.sigma_points <= self.layout.size:
            log.warning(
                "filters.dual: %d sigma points for a state of %d entries cannot be whitened: "
                "the parameters will drift and shrink by sampling error alone; use more than "
                "%d (default 100)", self.config.sigma_points, self.layout.size,
                self.layout.size,
            )  # fmt: skip
        pose_twist = np.column_stack([poses, np.zeros_like(poses)])
        com = None
        if self.config.prior.com_in_shape:
            com = (self.frames.footprint_mean_m, self.frames.footprint_cov_m2)
        self.belief = prior_belief(pose_twist, self.config.prior, self.layout, com)
        if self.known is not None and self.config.prior_from is not None:
            self.belief = known_parameters(
                self.belief, self.layout, self.known, self.config.prior_from,
                self.known_correlation,
            )  # fmt: skip
        self.prior = self.belief
        return self._public()

    def _joints(self, shape: ShapeEstimate, poses: FloatArray) -> torch.Tensor | None:
        """``facing_joints`` of the fit, or None (with a warning) when two links in a row
        do not meet, as a fit of three or more links may number them."""
        ends, nearest_m = facing_joints([link_outline(link)[0] for link in shape.links], poses)
        if (nearest_m > MAX_JOINT_GAP_M).any():
            log.warning(
                "filters.dual: no joints from the outlines (hinge_std_m, joints_from): fitted "
                "links %s come no nearer than %s mm to the next; the models keep the boxes' "
                "joints", np.flatnonzero(nearest_m > MAX_JOINT_GAP_M).tolist(),
                np.round(nearest_m * 1000, 1).tolist(),
            )  # fmt: skip
            return None
        world = [to_world_xy(ends[k, :1].numpy(), poses[k])[0].round(4).tolist()
                 for k in range(len(ends))]  # fmt: skip
        log.info("filters.dual: joints at %s (world x, y m)", world)
        return ends

    def update(self, episode: Episode) -> GaussianBelief:
        if self.belief is None or self.layout is None or self.shape is None:
            raise DataError("filters.dual: update before initialise")
        steps = [step for step in episode.steps if step.depth is not None]
        if not steps:
            raise DataError("filters.dual: the episode has no depth frames; record_depth: true")
        self._inflate_pose()
        filter_ = self._filter(steps[0])
        inputs = self._inputs(episode)
        dt_s = float(np.median(np.diff([s.time_s for s in steps]))) if len(steps) > 1 else 1 / 15
        start = None
        # Into step k with the TCP at its start, step k - 1, as the models were trained
        # (``ProcessInput``); into the first step with the first.
        starts = [steps[0], *steps[:-1]]
        with torch.no_grad():
            for step, step_start in zip(steps, starts, strict=True):
                observation = self._observation(step, filter_)
                self.belief = filter_.step(
                    self.belief, inputs(step_start), dt_s, observation, self.generator
                )
                if start is None:
                    start = self.belief
                if not self.config.estimate_parameters:
                    self._restore_prior_parameters()
                visual, tactile = filter_.last_log_likelihood.tolist()
                self.history.append(
                    {
                        "episode": episode.index,
                        "time_s": step.time_s,
                        "log_likelihood": {"visual": visual, "tactile": tactile},
                        **self._public().as_dict(),
                    }
                )
            if self.config.push_evidence.enabled and self.config.estimate_parameters:
                assert start is not None
                self._push_update(start, [inputs(step) for step in steps[:-1]], dt_s)
        return self._public()

    def _push_update(self, start: Belief, inputs: list[ProcessInput], dt_s: float) -> None:
        """The push-level evidence of one interaction (``push_evidence``)."""
        assert self.belief is not None and self.layout is not None and self.frames is not None
        layout, bound = self.layout, (self.config.max_link_speed_mps,
                                      self.config.max_link_rate_radps)

        predict = self.model.predict
        if self.config.push_evidence.mirror_average:
            predict = functools.partial(mirror_averaged, predict)

        def rollout(states: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
            return end_poses(predict, layout, states, inputs, dt_s, bound)

        sizes = self.frames.half_extents_m
        self.belief = push_update(
            self.belief, start, layout, self.config.push_evidence, rollout,
            torch.as_tensor(sizes, dtype=DTYPE), self.generator,
        )  # fmt: skip

    def predict_beliefs(
        self,
        actions: Sequence[Action],
        horizon_s: float,
        rate_hz: float,
        sigma_points: int | None = None,
    ) -> list[tuple[torch.Tensor, torch.Tensor]]:
        """The belief ``round(horizon_s * rate_hz)`` prediction steps (paper 1, eq. 21-26; no
        observation) into each action, from the current belief with the object at rest as
        ``update`` starts from (a zero horizon returns that start belief).

        The TCP starts at the action point (a push's contact point less the executor's
        ``pusher_offset_m`` along pd, so the pad touches it) and moves along pd at the action's
        speed. All actions are predicted in one batch with the same noise draws (a generator
        seeded by the skill seed on every call), so their beliefs differ only by the action.
        ``sigma_points``: C for the look-ahead (default: the filter's). Returns per action
        (mean [n], covariance [n, n]), float64.
        """
        if self.belief is None or self.layout is None or self.shape is None:
            raise DataError("filters.dual: predict_beliefs before initialise")
        if not actions:
            return []
        current = self.belief
        self._inflate_pose()
        start, self.belief = self.belief, current
        batch = len(actions)
        poses = self.layout.link_pose(start.mean).numpy()[None, :, :3].repeat(batch, 0)
        motion = self._action_motion(actions, poses)
        # The filter's own prediction (twist bound, push load); the observation model is never
        # called.
        filter_ = self.config.dual_filter(
            self.layout, _LookAheadModel(self.model),
            cast(ProjectionObservationModel, None), None, sigma_points,
        )  # fmt: skip
        generator = torch.Generator().manual_seed(self.ctx.seed)
        mean = start.mean.expand(batch, -1)
        belief = Belief(mean, start.cov.expand(batch, -1, -1))
        dt_s = 1.0 / rate_hz
        with torch.inference_mode():  # prediction only: no autograd bookkeeping at all
            for step in range(round(horizon_s * rate_hz)):
                inputs = motion.inputs(step * dt_s)
                state_noise = torch.randn(
                    (filter_.sigma_points, self.layout.size), generator=generator, dtype=DTYPE
                )
                process_noise = torch.randn(
                    (filter_.sigma_points, self.layout.n_pose), generator=generator, dtype=DTYPE
                )
                belief, _, _ = filter_.propagate(belief, inputs, dt_s, state_noise, process_noise)
        means, covs = belief.mean.clone(), belief.cov.clone()  # normal tensors again
        return [(means[i], covs[i]) for i in range(batch)]

    def predict_states(
        self, actions: Sequence[Action], rate_hz: float, states: torch.Tensor | None = None
    ) -> torch.Tensor:
        """Deterministic look-ahead for planning: the process model's mean prediction (no
        noise, the parameters held at their values) of each action from its state.

        states: [B, n] at rest before the actions (default: the current belief mean, twist
        zeroed); actions: B pushes or pulls, each carried out for its ``duration_s`` at
        ``rate_hz`` as the executor carries it out: a push from the executor's ``standoff_m``
        before contact (the pad travels that far before it touches the object), a pull from
        its grasp point. Returns the states [B, n] at the end of each action (float64).
        """
        if self.belief is None or self.layout is None or self.shape is None:
            raise DataError("filters.dual: predict_states before initialise")
        layout = self.layout
        if states is None:
            states = self.belief.mean.expand(len(actions), -1)
        if states.shape != (len(actions), layout.size):
            raise ValueError(f"states: expected [{len(actions)}, {layout.size}]")
        states = layout.at_rest(states).unsqueeze(-2)  # [B, 1, n]
        poses = layout.link_pose(states[:, 0]).numpy()[:, :, :3]
        motion = self._action_motion(actions, poses, standoff=True)
        steps = [round(a.duration_s * rate_hz) for a in actions]
        dt_s = 1.0 / rate_hz
        params = states[..., layout.parameter_slice]
        look_ahead = _LookAheadModel(self.model)
        with torch.inference_mode():  # prediction only: no autograd bookkeeping at all
            moving = torch.arange(max(steps, default=0))[:, None] < torch.as_tensor(steps)
            for step, which in enumerate(moving[..., None, None]):  # which: [B, 1, 1]
                prediction = look_ahead.predict(states, motion.inputs(step * dt_s), dt_s)
                moved = torch.cat([prediction.pose, params], -1)
                states = torch.where(which, moved, states)
            states = layout.at_rest(states[:, 0])
        return states.clone()  # a normal tensor again

    def _action_motion(
        self, actions: Sequence[Action], poses: FloatArray, standoff: bool = False
    ) -> _ActionMotion:
        """The gripper's straight motion during each action, with links [B, L, 3] at rest: a
        push's pad starts at its contact point, or with ``standoff`` the executor's
        ``standoff_m`` before it."""
        assert self.frames is not None
        batch = len(actions)
        points = np.array([action_point(action) for action in actions]).reshape(batch, 2)
        headings = np.array([[np.cos(a.pd_rad), np.sin(a.pd_rad)] for a in actions])
        executor_config = getattr(self.ctx.find("executor"), "config", None)
        defaults = CartesianExecutor.Config()
        offset_m = float(getattr(executor_config, "pusher_offset_m", defaults.pusher_offset_m))
        if standoff:
            offset_m += float(getattr(executor_config, "standoff_m", defaults.standoff_m))
        is_pull = np.array([isinstance(action, Pull) for action in actions])
        links = self.frames.link_at(points[:, None], poses)[:, 0]
        sizes = self.frames.half_extents_m
        return _ActionMotion(
            start_xy=points - np.where(is_pull, 0.0, offset_m)[:, None] * headings,
            yaw_rad=np.array(
                [a.grasp_axis_rad if isinstance(a, Pull) else a.pd_rad for a in actions]
            ),
            velocity_mps=np.array([a.speed_mps for a in actions])[:, None] * headings,
            fixed={
                "pd_rad": torch.tensor([a.pd_rad for a in actions], dtype=DTYPE),
                "is_pull": torch.as_tensor(is_pull, dtype=DTYPE),
                "link": torch.as_tensor(links),
                "link_size_m": torch.as_tensor(sizes, dtype=DTYPE).expand(batch, -1, -1),
                "link_offset": torch.as_tensor(relative_poses(poses), dtype=DTYPE),
                **self._model_joints(),
            },
        )

    def observe_positions(self, shape: ShapeEstimate, std_m: float) -> GaussianBelief:
        """A look as a measurement: Kalman update of the link positions (x_i, y_i) with the
        centres of a fresh fit, each belief link matched to the nearest fitted link, with a
        measurement noise of ``std_m`` per coordinate. The correlated entries (twist,
        parameters) move with them. Unchanged when the fit has another link count."""
        if self.belief is None or self.layout is None:
            raise DataError("filters.dual: observe_positions before initialise")
        if shape is self._observed_shape:
            return self._public()  # a measurement counts once
        self._observed_shape = shape
        fitted = ModelFrames.of(shape, self.config.link_frames).poses[:, :2]
        believed = self.layout.link_pose(self.belief.mean).numpy()[:, :2]
        if len(fitted) != len(believed):
            log.warning("look: %d fitted link(s) for %d in the belief; belief not corrected",
                        len(fitted), len(believed))  # fmt: skip
            return self._public()
        match = np.linalg.norm(believed[:, None] - fitted[None], axis=-1).argmin(axis=1)
        rows = [self.layout.index(f"{axis}_{i}") for i in range(len(believed)) for axis in "xy"]
        self.belief = position_update(
            self.belief, rows, torch.as_tensor(fitted[match].reshape(-1), dtype=DTYPE), std_m
        )
        return self._public()

    @property
    def interactions(self) -> tuple[str, ...]:
        """The interactions (push, pull) the process model predicts, so those this filter
        can update from."""
        return tuple(getattr(self.model, "interactions", ("push", "pull")))

    def step_history(self) -> list[dict[str, Any]]:
        """The belief after every filter step so far: episode, time_s and per entry
        ``{"mean", "std"}``."""
        return list(self.history)

    # -- helpers --------------------------------------------------------------------------

    def _restore_prior_parameters(self) -> None:
        """Parameters back to the prior (and uncorrelated with the pose)."""
        assert self.belief is not None and self.layout is not None and self.prior is not None
        params = self.layout.parameter_slice
        mean, cov = self.belief.mean.clone(), self.belief.cov.clone()
        mean[params] = self.prior.mean[params]
        cov[params, :] = 0.0
        cov[:, params] = 0.0
        cov[params, params] = self.prior.cov[params, params]
        self.belief = Belief(mean, cov)

    def _inflate_pose(self) -> None:
        """Between interactions the gripper leaves and comes back: widen the pose belief."""
        assert self.belief is not None and self.layout is not None
        std_m = self.config.between_episodes_std_m
        extra = torch.zeros(self.layout.size, dtype=DTYPE)
        extra[self.layout.pose_slice] = torch.tensor([std_m, std_m, std_m * 10, 0, 0, 0]).repeat(
            self.layout.n_links
        )
        mean = self.layout.at_rest(self.belief.mean)  # the object is at rest again
        self.belief = Belief(mean, self.belief.cov + torch.diag(extra**2))

    def _filter(self, first: StepObservation) -> DualFilter:
        assert self.shape is not None and self.layout is not None and first.depth is not None
        assert self.frames is not None
        points = np.asarray(self.shape.cloud.points_m)
        size = self.config.depth_size_px
        frame = first.depth
        projector = DepthProjector(
            points, self.frames.link_at(points, self.frames.poses), self.frames.poses,
            frame.intrinsics, frame.world_from_camera,
            width_px=size, height_px=size, splat_px=self.config.splat_px,
        )  # fmt: skip
        self.background_m = projector.background_m
        observation = self.config.observation_model(self.layout, projector, self.noise_net)
        return self.config.dual_filter(
            self.layout, self.model, observation, self._measured_steps(),
            joint_ends_m=self.joint_ends_m,
        )

    def _measured_steps(self) -> float | None:
        """The noise checkpoint's evidence steps; None without a checkpoint."""
        if self.config.noise_checkpoint is None:
            return None
        return float(self.noise_net.evidence_steps)

    @property
    def evidence_scale(self) -> float:
        """See ``Config.evidence_scale``."""
        return self.config.evidence_scale(self._measured_steps())

    def _model_joints(self) -> dict[str, torch.Tensor]:
        """The ProcessInput ``hinge_m`` of ``joints_from: outlines`` (each joint in its
        first link's frame [L - 1, 2]), or nothing: the models place the joints."""
        if self.config.joints_from == "boxes" or self.joint_ends_m is None:
            return {}
        return {"hinge_m": self.joint_ends_m[:, 0]}

    def _inputs(self, episode: Episode) -> Any:
        """A function StepObservation -> ProcessInput for this episode's action."""
        assert self.shape is not None and self.belief is not None and self.layout is not None
        assert self.frames is not None
        sizes = self.frames.half_extents_m
        poses = self.layout.link_pose(self.belief.mean).numpy()[:, :3]
        point = action_point(episode.action)[None, :2]
        link = int(self.frames.link_at(np.column_stack([point, [[0.0]]]), poses)[0])
        fixed = {
            "pd_rad": torch.tensor(episode.action.pd_rad, dtype=DTYPE),
            "is_pull": torch.tensor(float(episode.action.kind == "pull"), dtype=DTYPE),
            "link": torch.tensor(link),
            "link_size_m": torch.as_tensor(sizes, dtype=DTYPE),
            "link_offset": torch.as_tensor(relative_poses(poses), dtype=DTYPE),
            **self._model_joints(),
        }

        def inputs(step: StepObservation) -> ProcessInput:
            pose, twist = step.arm.pose, step.arm.twist
            tcp = torch.as_tensor(
                [pose[0], pose[1], pose[3], twist[0], twist[1], twist[3]], dtype=DTYPE
            )
            return ProcessInput(tcp=tcp, **fixed)

        return inputs

    def _observation(self, step: StepObservation, filter_: DualFilter) -> torch.Tensor:
        """The observation vector of a step, its depth at float32 precision: what a run records
        (episodes/*/data.npz), so that ``vistac replay`` sees what the run saw."""
        assert step.depth is not None
        depth = torch.as_tensor(np.asarray(step.depth.depth_m, dtype=np.float32), dtype=DTYPE)
        force = torch.as_tensor(step.tactile.force_n.sum(axis=0), dtype=DTYPE)
        return observation_vector(depth, force, self.background_m)

    def _public(self) -> GaussianBelief:
        """The belief as reported: the filter's, plus ``com_discrepancy_m``."""
        assert self.belief is not None and self.layout is not None
        cov = self.belief.cov.numpy()
        cov = 0.5 * (cov + cov.T) + np.diag(self._reported_var)
        return GaussianBelief(self.belief.mean.numpy().copy(), cov, self.layout.names)
