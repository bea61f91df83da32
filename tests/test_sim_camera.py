"""sim.depth_camera: the table in closed form plus ray casting near the other geoms gives the
image that ``mj_multiRay`` over every pixel gives."""

from __future__ import annotations

from pathlib import Path

import mujoco
import numpy as np
import pytest
from simctx import add_camera, box_object, sim_setup
from vistac.plugins.hardware.sim.camera import SimDepthCamera
from vistac.types import Viewpoint

EXACT = {"depth_noise_m": 0.0, "dropout_prob": 0.0, "min_range_m": 0.0}

VIEWS = {
    "above the box": ((0.0, 0.45, 0.5), (0.0, 0.45, 0.0)),
    "box partly outside the image": ((0.2, 0.3, 0.3), (0.35, 0.45, 0.0)),
    "past the table's far edge": ((0.0, 0.0, 0.3), (0.0, 1.5, 0.1)),
    "past a side edge, from afar": ((-2.5, 0.45, 1.5), (0.5, 0.45, 0.0)),
    "from below the table": ((0.0, 0.45, -0.3), (0.0, 0.45, 0.05)),
    "from between the fingers": ((0.0, 0.45, 0.2), (0.0, 0.45, 0.0)),
    "gripper from the side": ((0.4, 0.2, 0.1), (0.0, 0.45, 0.1)),
}


def full_ray_cast(camera: SimDepthCamera) -> np.ndarray:
    """``mj_multiRay`` over every pixel with the camera's cutoff and range: [H, W]."""
    world, intrinsics = camera.world, camera.intrinsics
    rays_camera = intrinsics.pixel_rays().reshape(-1, 3)
    rays_world = np.ascontiguousarray(rays_camera @ camera.world_from_camera[:3, :3].T)
    count = len(rays_world)
    geom_id, depth_m = np.empty(count, dtype=np.int32), np.empty(count)
    cutoff = camera.config.max_range_m * float(np.linalg.norm(rays_camera, axis=1).max())
    origin = np.ascontiguousarray(camera.world_from_camera[:3, 3])
    mujoco.mj_multiRay(
        world.model, world.data, origin, rays_world.ravel(), None, 1, -1, geom_id, depth_m,
        None, count, cutoff,
    )  # fmt: skip
    depth_m[(geom_id < 0) | (depth_m > camera.config.max_range_m)] = np.nan
    return depth_m.reshape(intrinsics.height, intrinsics.width)


@pytest.mark.parametrize("view", list(VIEWS))
def test_depth_equals_ray_casting_every_pixel(tmp_path: Path, view: str) -> None:
    ctx = sim_setup(tmp_path, box_object(pose=[0.3, 0.45, 0.6]), gripper_start=(0, 0.45, 0.1, 0.5))
    camera = add_camera(ctx, width=160, height=120, **EXACT)
    eye, target = VIEWS[view]
    camera.move_to(Viewpoint(np.array(eye), np.array(target)))
    depth_m = camera.capture().depth_m
    expected_m = full_ray_cast(camera)
    np.testing.assert_array_equal(np.isnan(depth_m), np.isnan(expected_m))
    np.testing.assert_allclose(depth_m, expected_m, rtol=0, atol=1e-12)


def test_table_corner_matches_ray_casting(tmp_path: Path) -> None:
    """A view across the table's corner: its two edges cut the image."""
    ctx = sim_setup(tmp_path, box_object())
    camera = add_camera(ctx, width=64, height=48, **EXACT)
    camera.move_to(Viewpoint(np.array([0.6, 0.6, 0.4]), np.array([1.0, 1.0, 0.0])))
    depth_m = camera.capture().depth_m
    assert 0.2 < np.isnan(depth_m).mean() < 0.8
    np.testing.assert_array_equal(depth_m, full_ray_cast(camera))


def test_same_seed_gives_the_same_frames(tmp_path: Path) -> None:
    frames = []
    for run in ("a", "b"):
        camera = add_camera(sim_setup(tmp_path / run, box_object(), seed=3))
        frames.append([camera.capture(*size).depth_m for size in ((320, 240), (64, 64))])
    for first, second in zip(*frames, strict=True):
        np.testing.assert_array_equal(first, second)


def test_depth_follows_the_camera_and_the_gripper(tmp_path: Path) -> None:
    """What is kept between captures (the rays and the table of a pose) does not keep the
    gripper or an earlier pose in the image."""
    ctx = sim_setup(tmp_path, box_object(), gripper_start=(0.0, 0.3, 0.1, 0.0))
    camera = add_camera(ctx, width=80, height=60, **EXACT)
    views = [VIEWS["above the box"], VIEWS["gripper from the side"], VIEWS["above the box"]]
    frames = []
    for eye, target in views:
        camera.move_to(Viewpoint(np.array(eye), np.array(target)))
        for _ in range(2):
            frames.append(camera.capture().depth_m)
            np.testing.assert_allclose(frames[-1], full_ray_cast(camera), rtol=0, atol=1e-12)
            ctx.find("arm").command_velocity(np.array([0.0, 0.05, 0.0, 0.0]))
            ctx.find("world").step(0.5)
    assert not np.array_equal(frames[2], frames[3], equal_nan=True), "the gripper moved"
