"""Recorded interactions as filter training and evaluation data.

A run of a collection skill writes ``episodes/NNNN/{data.npz, meta.json}`` (see
``vistac.recording``). :func:`load_trajectories` reads them back as :class:`Trajectory`
objects with the true state per step (poses from the simulator, twists by central
differences), the robot input per step and the observations.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor
from vistac.errors import DataError
from vistac.objects import (
    LinkSpec,
    ObjectSpec,
    link_frames,
    points_inside,
    prism_distance_m,
    prism_surface_points,
    to_link_frame,
    to_world_xy,
)
from vistac.plugins.filters.mirror import reflect_poses
from vistac.plugins.filters.state import DTYPE, ProcessInput, StateLayout
from vistac.types import CameraIntrinsics, FloatArray

log = logging.getLogger(__name__)

CLOUD_POINTS = 2000
"""Points of the object cloud the depth projector moves with the links."""
MAX_TURN_RATE_RADPS = 6.0
"""A link turning faster than this between two recorded steps has left planar motion (tipped
over: its yaw is then ill-defined and jumps); :func:`load_trajectories` leaves it out."""
MISS_MARGIN_M = 0.008
"""How far a missed push's TCP stays from the object (:func:`missed_push`)."""
_PAD_HALF_WIDTH_M = 0.012
"""Half the width of the finger pad across the push (the simulated gripper's)."""


@dataclass(frozen=True)
class Trajectory:
    """One recorded push or pull at the control rate (T steps, L links).

    poses: [T, L, 3] true (x, y, theta), theta continuous along time; twists: [T, L, 3] (vx,
    vy, omega); tcp: [T, 6]; force_n: [T, 2] total force on the fingers (world x, y); depth_m:
    [T, H, W] or None with camera_pose [T, 4, 4] and intrinsics; parameters: true values by
    belief entry name.
    """

    source: str
    spec: ObjectSpec
    kind: str
    pd_rad: float
    link: int
    dt_s: float
    poses: FloatArray
    twists: FloatArray
    tcp: FloatArray
    force_n: FloatArray
    depth_m: FloatArray | None
    camera_pose: FloatArray | None
    intrinsics: CameraIntrinsics | None
    parameters: dict[str, float]
    reflected: bool = False
    """The mirror image of a recorded trajectory (:func:`mirrored`): its link offsets
    (``link_geometry`` of the unreflected ``spec``) are reflected too."""

    @property
    def steps(self) -> int:
        return len(self.poses)

    @property
    def n_links(self) -> int:
        return len(self.spec.links)

    def window(self, start: int, stop: int) -> Trajectory:
        """Steps ``start:stop`` as a trajectory of their own."""
        cut = slice(start, stop)
        return Trajectory(
            self.source, self.spec, self.kind, self.pd_rad, self.link, self.dt_s,
            self.poses[cut], self.twists[cut], self.tcp[cut], self.force_n[cut],
            None if self.depth_m is None else self.depth_m[cut],
            None if self.camera_pose is None else self.camera_pose[cut],
            self.intrinsics, self.parameters, self.reflected,
        )  # fmt: skip


def unwrap_theta(poses: FloatArray) -> FloatArray:
    """Poses [T, L, 3] with theta unwrapped along time (a copy): continuous across +-pi, so
    differences of poses are the motion (the simulator reports theta in (-pi, pi])."""
    unwrapped = np.array(poses, dtype=float)
    unwrapped[..., 2] = np.unwrap(unwrapped[..., 2], axis=0)
    return unwrapped


def central_twist(poses: FloatArray, dt_s: float) -> FloatArray:
    """Central-difference velocities [T, L, 3] of continuous poses [T, L, 3]."""
    if len(poses) < 2:
        return np.zeros_like(poses)
    return np.gradient(poses, dt_s, axis=0)


def too_fast_a_turn(poses: FloatArray, dt_s: float, source: object = None) -> bool:
    """Whether a link of the continuous poses [T, L, 3] turned faster than
    :data:`MAX_TURN_RATE_RADPS` between two steps (the object tipped over or was flung);
    logged with ``source`` when one is given."""
    turn_rate_radps = np.abs(np.diff(poses[..., 2], axis=0)).max(initial=0.0) / dt_s
    if turn_rate_radps > MAX_TURN_RATE_RADPS and source is not None:
        log.warning("left out %s: a link turned at %.0f rad/s between two steps (over %g: the "
                    "object tipped over or was flung)", source, turn_rate_radps,
                    MAX_TURN_RATE_RADPS)  # fmt: skip
    return bool(turn_rate_radps > MAX_TURN_RATE_RADPS)


def _episode(folder: Path) -> Trajectory | None:
    meta = json.loads((folder / "meta.json").read_text(encoding="utf-8"))
    truth = meta.get("ground_truth")
    if not truth or "object" not in truth:
        raise DataError(f"{folder}: no ground truth; record training data in simulation")
    with np.load(folder / "data.npz") as data:
        arrays = {name: data[name] for name in data.files}
    if "object_pose" not in arrays or len(arrays["time_s"]) < 3:
        return None
    time_s = arrays["time_s"]
    dt_s = float(np.median(np.diff(time_s)))
    poses = unwrap_theta(arrays["object_pose"])
    if too_fast_a_turn(poses, dt_s, folder):
        return None
    arm_pose, arm_twist = arrays["arm_pose"], arrays["arm_twist"]
    intrinsics = None
    if "depth_intrinsics" in arrays:
        fx, fy, cx, cy = arrays["depth_intrinsics"][0]
        height, width = arrays["depth_m"].shape[1:]
        intrinsics = CameraIntrinsics(width, height, fx, fy, cx, cy)
    action = meta["action"]
    return Trajectory(
        source=str(folder),
        spec=ObjectSpec.model_validate(truth["object"]),
        kind=action["kind"],
        pd_rad=float(action["pd_rad"]),
        link=int(action.get("link", 0)),
        dt_s=dt_s,
        poses=poses,
        twists=central_twist(poses, dt_s),
        tcp=np.column_stack([arm_pose[:, [0, 1, 3]], arm_twist[:, [0, 1, 3]]]),
        force_n=arrays["tactile_force_n"].sum(axis=1),
        depth_m=arrays.get("depth_m"),
        camera_pose=arrays.get("camera_pose"),
        intrinsics=intrinsics,
        parameters=dict(truth["parameters"]),
    )


def mirrored(trajectory: Trajectory) -> Trajectory:
    """The same interaction of the mirror image of the scene, reflected across the line of
    the push or pull (through the TCP's first position, along ``pd_rad``): what the simulator
    would have recorded for the reflected object, since planar pushing on an isotropic table
    is mirror-symmetric. Positions and velocities are reflected, angles become ``2 pd -
    theta``, rates change sign, and so do each link's CoM y and the y and angle of each
    link's offset from link 0 (in their own frames, which the reflection turns). The push
    direction and the TCP's path stay. Without depth images: the camera is not reflected."""
    origin = torch.as_tensor(trajectory.tcp[0, :2], dtype=DTYPE)
    pd_rad = torch.as_tensor(trajectory.pd_rad, dtype=DTYPE)

    def reflect(pose_twist: FloatArray) -> FloatArray:
        """Poses and twists [T, L, 6] reflected (``reflect_poses``)."""
        return reflect_poses(torch.as_tensor(pose_twist, dtype=DTYPE), origin, pd_rad).numpy()

    links = reflect(np.concatenate([trajectory.poses, trajectory.twists], axis=-1))
    tcp = reflect(trajectory.tcp[:, None, :])[:, 0]
    force_as_velocity = np.zeros((trajectory.steps, 1, 6))  # a force reflects as a velocity
    force_as_velocity[:, 0, 3:5] = trajectory.force_n
    force = reflect(force_as_velocity)
    parameters = {
        name: -value if name.startswith("com_y_") else value
        for name, value in trajectory.parameters.items()
    }
    return replace(
        trajectory, source=f"{trajectory.source} (mirrored)",
        poses=links[..., :3], twists=links[..., 3:], tcp=tcp,
        force_n=force[:, 0, 3:5], depth_m=None, camera_pose=None,
        parameters=parameters, reflected=not trajectory.reflected,
    )  # fmt: skip


def acted_link(trajectory: Trajectory, contact_force_n: float = 0.3) -> int:
    """The true link the robot acted on: the one nearest the TCP (at half the link's height)
    at the first step whose finger force exceeds ``contact_force_n`` (else the strongest)."""
    if trajectory.n_links == 1:
        return 0
    force_n = np.linalg.norm(trajectory.force_n, axis=1)
    touching = np.flatnonzero(force_n > contact_force_n)
    step = int(touching[0]) if touching.size else int(np.argmax(force_n))
    distances_m = [
        prism_distance_m(
            to_link_frame(np.array([[*trajectory.tcp[step, :2], link.height_m / 2]]), pose),
            link.polygon(), link.height_m,
        )[0]
        for link, pose in zip(trajectory.spec.links, trajectory.poses[step], strict=True)
    ]  # fmt: skip
    return int(np.argmin(distances_m))


def load_trajectories(roots: list[Path], kind: str | None = None) -> list[Trajectory]:
    """Every recorded episode under the run folders ``roots`` (of one interaction ``kind``
    when given), its ``link`` in the true link numbering (:func:`acted_link`: a recorded
    action names a link of the fitted shape, or link 0 for ``actions.outline``, while
    training builds the graph from the true links). Episodes under 3 steps and those whose
    object tipped over (:data:`MAX_TURN_RATE_RADPS`) are left out. DataError when a folder
    holds no episode folders."""
    trajectories: list[Trajectory] = []
    for root in roots:
        folders = sorted(p for p in (root / "episodes").glob("[0-9]*") if p.is_dir())
        if not folders:
            raise DataError(f"{root}: no episodes/NNNN folders; is this a run output folder?")
        for folder in folders:
            trajectory = _episode(folder)
            if trajectory is not None and (kind is None or trajectory.kind == kind):
                trajectories.append(replace(trajectory, link=acted_link(trajectory)))
    return trajectories


def missed_push(
    trajectory: Trajectory, lateral: bool, margin_m: float = MISS_MARGIN_M
) -> Trajectory | None:
    """The same push with its TCP path moved so that the fingers pass the object by: back
    along -pd by the path's own length plus ``margin_m`` (it ends short of where it began), or
    (``lateral``) across pd beyond the whole object. The object stays at rest where it was and
    the fingers feel no force, which is what such a push does. None for a path that still
    comes within ``margin_m`` of a link (at the links' start poses: back-shifted paths of a
    push from between two links can).

    Training on these teaches the learned models that a push moves the object only in
    contact: the recorded pushes all start 1 cm short of the object and reach it.
    """
    direction = np.array([np.cos(trajectory.pd_rad), np.sin(trajectory.pd_rad)])
    path = trajectory.tcp[:, :2]
    if lateral:
        across = np.array([-direction[1], direction[0]])
        corners = np.concatenate(
            [to_world_xy(np.pad(link.polygon(), ((0, 0), (0, 1))), pose)[:, :2]
             for link, pose in zip(trajectory.spec.links, trajectory.poses[0], strict=True)]
        )  # fmt: skip
        side = (corners - path[0]) @ across
        offset = (np.abs(side).max() + _PAD_HALF_WIDTH_M + margin_m) * across
    else:
        travel_m = float(np.linalg.norm(path[-1] - path[0]))
        offset = -(travel_m + margin_m) * direction
    tcp = trajectory.tcp.copy()
    tcp[:, :2] += offset
    if min(_path_gap_m(tcp[:, :2], link, pose)
           for link, pose in zip(trajectory.spec.links, trajectory.poses[0], strict=True)
           ) < margin_m:  # fmt: skip
        return None
    return replace(
        trajectory,
        source=f"{trajectory.source} (missed)",
        poses=np.repeat(trajectory.poses[:1], trajectory.steps, axis=0),
        twists=np.zeros_like(trajectory.twists),
        tcp=tcp,
        force_n=np.zeros_like(trajectory.force_n),
        depth_m=None,
        camera_pose=None,
    )


def _path_gap_m(path_m: FloatArray, link: LinkSpec, pose: FloatArray) -> float:
    """Least distance (m) of the points [T, 2] to the footprint of ``link`` at pose [3]
    (0 inside it)."""
    local = to_link_frame(np.column_stack([path_m, np.full(len(path_m), link.height_m / 2)]),
                          pose)  # fmt: skip
    polygon = link.polygon()
    gap_m = prism_distance_m(local, polygon, link.height_m)
    return float(np.where(points_inside(polygon, local[:, :2]), 0.0, gap_m).min())


def missed_pushes(trajectories: list[Trajectory]) -> list[Trajectory]:
    """One :func:`missed_push` per push, moved back and across in turn (those that would
    touch a link left out)."""
    pushes = [t for t in trajectories if t.kind == "push"]
    missed = [missed_push(t, lateral=bool(k % 2)) for k, t in enumerate(pushes)]
    return [t for t in missed if t is not None]


# ---------------------------------------------------------------------------------------------
# Tensors for the filter


def link_geometry(spec: ObjectSpec) -> tuple[FloatArray, FloatArray]:
    """(link_size_m [L, 2] half extents of each footprint, link_offset [L, 3] initial pose
    of each link relative to link 0, in link 0's frame)."""
    size = np.array([np.abs(link.polygon()).max(axis=0) for link in spec.links])
    return size, relative_poses(link_frames(spec))


def _link_geometry(trajectory: Trajectory) -> tuple[FloatArray, FloatArray]:
    """``link_geometry`` of the trajectory's object, reflected where the trajectory is."""
    size, offset = link_geometry(trajectory.spec)
    if trajectory.reflected:
        offset = offset * np.array([1.0, -1.0, -1.0])
    return size, offset


def relative_poses(poses: FloatArray) -> FloatArray:
    """Each planar pose [..., L, 3] relative to the first, in the first's frame: [..., L, 3]."""
    first = poses[..., :1, :]
    c, s = np.cos(first[..., 2]), np.sin(first[..., 2])  # [..., 1]
    rel = poses[..., :2] - first[..., :2]
    return np.stack(
        [
            c * rel[..., 0] + s * rel[..., 1],
            -s * rel[..., 0] + c * rel[..., 1],
            poses[..., 2] - first[..., 2],
        ],
        axis=-1,
    )


def true_states(trajectory: Trajectory, layout: StateLayout) -> Tensor:
    """The true joint state per step: [T, n]."""
    pose_twist = np.concatenate([trajectory.poses, trajectory.twists], axis=-1)  # [T, L, 6]
    params = np.array([trajectory.parameters.get(name, 0.0) for name in parameter_names(layout)])
    if layout.n_joints and trajectory.spec.type == "heterogeneous":
        params[-layout.n_joints :] = 1.0  # a welded joint: "rigid", as paper 1 IV-A sets it
    states = np.concatenate(
        [pose_twist.reshape(trajectory.steps, -1), np.tile(params, (trajectory.steps, 1))], axis=1
    )
    return torch.as_tensor(states, dtype=DTYPE)


def parameter_names(layout: StateLayout) -> tuple[str, ...]:
    return layout.names[layout.n_pose :]


def process_inputs(trajectories: list[Trajectory]) -> list[ProcessInput]:
    """Per step t, one ProcessInput batched over the trajectories (same length T)."""
    sizes, offsets = zip(*(_link_geometry(t) for t in trajectories), strict=True)
    link_size = torch.as_tensor(np.stack(sizes), dtype=DTYPE)
    link_offset = torch.as_tensor(np.stack(offsets), dtype=DTYPE)
    tcp = torch.as_tensor(np.stack([t.tcp for t in trajectories]), dtype=DTYPE)  # [B, T, 6]
    pd = torch.as_tensor([t.pd_rad for t in trajectories], dtype=DTYPE)
    pull = torch.as_tensor([float(t.kind == "pull") for t in trajectories], dtype=DTYPE)
    link = torch.as_tensor([t.link for t in trajectories], dtype=torch.int64)
    return [
        ProcessInput(tcp[:, step], pd, pull, link, link_size, link_offset)
        for step in range(tcp.shape[1])
    ]


def object_cloud(
    spec: ObjectSpec, rng: np.random.Generator, count: int = CLOUD_POINTS
) -> tuple[FloatArray, FloatArray]:
    """The object's visible surface (all but the bottom faces) at its initial pose: points
    [P, 3] (world, m) and their link index [P]."""
    per_link = max(1, count // len(spec.links))
    points, owners = [], []
    for index, (link, pose) in enumerate(zip(spec.links, link_frames(spec), strict=True)):
        surface = prism_surface_points(link.polygon(), link.height_m, 2 * per_link, rng)
        surface = surface[surface[:, 2] > 1e-6][:per_link]
        points.append(to_world_xy(surface, pose))
        owners.append(np.full(len(surface), index))
    return np.concatenate(points), np.concatenate(owners)


def stack_equal_length(trajectories: list[Trajectory], steps: int) -> list[Trajectory]:
    """Cut every trajectory into consecutive windows of ``steps`` steps (the rest dropped)."""
    windows = []
    for trajectory in trajectories:
        for start in range(0, trajectory.steps - steps + 1, steps):
            windows.append(trajectory.window(start, start + steps))
    return windows


def describe(trajectories: list[Trajectory]) -> dict[str, Any]:
    """Counts by object type and interaction, for logs and reports."""
    counts: dict[str, int] = {}
    for trajectory in trajectories:
        key = f"{trajectory.spec.type}/{trajectory.kind}"
        counts[key] = counts.get(key, 0) + 1
    return {"trajectories": len(trajectories), "by_type": counts}
