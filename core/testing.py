"""Conformance checks per component kind, for vistac's own plugins and third-party ones.

Use from pytest::

    from vistac.testing import build_components, check_component

    def test_my_camera(tmp_path):
        ctx = build_components({"world": {"plugin": "sim.mujoco", "with": {...}},
                                "camera": {"plugin": "my.camera"}}, tmp_path)
        check_component(ctx.component("camera"), advance=ctx.clock.advance)

Each check raises ``AssertionError`` naming the broken promise. ``advance(dt_s)`` moves time
forward (the world's physics in simulation, a sleep on hardware).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import BaseModel
from vistac.pluginmanager import Plugins, load_plugins
from vistac.protocols import KINDS, PROTOCOLS, Scene
from vistac.recording import RunRecorder
from vistac.run import RunContext
from vistac.skill import validate_skill
from vistac.types import (
    RGBD,
    ArmState,
    FloatArray,
    GripperState,
    PixelWindow,
    PointCloud,
    Pull,
    Push,
    ShapeEstimate,
    Superquadric,
    TactileReading,
    Viewpoint,
)

Advance = Callable[[float], None]


def build_components(
    components: dict[str, dict[str, Any]],
    out_dir: Path,
    seed: int = 0,
    skill_dir: Path | None = None,
    plugins: Plugins | None = None,
) -> RunContext:
    """Validate ``{role: {plugin, with}}`` like a skill and return a context that builds
    them (``ctx.component(role)``); the world, if any, is built and reset."""
    plugins = plugins or load_plugins()
    data = {
        "version": 1,
        "name": "conformance",
        "seed": seed,
        "components": components,
        "tree": "stop",
    }
    skill = validate_skill(data, (skill_dir or Path.cwd()) / "conformance.yaml", plugins.registry)
    out_dir.mkdir(parents=True, exist_ok=True)
    ctx = RunContext(skill, plugins, RunRecorder(out_dir), seed)
    ctx.build_all()
    return ctx


def _sleep(dt_s: float) -> None:
    time.sleep(dt_s)


def check_component_class(cls: type) -> None:
    """A component class declares a known ``kind`` and a strict pydantic ``Config``."""
    kind = getattr(cls, "kind", None)
    assert kind in KINDS, f"{cls.__name__}.kind = {kind!r} is not one of {KINDS}"
    config = getattr(cls, "Config", None)
    assert isinstance(config, type) and issubclass(config, BaseModel), (
        f"{cls.__name__} needs a pydantic Config"
    )
    assert config.model_config.get("extra") == "forbid", (
        f"{cls.__name__}.Config must forbid unknown keys"
    )
    config()  # every option has a default or the class documents required ones


def check_component(instance: Any, kind: str | None = None, advance: Advance | None = None) -> None:
    """Check ``instance`` against the protocol of its kind and the behaviour it promises."""
    kind = kind or type(instance).kind
    protocol = PROTOCOLS.get(kind)
    if protocol is not None:
        assert isinstance(instance, protocol), (
            f"{type(instance).__name__} does not implement {protocol.__name__}"
        )
    checker = _CHECKS.get(kind)
    if checker is not None:
        checker(instance, advance or _sleep)


def _check_world(world: Any, advance: Advance) -> None:
    world.reset(0)
    start_s = world.time_s
    world.step(0.1)
    if world.simulated:
        assert abs(world.time_s - start_s - 0.1) < 1e-6, (
            "a simulated world's step(dt) advances time_s by dt"
        )
    truth = world.ground_truth()
    assert truth is None or isinstance(truth, dict), "ground_truth() returns a dict or None"


def _check_arm(arm: Any, advance: Advance) -> None:
    state = arm.state()
    assert isinstance(state, ArmState), "state() returns an ArmState"
    assert arm.max_speed_mps > 0, "max_speed_mps must be positive"
    arm.command_velocity(np.array([10 * arm.max_speed_mps, 0.0, 0.0, 0.0]))
    advance(0.2)
    speed = float(np.linalg.norm(arm.state().twist[:3]))
    assert speed <= arm.max_speed_mps * 1.05, (
        f"speed {speed:.4f} m/s above the cap {arm.max_speed_mps} m/s"
    )
    arm.stop()
    advance(0.2)
    stopped = float(np.linalg.norm(arm.state().twist[:3]))
    assert stopped < 1e-3, f"the arm still moves at {stopped:.4f} m/s after stop()"
    arm.stop()  # stopping twice is allowed
    later = arm.state()
    assert later.timestamp_s >= state.timestamp_s, "timestamps never go back"


def _check_gripper(gripper: Any, advance: Advance) -> None:
    gripper.open()
    advance(1.0)
    opened = gripper.state()
    assert isinstance(opened, GripperState), "state() returns a GripperState"
    gripper.close()
    advance(1.0)
    closed = gripper.state()
    assert closed.width_m < opened.width_m, "close() narrows the gripper"
    gripper.stop()


def _check_camera(camera: Any, advance: Advance) -> None:
    frame = camera.capture()
    assert isinstance(frame, RGBD), "capture() returns an RGBD"
    small = camera.capture(32, 24)
    assert small.depth_m.shape == (24, 32), "capture(width, height) resamples"
    window = PixelWindow(2, 1, 8, 6)
    crop = camera.capture(window=window)
    assert crop.depth_m.shape == (6, 8), "capture(window=...) crops"
    assert crop.intrinsics == frame.intrinsics.cropped(window), "the crop's intrinsics match"
    assert camera.capture(16, 12, window).depth_m.shape == (12, 16), "crop, then resample"
    if camera.movable:
        camera.move_to(Viewpoint(np.array([0.3, 0.2, 0.5]), np.array([0.0, 0.45, 0.0])))
        moved = camera.capture()
        assert not np.allclose(moved.world_from_camera, frame.world_from_camera), (
            "move_to moves the camera"
        )


def _check_tactile(tactile: Any, advance: Advance) -> None:
    reading = tactile.read()
    assert isinstance(reading, TactileReading), "read() returns a TactileReading"
    assert reading.force_n.shape[0] >= 1, "at least one pad"
    tactile.bias()
    advance(0.1)
    assert tactile.read().timestamp_s >= reading.timestamp_s, "timestamps never go back"


def _check_view_planner(planner: Any, advance: Advance) -> None:
    views = 0
    while planner.next_view(None, None, views) is not None:
        views += 1
        assert views < 100, "next_view must eventually return None"


def _reference_scene() -> Scene:
    """A 9 cm cube's top face and sides at (0, 0.45) on the table."""
    grid = np.linspace(-0.045, 0.045, 10)
    xx, yy = np.meshgrid(grid, grid)
    top = np.stack([xx.ravel(), yy.ravel() + 0.45, np.full(xx.size, 0.05)], axis=1)
    return Scene(PointCloud(top))


def two_box_scene() -> Scene:
    """Two fitted 100 x 80 x 50 mm boxes side by side at y = 0.45 m (links at x = -0.05 and
    0.05 m), with a 500-point cloud around them: a two-link object for filters and planners."""
    links = []
    for x_m in (-0.05, 0.05):
        pose = np.eye(4)
        pose[:3, 3] = [x_m, 0.45, 0.025]
        links.append(Superquadric(np.array([0.05, 0.04, 0.025]), np.array([0.1, 0.1]), pose))
    cloud = PointCloud(np.random.default_rng(0).normal([0.0, 0.45, 0.03], 0.02, (500, 3)))
    poses = np.array([[-0.05, 0.45, 0.0], [0.05, 0.45, 0.0]])
    return Scene(cloud, ShapeEstimate(tuple(links), poses, np.zeros((2, 14)), cloud))


def _check_action_sampler(sampler: Any, advance: Advance) -> None:
    scene = _reference_scene()
    first = sampler.sample(scene, np.random.default_rng(1))
    again = sampler.sample(scene, np.random.default_rng(1))
    assert first and all(isinstance(a, Push | Pull) for a in first), "sample() returns pushes/pulls"
    assert [a.pd_rad for a in first] == [a.pd_rad for a in again], "same seed, same candidates"


def _check_action_selector(selector: Any, advance: Advance) -> None:
    candidates = [Push(np.array([0.0, 0.4 + 0.01 * i]), 0.1 * i, 0.02) for i in range(5)]
    scene = _reference_scene()
    chosen = selector.select(candidates, scene, np.random.default_rng(3))
    assert any(chosen is c for c in candidates), "select() returns one of the candidates"
    assert selector.select(candidates, scene, np.random.default_rng(3)) is chosen, (
        "same seed, same choice"
    )


def _is_point(value: Any) -> bool:
    array = np.asarray(value, dtype=np.float64)
    return array.shape == (3,) and bool(np.all(np.isfinite(array)))


def _check_touch_probe(probe: Any, advance: Advance) -> None:
    far = np.array([50.0, 50.0, 50.0])
    result = probe.probe(far, far + np.array([0.0, 0.0, 0.1]))
    assert result is None, "a touch far from everything is a miss (None)"
    start, target = np.array([0.0, 0.5, 1.5]), np.array([0.0, 0.5, -0.5])
    result = probe.probe(start, target)
    if result is not None:
        point, normal = result
        assert _is_point(point) and _is_point(normal), "a contact is (point [3], normal [3])"
        assert abs(float(np.linalg.norm(normal)) - 1.0) < 1e-6, "the normal is a unit vector"


def _check_touch_estimator(estimator: Any, advance: Advance) -> None:
    far = np.array([50.0, 50.0, 50.0])
    estimate = estimator.update(far, far + np.array([0.0, 0.0, 0.1]), None)
    assert isinstance(estimate, dict), "update() returns a dict"


def _check_touch_explorer(explorer: Any, advance: Advance) -> None:
    first = explorer.next_touch({}, np.random.default_rng(5))
    assert first is not None, "with no data yet the explorer proposes a touch"
    start, target = first
    assert _is_point(start) and _is_point(target), "a touch is (start [3], target [3])"
    assert float(np.linalg.norm(np.asarray(target) - np.asarray(start))) > 0, (
        "a touch moves somewhere"
    )


BOX_HALF_M = np.array([0.045, 0.03, 0.025])
BOX_POSE = (0.02, 0.45, 0.3)
"""The reference object of the shape-estimator check: a 90 x 60 x 50 mm box on the table at
(x_m, y_m, yaw_rad)."""


def reference_box_cloud(spacing_m: float = 0.004) -> PointCloud:
    """The surface a camera above sees of the box ``BOX_POSE``: its top and four sides, points
    ``spacing_m`` apart (world frame)."""
    (a, b, c), (x_m, y_m, yaw) = BOX_HALF_M, BOX_POSE

    def grid(u_half: float, v_half: float) -> tuple[FloatArray, FloatArray]:
        u = np.arange(-u_half, u_half + 1e-9, spacing_m)
        v = np.arange(-v_half, v_half + 1e-9, spacing_m)
        uu, vv = np.meshgrid(u, v)
        return uu.ravel(), vv.ravel()

    faces = []
    u, v = grid(a, b)
    faces.append(np.column_stack([u, v, np.full(u.size, c)]))  # top
    u, w = grid(a, c)
    for side in (-b, b):
        faces.append(np.column_stack([u, np.full(u.size, side), w]))
    v, w = grid(b, c)
    for side in (-a, a):
        faces.append(np.column_stack([np.full(v.size, side), v, w]))
    local = np.concatenate(faces) + np.array([0.0, 0.0, c])  # standing on the table
    turn = np.array([[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]])
    world = local.copy()
    world[:, :2] = local[:, :2] @ turn.T + np.array([x_m, y_m])
    return PointCloud(world)


def _check_shape_estimator(estimator: Any, advance: Advance) -> None:
    cloud = reference_box_cloud()
    estimate = estimator.fit(cloud)
    assert isinstance(estimate, ShapeEstimate), "fit() returns a ShapeEstimate"
    count = len(estimate.links)
    assert count >= 1 and all(isinstance(link, Superquadric) for link in estimate.links), (
        "a ShapeEstimate has at least one Superquadric link"
    )
    poses = np.asarray(estimate.initial_poses, dtype=np.float64)
    assert poses.shape == (count, 3) and np.all(np.isfinite(poses)), (
        "initial_poses is finite [L, 3], one (x, y, theta) per link"
    )
    std = np.asarray(estimate.uncertainty, dtype=np.float64)
    assert std.ndim == 2 and len(std) == count and np.all(np.isfinite(std)) and np.all(std >= 0), (
        "uncertainty is [L, K], finite and non-negative"
    )
    for link in estimate.links:
        assert np.all(np.isfinite(link.scale_m)) and np.all(link.scale_m > 0), "scale_m > 0"
        rotation = np.asarray(link.world_from_sq)[:3, :3]
        assert np.allclose(rotation @ rotation.T, np.eye(3), atol=1e-6), (
            "world_from_sq is a rigid transform"
        )
    largest = max(range(count), key=lambda i: float(np.prod(estimate.links[i].scale_m)))
    offset_m = float(np.hypot(*(poses[largest, :2] - np.array(BOX_POSE[:2]))))
    assert offset_m < 0.01, (
        f"the largest link's centre lies {1e3 * offset_m:.1f} mm from the box's (over 10 mm)"
    )


def _check_process_model(model: Any, advance: Advance) -> None:
    from vistac.plugins.filters.conformance import check_process_model

    check_process_model(model)


_CHECKS: dict[str, Callable[[Any, Advance], None]] = {
    "world": _check_world,
    "arm": _check_arm,
    "gripper": _check_gripper,
    "camera": _check_camera,
    "tactile": _check_tactile,
    "view_planner": _check_view_planner,
    "action_sampler": _check_action_sampler,
    "action_selector": _check_action_selector,
    "touch_probe": _check_touch_probe,
    "touch_estimator": _check_touch_estimator,
    "touch_explorer": _check_touch_explorer,
    "process_model": _check_process_model,
    "shape_estimator": _check_shape_estimator,
}
