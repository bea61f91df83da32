"""One object and the gripper in a MuJoCo model of their own, for replays and predictions.

Unlike the ``sim.mujoco`` world, whose object keeps its parameters, an :class:`ObjectSim`'s
object parameters (mass, table friction, CoM per link, the hinge's friction) can be set
between runs, and its state put anywhere: the object's links at given planar poses and twists,
the gripper with its fingers closed at a given pose, moving at a given velocity.
"""

from __future__ import annotations

import math

import mujoco
import numpy as np
from vistac.objects import ObjectSpec
from vistac.plugins.hardware.sim.mjcf import GripperGeometry, build_mjcf
from vistac.plugins.hardware.sim.tactile import pad_forces
from vistac.plugins.hardware.sim.world import SimIndex, planar_poses
from vistac.types import FloatArray

TIMESTEP_S = 0.002
"""The simulator's step (``sim.world``'s default)."""
GRIPPER = GripperGeometry(0.15)
"""``sim.world``'s default gripper; a push's fingers are closed, so the opening does not
matter."""
SEAT_ITERATIONS = 6
"""The most forward passes that seat a pressed pad (:meth:`ObjectSim.place`)."""
SEAT_TOLERANCE_N = 0.02
"""Seated: the pad's contact force within this of what its finger's servo holds."""


class ObjectSim:
    """The simulated world of one object, whose parameters and state can be set.

    Parameters are given as ``values`` [4 L (+ 1)]: m (kg), f, com_x, com_y (m, link frame)
    per link, then the hinge's friction (N m) where the object has a hinge."""

    def __init__(self, spec: ObjectSpec, tilt_rad: float | None = None) -> None:
        tilt = spec.table_tilt_rad if tilt_rad is None else tilt_rad
        self.spec = spec
        self.model = mujoco.MjModel.from_xml_string(build_mjcf(spec, GRIPPER, TIMESTEP_S, tilt))
        self.data = mujoco.MjData(self.model)
        self.index = SimIndex.of(self.model, len(spec.links))
        model = self.model
        self._link_geoms = np.array([
            mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, f"link{i}_geom")
            for i in range(len(spec.links))
        ])  # fmt: skip
        self._free = model.jnt_qposadr[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT,
                                                         "object")]  # fmt: skip
        self._free_dof = model.jnt_dofadr[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT,
                                                            "object")]  # fmt: skip
        hinge = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, "hinge")
        self.hinge = None if hinge < 0 else (model.jnt_qposadr[hinge], model.jnt_dofadr[hinge])
        """(qpos address, dof address) of the hinge; None for one link or a welded pair."""
        bodies = self.index.link_bodies
        self._inertia_per_kg = model.body_inertia[bodies] / model.body_mass[bodies, None]
        servos = self.index.arm_actuators  # integrated-velocity servos: gain kp, bias -kv
        self._servo_act = model.actuator_actadr[servos]
        self._servo_kp = model.actuator_gainprm[servos, 0]
        self._servo_kv = -model.actuator_biasprm[servos, 2]
        self._finger_kp = model.actuator_gainprm[self.index.finger_actuators, 0]

    def set_parameters(self, values: FloatArray) -> None:
        """Set m (kg, the inertia scaled with it), f, com (m, link frame) per link and the
        hinge's friction (N m) from ``values`` (see the class)."""
        model = self.model
        for i, body in enumerate(self.index.link_bodies):
            mass_kg, friction, com_x, com_y = values[4 * i : 4 * i + 4]
            model.body_mass[body] = mass_kg
            model.body_inertia[body] = self._inertia_per_kg[i] * mass_kg
            model.body_ipos[body, :2] = (com_x, com_y)
            model.geom_friction[self._link_geoms[i], 0] = friction
        if self.hinge is not None:
            model.dof_frictionloss[self.hinge[1]] = values[4 * len(self._link_geoms)]
        mujoco.mj_setConst(model, self.data)

    def place(self, link0_pose: FloatArray, hinge_rad: float, arm_pose: FloatArray) -> None:
        """Reset to link 0's frame at ``link0_pose`` [3] (x m, y m, theta rad), the hinge at
        ``hinge_rad`` (link 1's yaw less link 0's; ignored without a hinge), everything at
        rest, and the gripper at ``arm_pose`` [4] (x, y, z m, yaw rad) with the fingers
        closed."""
        model, data, index = self.model, self.data, self.index
        mujoco.mj_resetData(model, data)
        x, y, theta = link0_pose
        data.qpos[self._free : self._free + 7] = [x, y, 0.0, math.cos(theta / 2), 0.0, 0.0,
                                                  math.sin(theta / 2)]  # fmt: skip
        if self.hinge is not None:
            data.qpos[self.hinge[0]] = hinge_rad
        data.qpos[index.arm_qpos] = arm_pose
        data.act[self._servo_act] = arm_pose
        data.qpos[index.finger_qpos] = 0.0
        data.ctrl[index.finger_actuators] = 0.0
        mujoco.mj_forward(model, data)
        self._seat_pads()

    def _seat_pads(self) -> None:
        """Let each pad that reaches into the object give way, as its finger does in a push,
        until the finger's position servo holds the pad's contact force. Pressed into the
        object by a push, a finger gives millimetres (2.5 mm at 2.4 N), the soft contact a
        tenth of that; without it a point placed mid-push starts with several times the
        force. The give solves ``force(give) = kp give`` by false position (the far end's
        value halved each step, as in the Illinois method), the force falling from its value
        at no give to none at the whole overlap."""
        data = self.data
        for i, overlap_m in enumerate(self._pad_overlap_m()):
            if overlap_m <= 0.0:
                continue
            kp = float(self._finger_kp[i])
            low, high = (0.0, self._pad_force_n(i)), (overlap_m, -kp * overlap_m)
            for _ in range(SEAT_ITERATIONS):
                give_m = (low[0] * high[1] - high[0] * low[1]) / (high[1] - low[1])
                data.qpos[self.index.finger_qpos[i]] = -give_m
                excess = self._pad_force_n(i) - kp * give_m
                if excess > 0:
                    low, high = (give_m, excess), (high[0], 0.5 * high[1])
                else:
                    low, high = (low[0], 0.5 * low[1]), (give_m, excess)
                if abs(excess) < SEAT_TOLERANCE_N:
                    break
        mujoco.mj_forward(self.model, data)

    def _pad_force_n(self, pad: int) -> float:
        """The magnitude of the object's contact force on pad ``pad`` (N), after a forward
        pass of the state."""
        model, data = self.model, self.data
        mujoco.mj_forward(model, data)
        geoms = data.contact.geom[: data.ncon]
        on_pad = (geoms == self.index.pad_geoms[pad]).any(axis=1)
        on_object = (geoms[:, :, None] == self._link_geoms).any(axis=(1, 2))
        total, wrench = np.zeros(3), np.zeros(6)
        for i in np.flatnonzero(on_pad & on_object):
            mujoco.mj_contactForce(model, data, int(i), wrench)
            total += data.contact.frame[i].reshape(3, 3).T @ wrench[:3]
        return float(np.linalg.norm(total))

    def _pad_overlap_m(self) -> FloatArray:
        """How deep each pad [2] reaches into the object (m, 0 where it does not touch)."""
        data, pads = self.data, self.index.pad_geoms
        overlap = np.zeros(len(pads))
        geoms, dist = data.contact.geom[: data.ncon], data.contact.dist[: data.ncon]
        on_object = (geoms[:, :, None] == self._link_geoms).any(axis=(1, 2))
        for i, pad in enumerate(pads):
            touching = (geoms == pad).any(axis=1) & on_object
            if touching.any():
                overlap[i] = max(0.0, -float(dist[touching].min()))
        return overlap

    def set_twist(
        self, link0_twist: FloatArray, hinge_rate: float, arm_velocity: FloatArray
    ) -> None:
        """Link 0's frame moving at ``link0_twist`` [3] (vx, vy m/s of its origin, omega
        rad/s), the hinge at ``hinge_rate`` (rad/s) and the gripper at ``arm_velocity`` [4]."""
        data = self.data
        vx, vy, omega = link0_twist
        data.qvel[self._free_dof : self._free_dof + 6] = [vx, vy, 0.0, 0.0, 0.0, omega]
        if self.hinge is not None:
            data.qvel[self.hinge[1]] = hinge_rate
        data.qvel[self.index.arm_dof] = arm_velocity
        mujoco.mj_forward(self.model, data)

    def link_poses(self) -> FloatArray:
        """[L, 3] = (x_m, y_m, theta_rad) of the link frames."""
        return planar_poses(self.data, self.index.link_bodies)

    def link_twists(self) -> FloatArray:
        """[L, 3] = (vx, vy m/s of each link frame's origin, omega rad/s), world frame."""
        velocity = np.zeros(6)
        twists = []
        for body in self.index.link_bodies:
            mujoco.mj_objectVelocity(self.model, self.data, mujoco.mjtObj.mjOBJ_XBODY, int(body),
                                     velocity, 0)  # fmt: skip
            twists.append([velocity[3], velocity[4], velocity[2]])
        return np.array(twists)

    def finger_force_n(self) -> FloatArray:
        """Total force [2] (world x, y, N) of the object on both pads, as the tactile sum."""
        return pad_forces(self.model, self.data, self.index.pad_geoms)[:, :2].sum(axis=0)

    def drive(self, arm_pose: FloatArray, velocity: FloatArray, dt_s: float) -> None:
        """Step ``dt_s`` with the gripper at ``velocity`` [4] from ``arm_pose`` [4], its
        servo's target put where it leads that pose by the servo's lag (its speed and the
        finger force over its stiffness), so that no lag adds up over many steps."""
        load = np.zeros(4)
        load[:2] = self.finger_force_n()
        target = arm_pose + (self._servo_kv * velocity - load) / self._servo_kp
        self.data.act[self._servo_act] = target
        self.data.ctrl[self.index.arm_actuators] = velocity
        mujoco.mj_step(self.model, self.data, nstep=max(1, round(dt_s / TIMESTEP_S)))

    def refresh(self) -> None:
        """Make :meth:`link_poses`, :meth:`link_twists` and :meth:`finger_force_n` those of
        the state reached: after ``mj_step`` they are one simulator step behind, as the
        ``sim.mujoco`` world records them. (It also sets the solver's warm start, so a
        replay that refreshed steps on differently.)"""
        mujoco.mj_forward(self.model, self.data)
