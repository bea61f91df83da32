"""Superquadric affordances, the push/pull rule, and the uniform and info-gain selectors."""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from pydantic import ValidationError
from scipy.stats import spearmanr
from simctx import TestContext
from vistac.errors import ConfigError, DataError
from vistac.plugins.actions.affordances import (
    PushPullRule,
    SuperquadricAffordances,
    in_rectangle,
    inside_link,
    link_outline,
)
from vistac.plugins.actions.info_gain import (
    InfoGainSelector,
    gaussian_kl,
    parameter_information,
)
from vistac.plugins.actions.selectors import UniformSelector
from vistac.plugins.filters.dual import Belief
from vistac.plugins.filters.state import Prediction
from vistac.plugins.shape.superquadric import inside_outside, to_superquadric_frame
from vistac.protocols import Scene
from vistac.testing import build_components
from vistac.types import Action, PointCloud, Pull, Push, ShapeEstimate, Superquadric

ROOT = Path(__file__).resolve().parents[1]
BOX = np.array([0.15, 0.04, 0.025])
"""A wide box: 0.30 m along x (wider than the gripper), 0.08 m along y."""
ELLIPSE = np.array([0.06, 0.03, 0.025])
EMPTY = Scene(PointCloud(np.zeros((1, 3))))


def _link(scale_m: np.ndarray, xy: tuple[float, float], exponents: float = 0.1) -> Superquadric:
    pose = np.eye(4)
    pose[:3, 3] = [xy[0], xy[1], scale_m[2]]
    return Superquadric(scale_m, np.array([exponents, exponents]), pose)


def _shape(*links: Superquadric, cloud_m: np.ndarray | None = None) -> ShapeEstimate:
    """The links with, unless ``cloud_m`` [P, 3] is given, a cloud of their top faces."""
    poses = np.array([[link.world_from_sq[0, 3], link.world_from_sq[1, 3], 0.0] for link in links])
    if cloud_m is None:
        cloud_m = np.concatenate([_top_face(link) for link in links])
    return ShapeEstimate(links, poses, np.zeros((len(links), 14)), PointCloud(cloud_m))


def _top_face(link: Superquadric, step_m: float = 0.004) -> np.ndarray:
    """Points [P, 3] on a grid of ``step_m`` over the link's top face (its mid-height
    outline, at its top)."""
    radius = float(np.max(link.scale_m[:2]))
    grid = np.arange(-radius, radius + step_m, step_m)
    xy = np.stack(np.meshgrid(grid, grid), -1).reshape(-1, 2) + link.world_from_sq[:2, 3]
    xy = xy[inside_link(link, xy)]
    return np.column_stack([xy, np.full(len(xy), 2.0 * link.world_from_sq[2, 3])])


def _scene(*links: Superquadric) -> Scene:
    shape = _shape(*links)
    return Scene(shape.cloud, shape)


def _sampler(tmp_path: Path, cls: type = SuperquadricAffordances, **options: Any) -> Any:
    return TestContext(tmp_path).add(cls, **options)


def _mid_height_f(link: Superquadric, points_xy: np.ndarray) -> np.ndarray:
    height = np.full((len(points_xy), 1), link.world_from_sq[2, 3])
    local = to_superquadric_frame(link, np.hstack([points_xy, height]))
    return inside_outside(local, link.scale_m, link.exponents, link.taper)


def _angle_deg(a_rad: float, b_rad: float) -> float:
    return abs(math.degrees(math.remainder(a_rad - b_rad, 2 * math.pi)))


# -- outline geometry -------------------------------------------------------------------------


def test_box_outline_points_are_on_the_surface_with_axis_normals() -> None:
    link = _link(BOX, (0.1, 0.45))
    points, normals = link_outline(link)
    assert _mid_height_f(link, points) == pytest.approx(1.0, abs=1e-6)
    local = points - [0.1, 0.45]
    on_end = np.abs(local[:, 1]) < 0.5 * BOX[1]  # away from the (slightly rounded) corners
    on_side = np.abs(local[:, 0]) < 0.5 * BOX[0]
    assert on_end.sum() > 20 and on_side.sum() > 20
    assert np.abs(normals[on_end, 0] - np.sign(local[on_end, 0])).max() < 1e-3
    assert np.abs(normals[on_side, 1] - np.sign(local[on_side, 1])).max() < 1e-3


def test_ellipse_outline_normals_follow_the_gradient() -> None:
    link = _link(ELLIPSE, (0.0, 0.45), exponents=1.0)
    points, normals = link_outline(link)
    local = points - [0.0, 0.45]
    assert (local[:, 0] / ELLIPSE[0]) ** 2 + (local[:, 1] / ELLIPSE[1]) ** 2 == pytest.approx(1.0)
    gradient = local / ELLIPSE[:2] ** 2
    expected = gradient / np.linalg.norm(gradient, axis=1, keepdims=True)
    assert np.max(np.abs(normals - expected)) < 5e-3


def test_tapered_and_sheared_outline_stays_on_the_surface() -> None:
    pose = np.eye(4)
    pose[:3, 3] = [0.0, 0.45, 0.025]
    link = Superquadric(BOX / 2, np.array([0.2, 0.5]), pose, np.array([0.4, 0.2, 0.3]))
    points, normals = link_outline(link)
    assert _mid_height_f(link, points) == pytest.approx(1.0, abs=1e-6)
    assert not inside_link(link, points + 0.002 * normals).any()
    assert inside_link(link, points - 0.002 * normals).all()


# -- actions.affordances ----------------------------------------------------------------------


def test_pushes_start_on_the_outline_along_the_jittered_inward_normal(tmp_path: Path) -> None:
    link = _link(ELLIPSE, (0.0, 0.45), exponents=1.0)
    sampler = _sampler(tmp_path, samples=64, interactions=["push"])
    actions = sampler.sample(_scene(link), np.random.default_rng(1))
    assert len(actions) == 64 and all(isinstance(a, Push) for a in actions)
    points = np.array([a.cp_m for a in actions])
    assert _mid_height_f(link, points) == pytest.approx(1.0, abs=0.02)
    local = points - [0.0, 0.45]
    gradient = local / ELLIPSE[:2] ** 2
    inward = np.arctan2(-gradient[:, 1], -gradient[:, 0])
    errors = [_angle_deg(a.pd_rad, n) for a, n in zip(actions, inward, strict=True)]
    assert max(errors) <= 5.5 and max(errors) > 2.0  # jittered, within +-5 deg


def test_pulls_only_where_the_chord_fits_the_gripper(tmp_path: Path) -> None:
    sampler = _sampler(tmp_path, samples=64, interactions=["pull"])
    actions = sampler.sample(_scene(_link(BOX, (0.0, 0.45))), np.random.default_rng(2))
    assert 32 < len(actions) < 64 and all(isinstance(a, Pull) for a in actions)
    # Fingers close across y (0.08 m; tilted up to ~20 deg at the rounded corners), never
    # along the 0.30 m long axis: the grasps sampled on the short ends are dropped.
    assert all(_angle_deg(a.grasp_axis_rad % math.pi, math.pi / 2) < 25.0 for a in actions)
    assert all(abs(a.gp_m[1] - 0.45) < 1e-3 for a in actions)  # the chord's midpoint
    narrow = _sampler(tmp_path, samples=64, interactions=["pull"], max_grasp_width_m=0.05)
    assert narrow.sample(_scene(_link(BOX, (0.0, 0.45))), np.random.default_rng(2)) == []


def test_fingers_never_descend_onto_or_sweep_over_another_link(tmp_path: Path) -> None:
    """Two 6 cm round links 3 cm apart along x: a grasp on one closing along x would put
    the open pads (15 cm apart) on the other, so only grasps closing across y are kept."""
    links = (_link(np.array([0.03, 0.03, 0.025]), (-0.045, 0.45), exponents=1.0),
             _link(np.array([0.03, 0.03, 0.025]), (0.045, 0.45), exponents=1.0))  # fmt: skip
    sampler = _sampler(tmp_path, samples=128, interactions=["pull"])
    actions = sampler.sample(_scene(*links), np.random.default_rng(4))
    assert len(actions) > 10
    for action in actions:
        axis = np.array([math.cos(action.grasp_axis_rad), math.sin(action.grasp_axis_rad)])
        for side in (-1.0, 1.0):
            pad_xy = action.gp_m + side * (0.075 + 0.005) * axis
            assert not any(inside_link(link, pad_xy[None]).any() for link in links)
    assert all(_angle_deg(a.grasp_axis_rad % math.pi, math.pi / 2) < 65.0 for a in actions)
    wide = _sampler(tmp_path, samples=128, interactions=["pull"], gripper_opening_m=0.07,
                    max_grasp_width_m=0.065)  # fmt: skip
    assert any(_angle_deg(a.grasp_axis_rad % math.pi, 0.0) < 20.0
               for a in wide.sample(_scene(*links), np.random.default_rng(4)))  # fmt: skip
    # A small link 5 mm beside a large one: the open pads land beyond it, but closing along
    # x on the large link the pad would sweep over the small one and squeeze both.
    links = (_link(np.array([0.015, 0.015, 0.025]), (-0.02, 0.45), exponents=1.0),
             _link(np.array([0.03, 0.03, 0.025]), (0.03, 0.45), exponents=1.0))  # fmt: skip
    actions = sampler.sample(_scene(*links), np.random.default_rng(5))
    on_large = [a for a in actions if a.link == 1]
    assert len(on_large) > 5
    assert all(_angle_deg(a.grasp_axis_rad % math.pi, 0.0) > 30.0 for a in on_large)


def test_fingers_keep_their_clearance_from_every_link(tmp_path: Path) -> None:
    """Two round links with a 33 mm gap: pushing the right one from the gap puts the closed
    fingers (20 mm, 10-30 mm behind the contact) 3 mm from the left one, which a 5 mm
    clearance refuses and no clearance allows."""
    links = (_link(np.array([0.03, 0.03, 0.025]), (-0.0465, 0.45), exponents=1.0),
             _link(np.array([0.03, 0.03, 0.025]), (0.0465, 0.45), exponents=1.0))  # fmt: skip

    def from_the_gap(clearance_m: float) -> int:
        sampler = _sampler(tmp_path, samples=256, interactions=["push"],
                           finger_clearance_m=clearance_m)  # fmt: skip
        actions = sampler.sample(_scene(*links), np.random.default_rng(6))
        return sum(
            a.link == 1 and _angle_deg(a.pd_rad, 0.0) < 10.0 and abs(a.cp_m[1] - 0.45) < 0.005
            for a in actions
        )

    assert from_the_gap(0.0) > 0
    assert from_the_gap(0.005) == 0


def test_a_grasp_as_wide_as_the_gripper_opens_is_rejected(tmp_path: Path) -> None:
    with pytest.raises(ValidationError, match=r"max_grasp_width_m .* gripper_opening_m"):
        _sampler(tmp_path, interactions=["pull"], gripper_opening_m=0.085)


def test_unreachable_candidates_are_dropped(tmp_path: Path) -> None:
    workspace = ((-0.45, 0.45), (0.2, 0.47))
    sampler = _sampler(tmp_path, samples=64, workspace_xy_m=workspace)
    actions = sampler.sample(_scene(_link(BOX, (0.0, 0.45))), np.random.default_rng(3))
    assert 0 < len(actions) < 64
    for action in actions:
        start = action.cp_m if isinstance(action, Push) else action.gp_m
        end = start + action.speed_mps * action.duration_s * np.array(
            [math.cos(action.pd_rad), math.sin(action.pd_rad)]
        )
        assert 0.2 <= start[1] <= 0.47 and 0.2 <= end[1] <= 0.47


def test_pushes_keep_the_object_inside_the_workspace(tmp_path: Path) -> None:
    """An ellipse (3 cm half-width across y) whose outline lies 7 cm from the workspace's near
    edge (y 0.2), and 10 cm pushes: a push may leave its outline no nearer the edge than
    object_margin_m (3 cm), so only pushes heading less than asin(0.4) towards the edge are
    kept; without the margin some go further. An outline 1 cm from the edge, inside the
    margin already, may only be pushed no nearer."""

    def outlines_after(y_m: float, **options: Any) -> np.ndarray:
        scene = _scene(_link(ELLIPSE, (0.0, y_m), exponents=1.0))
        sampler = _sampler(tmp_path, samples=200, interactions=["push"], **options)
        pushes = sampler.sample(scene, np.random.default_rng(6))
        return np.array([y_m - 0.03 + 0.1 * math.sin(p.pd_rad) for p in pushes])

    kept = outlines_after(0.30)
    assert kept.min() >= 0.23 - 1e-9 and kept.max() > 0.32
    assert kept.min() < 0.26  # pushes towards the edge are kept while they stay 3 cm in
    assert outlines_after(0.30, object_margin_m=None).min() < 0.20
    near = outlines_after(0.24)
    assert len(near) > 20 and near.min() >= 0.21 - 1e-9


def test_long_objects_keep_their_far_end_in_reach(tmp_path: Path) -> None:
    """The margin is measured to the outline: a 30 cm box along y, its centre 20 cm and its
    far end 5 cm from the workspace's far edge (y 0.8), may be pushed at most 2 cm further
    that way (sin(pd) <= 0.2 for 10 cm pushes), though its centre would stay far inside.
    Without the margin, pushes into its near end head straight at the edge."""
    upright = _link(BOX, (0.0, 0.0))
    pose = upright.world_from_sq.copy()
    pose[:3, :3] = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    pose[:2, 3] = [0.0, 0.60]
    scene = _scene(Superquadric(BOX, upright.exponents, pose))

    def headings_y(**options: Any) -> np.ndarray:
        sampler = _sampler(tmp_path, samples=200, interactions=["push"], **options)
        pushes = sampler.sample(scene, np.random.default_rng(2))
        return np.array([math.sin(push.pd_rad) for push in pushes])

    kept = headings_y()
    assert len(kept) > 10 and kept.max() <= 0.2 + 1e-9
    assert headings_y(object_margin_m=None).max() > 0.9


def test_pulls_keep_the_object_inside_the_workspace(tmp_path: Path) -> None:
    """Pulls heading anywhere (spread pi) on an object whose outline is 7 cm from the near
    edge: those that would bring it within 3 cm of the edge are dropped, so a skill of pulls
    alone can go on pulling (before, pulls towards the robot walked it out of reach)."""
    scene = _scene(_link(ELLIPSE, (0.0, 0.30), exponents=1.0))
    options = {"samples": 200, "interactions": ["pull"], "pull_spread_rad": math.pi}
    pulls = _sampler(tmp_path, **options).sample(scene, np.random.default_rng(6))
    after = np.array([0.27 + 0.1 * math.sin(p.pd_rad) for p in pulls])
    assert len(pulls) > 20 and after.min() >= 0.23 - 1e-9 and after.max() > 0.32
    free = _sampler(tmp_path, object_margin_m=None, **options).sample(
        scene, np.random.default_rng(6)
    )
    assert min(0.27 + 0.1 * math.sin(p.pd_rad) for p in free) < 0.20


def test_pushes_keep_within_the_spread_of_the_chosen_direction(tmp_path: Path) -> None:
    link = _link(ELLIPSE, (0.0, 0.45), exponents=1.0)
    sampler = _sampler(tmp_path, samples=200, interactions=["push", "pull"],
                       push_towards_rad=math.pi / 2, push_spread_rad=math.pi / 6)  # fmt: skip
    actions = sampler.sample(_scene(link), np.random.default_rng(5))
    pushes = [a for a in actions if isinstance(a, Push)]
    assert 10 < len(pushes) < 60  # about a sixth of the ~100 pushes drawn
    assert all(_angle_deg(a.pd_rad, math.pi / 2) <= 30.0 for a in pushes)
    assert all(a.cp_m[1] < 0.45 for a in pushes)  # on the near side, heading +y
    assert any(isinstance(a, Pull) for a in actions)  # pulls keep their own directions


def test_pushes_whose_approach_starts_inside_another_link_are_dropped(tmp_path: Path) -> None:
    left, right = _link(BOX / 2, (-0.075, 0.45)), _link(BOX / 2, (0.085, 0.45))  # 1 cm gap
    sampler = _sampler(tmp_path, samples=200, interactions=["push"], link=0)
    actions = sampler.sample(_scene(left, right), np.random.default_rng(4))
    assert all(a.link == 0 for a in actions) and 0 < len(actions) < 200
    starts = np.array(
        [a.cp_m - 0.02 * np.array([math.cos(a.pd_rad), math.sin(a.pd_rad)]) for a in actions]
    )
    assert not inside_link(right, starts).any()
    assert not any(a.cp_m[0] > -0.01 and abs(a.cp_m[1] - 0.45) < 0.015 for a in actions)


def _fingers_hit_box(push: Push, centre: tuple[float, float], half_m: tuple[float, float]) -> bool:
    """Whether the closed fingers (20 x 24 mm about the TCP, 2 cm behind the contact) overlap
    an axis-aligned box shrunk by 1 mm (a superquadric of exponent 0.1 rounds its corners)."""
    heading = np.array([math.cos(push.pd_rad), math.sin(push.pd_rad)])
    across = np.array([-heading[1], heading[0]])
    grid = np.linspace(-1.0, 1.0, 41)
    tcp = push.cp_m - 0.02 * heading
    points = tcp + 0.01 * grid[:, None, None] * heading + 0.012 * grid[None, :, None] * across
    inside = np.abs(points - np.array(centre)) < np.array(half_m) - 0.001
    return bool(inside.all(-1).any())


def test_pushes_whose_fingers_would_descend_onto_another_link_are_dropped(
    tmp_path: Path,
) -> None:
    """Pushes on the top face of the left link near its end start just beside the taller
    right link (1 cm gap): the TCP is clear of it, the fingers are not."""
    left = _link(np.array([0.04, 0.02, 0.025]), (-0.045, 0.45))
    right = _link(np.array([0.04, 0.05, 0.025]), (0.045, 0.45))
    scene = _scene(left, right)

    def pushes(**options: Any) -> list[Push]:
        sampler = _sampler(tmp_path, samples=400, interactions=["push"], link=0, **options)
        return sampler.sample(scene, np.random.default_rng(3))

    assert not any(_fingers_hit_box(p, (0.045, 0.45), (0.04, 0.05)) for p in pushes())
    tcp_only = pushes(finger_footprint_m=(0.0, 0.0))
    assert any(_fingers_hit_box(p, (0.045, 0.45), (0.04, 0.05)) for p in tcp_only)


def test_in_rectangle_of_a_turned_footprint() -> None:
    points = np.array([[0.0, 0.0], [0.0, 0.009], [0.0, 0.011], [-0.019, 0.0], [0.021, 0.0]])
    centre = np.array([1.0, 2.0])
    inside = in_rectangle(points + centre, centre, math.pi / 2, (0.02, 0.04))
    assert inside.tolist() == [True, True, False, True, False]  # along y +-1 cm, across +-2 cm


def test_pushes_whose_fingers_would_descend_onto_unfitted_points_are_dropped(
    tmp_path: Path,
) -> None:
    """A part of the object the fit missed (a patch beyond the box's +x end, seen in the
    cloud): pushes whose fingers would descend onto it are dropped, unless the check is off."""
    link = _link(BOX, (0.0, 0.45))
    grid = np.stack(np.meshgrid(np.arange(0.152, 0.176, 0.004), np.arange(0.43, 0.47, 0.004)), -1)
    patch = np.column_stack([grid.reshape(-1, 2), np.full(grid.size // 2, 0.05)])
    shape = _shape(link, cloud_m=np.concatenate([_top_face(link), patch]))

    def on_patch(push: Push) -> bool:
        start = push.cp_m - 0.02 * np.array([math.cos(push.pd_rad), math.sin(push.pd_rad)])
        return int(in_rectangle(patch[:, :2], start, push.pd_rad, (0.03, 0.034)).sum()) > 2

    def pushes(**options: Any) -> list[Push]:
        sampler = _sampler(tmp_path, samples=400, interactions=["push"], **options)
        return sampler.sample(Scene(shape.cloud, shape), np.random.default_rng(5))

    assert not any(on_patch(p) for p in pushes())
    assert any(on_patch(p) for p in pushes(max_cloud_points_under_fingers=None))


def test_a_sampler_that_drops_every_candidate_says_why(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    sampler = _sampler(tmp_path, samples=16, interactions=["push"], finger_clearance_m=0.2)
    with caplog.at_level("WARNING"):
        assert sampler.sample(_scene(_link(ELLIPSE, (0.0, 0.45))), np.random.default_rng(0)) == []
    assert "all 16 candidates dropped: 16 where the fingers" in caplog.text
    assert "finger_clearance_m" in caplog.text


def test_affordances_need_a_shape(tmp_path: Path) -> None:
    scene = Scene(_shape(_link(BOX, (0.0, 0.45))).cloud)
    with pytest.raises(DataError, match="no shape estimate"):
        _sampler(tmp_path).sample(scene, np.random.default_rng(0))


def test_sampling_is_seeded_by_the_rng(tmp_path: Path) -> None:
    scene = _scene(_link(BOX, (0.0, 0.45)))
    first = _sampler(tmp_path).sample(scene, np.random.default_rng(5))
    second = _sampler(tmp_path).sample(scene, np.random.default_rng(5))
    assert [a.pd_rad for a in first] == [a.pd_rad for a in second]


# -- actions.push_pull_rule --------------------------------------------------------------------


@pytest.mark.parametrize(
    ("links", "y_m", "kind"),
    [(2, 0.25, "pull"), (2, 0.45, "push"), (1, 0.25, "push")],
    ids=["two-links-near-edge", "two-links-far", "one-link-near-edge"],
)
def test_push_pull_rule(tmp_path: Path, links: int, y_m: float, kind: str) -> None:
    parts = [_link(BOX / 2, (-0.08 + 0.16 * i, y_m)) for i in range(links)]
    sampler = _sampler(tmp_path, PushPullRule, samples=32, workspace_xy_m=((-1, 1), (-1, 1)))
    actions = sampler.sample(_scene(*parts), np.random.default_rng(6))
    assert actions and {a.kind for a in actions} == {kind}


# -- KL and info gain ------------------------------------------------------------------------


def _t(values: Any) -> torch.Tensor:
    return torch.as_tensor(values, dtype=torch.float64)


@pytest.mark.parametrize(
    ("p", "q", "expected"),
    [
        (([1.0], [[2.0]]), ([0.0], [[1.0]]), 0.5 * (2.0 - math.log(2.0))),
        (([1.0, 0.0], [[1.0, 0.0], [0.0, 4.0]]), ([0.0, 0.0], [[2.0, 0.0], [0.0, 1.0]]),
         0.5 * (3.0 - math.log(2.0))),
        (([0.0, 0.0], [[1.0, 0.5], [0.5, 1.0]]), ([0.0, 0.0], [[1.0, 0.0], [0.0, 1.0]]),
         -0.5 * math.log(0.75)),
    ],
    ids=["1d", "2d-diagonal", "2d-correlated"],
)  # fmt: skip
def test_gaussian_kl_matches_hand_computed_values(p: Any, q: Any, expected: float) -> None:
    kl = gaussian_kl(_t(p[0]), _t(p[1]), _t(q[0]), _t(q[1]))
    assert float(kl) == pytest.approx(expected, rel=1e-9)
    assert float(gaussian_kl(_t(q[0]), _t(q[1]), _t(q[0]), _t(q[1]))) == pytest.approx(0.0)


def test_parameter_information_matches_the_scalar_linear_gaussian_case() -> None:
    # theta ~ N(0, s2), y = a theta + process noise q, observed with noise r:
    # I(theta; y_obs) = 0.5 ln(1 + a^2 s2 / (q + r)).
    s2, a, q, r = 0.04, 3.0, 0.01, 0.02
    cov = torch.tensor([[a * a * s2 + q, a * s2], [a * s2, s2]], dtype=torch.float64)
    observed, noise_var = torch.tensor([0]), torch.tensor([r], dtype=torch.float64)
    info = parameter_information(cov, observed, slice(1, 2), noise_var)
    assert float(info) == pytest.approx(0.5 * math.log(1 + a * a * s2 / (q + r)), rel=1e-12)
    uncorrelated = cov.clone()
    uncorrelated[0, 1] = uncorrelated[1, 0] = 0.0
    info = parameter_information(uncorrelated, observed, slice(1, 2), noise_var)
    assert float(info) == pytest.approx(0.0, abs=1e-12)


def _info_gain(
    tmp_path: Path, seed: int = 0, objective: str = "parameters"
) -> tuple[InfoGainSelector, Any]:
    """An info-gain selector over a dual filter with the analytical model, initialised on a
    90 x 90 mm box at (0, 0.45)."""
    planner = {"sigma_points": 100, "objective": objective}
    specs = {
        "model": {"plugin": "filters.analytical"},
        "filter": {"plugin": "filters.dual"},
        "planner": {"plugin": "actions.info_gain", "with": planner},
    }
    ctx = build_components(specs, tmp_path, seed=seed)
    filter_ = ctx.component("filter")
    square = _link(np.array([0.045, 0.045, 0.025]), (0.0, 0.45))
    filter_.initialise(_scene(square))
    return ctx.component("planner"), filter_


def _certain_but(filter_: Any, name: str) -> None:
    """A hand-made belief: the initial mean, small stds, and 15 mm std in ``name``."""
    std = torch.tensor([0.005, 0.005, 0.05, 1e-3, 1e-3, 1e-3, 0.02, 0.02, 1e-3, 1e-3])
    std[filter_.layout.index(name)] = 0.015
    filter_.belief = Belief(filter_.belief.mean.clone(), torch.diag(std.double() ** 2))


CENTRAL_X = Push(np.array([-0.045, 0.45]), 0.0, 0.02)
"""Pushes along +x through the middle of the left side: the torque about the CoM is
com_y times the force, so the rotation reveals com_y (and not com_x)."""
CENTRAL_Y = Push(np.array([0.0, 0.405]), math.pi / 2, 0.02)
"""Pushes along +y through the middle of the near side: reveals com_x, not com_y."""


@pytest.mark.parametrize("objective", ["joint", "parameters"])
@pytest.mark.parametrize(
    ("uncertain", "informative", "other"),
    [("com_y_0", CENTRAL_X, CENTRAL_Y), ("com_x_0", CENTRAL_Y, CENTRAL_X)],
)
def test_info_gain_prefers_the_action_that_excites_the_uncertain_parameter(
    tmp_path: Path, uncertain: str, informative: Push, other: Push, objective: str
) -> None:
    selector, filter_ = _info_gain(tmp_path, objective=objective)
    _certain_but(filter_, uncertain)
    gains = selector.gains([other, informative])
    assert float(gains[1]) > 1.2 * float(gains[0])
    scene = _scene(_link(np.array([0.045, 0.045, 0.025]), (0.0, 0.45)))
    assert selector.select([other, informative], scene, np.random.default_rng(0)) is informative


def test_info_gain_selection_is_deterministic_under_a_seed(tmp_path: Path) -> None:
    square = _link(np.array([0.045, 0.045, 0.025]), (0.0, 0.45))
    candidates = _sampler(tmp_path, samples=16).sample(_scene(square), np.random.default_rng(7))

    def choose(index: int) -> tuple[int, list[float]]:
        selector, _ = _info_gain(tmp_path / str(index))
        chosen = selector.select(candidates, _scene(square), np.random.default_rng(index))
        position = next(i for i, c in enumerate(candidates) if c is chosen)
        return position, selector.gains(candidates).tolist()

    assert choose(0) == choose(1)


def test_predictions_do_not_depend_on_the_other_candidates(tmp_path: Path) -> None:
    _, filter_ = _info_gain(tmp_path)
    alone = filter_.predict_beliefs([CENTRAL_X], 1.0, 15.0)[0]
    batched = filter_.predict_beliefs([CENTRAL_Y, CENTRAL_X], 1.0, 15.0)[1]
    assert torch.allclose(alone[0], batched[0]) and torch.allclose(alone[1], batched[1])
    start_mean, _ = filter_.predict_beliefs([CENTRAL_X], 0.0, 15.0)[0]
    assert torch.equal(start_mean, filter_.belief.mean)  # at rest: zero twist already
    assert float(alone[0][0]) > float(start_mean[0]) + 0.01  # pushed along +x


class _Runaway:
    """A process model whose velocity doubles every step."""

    n_links = None

    def predict(self, states: torch.Tensor, inputs: Any, dt_s: float) -> Prediction:
        pose = states[..., :6].clone()
        pose[..., 3] = 2.0 * pose[..., 3] + 1.0
        pose[..., 0] = pose[..., 0] + dt_s * pose[..., 3]
        force = torch.zeros(*states.shape[:-1], 2, dtype=states.dtype)
        return Prediction(pose, force, torch.full((6,), 1e-8, dtype=states.dtype))


def test_the_look_ahead_keeps_the_filters_twist_bound(tmp_path: Path) -> None:
    """The look-ahead is the filter's own prediction: a runaway model's twist is capped at
    max_link_speed_mps there too."""
    _, filter_ = _info_gain(tmp_path)
    filter_.model = _Runaway()
    mean, _ = filter_.predict_beliefs([CENTRAL_X], 1.0, 15.0)[0]
    assert float(mean[3]) == pytest.approx(filter_.config.max_link_speed_mps, rel=1e-6)


def test_info_gain_needs_a_filter_with_predictions(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="needs a filter"):
        build_components({"planner": {"plugin": "actions.info_gain"}}, tmp_path).component(
            "planner"
        )
    ctx = TestContext(tmp_path)
    ctx.components["filter"] = object()
    with pytest.raises(ConfigError, match="object has none"):
        ctx.add(InfoGainSelector)


# -- actions.uniform ---------------------------------------------------------------------------


def test_uniform_cycles_through_the_directions(tmp_path: Path) -> None:
    degrees = [100, -95, 10, 170, 60, -40]
    candidates: list[Action] = [Push(np.array([0.0, 0.4]), math.radians(d), 0.02) for d in degrees]
    selector = TestContext(tmp_path).add(UniformSelector, directions=4)
    chosen = [selector.select(candidates, EMPTY, np.random.default_rng(i)).pd_rad for i in range(5)]
    assert [round(math.degrees(c)) for c in chosen] == [10, 100, 170, -95, 10]


# -- end to end --------------------------------------------------------------------------------


def test_explore_active_skill_runs(
    tmp_path: Path, cli: Callable[..., tuple[int, str, str]]
) -> None:
    code, out, err = cli(
        "-q", "run", str(ROOT / "skills/explore_active.yaml"), "--out", str(tmp_path / "run"),
        "--set", "tree.sequence.1.repeat.max=1",
    )  # fmt: skip
    assert code == 0, err
    assert (tmp_path / "run" / "episodes" / "0000").is_dir() and "episode 0" in out


def test_info_gain_look_ahead_has_enough_points_for_three_links(tmp_path: Path) -> None:
    """A three-link object has 32 state entries: 32 look-ahead points cannot be whitened and
    their gains rank the candidates about as a coin would; the selector uses 48 (1.5 times the
    entries, rounded up to even), whose gains rank like those of 144 points."""
    checkpoint = ROOT / "skills/checkpoints/gnn_push.pt"
    specs: dict[str, Any] = {
        "model": {"plugin": "filters.gnn", "with": {"checkpoint": str(checkpoint), "hidden": 32}},
        "filter": {"plugin": "filters.dual"},
        "planner": {"plugin": "actions.info_gain"},
        "reference": {"plugin": "actions.info_gain", "with": {"sigma_points": 144}},
        "affordances": {"plugin": "actions.affordances", "with": {"samples": 96}},
    }
    ctx = build_components(specs, tmp_path)
    scene = _scene(*[_link(BOX / 3, (x_m, 0.45)) for x_m in (-0.1, 0.0, 0.1)])
    ctx.component("filter").initialise(scene)
    planner, reference = ctx.component("planner"), ctx.component("reference")
    assert planner.sigma_points() == 48 and reference.sigma_points() == 144
    candidates = ctx.component("affordances").sample(scene, np.random.default_rng(0))[:24]
    assert len(candidates) == 24
    best = reference.gains(candidates).numpy()
    assert spearmanr(planner.gains(candidates).numpy(), best).correlation > 0.85
    planner.sigma_points = lambda: 32  # what the configured count alone gave
    assert spearmanr(planner.gains(candidates).numpy(), best).correlation < 0.5
