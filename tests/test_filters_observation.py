"""Observation model of the dual filter (``filters.observation``): known-answer renders of
small clouds, the observation vector's NaN convention, ObsNoiseNet and the filter interface."""

from __future__ import annotations

import logging
import math

import numpy as np
import pytest
import torch
from torch import Tensor
from vistac.plugins.filters.observation import (
    DepthProjector,
    ObsNoiseNet,
    ProjectionObservationModel,
    observation_vector,
    split_observation,
)
from vistac.plugins.filters.state import DTYPE, StateLayout
from vistac.plugins.hardware.sim.camera import look_at
from vistac.types import CameraIntrinsics, Viewpoint

logger = logging.getLogger(__name__)

# A 64x64 camera 1 m above the table origin, looking straight down: a point at height h lies
# at depth 1 - h; image right is world +x, image down is world -y.
CAMERA_HEIGHT_M = 1.0
FOCAL_PX = 100.0
CENTRE_PX = 31.5
DOWN = CameraIntrinsics(64, 64, FOCAL_PX, FOCAL_PX, CENTRE_PX, CENTRE_PX)
DOWN_POSE = np.array(
    [[1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, 0.0], [0.0, 0.0, -1.0, 1.0], [0.0, 0.0, 0.0, 1.0]]
)
ORIGIN_POSE = torch.zeros(1, 3, dtype=DTYPE)


def world_xy(row: float, col: float, height_m: float) -> tuple[float, float]:
    """Hand inversion of the pinhole model for DOWN: the world (x, y) whose projection at
    ``height_m`` is the centre of pixel (row, col)."""
    depth_m = CAMERA_HEIGHT_M - height_m
    return (col - CENTRE_PX) * depth_m / FOCAL_PX, -(row - CENTRE_PX) * depth_m / FOCAL_PX


def cloud_at(pixels: list[tuple[int, int]], height_m: float) -> Tensor:
    """Points [P, 3] at ``height_m`` that project onto the centres of ``pixels`` (row, col)."""
    return torch.tensor([[*world_xy(r, c, height_m), height_m] for r, c in pixels], dtype=DTYPE)


def projector(points: Tensor, **options: object) -> DepthProjector:
    """Single-link projector for DOWN, the link initially at the origin."""
    links = torch.zeros(len(points), dtype=torch.int64)
    return DepthProjector(points, links, ORIGIN_POSE, DOWN, DOWN_POSE, **options)


def block(rows: range, cols: range) -> list[tuple[int, int]]:
    return [(r, c) for r in rows for c in cols]


def expected_image(pixels: list[tuple[int, int]], depth_m: float, background_m: float) -> Tensor:
    image = torch.full((64, 64), background_m, dtype=DTYPE)
    for r, c in pixels:
        image[r, c] = depth_m
    return image


def test_down_pose_is_the_simulators_look_at() -> None:
    view = Viewpoint(np.array([0.0, 0.0, CAMERA_HEIGHT_M]), np.zeros(3))
    np.testing.assert_allclose(look_at(view), DOWN_POSE, atol=1e-12)


def test_square_renders_hand_computed_depth_at_hand_computed_pixels() -> None:
    pixels = block(range(10, 14), range(40, 44))  # off-centre: catches flipped axes
    render = projector(cloud_at(pixels, 0.5)).render(ORIGIN_POSE)
    torch.testing.assert_close(render, expected_image(pixels, 0.5, CAMERA_HEIGHT_M))


def test_table_depth_straight_down_is_the_camera_height() -> None:
    proj = projector(cloud_at([(5, 5)], 0.2))
    torch.testing.assert_close(proj.background_m, torch.full((64, 64), 1.0, dtype=DTYPE))


def test_table_depth_of_a_tilted_camera_is_analytic() -> None:
    """45 degrees down from height h: the ray through row v meets z = 0 at depth
    h sqrt(2) / (1 + (v - cy) / fy), whatever the column."""
    height_m = 0.5
    intrinsics = CameraIntrinsics.from_fov(65, 65, math.radians(58.0))
    pose = look_at(Viewpoint(np.array([0.0, -height_m, height_m]), np.zeros(3)))
    proj = DepthProjector(
        torch.zeros(1, 3), torch.zeros(1), ORIGIN_POSE, intrinsics, pose, width_px=65, height_px=65
    )
    rows = torch.arange(65, dtype=DTYPE)[:, None]
    expected = height_m * math.sqrt(2.0) / (1.0 + (rows - intrinsics.cy) / intrinsics.fy)
    torch.testing.assert_close(proj.background_m, expected.expand(65, 65))
    assert proj.background_m[32, 32] == pytest.approx(height_m * math.sqrt(2.0))


def test_rays_missing_the_table_get_the_max_range() -> None:
    """A horizontal camera at height h: rows above the centre look up (max range); row v
    below it meets the table at depth h / t with t = (v - cy) / fy, capped at the range."""
    height_m, max_range_m = 0.2, 3.0
    intrinsics = CameraIntrinsics.from_fov(64, 64, math.radians(58.0))
    pose = look_at(Viewpoint(np.array([0.0, -1.0, height_m]), np.array([0.0, 0.0, height_m])))
    proj = DepthProjector(
        torch.zeros(1, 3), torch.zeros(1), ORIGIN_POSE, intrinsics, pose, max_range_m=max_range_m
    )
    slope = (torch.arange(64, dtype=DTYPE) - intrinsics.cy) / intrinsics.fy
    depth_m = torch.where(slope > 0, height_m / slope, torch.full_like(slope, math.inf))
    expected = depth_m.clamp(max=max_range_m)[:, None].expand(64, 64)
    torch.testing.assert_close(proj.background_m, expected)
    assert bool((proj.background_m[:32] == max_range_m).all())


def test_translation_moves_the_blob_by_the_predicted_pixel_shift() -> None:
    """At depth 0.5 m one pixel is 5 mm: dx = +10 mm -> 2 columns right, dy = -5 mm -> 1 row
    down (image down is world -y)."""
    pixels = block(range(20, 24), range(30, 33))
    proj = projector(cloud_at(pixels, 0.5))
    render = proj.render(torch.tensor([[0.010, -0.005, 0.0]], dtype=DTYPE))
    moved = [(r + 1, c + 2) for r, c in pixels]
    torch.testing.assert_close(render, expected_image(moved, 0.5, CAMERA_HEIGHT_M))


def test_rotation_turns_the_blob_about_the_link_origin() -> None:
    """A row of points starting at the link's origin (pixel (32, 32)), initial theta 0.3: a
    further +90 degrees turns it to point along world +y, i.e. up the image."""
    theta0 = 0.3
    origin_x, origin_y = world_xy(32, 32, 0.5)
    points = cloud_at([(32, 32 + k) for k in range(4)], 0.5)
    initial = torch.tensor([[origin_x, origin_y, theta0]], dtype=DTYPE)
    proj = DepthProjector(points, torch.zeros(4), initial, DOWN, DOWN_POSE)
    turned = initial + torch.tensor([[0.0, 0.0, math.pi / 2]], dtype=DTYPE)
    reversed_ = initial + torch.tensor([[0.0, 0.0, math.pi]], dtype=DTYPE)
    renders = proj.render(torch.stack([initial, turned, reversed_]))
    for render, pixels in zip(
        renders,
        [[(32, 32 + k) for k in range(4)], [(32 - k, 32) for k in range(4)],
         [(32, 32 - k) for k in range(4)]],
        strict=True,
    ):
        torch.testing.assert_close(render, expected_image(pixels, 0.5, CAMERA_HEIGHT_M))


@pytest.mark.parametrize("near_first", [True, False])
def test_zbuffer_keeps_the_nearest_point(near_first: bool) -> None:
    near = cloud_at([(32, 32)], 0.5)  # depth 0.5
    far = cloud_at([(32, 32)], 0.3)  # depth 0.7, same pixel
    below_table = cloud_at([(40, 40)], -0.1)  # depth 1.1: hidden by the table at 1.0
    points = torch.cat([near, far, below_table] if near_first else [below_table, far, near])
    render = projector(points).render(ORIGIN_POSE)
    torch.testing.assert_close(render, expected_image([(32, 32)], 0.5, CAMERA_HEIGHT_M))


def test_points_behind_the_camera_or_out_of_range_are_dropped() -> None:
    behind = torch.tensor([[0.0005, 0.0005, 1.2]], dtype=DTYPE)  # naive projection: in image
    too_near = cloud_at([(10, 10)], 0.95)  # depth 0.05 < min_range_m = 0.1
    too_far = cloud_at([(20, 20)], 0.1)  # depth 0.9 > max_range_m = 0.8
    off_image = torch.tensor([[5.0, 0.0, 0.5]], dtype=DTYPE)  # u = 1031.5
    points = torch.cat([behind, too_near, too_far, off_image])
    proj = projector(points, min_range_m=0.1, max_range_m=0.8)
    render = proj.render(ORIGIN_POSE)
    torch.testing.assert_close(render, torch.full((64, 64), 0.8, dtype=DTYPE))  # table at 1.0
    torch.testing.assert_close(render, proj.background_m)


@pytest.mark.parametrize(
    ("splat_px", "covered"),
    [
        (1, block(range(30, 33, 2), range(30, 33, 2))),  # four isolated pixels
        (2, block(range(30, 34), range(30, 34))),  # nearest 2x2: holes filled
        (3, block(range(29, 34), range(29, 34))),  # centred 3x3
    ],
)
def test_splat_footprint_fills_a_sparse_grid(splat_px: int, covered: list[tuple[int, int]]) -> None:
    """Points on pixel centres two pixels apart; the footprint of a point on a centre starts at
    that pixel for an even size and is centred on it for an odd one."""
    points = cloud_at(block(range(30, 33, 2), range(30, 33, 2)), 0.5)
    render = projector(points, splat_px=splat_px).render(ORIGIN_POSE)
    torch.testing.assert_close(render, expected_image(covered, 0.5, CAMERA_HEIGHT_M))


def test_splat_at_the_image_border_is_clipped_without_wrapping() -> None:
    points = cloud_at([(0, 0), (40, 63), (63, 20)], 0.5)
    render = projector(points, splat_px=3).render(ORIGIN_POSE)
    covered = [(0, 0), (0, 1), (1, 0), (1, 1)]
    covered += [(r, c) for r in (39, 40, 41) for c in (62, 63)]
    covered += [(r, c) for r in (62, 63) for c in (19, 20, 21)]
    torch.testing.assert_close(render, expected_image(covered, 0.5, CAMERA_HEIGHT_M))


def reference_render(proj_args: dict[str, Tensor], link_poses: Tensor, splat_px: int,
                     background_m: Tensor) -> Tensor:
    """Point-by-point render [H, W] of link_poses [L, 3] with Python loops, as the docstring
    states it: rotate by the change in theta around the link origin, translate."""
    points, links, initial = proj_args["points"], proj_args["links"], proj_args["initial"]
    rotation_cw = torch.as_tensor(DOWN_POSE[:3, :3], dtype=DTYPE).T
    translation_wc = torch.as_tensor(DOWN_POSE[:3, 3], dtype=DTYPE)
    image = background_m.clone()
    for point, link in zip(points, links.tolist(), strict=True):
        turn = float(link_poses[link, 2] - initial[link, 2])
        rotation = torch.tensor(
            [[math.cos(turn), -math.sin(turn)], [math.sin(turn), math.cos(turn)]], dtype=DTYPE
        )
        xy = rotation @ (point[:2] - initial[link, :2]) + link_poses[link, :2]
        camera = rotation_cw @ (torch.cat([xy, point[2:]]) - translation_wc)
        depth_m = float(camera[2])
        if not 0.1 <= depth_m <= 3.0:
            continue
        u = DOWN.fx * float(camera[0]) / depth_m + DOWN.cx
        v = DOWN.fy * float(camera[1]) / depth_m + DOWN.cy
        col0 = math.floor(u - 0.5 * (splat_px - 1) + 0.5)
        row0 = math.floor(v - 0.5 * (splat_px - 1) + 0.5)
        for row in range(row0, row0 + splat_px):
            for col in range(col0, col0 + splat_px):
                if 0 <= row < 64 and 0 <= col < 64:
                    image[row, col] = min(float(image[row, col]), depth_m)
    return image


def random_two_link_cloud(n_points: int, seed: int) -> dict[str, Tensor]:
    generator = torch.Generator().manual_seed(seed)
    points = torch.rand(n_points, 3, generator=generator, dtype=DTYPE)
    points = points * torch.tensor([0.2, 0.2, 0.1], dtype=DTYPE) - torch.tensor(
        [0.1, 0.1, 0.0], dtype=DTYPE
    )
    links = (points[:, 0] > 0.0).long()
    initial = torch.tensor([[-0.05, 0.0, 0.2], [0.05, 0.01, -0.4]], dtype=DTYPE)
    return {"points": points, "links": links, "initial": initial}


def random_poses(initial: Tensor, shape: tuple[int, ...], seed: int) -> Tensor:
    """Link poses [*shape, L, 3] near ``initial``."""
    generator = torch.Generator().manual_seed(seed)
    noise = torch.randn(*shape, *initial.shape, generator=generator, dtype=DTYPE)
    return initial + noise * torch.tensor([0.02, 0.02, 0.3], dtype=DTYPE)


@pytest.mark.parametrize("splat_px", [1, 2])
def test_render_matches_a_point_by_point_reference(splat_px: int) -> None:
    args = random_two_link_cloud(300, seed=1)
    proj = DepthProjector(
        args["points"], args["links"], args["initial"], DOWN, DOWN_POSE, splat_px=splat_px
    )
    poses = random_poses(args["initial"], (3,), seed=2)
    renders = proj.render(poses)
    for render, pose in zip(renders, poses, strict=True):
        expected = reference_render(args, pose, splat_px, proj.background_m)
        torch.testing.assert_close(render, expected)


@pytest.mark.parametrize("splat_px", [1, 3])
def test_render_with_dropped_points_matches_the_reference(splat_px: int) -> None:
    """Some points nearer than min_range_m among visible ones: the clamped-depth path."""
    args = random_two_link_cloud(400, seed=5)
    args["points"][::7, 2] = 0.95  # depth 0.05 < min_range_m = 0.1: dropped
    proj = DepthProjector(
        args["points"], args["links"], args["initial"], DOWN, DOWN_POSE, splat_px=splat_px
    )
    poses = random_poses(args["initial"], (3,), seed=6)
    for render, pose in zip(proj.render(poses), poses, strict=True):
        expected = reference_render(args, pose, splat_px, proj.background_m)
        torch.testing.assert_close(render, expected)


def test_renders_of_other_batch_sizes_in_between_do_not_interfere() -> None:
    """The projector keeps working tensors per image count: reuse gives the same images."""
    args = random_two_link_cloud(500, seed=7)
    proj = DepthProjector(args["points"], args["links"], args["initial"], DOWN, DOWN_POSE)
    poses = random_poses(args["initial"], (4,), seed=8)
    first = proj.render(poses)
    for count in range(1, 7):
        proj.render(random_poses(args["initial"], (count,), seed=count))
    torch.testing.assert_close(proj.render(poses), first, rtol=0, atol=0)
    assert first.data_ptr() != proj.render(poses).data_ptr()  # results are never shared


def test_batched_render_equals_separate_renders() -> None:
    args = random_two_link_cloud(500, seed=3)
    proj = DepthProjector(args["points"], args["links"], args["initial"], DOWN, DOWN_POSE)
    poses = random_poses(args["initial"], (2, 5), seed=4)  # [2, C=5, L, 3]
    batched = proj.render(poses)
    assert batched.shape == (2, 5, 64, 64)
    assert batched.dtype == DTYPE
    for b in range(2):
        for c in range(5):
            torch.testing.assert_close(batched[b, c], proj.render(poses[b, c]), rtol=0, atol=0)


def test_render_of_the_initial_poses_with_resampled_intrinsics() -> None:
    """Intrinsics of a larger camera are resampled to the observation size."""
    big = CameraIntrinsics(256, 256, 4 * FOCAL_PX, 4 * FOCAL_PX, 127.5, 127.5)
    pixels = block(range(10, 12), range(50, 53))
    proj = DepthProjector(
        cloud_at(pixels, 0.5), torch.zeros(len(pixels)), ORIGIN_POSE, big, DOWN_POSE
    )
    assert proj.intrinsics == DOWN
    torch.testing.assert_close(
        proj.render(ORIGIN_POSE), expected_image(pixels, 0.5, CAMERA_HEIGHT_M)
    )


def test_projector_rejects_bad_inputs() -> None:
    points = cloud_at([(1, 1)], 0.5)
    with pytest.raises(ValueError, match="link_index"):
        DepthProjector(points, torch.tensor([1]), ORIGIN_POSE, DOWN, DOWN_POSE)
    with pytest.raises(ValueError, match="splat_px"):
        projector(points, splat_px=0)
    with pytest.raises(ValueError, match="link_poses"):
        projector(points).render(torch.zeros(4, 2, 3, dtype=DTYPE))


def test_observation_vector_replaces_no_return_pixels_by_the_background() -> None:
    background = torch.linspace(0.5, 1.5, 64 * 64, dtype=DTYPE).reshape(64, 64)
    depth = torch.full((2, 64, 64), 0.7, dtype=DTYPE)
    depth[0, 3, 4] = math.nan
    depth[1, 60, 1] = math.nan
    depth[1, 0, 0] = math.inf
    force = torch.tensor([[1.0, -2.0], [0.5, 0.0]], dtype=DTYPE)
    observation = observation_vector(depth, force, background)
    assert observation.shape == (2, 4098)
    assert bool(observation.isfinite().all())
    image, tactile = split_observation(observation, 64, 64)
    torch.testing.assert_close(tactile, force)
    for b, r, c in [(0, 3, 4), (1, 60, 1), (1, 0, 0)]:
        assert image[b, r, c] == background[r, c]
    finite = depth.isfinite()
    torch.testing.assert_close(image[finite], depth[finite])
    assert observation[0, 3 * 64 + 4] == background[3, 4]  # row-major flattening


def test_observation_vector_checks_shapes() -> None:
    background = torch.ones(64, 64, dtype=DTYPE)
    with pytest.raises(ValueError, match="depth_m"):
        observation_vector(torch.ones(32, 32, dtype=DTYPE), torch.zeros(2), background)
    with pytest.raises(ValueError, match="force_n"):
        observation_vector(torch.ones(64, 64, dtype=DTYPE), torch.zeros(3), background)
    with pytest.raises(ValueError, match="observation"):
        split_observation(torch.ones(4097, dtype=DTYPE), 64, 64)


def noisy_observations(shape: tuple[int, ...], seed: int) -> Tensor:
    generator = torch.Generator().manual_seed(seed)
    depth = 0.6 + 0.05 * torch.rand(*shape, 64, 64, generator=generator, dtype=DTYPE)
    force = torch.randn(*shape, 2, generator=generator, dtype=DTYPE)
    return observation_vector(depth, force, torch.ones(64, 64, dtype=DTYPE))


@pytest.mark.parametrize("shape", [(), (3,), (2, 4)])
def test_obs_noise_net_shapes_and_initial_values(shape: tuple[int, ...]) -> None:
    torch.manual_seed(0)
    net = ObsNoiseNet()
    var = net.noise_var(noisy_observations(shape, seed=5))
    assert var.shape == (*shape, 4098)
    assert var.dtype == DTYPE
    assert bool((var > 0).all())
    visual_std, tactile_std = var[..., :4096].sqrt(), var[..., 4096:].sqrt()
    assert bool((visual_std == visual_std[..., :1]).all())  # one scalar per image
    assert bool((tactile_std == tactile_std[..., :1]).all())
    torch.testing.assert_close(visual_std, torch.full_like(visual_std, 0.005), rtol=0.05, atol=0)
    torch.testing.assert_close(tactile_std, torch.full_like(tactile_std, 0.2), rtol=0.05, atol=0)


def test_obs_noise_net_stays_positive_and_finite_for_extreme_inputs() -> None:
    torch.manual_seed(0)
    net = ObsNoiseNet(log_var_bound=math.log(100.0))
    with torch.no_grad():
        for parameter in net.parameters():
            parameter.mul_(1e3)  # saturate the raw outputs
    extreme = noisy_observations((2,), seed=6) * torch.tensor([[1e6], [-1e6]], dtype=DTYPE)
    with torch.no_grad():
        var = net.noise_var(extreme)
    assert bool(var.isfinite().all())
    assert bool((var > 0).all())
    initial_var = torch.cat([net.log_var_init[:1].expand(4096), net.log_var_init[1:].expand(2)])
    ratio = var / initial_var.exp()
    assert bool((ratio <= 100.0 * (1 + 1e-9)).all())
    assert bool((ratio >= 0.01 * (1 - 1e-9)).all())
    assert float(ratio.max()) > 10.0 or float(ratio.min()) < 0.1  # it did saturate


def test_obs_noise_net_is_differentiable_in_its_weights() -> None:
    torch.manual_seed(0)
    net = ObsNoiseNet()
    observation = noisy_observations((3,), seed=7)
    var = net.noise_var(observation)
    loss = (var.log() + (0.01 * observation) ** 2 / var).sum()  # a Gaussian NLL
    loss.backward()
    for name, parameter in net.named_parameters():
        assert parameter.grad is not None, name
        assert bool(parameter.grad.isfinite().all()), name
        assert float(parameter.grad.abs().sum()) > 0.0, name


def make_model(n_links: int = 2) -> tuple[ProjectionObservationModel, dict[str, Tensor]]:
    args = random_two_link_cloud(400, seed=8)
    proj = DepthProjector(args["points"], args["links"], args["initial"], DOWN, DOWN_POSE)
    return ProjectionObservationModel(StateLayout(n_links), proj, ObsNoiseNet()), args


def test_model_expected_renders_the_pose_block_and_appends_the_forces() -> None:
    model, args = make_model()
    layout = model.layout
    poses = random_poses(args["initial"], (2, 5), seed=9)  # [2, C=5, L, 3]
    generator = torch.Generator().manual_seed(10)
    states = torch.randn(2, 5, layout.size, generator=generator, dtype=DTYPE)
    pose_block = states[..., layout.pose_slice].reshape(2, 5, layout.n_links, 6)
    pose_block[..., :3] = poses
    force = torch.randn(2, 5, 2, generator=generator, dtype=DTYPE)
    expected = model.expected(states, force)
    assert expected.shape == (2, 5, model.size) == (2, 5, 4098)
    image, tactile = split_observation(expected, 64, 64)
    torch.testing.assert_close(image, model.projector.render(poses))
    torch.testing.assert_close(tactile, force)
    states_other_velocity = states.clone()
    states_other_velocity[..., layout.index("vx_1")] += 1.0
    states_other_velocity[..., layout.index("m_0")] += 1.0
    torch.testing.assert_close(model.expected(states_other_velocity, force), expected)


def test_model_expected_passes_force_gradients_but_not_pose_gradients() -> None:
    model, args = make_model()
    states = torch.zeros(4, model.layout.size, dtype=DTYPE)
    states[:, model.layout.pose_slice] = torch.cat(
        [args["initial"], torch.zeros(2, 3, dtype=DTYPE)], -1
    ).reshape(-1)
    states.requires_grad_(True)
    force = torch.ones(4, 2, dtype=DTYPE, requires_grad=True)
    model.expected(states, force).sum().backward()
    assert force.grad is not None
    torch.testing.assert_close(force.grad, torch.ones_like(force))
    assert states.grad is None  # the render is values only


def test_model_noise_var_and_measured_observation() -> None:
    model, _ = make_model()
    depth = torch.full((64, 64), 0.6, dtype=DTYPE)
    depth[5, 5] = math.nan
    observation = model.observation(depth, torch.tensor([0.1, 0.2], dtype=DTYPE))
    assert observation[5 * 64 + 5] == model.projector.background_m[5, 5]
    var = model.noise_var(observation)
    assert var.shape == (4098,)
    torch.testing.assert_close(var, model.noise_net.noise_var(observation))


def test_tactile_std_grows_with_the_measured_force() -> None:
    """tactile_std (a, b): std a + b |f| on the two force entries, the pixels' untouched."""
    model, _ = make_model()
    scaled = ProjectionObservationModel(
        model.layout, model.projector, model.noise_net, tactile_std=(0.05, 0.2)
    )
    observation = torch.full((3, 4098), 0.6, dtype=DTYPE)
    observation[:, -2:] = torch.tensor([[0.0, 0.0], [3.0, 4.0], [-0.6, 0.8]], dtype=DTYPE)
    var = scaled.noise_var(observation)
    learned = model.noise_var(observation)
    torch.testing.assert_close(var[:, :-2], learned[:, :-2])
    std_n = torch.tensor([0.05, 0.05 + 0.2 * 5.0, 0.05 + 0.2 * 1.0], dtype=DTYPE)
    torch.testing.assert_close(var[:, -2:], std_n.square()[:, None].expand(3, 2))
    for bad in ((0.0, 0.2), (0.1, -0.1)):
        with pytest.raises(ValueError, match="tactile_std"):
            ProjectionObservationModel(model.layout, model.projector, model.noise_net,
                                       tactile_std=bad)  # fmt: skip


def test_forces_below_contact_are_unexplained() -> None:
    """contact_force_n: both force entries are unexplained while the measured force is weaker
    (no contact: the force says nothing of the parameters), never the pixels by this."""
    model, _ = make_model()
    gated = ProjectionObservationModel(
        model.layout, model.projector, model.noise_net, occlusion_margin_m=None,
        contact_force_n=0.2,
    )  # fmt: skip
    observation = torch.full((3, 4098), 0.6, dtype=DTYPE)
    observation[:, -2:] = torch.tensor([[0.02, -0.01], [0.12, 0.16], [0.15, 0.15]], dtype=DTYPE)
    expected = torch.full((3, 5, 4098), 0.6, dtype=DTYPE)
    mask = gated.unexplained(observation, expected)
    assert mask[:, -2:].tolist() == [[True, True], [False, False], [False, False]]
    assert not bool(mask[:, :-2].any())
    with pytest.raises(ValueError, match="contact_force_n"):
        ProjectionObservationModel(model.layout, model.projector, model.noise_net,
                                   contact_force_n=-0.1)  # fmt: skip


def test_model_rejects_mismatched_parts() -> None:
    model, _ = make_model()
    with pytest.raises(ValueError, match="links"):
        ProjectionObservationModel(StateLayout(1), model.projector, model.noise_net)
    with pytest.raises(ValueError, match="image sizes"):
        ProjectionObservationModel(
            model.layout, model.projector, ObsNoiseNet(height_px=32, width_px=32)
        )
    with pytest.raises(ValueError, match="states"):
        model.expected(torch.zeros(5, 7, dtype=DTYPE), torch.zeros(5, 2, dtype=DTYPE))


def test_render_of_100_sigma_points_and_2000_points() -> None:
    """100 sigma points of a 2000-point cloud render to 64x64 with the object in view (the
    speed is measured in benchmarks/bench_filter.py, not here)."""
    args = random_two_link_cloud(2000, seed=11)
    pose = look_at(Viewpoint.on_hemisphere(np.zeros(3), 0.5, -math.pi / 2, math.radians(60.0)))
    intrinsics = CameraIntrinsics.from_fov(320, 240, math.radians(58.0))
    proj = DepthProjector(args["points"], args["links"], args["initial"], intrinsics, pose)
    poses = random_poses(args["initial"], (100,), seed=12)
    render = proj.render(poses)
    assert render.shape == (100, 64, 64)
    assert bool((render < proj.background_m).any(dim=(1, 2)).all())  # the object is seen


def test_unexplained_entries_are_pixels_nearer_than_every_rendering() -> None:
    from vistac.plugins.filters.observation import unexplained_entries

    expected = torch.full((3, 6), 0.5, dtype=DTYPE)
    expected[1, 0] = 0.3
    observation = torch.tensor([0.25, 0.45, 0.49, 0.8, 0.1, 0.1], dtype=DTYPE)
    mask = unexplained_entries(observation, expected, 4, 0.01)
    assert mask.tolist() == [True, True, False, False, False, False]
    assert not bool(unexplained_entries(observation, expected, 4, None).any())


def test_unexplained_entries_among_candidates_equal_the_dense_test() -> None:
    """With candidates (different ones per batch element) only their columns are compared;
    the mask must equal the nearer-than-every-rendering test of all pixels, and-ed with them."""
    from vistac.plugins.filters.observation import unexplained_entries

    generator = torch.Generator().manual_seed(3)
    n_depth, k = 50, 52
    expected = torch.rand((2, 7, k), generator=generator, dtype=DTYPE)
    observation = torch.rand((2, k), generator=generator, dtype=DTYPE) - 0.3
    candidates = torch.rand((2, n_depth), generator=generator) < 0.3
    dense = observation[..., :n_depth] < expected[..., :n_depth].amin(-2) - 0.01
    mask = unexplained_entries(observation, expected, n_depth, 0.01, candidates)
    assert mask[..., :n_depth].tolist() == (dense & candidates).tolist()
    assert not bool(mask[..., n_depth:].any())
    assert bool(mask.any()) and not bool((mask[..., :n_depth] & ~candidates).any())
    none = torch.zeros_like(candidates)
    assert not bool(unexplained_entries(observation, expected, n_depth, 0.01, none).any())


def test_world_points_invert_the_projection() -> None:
    proj = projector(cloud_at([(10, 20)], 0.04))
    depth = torch.full((64 * 64,), CAMERA_HEIGHT_M - 0.03, dtype=DTYPE)
    points = proj.world_points(depth).reshape(64, 64, 3)
    x_m, y_m = world_xy(40, 12, 0.03)
    torch.testing.assert_close(points[40, 12], torch.tensor([x_m, y_m, 0.03], dtype=DTYPE))
    assert proj.object_top_m == pytest.approx(0.04)


def test_robot_pixels_are_above_the_object_or_near_the_tcp() -> None:
    proj = projector(cloud_at(block(range(30, 34), range(30, 34)), 0.04))
    depth = torch.full((64, 64), CAMERA_HEIGHT_M, dtype=DTYPE)  # the table
    depth[5, 5] = CAMERA_HEIGHT_M - 0.2  # the arm, high above the object
    depth[50, 50] = CAMERA_HEIGHT_M - 0.03  # something object-high, far from the TCP
    depth[40, 40] = CAMERA_HEIGHT_M - 0.03  # the same near the TCP: a finger
    tcp_xy = torch.tensor(world_xy(40, 41, 0.03), dtype=DTYPE)  # ~ 1 mm from (40, 40)
    robot = proj.robot_pixels(depth.reshape(-1), tcp_xy, 0.02, 0.01).reshape(64, 64)
    assert bool(robot[5, 5]) and bool(robot[40, 40])
    assert not bool(robot[50, 50]) and not bool(robot[20, 20])
    assert int(robot.sum()) < 64  # the table far from the TCP is not the robot


def test_model_unexplained_keeps_object_pixels_far_from_the_robot() -> None:
    """A belief that has lost the object: the observed object is nearer than every rendering.
    Its pixels must stay in the update unless the robot may be what the camera sees."""
    pixels = block(range(30, 34), range(30, 34))
    proj = projector(cloud_at(pixels, 0.04))
    model = ProjectionObservationModel(StateLayout(1), proj, ObsNoiseNet())
    states = torch.zeros(3, model.layout.size, dtype=DTYPE)
    states[:, 0] = 0.15  # every sigma point 15 cm off to +x: the renderings miss the object
    expected = model.expected(states, torch.zeros(3, 2, dtype=DTYPE))
    observation = model.expected(torch.zeros(1, model.layout.size, dtype=DTYPE),
                                 torch.zeros(1, 2, dtype=DTYPE))[0]  # fmt: skip
    object_entries = torch.tensor([r * 64 + c for r, c in pixels])
    far_tcp = torch.tensor([-0.3, 0.3], dtype=DTYPE)
    assert not bool(model.unexplained(observation, expected, far_tcp)[object_entries].any())
    near_tcp = torch.zeros(2, dtype=DTYPE)
    assert bool(model.unexplained(observation, expected, near_tcp)[object_entries].all())
    assert bool(model.unexplained(observation, expected)[object_entries].all())  # no TCP
