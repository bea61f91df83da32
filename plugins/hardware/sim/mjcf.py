"""The MJCF model of the simulated world, built as a string from an :class:`ObjectSpec`.

Contents: a table plane at z = 0; the object's links as bodies with extruded convex-mesh geoms,
the true mass and CoM as each body's ``inertial``; a Cartesian two-finger gripper.

Friction. A contact takes the friction of the geom with the higher ``priority``: the object
(priority 1) wins against the table (0), so object-table friction is the link's friction; the
finger pads (priority 2, friction :data:`PAD_FRICTION`) win against the object, so a grasp holds
while pulling.
A hinge's friction (``frictionloss``) is made nearly hard (:data:`HINGE_SOLIMP`): below its
friction torque the hinge holds, above it slips.

Gripper. The gripper body slides along world x, y, z and turns about z (yaw); each of the four
joints has an ``intvelocity`` actuator: its control is a velocity, its activation is the
integrated position target (limited by ``actrange`` = the arm's workspace) and a stiff, critically
damped servo tracks it. The tool centre point (TCP) is the body origin, midway between the pads.
The fingers slide along the gripper's local x axis (the closing axis); finger 0 is on the +x
side. Each finger is one box geom, the tactile pad. The palm is visible to rays (it occludes the
camera) but does not collide.

Contacts use elliptic friction cones with ``impratio`` 10: stiffer static friction, so a grasped
link does not creep out of the fingers while pulling.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from vistac.objects import ObjectSpec, attachment, polygon_area, polygon_second_moments
from vistac.types import FloatArray

GRAVITY_MPS2 = 9.81
PAD_FRICTION = 1.0
PAD_HALF_SIZE_M = (0.005, 0.012, 0.03)
"""Finger box half sizes: along the closing axis, across it, vertical."""
PAD_CENTRE_Z_M = 0.02
"""Height of the finger box centre above the TCP (the box spans TCP z - 0.01 .. + 0.05)."""
ARM_JOINTS = ("arm_x", "arm_y", "arm_z", "arm_yaw")
FINGER_JOINTS = ("finger0", "finger1")
PAD_GEOMS = ("pad0", "pad1")
HINGE_SOLIMP = (0.999, 0.9999, 0.001, 0.5, 2.0)
"""``solimpfriction`` of a hinge, so that its friction holds. MuJoCo's default impedance (0.9,
0.95) makes dry friction a soft constraint: a loaded hinge crept at a rate set by the solver's
regularisation, not by its friction (10-30 deg in a test push at 0.35, 0.6 or 5 N m alike);
with this, 0.3-0.6 deg."""

_GRIPPER_MASS_KG = 2.0
_FINGER_MASS_KG = 0.05
_ARM_KP = 2.0e4
_YAW_KP = 50.0
_FINGER_KP = 1000.0
_FINGER_FORCE_N = 15.0
_FINGER_SPEED_MPS = 0.1
"""Closing (and opening) speed of each finger: its slide's damping is the force limit over
this. A real parallel gripper closes at 0.02-0.15 m/s; undamped, the force-limited fingers
hit the object at metres per second, tunnel into it within a physics step, and the contact
resolves the overlap by lifting the pads onto the object's top."""


@dataclass(frozen=True)
class GripperGeometry:
    """Gripper dimensions shared by the model and the sim devices."""

    max_opening_m: float

    @property
    def max_finger_travel_m(self) -> float:
        """Travel of each finger from closed (pads touching) to fully open."""
        return 0.5 * self.max_opening_m


def _vec(values: FloatArray | tuple[float, ...] | list[float]) -> str:
    return " ".join(f"{float(v):.9g}" for v in values)


def _prism_inertia(polygon: FloatArray, height_m: float, mass_kg: float) -> FloatArray:
    """Uniform extruded prism inertia about its centroid: [6] = (xx, yy, zz, xy, xz, yz)."""
    area = polygon_area(polygon)
    x2, y2, xy = polygon_second_moments(polygon) * mass_kg / area
    vertical = mass_kg * height_m**2 / 12.0
    return np.array([y2 + vertical, x2 + vertical, x2 + y2, -xy, 0.0, 0.0])


def _mesh_asset(name: str, polygon: FloatArray, height_m: float) -> str:
    bottom = np.column_stack([polygon, np.zeros(len(polygon))])
    top = np.column_stack([polygon, np.full(len(polygon), height_m)])
    return f'<mesh name="{name}" vertex="{_vec(np.concatenate([bottom, top]).ravel())}"/>'


def _link_body(spec: ObjectSpec, index: int, pos: FloatArray, euler_z: float, inner: str) -> str:
    link = spec.links[index]
    polygon = link.polygon()
    com = [link.com_m[0], link.com_m[1], 0.5 * link.height_m]
    inertia = _prism_inertia(polygon, link.height_m, link.mass_kg)
    friction = f"{link.friction:.6g} 0.005 0.0001"
    return (
        f'<body name="link{index}" pos="{_vec(pos)}" euler="0 0 {euler_z:.9g}">'
        f"{inner}"
        f'<inertial pos="{_vec(com)}" mass="{link.mass_kg:.9g}" fullinertia="{_vec(inertia)}"/>'
        f'<geom name="link{index}_geom" type="mesh" mesh="link{index}_mesh" priority="1" '
        f'friction="{friction}" contype="1" conaffinity="3" rgba="0.8 0.5 0.2 1"/>'
    )


def _object_bodies(spec: ObjectSpec) -> str:
    x, y, theta = spec.pose
    root = _link_body(spec, 0, np.array([x, y, 0.0]), theta, '<freejoint name="object"/>')
    if len(spec.links) == 1:
        return root + "</body>"
    offset, hinge = attachment(spec)
    joint = ""
    if hinge is not None and spec.joint is not None:
        hinge_in_child = np.append(hinge - offset, 0.0)
        joint = (
            f'<joint name="hinge" type="hinge" axis="0 0 1" pos="{_vec(hinge_in_child)}" '
            f'frictionloss="{spec.joint.friction_nm:.9g}" damping="{spec.joint.damping_nms:.9g}" '
            f'solimpfriction="{_vec(HINGE_SOLIMP)}"/>'
        )
    child = _link_body(spec, 1, np.append(offset, 0.0), 0.0, joint) + "</body>"
    return root + child + "</body>"


def _finger(index: int, sign: float) -> str:
    hx, hy, hz = PAD_HALF_SIZE_M
    return (
        f'<body name="finger{index}" gravcomp="1">'
        f'<joint name="finger{index}" type="slide" axis="{sign:g} 0 0" '
        f'damping="{_FINGER_FORCE_N / _FINGER_SPEED_MPS:g}"/>'
        f'<inertial pos="{sign * hx:g} 0 {PAD_CENTRE_Z_M:g}" mass="{_FINGER_MASS_KG:g}" '
        f'diaginertia="1e-5 1e-5 1e-5"/>'
        f'<geom name="pad{index}" type="box" size="{hx:g} {hy:g} {hz:g}" '
        f'pos="{sign * hx:g} 0 {PAD_CENTRE_Z_M:g}" priority="2" '
        f'friction="{PAD_FRICTION:g} 0.005 0.0001" contype="2" conaffinity="1" '
        f'rgba="0.2 0.2 0.8 1"/>'
        f"</body>"
    )


def _gripper(geometry: GripperGeometry) -> str:
    palm_half_x = geometry.max_finger_travel_m + 2 * PAD_HALF_SIZE_M[0]
    palm_z = PAD_CENTRE_Z_M + PAD_HALF_SIZE_M[2] + 0.01
    return (
        '<body name="gripper" gravcomp="1">'
        + "".join(
            f'<joint name="{name}" type="{kind}" axis="{axis}"/>'
            for name, kind, axis in zip(
                ARM_JOINTS,
                ("slide", "slide", "slide", "hinge"),
                ("1 0 0", "0 1 0", "0 0 1", "0 0 1"),
                strict=True,
            )
        )
        + f'<inertial pos="0 0 {palm_z:g}" mass="{_GRIPPER_MASS_KG:g}" '
        'diaginertia="0.01 0.01 0.01"/>'
        f'<geom name="palm" type="box" size="{palm_half_x:g} 0.02 0.01" pos="0 0 {palm_z:g}" '
        'contype="0" conaffinity="0" rgba="0.3 0.3 0.3 1"/>'
        + _finger(0, 1.0)
        + _finger(1, -1.0)
        + "</body>"
    )


def _actuators(geometry: GripperGeometry) -> str:
    mass = _GRIPPER_MASS_KG + 2 * _FINGER_MASS_KG
    arm_kv = 2.0 * np.sqrt(_ARM_KP * mass)
    yaw_kv = 2.0 * np.sqrt(_YAW_KP * 0.01)
    finger_kv = 2.0 * np.sqrt(_FINGER_KP * _FINGER_MASS_KG)
    servos = [
        f'<intvelocity name="{name}" joint="{name}" kp="{kp:.6g}" kv="{kv:.6g}" '
        f'actrange="-1000 1000"/>'
        for name, kp, kv in zip(
            ARM_JOINTS, (_ARM_KP,) * 3 + (_YAW_KP,), (arm_kv,) * 3 + (yaw_kv,), strict=True
        )
    ]
    fingers = [
        f'<position name="{name}" joint="{name}" kp="{_FINGER_KP:g}" kv="{finger_kv:.6g}" '
        f'ctrlrange="0 {geometry.max_finger_travel_m:.6g}" forcerange="-{_FINGER_FORCE_N:g} '
        f'{_FINGER_FORCE_N:g}"/>'
        for name in FINGER_JOINTS
    ]
    return "<actuator>" + "".join(servos + fingers) + "</actuator>"


def gravity_vector(tilt_rad: float) -> FloatArray:
    """Gravity [3] for a table tilted by ``tilt_rad`` about world x (+y edge raised)."""
    return GRAVITY_MPS2 * np.array([0.0, -np.sin(tilt_rad), -np.cos(tilt_rad)])


def build_mjcf(
    spec: ObjectSpec, geometry: GripperGeometry, timestep_s: float, tilt_rad: float
) -> str:
    """The complete MJCF document of the world."""
    meshes = "".join(
        _mesh_asset(f"link{i}_mesh", link.polygon(), link.height_m)
        for i, link in enumerate(spec.links)
    )
    return (
        f'<mujoco model="vistac_{spec.name}">'
        '<compiler angle="radian"/>'  # MJCF's default unit is degrees; vistac's are radians
        f'<option timestep="{timestep_s:.9g}" integrator="implicitfast" '
        'cone="elliptic" impratio="10" '
        f'gravity="{_vec(gravity_vector(tilt_rad))}"/>'
        f"<asset>{meshes}</asset>"
        "<worldbody>"
        '<geom name="table" type="plane" size="1 1 0.01" contype="1" conaffinity="1" '
        'friction="0.3 0.005 0.0001" rgba="0.9 0.9 0.9 1"/>'
        f"{_object_bodies(spec)}{_gripper(geometry)}"
        "</worldbody>"
        f"{_actuators(geometry)}"
        "</mujoco>"
    )
