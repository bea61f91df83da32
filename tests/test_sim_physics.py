"""Physics sanity of the simulated world, devices and the Cartesian executor."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from simctx import TestContext, add_camera, box_object, sim_setup
from vistac.component import Component
from vistac.errors import HardwareError, SafetyError
from vistac.objects import HINGE_GAP_M, ObjectSpec, link_frames
from vistac.plugins.actions import plugin as actions_plugin
from vistac.plugins.actions.executor import CartesianExecutor
from vistac.plugins.hardware.sim import plugin as sim_plugin
from vistac.plugins.hardware.sim.world import MujocoWorld
from vistac.protocols import PROTOCOLS
from vistac.registry import Registry
from vistac.types import Action, Pull, Push, Viewpoint

DT_S = 1.0 / 15.0
PUSH_UP = Push(cp_m=np.array([0.0, 0.405]), pd_rad=math.pi / 2, speed_mps=0.02)


def execute(
    ctx: TestContext,
    action: Action,
    tcp_z_m: list[float] | None = None,
    poses: list[np.ndarray] | None = None,
    **options: Any,
) -> np.ndarray:
    """Run ``action`` to the end with a CartesianExecutor of ``options``; returns the tactile
    forces [T, 2, 2] of the interaction (and appends the TCP height of each of its steps to
    ``tcp_z_m``, the object's link poses [L, 3] to ``poses``)."""
    executor: CartesianExecutor = ctx.add(CartesianExecutor, **options)
    world: MujocoWorld = ctx.find("world")
    executor.start(action)
    forces: list[np.ndarray] = []
    for _ in range(5000):
        phase, interacting = executor.step(DT_S)
        if phase == "done":
            return np.array(forces)
        world.step(DT_S)
        if interacting:
            forces.append(ctx.find("tactile").read().force_n)
            if tcp_z_m is not None:
                tcp_z_m.append(float(ctx.find("arm").state().pose[2]))
            if poses is not None:
                poses.append(world.link_poses().copy())
    raise AssertionError("the action did not finish")


def push_force_n(tmp_path: Path, **link: Any) -> float:
    """Mean total pad force over the last 2 s of a straight push through the CoM."""
    forces = execute(sim_setup(tmp_path, box_object(link=link)), PUSH_UP)
    assert len(forces) == 75
    return float(np.linalg.norm(forces[-30:].sum(axis=1), axis=1).mean())


def test_push_moves_box_along_pd_and_force_matches_coulomb(tmp_path: Path) -> None:
    ctx = sim_setup(tmp_path, box_object())
    forces = execute(ctx, PUSH_UP)
    x, y, theta = ctx.find("world").link_poses()[0]
    # 5 s at 20 mm/s, minus the 10 mm standoff before contact.
    assert y - 0.45 == pytest.approx(0.09, abs=0.004)
    assert abs(x) < 1e-3 and abs(theta) < 0.01
    total = forces[-30:].sum(axis=1).mean(axis=0)
    assert total[1] == pytest.approx(-0.3 * 0.5 * 9.81, rel=0.15), "object pushes back on the pad"
    assert abs(total[0]) < 0.05


@pytest.mark.parametrize(("back_off_m", "moves"), [(0.02, False), (0.0, True)])
def test_the_pad_backs_off_before_it_rises_and_leaves_the_object_where_the_push_did(
    tmp_path: Path, back_off_m: float, moves: bool
) -> None:
    """Between pushes nobody watches the object, so it must stay where the observed push
    left it. A pad lifted while it still presses on a heavy box drags the box on (and can
    tip a tall one over); backing off along -pd first leaves it within a millimetre."""
    ctx = sim_setup(tmp_path, box_object(link={"mass_kg": 1.5, "friction": 0.45}))
    poses: list[np.ndarray] = []
    execute(ctx, PUSH_UP, poses=poses, back_off_m=back_off_m)
    after = ctx.find("world").link_poses()[0] - poses[-1][0]
    assert abs(after[2]) < 0.01
    assert bool(np.hypot(*after[:2]) > 0.0025) is moves, f"moved {after[:2]} m after the push"


ON_TOP = Push(cp_m=np.array([0.0, 0.47]), pd_rad=math.pi / 2, speed_mps=0.02)
"""A push whose pre-contact point lies on the box: the believed pose is off."""


def test_a_descent_onto_the_object_fails_as_blocked_when_told_to(tmp_path: Path) -> None:
    """The fingers must not press into the box until the workspace floor: the stalled
    descent stops the arm, and with ``on_blocked_descent: fail`` the action fails."""
    ctx = sim_setup(tmp_path, box_object())
    world = ctx.find("world")
    with pytest.raises(HardwareError, match=r"'descend' move is blocked at .* something in"):
        execute(ctx, ON_TOP, on_blocked_descent="fail")
    np.testing.assert_array_equal(world.data.ctrl[world.index.arm_actuators], 0.0)
    x, y, _ = world.link_poses()[0]
    assert abs(x) < 1e-3 and abs(y - 0.45) < 1e-3, "the object was not shoved"
    assert ctx.find("arm").state().pose[2] > 0.03, "the fingers stayed on the box"


def test_a_blocked_descent_lifts_the_arm_off_and_parks_it_without_an_interaction(
    tmp_path: Path,
) -> None:
    ctx = sim_setup(tmp_path, box_object())
    world = ctx.find("world")
    assert len(execute(ctx, ON_TOP)) == 0, "no interaction step"
    blocked_at = ctx.find("executor").blocked_at_m
    # Stopped over the pre-contact point (20 mm behind the contact point), on the box's top.
    np.testing.assert_allclose(blocked_at[:2], [0.0, 0.45], atol=0.003)
    assert 0.05 < blocked_at[2] < 0.08
    park = CartesianExecutor.Config().park_pose
    assert park is not None
    np.testing.assert_allclose(ctx.find("arm").state().pose, park, atol=0.003)
    x, y, _ = world.link_poses()[0]
    assert abs(x) < 1e-3 and abs(y - 0.45) < 1e-3, "the object was not shoved"
    ctx.find("executor").start(PUSH_UP)  # the next action starts afresh
    assert ctx.find("executor").blocked_at_m is None


def test_heavier_object_needs_more_force(tmp_path: Path) -> None:
    light = push_force_n(tmp_path / "a", mass_kg=0.3)
    heavy = push_force_n(tmp_path / "b", mass_kg=1.2)
    assert heavy > 3.0 * light


def test_higher_friction_needs_more_force(tmp_path: Path) -> None:
    low = push_force_n(tmp_path / "a", friction=0.15)
    high = push_force_n(tmp_path / "b", friction=0.45)
    assert high > 2.5 * low


def test_push_off_the_com_line_rotates_the_box(tmp_path: Path) -> None:
    central = sim_setup(tmp_path / "a", box_object())
    offset = sim_setup(tmp_path / "b", box_object())
    execute(central, PUSH_UP)
    execute(offset, Push(cp_m=np.array([0.03, 0.405]), pd_rad=math.pi / 2, speed_mps=0.02))
    assert abs(central.find("world").link_poses()[0, 2]) < 0.01
    # Pushed right of the CoM along +y: the box turns counter-clockwise.
    assert offset.find("world").link_poses()[0, 2] > 0.2


def _two_rects(kind: str) -> dict[str, Any]:
    link = box_object()["links"][0]
    spec: dict[str, Any] = {"name": kind, "type": kind, "pose": [-0.047, 0.45, 0.0]}
    spec["links"] = [link, link]
    if kind == "articulated":
        spec["joint"] = {"friction_nm": 0.0}
    return spec


def _hinge_from(pose: np.ndarray, local_x_m: float) -> np.ndarray:
    """World position [2] of the point (local_x_m, 0) of a link frame pose [3]."""
    return pose[:2] + local_x_m * np.array([np.cos(pose[2]), np.sin(pose[2])])


@pytest.mark.parametrize("kind", ["heterogeneous", "articulated"])
def test_articulated_free_link_swings_about_the_hinge(tmp_path: Path, kind: str) -> None:
    ctx = sim_setup(tmp_path, _two_rects(kind))
    world = ctx.find("world")
    # Push link 0 left of the pair's CoM: the pair turns clockwise.
    execute(ctx, Push(cp_m=np.array([-0.07, 0.405]), pd_rad=math.pi / 2, speed_mps=0.02))
    poses = world.link_poses()
    assert poses[0, 2] < -0.3
    relative_rad = poses[1, 2] - poses[0, 2]
    if kind == "heterogeneous":
        assert abs(relative_rad) < 1e-3, "welded links keep their relative pose"
        return
    assert relative_rad > 0.3, "the free link trails behind, turning less than link 0"
    # Both links still meet at the hinge (47 mm + half the gap from each frame).
    half_m = 0.045 + HINGE_GAP_M / 2
    np.testing.assert_allclose(
        _hinge_from(poses[0], half_m), _hinge_from(poses[1], -half_m), atol=1e-3
    )


def test_a_hinge_its_friction_holds_does_not_creep(tmp_path: Path) -> None:
    """The push that swings a free link, with the hinge's friction at the object set's most
    (0.5 N m) against a load of about 0.1 N m: the pair turns as one. (With MuJoCo's default
    soft friction constraint such a hinge crept 10-30 deg in a push whatever its friction.)"""
    spec = _two_rects("articulated")
    spec["joint"]["friction_nm"] = 0.5
    ctx = sim_setup(tmp_path, spec)
    execute(ctx, Push(cp_m=np.array([-0.07, 0.405]), pd_rad=math.pi / 2, speed_mps=0.02))
    poses = ctx.find("world").link_poses()
    assert poses[0, 2] < -0.3
    assert abs(poses[1, 2] - poses[0, 2]) < math.radians(1.0)


@pytest.mark.parametrize("kind", ["homogeneous", "heterogeneous", "articulated"])
def test_the_object_spawns_at_its_spec_pose_in_radians(tmp_path: Path, kind: str) -> None:
    """The link poses at the start are ``link_frames`` of the spec, its yaw in radians (MJCF
    reads angles in degrees unless told otherwise: 1.2 rad once spawned as 1.2 degrees)."""
    spec = _two_rects(kind) if kind != "homogeneous" else box_object()
    spec["pose"] = [0.01, 0.46, 1.2]
    world = sim_setup(tmp_path, spec).find("world")
    expected = link_frames(ObjectSpec.model_validate(spec))
    np.testing.assert_allclose(world.link_poses(), expected, atol=1e-9)
    for _ in range(5):
        world.step(DT_S)
    np.testing.assert_allclose(world.link_poses(), expected, atol=1e-4)  # it rests there


@pytest.mark.parametrize(("friction", "slides"), [(0.1, True), (0.5, False)])
def test_tilted_table(tmp_path: Path, friction: float, slides: bool) -> None:
    # tan(0.3 rad) = 0.31: between the two friction coefficients.
    ctx = sim_setup(tmp_path, box_object(link={"friction": friction}), table_tilt_rad=0.3)
    world = ctx.find("world")
    for _ in range(15):
        world.step(DT_S)
    moved_m = 0.45 - world.link_poses()[0, 1]
    assert (moved_m > 0.05) == slides
    assert moved_m < 0.001 or slides
    assert world.ground_truth()["table_tilt_rad"] == pytest.approx(0.3)


def test_pull_moves_the_grasped_link_along_pd(tmp_path: Path) -> None:
    ctx = sim_setup(tmp_path, box_object())
    pull = Pull(gp_m=np.array([0.0, 0.45]), pd_rad=-math.pi / 2, speed_mps=0.02, grasp_axis_rad=0.0)
    forces = execute(ctx, pull)
    x, y, _ = ctx.find("world").link_poses()[0]
    assert 0.45 - y == pytest.approx(0.1, abs=0.004)
    assert abs(x) < 1e-3
    # Both pads squeeze the box (opposite x forces) and are dragged back by it (+y).
    last = forces[-10:].mean(axis=0)
    assert last[0, 0] * last[1, 0] < 0 and min(abs(last[:, 0])) > 5.0
    assert last[:, 1].sum() == pytest.approx(0.3 * 0.5 * 9.81, rel=0.15)


@pytest.mark.parametrize("footprint", ["hexagon", "ellip1"])
def test_a_grasp_across_slanted_or_round_sides_holds_at_finger_height(
    tmp_path: Path, footprint: str
) -> None:
    """The fingers close at a gripper's speed: they stop on the sides instead of tunnelling
    into the object and being lifted onto its top (which read 10-16 times the friction)."""
    link = {"footprint": footprint, "height_m": 0.043, "mass_kg": 1.14, "friction": 0.23}
    ctx = sim_setup(tmp_path, box_object(link=link, pose=[0.0, 0.45, 0.047]))
    pull = Pull(gp_m=np.array([0.0, 0.45]), pd_rad=-1.41, speed_mps=0.02, grasp_axis_rad=0.5857)
    tcp_z_m: list[float] = []
    forces = execute(ctx, pull, tcp_z_m)
    assert max(tcp_z_m) < 0.025  # finger height 0.02 m; the box is 0.05 m tall
    moved_m = np.linalg.norm(ctx.find("world").link_poses()[0][:2] - [0.0, 0.45])
    assert moved_m == pytest.approx(0.1, abs=0.01)
    pulled_n = np.linalg.norm(forces[-30:].sum(axis=1), axis=1).mean()
    assert pulled_n == pytest.approx(0.23 * 1.14 * 9.81, rel=0.25)


def test_gripper_detects_object_only_when_stalled_on_it(tmp_path: Path) -> None:
    ctx = sim_setup(tmp_path, box_object(), gripper_start=(0.0, 0.45, 0.02, 0.0))
    gripper, world = ctx.find("gripper"), ctx.find("world")
    gripper.close()
    for _ in range(10):
        world.step(DT_S)
    state = gripper.state()
    assert state.object_detected and not state.moving
    assert state.width_m == pytest.approx(0.09, abs=0.003)
    gripper.open()
    world.step(DT_S)
    assert not gripper.state().object_detected


def test_tactile_bias_zeroes_the_current_reading(tmp_path: Path) -> None:
    ctx = sim_setup(tmp_path, box_object(), gripper_start=(0.0, 0.45, 0.02, 0.0))
    ctx.find("gripper").close()
    for _ in range(10):
        ctx.find("world").step(DT_S)
    tactile = ctx.find("tactile")
    assert np.abs(tactile.read().force_n).max() > 5.0
    tactile.bias()
    np.testing.assert_allclose(tactile.read().force_n, 0.0, atol=1e-9)


def test_arm_speed_never_exceeds_the_cap(tmp_path: Path) -> None:
    ctx = sim_setup(tmp_path, box_object())
    arm, world = ctx.find("arm"), ctx.find("world")
    start = arm.state().pose
    speeds = []
    for _ in range(30):
        arm.command_velocity(np.array([1.0, -1.0, 0.5, 0.0]))
        world.step(DT_S)
        speeds.append(np.linalg.norm(arm.state().twist[:3]))
    assert max(speeds) <= arm.max_speed_mps * 1.001
    assert speeds[-1] == pytest.approx(arm.max_speed_mps, rel=0.01)
    travelled = np.linalg.norm(arm.state().pose[:3] - start[:3])
    assert travelled == pytest.approx(0.025 * 2.0, abs=0.002)


def test_arm_stops_at_the_workspace_boundary_and_refuses_to_leave(tmp_path: Path) -> None:
    ctx = sim_setup(tmp_path, box_object())
    arm, world = ctx.find("arm"), ctx.find("world")
    arm.command_velocity(np.array([0.0, 0.0, -0.025, 0.0]))
    for _ in range(90):  # held for 6 s: from z = 0.12 at 25 mm/s it would reach z = -0.03
        world.step(DT_S)
    assert arm.state().pose[2] == pytest.approx(0.015, abs=5e-4)
    with pytest.raises(SafetyError, match=r"z min = 0\.015"):
        arm.command_velocity(np.array([0.01, 0.0, -0.01, 0.0]))
    np.testing.assert_array_equal(world.data.ctrl[world.index.arm_actuators], 0.0)
    arm.command_velocity(np.array([0.0, 0.0, 0.02, 0.0]))  # back inside: accepted
    world.step(DT_S)
    assert arm.state().pose[2] > 0.015


def test_world_time_follows_the_requested_steps(tmp_path: Path) -> None:
    world = sim_setup(tmp_path, box_object()).find("world")
    for _ in range(75):
        world.step(DT_S)
    assert world.time_s == pytest.approx(5.0, abs=0.001)
    world.reset(0)
    assert world.time_s == 0.0


def _top_view(ctx: TestContext, **camera: Any) -> np.ndarray:
    cam = add_camera(ctx, **camera)
    cam.move_to(Viewpoint(eye_m=np.array([0.0, 0.45, 0.5]), target_m=np.array([0.0, 0.45, 0.0])))
    return cam.capture().depth_m


def test_camera_sees_the_box_top_at_its_height(tmp_path: Path) -> None:
    ctx = sim_setup(tmp_path, box_object())
    cam = add_camera(ctx, dropout_prob=0.0)
    cam.move_to(Viewpoint(eye_m=np.array([0.0, 0.45, 0.5]), target_m=np.array([0.0, 0.45, 0.0])))
    rgbd = cam.capture()
    assert rgbd.depth_m.shape == (240, 320)
    assert rgbd.depth_m[120, 160] == pytest.approx(0.45, abs=0.008)
    points = rgbd.point_cloud().points_m
    on_box = (np.abs(points[:, 0]) < 0.04) & (np.abs(points[:, 1] - 0.45) < 0.04)
    assert on_box.sum() > 1000
    np.testing.assert_allclose(points[on_box, 2], 0.05, atol=0.008)
    assert abs(points[on_box, 2].mean() - 0.05) < 5e-4
    table = (np.abs(points[:, 0]) > 0.1) & (points[:, 1] > 0.3)
    np.testing.assert_allclose(points[table, 2], 0.0, atol=0.02)


def test_a_short_range_keeps_every_pixel_whose_depth_is_within_it(tmp_path: Path) -> None:
    """The range limits depth, not the distance along a ray: a box top at depth 0.5 m seen
    off-axis (rays up to 0.62 m long) stays whole with a 0.52 m range."""
    depths = []
    for max_range_m in (3.0, 0.52):
        ctx = sim_setup(tmp_path / str(max_range_m), box_object(pose=[0.38, 0.45, 0.0]))
        cam = add_camera(ctx, dropout_prob=0.0, depth_noise_m=0.0, max_range_m=max_range_m)
        eye, target = np.array([0.0, 0.45, 0.55]), np.array([0.0, 0.45, 0.0])
        cam.move_to(Viewpoint(eye_m=eye, target_m=target))
        depths.append(cam.capture().depth_m)
    top = np.abs(depths[0] - 0.5) < 1e-6
    assert top.sum() > 500
    np.testing.assert_allclose(depths[1][top], 0.5, atol=1e-6)
    assert np.isnan(depths[1][depths[0] > 0.52]).all()  # the table beyond the range


def test_camera_dropouts_are_nan_and_resampling_works(tmp_path: Path) -> None:
    ctx = sim_setup(tmp_path, box_object())
    clean = _top_view(ctx, dropout_prob=0.0)
    assert not np.isnan(clean).any()
    ctx = sim_setup(tmp_path, box_object())
    dropped = _top_view(ctx, dropout_prob=0.3)
    assert np.isnan(dropped).mean() == pytest.approx(0.3, abs=0.02)
    small = ctx.find("camera").capture(64, 48)
    assert small.depth_m.shape == (48, 64) and small.intrinsics.width == 64


def test_gripper_occludes_the_camera(tmp_path: Path) -> None:
    free = _top_view(sim_setup(tmp_path / "a", box_object()), dropout_prob=0.0, depth_noise_m=0.0)
    ctx = sim_setup(tmp_path / "b", box_object(), gripper_start=(0.0, 0.45, 0.15, 0.0))
    occluded = _top_view(ctx, dropout_prob=0.0, depth_noise_m=0.0)
    assert free[120, 160] == pytest.approx(0.45, abs=1e-6)
    assert occluded[120, 160] == pytest.approx(0.5 - 0.15 - 0.07, abs=1e-6), "palm top"


def test_components_implement_their_protocols(tmp_path: Path) -> None:
    ctx = sim_setup(tmp_path, box_object())
    add_camera(ctx)
    executor = ctx.add(CartesianExecutor)
    for kind, protocol in PROTOCOLS.items():
        component = executor if kind == "executor" else ctx.find(kind)
        if component is not None:
            assert isinstance(component, protocol), kind
    assert isinstance(ctx.find("world"), PROTOCOLS["world"])


def test_plugins_register_loadable_components() -> None:
    registry = Registry()
    actions_plugin.vistac_register(registry)
    sim_plugin.vistac_register(registry)
    assert registry.load("actions.cartesian", "executor") is CartesianExecutor
    assert registry.load("sim.mujoco", "world") is MujocoWorld
    for name in ("sim.arm", "sim.gripper", "sim.depth_camera", "sim.tactile"):
        assert issubclass(registry.load(name), Component)
