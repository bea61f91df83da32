"""The per-step depth image's region of interest: cropped intrinsics, the pixel window of a
world box, the camera crops, and where ``execute_action`` puts the window."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from simctx import add_camera, box_object, sim_setup
from vistac.behaviours.interaction import action_region, object_region
from vistac.errors import DataError
from vistac.plugins.hardware.camera.image import resample
from vistac.types import RGBD, CameraIntrinsics, GaussianBelief, PixelWindow, Push, Viewpoint

K = CameraIntrinsics.from_fov(320, 240, np.radians(58.0))
DOWN = np.array(  # 0.5 m above (0, 0.45), looking straight down, image up = world +y
    [[1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, 0.45], [0.0, 0.0, -1.0, 0.5], [0.0, 0.0, 0.0, 1.0]]
)


def test_a_cropped_camera_has_the_same_rays_as_the_pixels_it_keeps() -> None:
    window = PixelWindow(40, 30, 100, 50)
    crop = K.cropped(window)
    assert (crop.width, crop.height, crop.fx) == (100, 50, K.fx)
    np.testing.assert_allclose(crop.pixel_rays(), K.pixel_rays()[30:80, 40:140])
    with pytest.raises(DataError, match="not inside the 320x240 image"):
        K.cropped(PixelWindow(300, 0, 40, 10))


def test_project_and_window_of_a_table_square() -> None:
    centre = np.array([[0.0, 0.45, 0.0]])
    np.testing.assert_allclose(K.project(DOWN, centre), [[K.cx, K.cy]])
    half_m = 0.05
    square = np.array([[x, 0.45 + y, 0.0] for x in (-half_m, half_m) for y in (-half_m, half_m)])
    window = K.window_of(DOWN, square)
    assert window is not None
    half_px = K.fx * half_m / 0.5  # 20.8 px at 0.5 m
    assert window.width == pytest.approx(2 * half_px, abs=1.5)
    assert window.height == pytest.approx(2 * half_px, abs=1.5)
    assert window.u0 + window.width / 2 == pytest.approx(K.cx + 0.5, abs=1.0)
    # Partly out of view: clipped to the image; behind the camera or beside it: None.
    wide = K.window_of(DOWN, np.array([[-5.0, 0.45, 0.0], [0.0, 0.45, 0.0]]))
    assert wide is not None and wide.u0 == 0 and wide.u0 + wide.width <= K.width
    assert K.window_of(DOWN, np.array([[0.0, 0.45, 1.0]])) is None
    assert K.window_of(DOWN, np.array([[5.0, 0.45, 0.0], [6.0, 0.45, 0.0]])) is None


def test_resample_crops_before_it_resamples() -> None:
    depth = np.arange(240 * 320, dtype=np.float64).reshape(240, 320)
    rgb = np.zeros((240, 320, 3), np.uint8)
    rgb[..., 0] = np.arange(320) % 256
    frame = RGBD(depth, K, DOWN, 0.0, rgb)
    window = PixelWindow(10, 20, 30, 40)
    crop = resample(frame, None, None, window)
    np.testing.assert_array_equal(crop.depth_m, depth[20:60, 10:40])
    assert crop.rgb is not None and crop.rgb[0, 0, 0] == 10
    small = resample(frame, 15, 20, window)
    assert small.depth_m.shape == (20, 15)
    assert small.intrinsics == K.cropped(window).scaled(15, 20)
    np.testing.assert_array_equal(small.depth_m, depth[21:60:2, 11:40:2])  # pixel centres


def test_the_sim_camera_casts_only_the_window(tmp_path: Path) -> None:
    ctx = sim_setup(tmp_path, box_object())
    camera = add_camera(ctx, dropout_prob=0.0, depth_noise_m=0.0)
    camera.move_to(Viewpoint(np.array([0.0, 0.45, 0.5]), np.array([0.0, 0.45, 0.0])))
    full = camera.capture()
    window = PixelWindow(120, 90, 80, 60)
    crop = camera.capture(window=window)
    np.testing.assert_allclose(crop.depth_m, full.depth_m[90:150, 120:200])
    # Resampled to more pixels than the window has: real rays, not repeated pixels.
    fine = camera.capture(160, 120, window)
    assert fine.intrinsics.fx == pytest.approx(2 * full.intrinsics.fx)
    same = np.abs(fine.depth_m[::2, ::2] - crop.depth_m) < 1e-3  # a quarter pixel apart
    assert same.mean() > 0.9 and not np.array_equal(fine.depth_m[::2, 1::2], crop.depth_m)
    assert fine.depth_m[60, 80] == pytest.approx(0.45, abs=1e-6)  # the box top, 5 cm high


def test_object_region_follows_the_belief_and_the_action_sweeps_it() -> None:
    points = np.array([[0.1, 0.4, 0.0], [0.14, 0.43, 0.05]])
    np.testing.assert_allclose(
        object_region(points, None, None, 0.01), [[0.09, 0.39], [0.15, 0.44]]
    )  # the points' extent
    shape = SimpleNamespace(links=(None,), initial_poses=np.array([[0.1, 0.4, 0.0]]))
    names = ("x_0", "y_0", "theta_0")
    belief = GaussianBelief(np.array([0.2, 0.5, 0.0]), np.eye(3), names)
    moved = object_region(points, shape, belief, 0.01)  # type: ignore[arg-type]
    np.testing.assert_allclose(moved, [[0.14, 0.44], [0.26, 0.56]])  # radius 0.05 + 0.01
    push = Push(np.array([0.0, 0.0]), pd_rad=np.pi / 2, speed_mps=0.02, duration_s=5.0)
    corners = action_region(push, moved, 0.05)
    np.testing.assert_allclose(corners.min(axis=0), [0.14, 0.44, 0.0], atol=1e-12)
    np.testing.assert_allclose(corners.max(axis=0), [0.26, 0.66, 0.05], atol=1e-12)


def test_execute_action_watches_from_its_view_of_the_object(tmp_path: Path) -> None:
    from vistac.cli import main

    skills = Path(__file__).resolve().parents[1] / "skills"
    view = "{azimuth_deg: 90, elevation_deg: 60, radius_m: 0.45}"
    tree = f"[look, choose_action, {{execute_action: {{view: {view}}}}}, stop]"
    out = tmp_path / "out"
    args = ["run", str(skills / "explore_push.yaml"), "--out", str(out), "--set", f"tree={tree}",
            "--set", "components.filter.with.push_evidence.enabled=false"]  # fmt: skip
    assert main(args) == 0
    data = np.load(out / "episodes" / "0000" / "data.npz")
    object_xy = data["object_pose"][0, 0, :2]  # rect2 at (0, 0.45), the fit's centroid near it
    for pose in data["camera_pose"]:
        eye, forward = pose[:3, 3], pose[:3, 2]
        assert np.degrees(np.arcsin(-forward[2])) == pytest.approx(60.0, abs=1e-6)
        offset = eye[:2] - object_xy
        assert np.degrees(np.arctan2(offset[1], offset[0])) == pytest.approx(90.0, abs=3.0)
        assert np.linalg.norm(offset) == pytest.approx(0.45 * np.cos(np.radians(60)), abs=0.01)
