"""``sim.physics``: the simulator itself as the filter's process model.

A process model for simulated skills that predicts each sigma point by simulating it: the
object of the skill's world (``sim.mujoco``), with the point's mass, table friction, CoM per
link and joint friction, is put at the point's link poses and twists in a MuJoCo model of its
own (:class:`~vistac.plugins.hardware.sim.object_sim.ObjectSim`), the gripper at the step's
TCP with its fingers closed, and stepped for the filter's step. The mean prediction is then
the world's own motion, and what the filter still misses is what its state leaves out (the
gripper's lag, contacts' history) and its own approximations: swapping it for ``filters.gnn``
in a skill measures what a learned model's errors cost the estimates
(``vistac replay RUN --set 'components.process_model={plugin: sim.physics}'``).

The filter's link frames need not be the object's: at its first prediction the model takes
the frames the points are in (their mean) to be where the object's links stood at the run's
start, and keeps each link's offset from its frame. It needs the link count of the object,
models pushes only (a pull's grasp is not in its state), and runs one simulation per sigma
point and step (about 0.1 s for 100 points on one core), so pair it with ``actions.uniform``
or ``actions.random``, or replay a run's pushes, rather than with a look-ahead.
"""

from __future__ import annotations

import logging
import math
from typing import Any

import numpy as np
import torch
from pydantic import Field
from torch import Tensor
from vistac.component import Component, ComponentConfig, ComponentContext
from vistac.errors import ConfigError, DataError
from vistac.objects import link_frames, match_links
from vistac.plugins.filters.state import DTYPE, Prediction, ProcessInput, StateLayout
from vistac.plugins.hardware.sim.object_sim import ObjectSim
from vistac.types import FloatArray

logger = logging.getLogger(__name__)

MAX_FRAME_OFFSET_M = 0.05
"""The farthest a fitted link frame may lie from its link's at the run's start (a fitted
box centre lies up to about 2 cm from a triangle's centroid)."""
MIN_MASS_KG = 1e-3
"""The least mass a point is simulated with (the simulator cannot move a massless body)."""


def compose(first: FloatArray, second: FloatArray) -> FloatArray:
    """Planar poses [..., 3] (x, y, theta): ``second`` given in ``first``'s frame -> world."""
    c, s = np.cos(first[..., 2]), np.sin(first[..., 2])
    x = first[..., 0] + c * second[..., 0] - s * second[..., 1]
    y = first[..., 1] + s * second[..., 0] + c * second[..., 1]
    return np.stack([x, y, first[..., 2] + second[..., 2]], -1)


def relative(first: FloatArray, second: FloatArray) -> FloatArray:
    """Planar pose [..., 3] of ``second`` in ``first``'s frame (both world poses [..., 3])."""
    c, s = np.cos(first[..., 2]), np.sin(first[..., 2])
    dx, dy = second[..., 0] - first[..., 0], second[..., 1] - first[..., 1]
    return np.stack([c * dx + s * dy, -s * dx + c * dy, second[..., 2] - first[..., 2]], -1)


def moved_twist(twist: FloatArray, origin: FloatArray, to: FloatArray) -> FloatArray:
    """A planar twist [3] (vx, vy of the point ``origin`` [2], omega) at the point ``to``
    [2] of the same body."""
    arm = to - origin
    return np.array([twist[0] - twist[2] * arm[1], twist[1] + twist[2] * arm[0], twist[2]])


def wrapped(angle_rad: FloatArray) -> FloatArray:
    """Angles [...] (rad) into [-pi, pi)."""
    return np.asarray((angle_rad + math.pi) % (2 * math.pi) - math.pi)


class PhysicsProcessModel(Component):
    """Predicts every sigma point by simulating the world's object with its parameters."""

    kind = "process_model"
    interactions = ("push",)

    class Config(ComponentConfig):
        finger_height_m: float = Field(
            0.02, gt=0.0, description="height of the TCP in a push (the executor's "
            "`finger_height_m`)",
        )
        position_std_m: float = Field(0.0006, gt=0.0, description="process noise per step")
        theta_std_rad: float = Field(0.012, gt=0.0)
        speed_std_mps: float = Field(0.0013, gt=0.0)
        rate_std_radps: float = Field(0.014, gt=0.0)
        """The defaults are the shipped push GNN's learned process noise, so that the two
        models differ only in their mean."""

    config: Config

    def __init__(self, config: Config, ctx: ComponentContext) -> None:
        super().__init__(config, ctx)
        std = [config.position_std_m] * 2 + [config.theta_std_rad]
        std += [config.speed_std_mps] * 2 + [config.rate_std_radps]
        self.process_var = torch.tensor(std, dtype=DTYPE) ** 2
        self._sim: ObjectSim | None = None
        self._offsets: FloatArray | None = None
        """[L, 3]: each true link's frame in its matched filter link's frame (true order)."""
        self._inverse: FloatArray = np.zeros((0, 3))
        """[L, 3]: each matched filter link's frame in its true link's frame."""
        self._filter_link: list[int] = []
        """The filter link matched to each true link."""

    @property
    def n_links(self) -> int:
        """The world object's link count, the only one this model predicts."""
        return len(self._world_sim().spec.links)

    def _world_sim(self) -> ObjectSim:
        if self._sim is None:
            world: Any = self.ctx.find("world")
            if world is None or not hasattr(world, "spec"):
                raise ConfigError(
                    "sim.physics simulates the skill's world object: the skill needs "
                    "components.world with plugin sim.mujoco (on a real robot use filters.gnn "
                    "or filters.analytical)"
                )
            self._sim = ObjectSim(world.spec, float(world.table_tilt_rad))
        return self._sim

    def _match_frames(self, poses: FloatArray) -> None:
        """Fix each true link's offset from the filter link nearest it, from the points'
        link poses [P, L, 3] at the first prediction and the object's starting poses."""
        spec = self._world_sim().spec
        if poses.shape[1] != len(spec.links):
            raise DataError(
                f"sim.physics: the filter has {poses.shape[1]} link(s) but the object "
                f"{spec.name!r} has {len(spec.links)}; fit the shape with sim.true_shape"
            )
        theta = np.arctan2(np.sin(poses[..., 2]).mean(0), np.cos(poses[..., 2]).mean(0))
        frames = np.column_stack([poses[..., :2].mean(0), theta])
        truth = link_frames(spec)
        match = match_links(frames[:, :2], truth[:, :2])
        apart_m = max(float(np.linalg.norm(frames[b, :2] - truth[t, :2])) for b, t in match.items())
        if apart_m > MAX_FRAME_OFFSET_M:
            raise DataError(
                f"sim.physics: its first prediction has a link {apart_m * 100:.1f} cm from "
                f"where the object {spec.name!r} starts; it takes the first prediction's frames "
                "to be the object's where the run found it, so use it from a run's start "
                "(a skill run or `vistac replay`)"
            )
        self._filter_link = [next(b for b, t in match.items() if t == true)
                             for true in range(len(truth))]  # fmt: skip
        self._offsets = relative(frames[self._filter_link], truth)
        self._inverse = relative(self._offsets, np.zeros(3))
        logger.info(
            "sim.physics: true links in the filter's frames %s",
            np.round(self._offsets, 4).tolist(),
        )

    def predict(self, states: Tensor, inputs: ProcessInput, dt_s: float) -> Prediction:
        """states [..., C, 11 L - 1] -> Prediction with process_var [..., 6 L]."""
        if bool((inputs.is_pull > 0.5).any()):
            raise DataError(
                "sim.physics predicts pushes only (a pull's grasp is not in the filter's "
                "state); use filters.gnn or filters.analytical for pulls"
            )
        layout = StateLayout((states.shape[-1] + 1) // 11)
        flat = states.detach().reshape(-1, *states.shape[-2:]).cpu().numpy()
        tcp = inputs.tcp.detach().reshape(-1, 6).cpu().numpy()
        tcp = np.broadcast_to(tcp, (flat.shape[0], 6))
        if self._offsets is None:
            self._match_frames(flat.reshape(-1, layout.size)[:, : layout.n_pose]
                               .reshape(-1, layout.n_links, 6)[..., :3])  # fmt: skip
        pose = np.empty((*flat.shape[:-1], layout.n_pose))
        force = np.empty((*flat.shape[:-1], 2))
        height = self.config.finger_height_m
        for batch, points in enumerate(flat):
            arm_pose = np.array([tcp[batch, 0], tcp[batch, 1], height, tcp[batch, 2]])
            arm_velocity = np.array([tcp[batch, 3], tcp[batch, 4], 0.0, tcp[batch, 5]])
            for point, state in enumerate(points):
                pose[batch, point], force[batch, point] = self._simulate(
                    layout, state, arm_pose, arm_velocity, dt_s
                )
        shape = (*states.shape[:-1],)
        variance = self.process_var.repeat(layout.n_links).expand(*inputs.tcp.shape[:-1], -1)
        return Prediction(
            pose=torch.as_tensor(pose, dtype=DTYPE).reshape(*shape, layout.n_pose),
            force_n=torch.as_tensor(force, dtype=DTYPE).reshape(*shape, 2),
            process_var=variance,
        )

    def _simulate(
        self,
        layout: StateLayout,
        state: FloatArray,
        arm_pose: FloatArray,
        arm_velocity: FloatArray,
        dt_s: float,
    ) -> tuple[FloatArray, FloatArray]:
        """One point's state [n] one step on: its pose block [6 L] and finger force [2]."""
        assert self._offsets is not None
        sim = self._world_sim()
        links = state[: layout.n_pose].reshape(layout.n_links, 6)
        mine = links[self._filter_link]  # [L, 6], true link order
        true_poses = compose(mine[:, :3], self._offsets)
        twists = [moved_twist(link[3:], link[:2], true[:2])
                  for link, true in zip(mine, true_poses, strict=True)]  # fmt: skip
        sim.set_parameters(self._true_parameters(layout, state))
        sim.place(true_poses[0], float(true_poses[-1, 2] - true_poses[0, 2]), arm_pose)
        sim.set_twist(twists[0], float(twists[-1][2] - twists[0][2]), arm_velocity)
        sim.drive(arm_pose, arm_velocity, dt_s)
        sim.refresh()  # the state reached: the point started from the world's recorded state,
        # one simulator step behind its time as the world records it, and so ends as recorded
        new_true, new_twists = sim.link_poses(), sim.link_twists()
        out = links.copy()
        for true, b in enumerate(self._filter_link):
            frame = compose(new_true[true], self._inverse[true])
            frame[2] = links[b, 2] + wrapped(frame[2] - links[b, 2])
            out[b, :3] = frame
            out[b, 3:] = moved_twist(new_twists[true], new_true[true, :2], frame[:2])
        return out.reshape(-1), sim.finger_force_n()

    def _true_parameters(self, layout: StateLayout, state: FloatArray) -> FloatArray:
        """The point's parameters [4 L (+ 1)] in the true links' order and frames."""
        assert self._offsets is not None
        block = state[layout.parameter_slice]
        values = []
        for true, b in enumerate(self._filter_link):
            mass_kg, friction, com_x, com_y = block[4 * b : 4 * b + 4]
            offset = self._offsets[true]
            com = relative(offset, np.array([com_x, com_y, 0.0]))[:2]
            values += [max(mass_kg, MIN_MASS_KG), max(friction, 0.0), *com]
        joints = block[4 * layout.n_links :]
        return np.array(values + [max(float(f), 0.0) for f in joints])
