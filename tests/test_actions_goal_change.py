"""iCEM goal pushing and change detection: known answers on toy models, and the skills."""

from __future__ import annotations

import json
import math
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import py_trees
import pytest
import torch
from py_trees.common import Status
from simctx import TestContext
from vistac.behaviours.belief import record_belief
from vistac.errors import ConfigError, DataError
from vistac.plugins.actions.affordances import (
    fingers_blocked,
    in_rectangle,
    inside_link,
    link_outline,
)
from vistac.plugins.actions.change import ChangeDetected, assess, auroc, window_means
from vistac.plugins.actions.icem import ICEMController, colored_noise, joined_outline
from vistac.plugins.filters.component import (
    known_parameters,
    load_prior_from,
)
from vistac.plugins.filters.dual import Belief, modality_log_likelihoods
from vistac.plugins.filters.state import DTYPE, StateLayout
from vistac.protocols import Episode, Scene
from vistac.testing import build_components
from vistac.types import GaussianBelief, PointCloud, Push, ShapeEstimate, Superquadric

ROOT = Path(__file__).resolve().parents[1]


# -- iCEM ------------------------------------------------------------------------------------


@pytest.mark.parametrize("length", [1, 2, 3, 5, 256])
@pytest.mark.parametrize("beta", [0.0, 2.0])
def test_colored_noise_values_are_standard_normal(beta: float, length: int) -> None:
    """Every value of every sequence has variance 1 and Gaussian tails, however short the
    horizon (scaled per sequence, one push's noise was infinite and two pushes always lay
    exactly 2 std apart)."""
    noise = colored_noise(beta, (20000,), length, np.random.default_rng(0))
    assert noise.shape == (20000, length)
    np.testing.assert_allclose(noise.var(axis=0), 1.0, atol=0.05)
    assert float((np.abs(noise) > 3.0).mean()) < 0.005  # 0.0027 for a Gaussian
    if length == 2:
        assert float(np.abs(noise[:, 0] - noise[:, 1]).std()) > 0.5


@pytest.mark.parametrize("length", [1, 2, 5])
def test_colored_noise_scaled_per_sequence(length: int) -> None:
    """"sequence": every sequence of two or more has unit std along the horizon (two pushes
    lie exactly 2 apart); a single push, which has no std of its own, the spectrum's."""
    noise = colored_noise(2.0, (20000,), length, np.random.default_rng(0), "sequence")
    assert np.isfinite(noise).all()
    if length == 1:
        assert float(noise.var()) == pytest.approx(1.0, abs=0.05)
    else:
        np.testing.assert_allclose(noise.std(axis=-1), 1.0)
    if length == 2:
        np.testing.assert_allclose(np.abs(noise[:, 0] - noise[:, 1]), 2.0)


def test_colored_noise_has_the_requested_spectrum() -> None:
    rng = np.random.default_rng(0)
    for beta in (0.0, 2.0):
        noise = colored_noise(beta, (400,), 256, rng)
        power = (np.abs(np.fft.rfft(noise, axis=-1)) ** 2).mean(0)[1:]
        frequencies = np.fft.rfftfreq(256)[1:]
        slope = np.polyfit(np.log(frequencies), np.log(power), 1)[0]
        assert slope == pytest.approx(-beta, abs=0.15)


class SlidingFilter:
    """A stand-in for filters.dual: the pushed box slides along the push direction by
    speed x duration (no rotation); one link, state (x, y, theta, twist, parameters)."""

    kind = "filter"

    def __init__(self, pose: tuple[float, float, float]) -> None:
        self.layout = StateLayout(1)
        mean = torch.zeros(self.layout.size, dtype=DTYPE)
        mean[:3] = torch.tensor(pose, dtype=DTYPE)
        self.belief = Belief(mean, torch.eye(self.layout.size, dtype=DTYPE))
        self.calls = 0

    def predict_states(
        self, actions: list[Push], rate_hz: float, states: torch.Tensor | None = None
    ) -> torch.Tensor:
        self.calls += 1
        if states is None:
            states = self.belief.mean.expand(len(actions), -1)
        states = states.clone()
        for i, push in enumerate(actions):
            distance = push.speed_mps * push.duration_s
            states[i, 0] += distance * math.cos(push.pd_rad)
            states[i, 1] += distance * math.sin(push.pd_rad)
        return states


def _box_shape(xy: tuple[float, float]) -> ShapeEstimate:
    pose = np.eye(4)
    pose[:3, 3] = [xy[0], xy[1], 0.025]
    link = Superquadric(np.array([0.045, 0.045, 0.025]), np.array([0.1, 0.1]), pose)
    cloud = PointCloud(np.zeros((1, 3)))
    return ShapeEstimate([link], np.array([[xy[0], xy[1], 0.0]]), np.zeros((1, 14)), cloud)


def _controller(tmp_path: Path, start: tuple[float, float, float], **options: Any) -> Any:
    ctx = TestContext(tmp_path)
    ctx.components["filter"] = SlidingFilter(start)
    return ctx.add(ICEMController, **options)


def test_icem_plans_pushes_that_bring_the_object_to_the_goal(tmp_path: Path) -> None:
    scene = Scene(PointCloud(np.zeros((1, 3))), _box_shape((0.0, 0.45)))
    goal = np.array([0.06, 0.49, 0.0])
    # The toy model moves the box from the first instant, so short pushes may end a plan.
    # Two pushes of at least 10 mm: the best plan ends the first 5 mm short, the second 5 mm
    # past the goal (cost 5 mm, the mean of the two); a plan not heading there costs 40+ mm.
    costs = []
    for seed in range(5):
        two = _controller(
            tmp_path, (0.0, 0.45, 0.0), iterations=6, population=96, duration_s=(0.5, 4.0)
        )
        assert isinstance(two.plan(scene, goal, np.random.default_rng(seed)), Push)
        costs.append(two.last_cost)
    assert float(np.median(costs)) < 0.01 and min(costs) < 0.006
    # With one push, it must start on the far side of the box and head for the goal.
    one = _controller(tmp_path, (0.0, 0.45, 0.0), iterations=4, population=48, horizon_pushes=1)
    push = one.plan(scene, goal, np.random.default_rng(0))
    assert one.last_cost < 0.01
    heading = np.array([math.cos(push.pd_rad), math.sin(push.pd_rad)])
    towards_goal = (goal[:2] - [0.0, 0.45]) / np.linalg.norm(goal[:2] - [0.0, 0.45])
    assert heading @ towards_goal > 0.95
    assert (push.cp_m - [0.0, 0.45]) @ towards_goal < 0  # behind the centre
    assert push.speed_mps * push.duration_s == pytest.approx(0.072, abs=0.005)


def test_icem_is_deterministic_under_a_seed_and_reuses_elites(tmp_path: Path) -> None:
    scene = Scene(PointCloud(np.zeros((1, 3))), _box_shape((0.0, 0.45)))
    goal = np.array([0.05, 0.45, 0.0])
    first = _controller(tmp_path, (0.0, 0.45, 0.0))
    second = _controller(tmp_path, (0.0, 0.45, 0.0))
    a = first.plan(scene, goal, np.random.default_rng(3))
    b = second.plan(scene, goal, np.random.default_rng(3))
    assert np.allclose(a.cp_m, b.cp_m) and a.pd_rad == b.pd_rad
    assert first._shifted is not None and first._shifted.shape == (5, 2, 3)


@pytest.mark.parametrize(("keep_elites", "kept"), [(0.0, 0), (0.5, 2), (1.0, 4)])
def test_icem_carries_over_the_share_of_elites_asked_for(
    tmp_path: Path, keep_elites: float, kept: int
) -> None:
    """Population 8 (its shrink by 1.25 floored at twice the 4 elites): each iteration but
    a plan's first scores the share ``keep_elites`` of the last iteration's elites on top, a
    plan's first those of the last plan, shifted; the last iteration adds the mean."""
    controller = _controller(tmp_path, (0.0, 0.45, 0.0), keep_elites=keep_elites, iterations=2,
                             population=8, elites=4)  # fmt: skip
    sizes: list[int] = []
    costs = controller._costs

    def counted(*args: Any) -> Any:
        sizes.append(len(args[1]))
        return costs(*args)

    controller._costs = counted  # type: ignore[method-assign]
    scene = Scene(PointCloud(np.zeros((1, 3))), _box_shape((0.0, 0.45)))
    for seed in (0, 1):
        controller.plan(scene, np.array([0.05, 0.45, 0.0]), np.random.default_rng(seed))
    assert sizes == [8, 9 + kept, 8 + kept, 9 + kept]


def _box(xy: tuple[float, float]) -> Superquadric:
    pose = np.eye(4)
    pose[:3, 3] = [xy[0], xy[1], 0.025]
    return Superquadric(np.array([0.045, 0.045, 0.025]), np.array([0.1, 0.1]), pose)


def test_icem_keeps_the_fingers_off_the_other_links(tmp_path: Path) -> None:
    """Towards a goal straight ahead, the best push starts right behind link 0; with a second
    link there, the planned push brings the fingers down clear of it; clear, too, of a part
    only the cloud shows (the fit missed it) unless the cloud check is off; and where no push
    is clear the plan fails with a message naming the options."""
    goal = np.array([0.06, 0.45, 0.0])
    behind = _box((-0.092, 0.45))  # link 1, 2 mm behind link 0
    one_link = Scene(PointCloud(np.zeros((1, 3))), _box_shape((0.0, 0.45)))
    options = {"iterations": 4, "population": 48, "horizon_pushes": 1}
    alone = _controller(tmp_path, (0.0, 0.45, 0.0), **options)
    push = alone.plan(one_link, goal, np.random.default_rng(0))
    heading = np.array([math.cos(push.pd_rad), math.sin(push.pd_rad)])
    start = push.cp_m - alone.config.approach_clearance_m * heading
    assert inside_link(behind, start[None])[0]  # where link 1 would be
    two = _box_shape((0.0, 0.45))
    two = ShapeEstimate([two.links[0], behind], np.array([[0.0, 0.45, 0.0], [-0.092, 0.45, 0.0]]),
                        np.zeros((2, 14)), two.cloud)  # fmt: skip
    controller = _controller(tmp_path, (0.0, 0.45, 0.0), **options)
    push = controller.plan(Scene(one_link.cloud, two), goal, np.random.default_rng(0))
    heading = np.array([math.cos(push.pd_rad), math.sin(push.pd_rad)])
    start = push.cp_m - controller.config.approach_clearance_m * heading
    size_m = controller.config.finger_footprint_m
    headings = np.array([push.pd_rad])
    assert not fingers_blocked(two, np.zeros((0, 2)), start[None], headings, size_m, None)[0]
    assert controller.last_cost < 0.06  # still nearer the goal than the start
    # A part the fit missed: cloud points where link 1 would be, no link there.
    grid = np.stack(np.meshgrid(np.linspace(-0.13, -0.05, 9), np.linspace(0.41, 0.49, 9)), -1)
    patch = np.column_stack([grid.reshape(-1, 2), np.full(81, 0.05)])
    fitted = _box_shape((0.0, 0.45))
    missed = ShapeEstimate(fitted.links, fitted.initial_poses, fitted.uncertainty,
                           PointCloud(patch))  # fmt: skip
    for most, on_patch in ((2, False), (None, True)):
        controller = _controller(tmp_path, (0.0, 0.45, 0.0), max_cloud_points_under_fingers=most,
                                 **options)  # fmt: skip
        push = controller.plan(Scene(missed.cloud, missed), goal, np.random.default_rng(0))
        heading = np.array([math.cos(push.pd_rad), math.sin(push.pd_rad)])
        start = push.cp_m - controller.config.approach_clearance_m * heading
        under = in_rectangle(patch[:, :2], start, push.pd_rad, size_m).sum()
        assert bool(under > 2) is on_patch
    wide = _controller(tmp_path, (0.0, 0.45, 0.0), finger_clearance_m=0.05, **options)
    with pytest.raises(DataError, match="finger_clearance_m"):
        wide.plan(Scene(one_link.cloud, two), goal, np.random.default_rng(0))


def test_joined_outline_is_the_outer_outline_of_touching_links() -> None:
    """Two boxes overlapping by 5 mm and a third apart: the outline of the first two goes
    round both (from -85 to +90 mm in x), leaves out the seam inside them, runs
    counter-clockwise with outward normals, and leaves the third out; a link alone keeps its
    own outline."""
    left, right, apart = _box((-0.04, 0.45)), _box((0.045, 0.45)), _box((0.3, 0.45))
    points, normals = joined_outline([left, right, apart], 0)
    assert points[:, 0].min() == pytest.approx(-0.085, abs=1e-3)
    assert points[:, 0].max() == pytest.approx(0.09, abs=1e-3)
    seam = (np.abs(points[:, 0] - 0.0025) < 0.002) & (np.abs(points[:, 1] - 0.45) < 0.04)
    assert not seam.any()
    offset = points - points.mean(axis=0)
    assert np.all(np.diff(np.arctan2(offset[:, 1], offset[:, 0])) >= 0)
    assert np.all(np.einsum("ij,ij->i", offset, normals) > 0)
    alone, _ = joined_outline([left, apart], 0)
    own, _ = link_outline(left)
    assert np.allclose(np.sort(alone, axis=0), np.sort(own, axis=0))


def test_icem_pushes_on_the_whole_object_when_a_look_splits_it(tmp_path: Path) -> None:
    """The belief holds one link; the last look fitted it as two overlapping boxes, the
    nearer on the goal's side. The push that brings it to the goal starts on the far box:
    iCEM plans on the outline of both, not of the nearer alone (whose far side lies inside
    the other box, where the fingers cannot come down)."""
    near, far = _box((-0.04, 0.45)), _box((0.045, 0.45))
    cloud = PointCloud(np.zeros((1, 3)))
    split = ShapeEstimate([near, far], np.array([[-0.04, 0.45, 0.0], [0.045, 0.45, 0.0]]),
                          np.zeros((2, 14)), cloud)  # fmt: skip
    goal = np.array([-0.06, 0.45, 0.0])
    controller = _controller(tmp_path, (0.0, 0.45, 0.0), iterations=4, population=48,
                             horizon_pushes=1)  # fmt: skip
    push = controller.plan(Scene(cloud, split), goal, np.random.default_rng(0))
    assert controller.last_cost < 0.01
    assert push.cp_m[0] == pytest.approx(0.09, abs=0.01)  # the far box's far side
    assert math.cos(push.pd_rad) < -0.95  # towards the goal


def test_icem_keeps_its_first_push_away_from_a_blocked_one(tmp_path: Path) -> None:
    """The best push towards a goal straight ahead starts behind the box; once a push there
    was blocked on its way down (the scene's blocked_xy_m), the plan starts elsewhere, at
    least ``avoid_blocked_m`` away; where every push is that near, it fails naming it."""
    goal = np.array([0.06, 0.45, 0.0])
    shape = _box_shape((0.0, 0.45))
    options = {"iterations": 4, "population": 48, "horizon_pushes": 1}
    first = _controller(tmp_path, (0.0, 0.45, 0.0), **options)
    best = first.plan(Scene(shape.cloud, shape), goal, np.random.default_rng(0))
    blocked = Scene(shape.cloud, shape, blocked_xy_m=best.cp_m[None])
    again = _controller(tmp_path, (0.0, 0.45, 0.0), **options)
    push = again.plan(blocked, goal, np.random.default_rng(0))
    assert np.linalg.norm(push.cp_m - best.cp_m) > again.config.avoid_blocked_m
    everywhere = _controller(tmp_path, (0.0, 0.45, 0.0), avoid_blocked_m=0.2, **options)
    with pytest.raises(DataError, match="avoid_blocked_m"):
        everywhere.plan(blocked, goal, np.random.default_rng(0))


def test_the_look_ahead_starts_a_push_where_the_executor_does(tmp_path: Path) -> None:
    """predict_states pushes as the executor does: the pad starts ``standoff_m`` before the
    contact point, so a larger standoff leaves the object that much shorter (a central push
    of a box with the analytical model: no turn)."""
    moved_m, box = [], str(ROOT / "skills/objects/rect1.yaml")
    for standoff_m in (0.01, 0.03):
        components = {
            "world": {"plugin": "sim.mujoco", "with": {"object": box}},
            "arm": {"plugin": "sim.arm"},
            "gripper": {"plugin": "sim.gripper"},
            "executor": {"plugin": "actions.cartesian", "with": {"standoff_m": standoff_m}},
            "model": {"plugin": "filters.analytical"},
            "filter": {"plugin": "filters.dual"},
        }  # fmt: skip
        filter_ = build_components(components, tmp_path / str(standoff_m)).component("filter")
        shape = _box_shape((0.0, 0.45))
        filter_.initialise(Scene(shape.cloud, shape))
        push = Push(np.array([0.0, 0.405]), math.pi / 2, 0.02, duration_s=4.0)
        x, y, theta = filter_.layout.link_pose(filter_.predict_states([push], 15.0))[0, 0, :3]
        assert abs(float(x)) < 1e-6 and abs(float(theta)) < 1e-6
        moved_m.append(float(y) - 0.45)
    assert 0.06 < moved_m[0] < 0.08  # 80 mm of travel, the first 10 mm before contact
    assert moved_m[0] - moved_m[1] == pytest.approx(0.02, abs=5e-4)


def test_icem_rejects_a_bad_goal_and_a_skill_without_a_filter(tmp_path: Path) -> None:
    controller = _controller(tmp_path, (0.0, 0.45, 0.0))
    scene = Scene(PointCloud(np.zeros((1, 3))), _box_shape((0.0, 0.45)))
    with pytest.raises(ConfigError, match="goal must be 3 finite numbers"):
        controller.plan(scene, np.array([0.1, math.nan, 0.0]), np.random.default_rng(0))
    with pytest.raises(ConfigError, match="needs a filter component with predict_states"):
        TestContext(tmp_path).add(ICEMController)


def test_a_goal_out_of_the_arms_reach_is_refused_before_anything_moves(tmp_path: Path) -> None:
    """The controller checks the goal against the arm's workspace; ``plan_push`` asks it
    when the tree is set up (`vistac run`: exit 2, no run folder; before, the skill pushed
    until its push budget ran out)."""
    from types import SimpleNamespace

    from vistac.plugins.actions.goal import PlanPush
    from vistac.plugins.hardware.limits import ArmLimits

    ctx = TestContext(tmp_path)
    ctx.components["filter"] = SlidingFilter((0.0, 0.45, 0.0))
    ctx.components["arm"] = SimpleNamespace(config=ArmLimits())  # x -0.5..0.5, y 0.15..0.85 m
    controller = ctx.add(ICEMController)
    controller.check_goal((0.06, 0.49, 0.0))
    controller.check_goal((0.5, 0.85, 3.0))  # on the edge
    for goal in ((0.6, 0.49, 0.0), (0.0, 0.1, 0.0)):
        with pytest.raises(ConfigError, match=rf"goal \({goal[0]:.3f}, {goal[1]:.3f}\) m lies "
                           r"outside the arm's workspace \(x -0\.50 to 0\.50 m, y 0\.15 to "
                           r"0\.85 m\); give a goal within it"):  # fmt: skip
            controller.check_goal(goal)
    node = PlanPush("plan", PlanPush.Config(goal=(0.6, 0.49, 0.0)), None)
    node.component = lambda field_name: controller  # type: ignore[method-assign]
    with pytest.raises(ConfigError, match=r"goal \(0\.600, 0\.490\) m lies outside"):
        node.setup()


# -- change detection --------------------------------------------------------------------------


def test_modality_log_likelihoods_match_equation_37() -> None:
    expected = torch.zeros(2, 6, dtype=DTYPE)  # C = 2 points, 4 depth + 2 tactile entries
    expected[1, 4:] = 2.0
    observation = torch.zeros(6, dtype=DTYPE)
    noise_var = torch.full((6,), 4.0, dtype=DTYPE)
    visual, tactile = modality_log_likelihoods(expected, observation, noise_var, 2).tolist()
    assert visual == pytest.approx(0.0)
    # per entry: point 0 has 0, point 1 has (2^2/4 * 2) / 2 = 1 -> log((1 + e^-0.5) / 2)
    assert tactile == pytest.approx(math.log((1 + math.exp(-0.5)) / 2))


def test_window_means_and_the_flag_time() -> None:
    time_s = np.arange(10) / 5.0  # 0 .. 1.8 s at 5 Hz
    values = np.where(time_s < 1.0, 0.0, -10.0)
    means = window_means(time_s, values, 0.6)  # windows of 3 steps, full from t = 0.6 s
    assert means[0] == pytest.approx(0.0)
    assert means[-1] == pytest.approx(-10.0)
    steps = [{"episode": 2, "time_s": t, "log_likelihood": {"tactile": v}}
             for t, v in zip(time_s, values, strict=True)]  # fmt: skip
    report = assess(steps, "tactile", 0.6, threshold=-2.0)
    # The window (0.6, 1.2] holds two drops: mean -6.7 < -2 at t = 1.2 s; (0.4, 1.0] has one.
    assert report.flagged and report.episode == 2
    assert report.flagged_after_s == pytest.approx(1.0)
    assert not assess(steps, "tactile", 0.6, threshold=-20.0).flagged


def _change_detected(steps: list[dict]) -> tuple[ChangeDetected, dict, Any]:
    """A change_detected node over a filter with the step history ``steps``; the node, the
    run's results and a blackboard client that writes ``episode``."""
    py_trees.blackboard.Blackboard.clear()
    results: dict = {}
    history = SimpleNamespace(step_history=lambda: steps)
    run = SimpleNamespace(component=lambda role: history, results=results)
    node = ChangeDetected("change_detected", ChangeDetected.Config(threshold=-2.0), run)
    writer = py_trees.blackboard.Client(name="execute_action")
    writer.register_key("episode", access=py_trees.common.Access.WRITE)
    return node, results, writer


def test_change_detected_assesses_each_interaction_once() -> None:
    """An action not carried out (episode None) is not assessed: not the one before again,
    and before any filter step not an error."""
    steps = [{"episode": 0, "time_s": t / 15, "log_likelihood": {"tactile": -5.0}}
             for t in range(30)]  # fmt: skip
    node, results, writer = _change_detected([])
    writer.episode = None
    assert node.update() == Status.FAILURE and "change_detection" not in results
    node, results, writer = _change_detected(steps)
    writer.episode = Episode(0, Push(np.zeros(2), 0.0, 0.02))
    assert node.update() == Status.SUCCESS
    writer.episode = None
    assert node.update() == Status.FAILURE
    assert [report["episode"] for report in results["change_detection"]] == [0]
    writer.episode = Episode(1, Push(np.zeros(2), 0.0, 0.02))  # update_belief left out
    with pytest.raises(ConfigError, match="no steps of interaction 1; put it after"):
        node.update()


def test_auroc_known_values() -> None:
    assert auroc([-5, -6], [-1, -2]) == 1.0
    assert auroc([-1, -2], [-5, -6]) == 0.0
    assert auroc([-1, -3], [-2]) == 0.5
    with pytest.raises(ValueError, match="at least one score"):
        auroc([], [1.0])


def test_correlation_dict_known_values() -> None:
    cov = np.array([[4.0, -2.0, 0.0], [-2.0, 4.0, 0.0], [0.0, 0.0, 0.0]])
    got = GaussianBelief(np.zeros(3), cov, ("a", "b", "c")).correlation_dict()
    assert got == {"names": ["a", "b", "c"],
                   "matrix": [[1.0, -0.5, 0.0], [-0.5, 1.0, 0.0], [0.0, 0.0, 1.0]]}  # fmt: skip


def test_prior_from_keeps_the_correlation_of_the_earlier_belief(tmp_path: Path) -> None:
    """m and f of a pushed object are known through their product: a later run must get
    them correlated as they were, or m f is far wider than the earlier run knew it."""
    layout = StateLayout(1)
    rng = np.random.default_rng(0)
    root = rng.normal(size=(layout.size, layout.size))
    cov = root @ root.T / layout.size + 0.01 * np.eye(layout.size)
    earlier = GaussianBelief(rng.normal(size=layout.size), cov, tuple(layout.names))
    results: dict[str, Any] = {}
    record_belief(results, earlier)
    path = tmp_path / "summary.json"
    path.write_text(json.dumps(results), encoding="utf-8")
    start = Belief(torch.zeros(layout.size, dtype=DTYPE), torch.eye(layout.size, dtype=DTYPE))
    known, correlation = load_prior_from(path)
    belief = known_parameters(start, layout, known, path, correlation)
    params = layout.parameter_slice
    np.testing.assert_allclose(belief.cov[params, params].numpy(), cov[params, params],
                               rtol=0, atol=1e-3 * float(np.abs(cov).max()))  # fmt: skip
    assert float(belief.cov[params, : params.start].abs().max()) == 0.0  # not with the pose
    # Without the correlation (a file of measured values): uncorrelated, the same std.
    uncorrelated = known_parameters(start, layout, load_prior_from(path)[0], path)
    block = uncorrelated.cov[params, params].numpy()
    np.testing.assert_allclose(block, np.diag(np.diag(cov[params, params])), atol=1e-9)
    # A pair the file leaves out is uncorrelated; rounding that breaks positive
    # definiteness is mended.
    names = layout.names[params]
    results["belief_correlation"] = {
        "names": [names[0], names[1], names[2]],
        "matrix": [[1.0, 1.0, -1.0], [1.0, 1.0, 1.0], [-1.0, 1.0, 1.0]],
    }
    path.write_text(json.dumps(results), encoding="utf-8")
    known, correlation = load_prior_from(path)
    mended = known_parameters(start, layout, known, path, correlation)
    assert bool((torch.linalg.eigvalsh(mended.cov) > 0).all())
    assert float(mended.cov[params, params][0, 3]) == 0.0
    results["belief_correlation"] = {"names": [names[0]], "matrix": [[1.0, 0.5]]}
    path.write_text(json.dumps(results), encoding="utf-8")
    with pytest.raises(ConfigError, match="belief_correlation"):
        load_prior_from(path)
    results["belief_correlation"] = {"matrix": [[1.0]]}  # no names
    path.write_text(json.dumps(results), encoding="utf-8")
    with pytest.raises(ConfigError, match="belief_correlation"):
        load_prior_from(path)


def test_prior_from_an_earlier_summary(tmp_path: Path) -> None:
    layout = StateLayout(1)
    names = layout.names[layout.parameter_slice]
    known = {name: {"mean": 0.1 * (i + 1), "std": 0.01} for i, name in enumerate(names)}
    path = tmp_path / "summary.json"
    path.write_text(json.dumps({"belief": known}), encoding="utf-8")
    start = Belief(torch.zeros(layout.size, dtype=DTYPE), torch.eye(layout.size, dtype=DTYPE))
    belief = known_parameters(start, layout, load_prior_from(path)[0], path)
    for name in names:
        index = layout.index(name)
        assert float(belief.mean[index]) == pytest.approx(known[name]["mean"])
        assert float(belief.cov[index, index]) == pytest.approx(1e-4)
    assert float(belief.cov[0, 0]) == 1.0
    path.write_text(json.dumps({"status": "error"}), encoding="utf-8")
    with pytest.raises(ConfigError, match="has no belief"):
        load_prior_from(path)
    with pytest.raises(ConfigError, match="cannot read"):
        load_prior_from(tmp_path / "missing.json")
    two_links = {name: {"mean": 1.0, "std": 0.1} for name in StateLayout(1).names}
    with pytest.raises(ConfigError, match="another number of links"):
        known_parameters(
            Belief(torch.zeros(21, dtype=DTYPE), torch.eye(21, dtype=DTYPE)),
            StateLayout(2), two_links, path,
        )  # fmt: skip


@pytest.mark.parametrize(
    "entry", [{"mean": 0.8}, 0.8, {"mean": "abc", "std": 0.1}, {"mean": 0.8, "std": -0.1}]
)
def test_a_malformed_prior_from_entry_names_it(tmp_path: Path, entry: object) -> None:
    """A hand-written file of measured values is checked entry by entry before anything
    moves: a missing std, a bare number, text or a negative std name the entry."""
    path = tmp_path / "measured.json"
    path.write_text(json.dumps({"belief": {"f_0": {"mean": 0.3, "std": 0.01}, "m_0": entry}}))
    with pytest.raises(ConfigError, match=r"belief\.m_0 is .*\{\"mean\": <number>"):
        load_prior_from(path)
