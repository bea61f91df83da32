"""Training data, the filters.dual component, `vistac train` and the explore skills."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any, cast

import numpy as np
import pytest
import torch
from conftest import run_vistac
from pydantic import ValidationError
from vistac.cli import build_parser, main
from vistac.errors import ConfigError
from vistac.objects import attachment, load_object, to_link_frame, to_world_xy
from vistac.plugins.filters.component import (
    AXES_CLEAR,
    DualFilterComponent,
    ModelFrames,
    Prior,
    frame_yaws,
    nearest_link,
    outline_axes,
    prior_belief,
    relative_poses,
)
from vistac.plugins.filters.data import (
    central_twist,
    link_geometry,
    load_trajectories,
    unwrap_theta,
)
from vistac.plugins.filters.dual import Belief
from vistac.plugins.filters.evaluate import (
    belief_poses,
    episode_true_poses,
    first_poses,
    run_links,
)
from vistac.plugins.filters.nets import hinge_offsets
from vistac.plugins.filters.state import DTYPE, ProcessInput, StateLayout
from vistac.plugins.filters.train import (
    TrainConfig,
    belief_loss,
    correlation_steps,
    fit,
    object_files,
    recorded_data,
    training_filter,
)
from vistac.protocols import Filter, Scene
from vistac.testing import build_components, check_component_class
from vistac.types import CameraIntrinsics, PointCloud, ShapeEstimate, Superquadric

ROOT = Path(__file__).resolve().parents[1]
SKILLS = ROOT / "skills"


def _wrapping_poses(dt_s: float, steps: int = 6) -> tuple[np.ndarray, np.ndarray]:
    """Poses [T, 1, 3] of a link turning at 0.5 rad/s whose reported theta wraps from +pi to
    -pi, and the continuous theta [T]."""
    t = np.arange(steps) * dt_s
    continuous = np.pi - 0.05 + 0.5 * t
    theta = np.angle(np.exp(1j * continuous))
    assert theta.min() < 0 < theta.max()
    return np.stack([0.02 * t, -0.01 * t, theta], axis=1)[:, None, :], continuous


def test_twist_by_central_differences_of_the_unwrapped_angle() -> None:
    poses, continuous = _wrapping_poses(0.1)
    unwrapped = unwrap_theta(poses)
    np.testing.assert_allclose(unwrapped[:, 0, 2], continuous, atol=1e-9)
    np.testing.assert_array_equal(unwrapped[..., :2], poses[..., :2])
    twist = central_twist(unwrapped, 0.1)
    np.testing.assert_allclose(twist[:, 0], np.tile([0.02, -0.01, 0.5], (6, 1)), atol=1e-9)


def _write_episode(run: Path, poses: np.ndarray, dt_s: float) -> None:
    """A recorded push of rect1 with the link poses [T, 1, 3] in ``run``/episodes/0000."""
    steps = len(poses)
    spec = load_object(SKILLS / "objects" / "rect1.yaml")
    folder = run / "episodes" / "0000"
    folder.mkdir(parents=True)
    meta = {"ground_truth": {"object": spec.model_dump(mode="json"),
                             "parameters": {"m_0": 0.8, "f_0": 0.3, "com_x_0": 0.0,
                                            "com_y_0": 0.0}},
            "action": {"kind": "push", "pd_rad": 0.0, "link": 0}}  # fmt: skip
    (folder / "meta.json").write_text(json.dumps(meta), encoding="utf-8")
    np.savez(folder / "data.npz", time_s=np.arange(steps) * dt_s, object_pose=poses,
             arm_pose=np.zeros((steps, 6)), arm_twist=np.zeros((steps, 6)),
             tactile_force_n=np.zeros((steps, 2, 2)))  # fmt: skip


def test_a_loaded_episode_turning_past_pi_has_a_continuous_angle(tmp_path: Path) -> None:
    """Else the pose error of training and validation is 2 pi where theta wraps."""
    dt_s = 1 / 15
    poses, continuous = _wrapping_poses(dt_s)
    _write_episode(tmp_path / "run", poses, dt_s)
    (trajectory,) = load_trajectories([tmp_path / "run"])
    np.testing.assert_allclose(trajectory.poses[:, 0, 2], continuous, atol=1e-9)
    np.testing.assert_allclose(trajectory.twists[:, 0, 2], 0.5, atol=1e-6)


def test_an_episode_whose_object_tipped_over_is_left_out(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """A link lying on its side has an ill-defined yaw that jumps by radians from one step to
    the next (recorded so in simulation): no planar model can learn that."""
    poses, _ = _wrapping_poses(1 / 15)
    poses[3:, 0, 2] = [-1.39, 2.24, -3.11]
    _write_episode(tmp_path / "run", poses, 1 / 15)
    assert load_trajectories([tmp_path / "run"]) == []
    assert "object tipped over" in caplog.text
    out = tmp_path / "out"
    code = main(["-q", "train", str(SKILLS / "collect_pushes.yaml"), "--preset", "tiny",
                 "--data", str(tmp_path / "run"), "--out", str(out)])  # fmt: skip
    assert code != 0 and not out.exists()  # nothing to train on, and no empty folder left


def test_link_geometry_of_a_two_link_object() -> None:
    spec = load_object(SKILLS / "objects" / "artic_rect_rect.yaml")
    size, offset = link_geometry(spec)
    np.testing.assert_allclose(size, [[0.045, 0.045], [0.045, 0.045]], atol=1e-9)
    # Link 1 sits one box width plus the 4 mm hinge gap along link 0's x axis.
    np.testing.assert_allclose(offset, [[0, 0, 0], [0.094, 0, 0]], atol=1e-9)


def test_nearest_link_and_relative_poses() -> None:
    poses = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, np.pi / 2]])
    sizes = np.array([[0.04, 0.02], [0.04, 0.02]])
    points = np.array([[0.03, 0.0, 0.01], [0.1, 0.035, 0.01], [0.07, 0.0, 0.0]])
    assert nearest_link(points, poses, sizes).tolist() == [0, 1, 1]
    np.testing.assert_allclose(relative_poses(poses), [[0, 0, 0], [0.1, 0, np.pi / 2]])
    # A batch of objects: each element as on its own.
    turned = poses + np.array([0.2, -0.1, 0.7])
    batch = np.stack([poses, turned, poses[::-1]])
    batch_points = np.stack([points, points + np.array([0.2, -0.1, 0.0]), points])
    want = [nearest_link(p, q, sizes).tolist() for p, q in zip(batch_points, batch, strict=True)]
    assert nearest_link(batch_points, batch, sizes).tolist() == want
    np.testing.assert_allclose(relative_poses(batch), [relative_poses(q) for q in batch])


def _box_shape() -> ShapeEstimate:
    pose = np.eye(4)
    pose[:3, 3] = [0.0, 0.45, 0.025]
    link = Superquadric(np.array([0.045, 0.056, 0.025]), np.array([0.1, 0.1]), pose)
    cloud = PointCloud(np.random.default_rng(0).normal([0, 0.45, 0.03], 0.02, (300, 3)))
    return ShapeEstimate((link,), np.array([[0.0, 0.45, 0.0]]), np.zeros((1, 14)), cloud)


def _filter(tmp_path: Path, model: dict[str, object]) -> DualFilterComponent:
    specs = {"model": model, "filter": {"plugin": "filters.dual"}}
    component: DualFilterComponent = build_components(specs, tmp_path).component("filter")
    return component


def _fit_quadratic(train_target: float, val_target: float, epochs: int = 5) -> tuple[float, int]:
    """fit() on one weight w (start 0), train loss (w - train_target)^2, validation loss
    (w - val_target)^2: (the weight it keeps, epochs run)."""
    weight = torch.nn.Linear(1, 1, bias=False)
    torch.nn.init.zeros_(weight.weight)

    def train() -> Any:
        yield (weight.weight.sum() - train_target).square()

    def val() -> float:
        return float((weight.weight.detach().sum() - val_target).square())

    config = TrainConfig(learning_rate=0.1, patience=2)
    history = fit(list(weight.parameters()), train, val, [weight], epochs, config, "test")
    return float(weight.weight.detach().sum()), len(history)


def test_fit_keeps_the_best_epoch_and_never_a_worse_model_than_the_start() -> None:
    kept, _ = _fit_quadratic(train_target=1.0, val_target=1.0)
    assert 0.4 < kept < 0.6  # Adam: about 0.1 per step; the last epoch is the best
    kept, epochs = _fit_quadratic(train_target=1.0, val_target=-1.0)
    assert kept == 0.0 and epochs == 2  # every epoch moved away: the start is kept


def test_belief_loss_by_hand_and_across_a_constraint() -> None:
    """One link, the belief equal to the starting one (std 1 cm, 0.1 rad, ... in the loss's
    units: 1; the parameters' 1): with the 1% floor each entry's variance is 1.01, and an
    error of one unit in x gives 0.5 (1 / 1.01 + 10 log 1.01) / 10 + 1 / 10. A belief with
    no variance left across a direction (a joint's constraint) that the truth misses by
    0.1 mm costs a few units, not the 1e10 of the exact NLL."""
    layout = StateLayout(1)
    scale = torch.tensor([0.01, 0.01, 0.1, 0.01, 0.01, 0.1] + [1.0] * 4, dtype=torch.float64)
    belief = Belief(torch.zeros(10, dtype=torch.float64), torch.diag(scale**2))
    truth = torch.zeros(10, dtype=torch.float64)
    truth[0] = 0.01
    expected = 0.5 * (1 / 1.01 + 10 * np.log(1.01)) / 10 + 1 / 10
    assert float(belief_loss(truth, belief, scale**2, layout)) == pytest.approx(expected)
    cov = belief.cov.clone()
    cov[0, 0] = cov[1, 1] = cov[0, 1] = cov[1, 0] = 0.01**2  # x and y move together
    truth[:2] = torch.tensor([0.0001, -0.0001])
    loss = float(belief_loss(truth, Belief(belief.mean, cov), scale**2, layout))
    assert abs(loss) < 5.0


def test_correlation_steps_of_known_error_sequences() -> None:
    constant = torch.full((40, 2), 0.3, dtype=torch.float64)  # a bias: one observation
    assert correlation_steps([constant]) == pytest.approx(40.0)
    alternating = torch.tensor([[1.0], [-1.0]] * 20, dtype=torch.float64)
    assert correlation_steps([alternating]) == 1.0  # rho_1 < 0: nothing summed
    white = torch.randn(200, 2, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    assert 0.7 < correlation_steps([white, white.flip(0)]) < 1.6


def test_the_filter_counts_the_noise_checkpoints_evidence_steps(tmp_path: Path) -> None:
    from vistac.plugins.filters.observation import ObsNoiseNet

    noise = ObsNoiseNet()
    noise.evidence_steps.fill_(25.0)
    torch.save(noise.state_dict(), tmp_path / "noise.pt")
    settings: dict[str, Any] = {"noise_checkpoint": str(tmp_path / "noise.pt")}
    specs = {"model": {"plugin": "filters.analytical"},
             "filter": {"plugin": "filters.dual", "with": settings}}  # fmt: skip
    # the measured steps times the default evidence_factor (2)
    assert build_components(specs, tmp_path).component("filter").evidence_scale == 1 / 50
    settings["evidence_factor"] = 1.0
    assert build_components(specs, tmp_path).component("filter").evidence_scale == 1 / 25
    settings["evidence_steps"] = 5.0  # the skill's setting wins
    assert build_components(specs, tmp_path).component("filter").evidence_scale == 1 / 5
    assert _filter(tmp_path, {"plugin": "filters.analytical"}).evidence_scale == 1.0  # untrained


def test_the_end_to_end_epochs_filter_with_a_skills_evidence_and_bounds(tmp_path: Path) -> None:
    from vistac.plugins.filters.observation import ObsNoiseNet, ProjectionObservationModel

    noise = ObsNoiseNet()
    noise.evidence_steps.fill_(20.0)
    model = build_components({"m": {"plugin": "filters.analytical"}}, tmp_path).component("m")
    observation = cast(ProjectionObservationModel, None)  # stored, not used to build
    dual = training_filter(StateLayout(2), model, observation, noise, sigma_points=16)
    skill = DualFilterComponent.Config()
    assert dual.sigma_points == 16
    assert dual.evidence_scale == pytest.approx(1 / (20.0 * skill.evidence_factor))
    assert dual.twist_bound == (skill.max_link_speed_mps, skill.max_link_rate_radps)
    assert (dual.liu_west_delta, dual.min_ess_fraction) == (
        skill.liu_west_delta, skill.min_ess_fraction
    )
    assert dual.push_load_only is skill.push_load_only is True
    off = DualFilterComponent.Config(push_load_only=False)
    assert not off.dual_filter(StateLayout(1), model, observation, None).push_load_only


def test_the_skills_tactile_settings_reach_the_observation_model() -> None:
    from vistac.plugins.filters.observation import DepthProjector, ObsNoiseNet

    points = np.array([[0.5, 0.0, 0.02], [0.52, 0.01, 0.02]])
    camera = np.eye(4)
    camera[:3, 3] = (0.5, 0.0, 0.6)
    camera[:3, :3] = np.diag([1.0, -1.0, -1.0])  # looking straight down
    projector = DepthProjector(
        points, np.zeros(2, dtype=np.int64), np.array([[0.5, 0.0, 0.0]]),
        CameraIntrinsics(320, 240, 300.0, 300.0, 160.0, 120.0), camera,
    )  # fmt: skip
    for setting, contact_n in ((None, None), ((0.05, 0.2), 0.3)):
        config = DualFilterComponent.Config(tactile_std=setting, contact_force_n=contact_n)
        model = config.observation_model(StateLayout(1), projector, ObsNoiseNet())
        assert (model.tactile_std, model.contact_force_n) == (setting, contact_n)
        assert model.occlusion_margin_m == config.occlusion_margin_m


def test_filters_dual_is_a_filter_component(tmp_path: Path) -> None:
    check_component_class(DualFilterComponent)
    assert isinstance(_filter(tmp_path, {"plugin": "filters.analytical"}), Filter)


def test_initial_belief_comes_from_the_shape_and_the_prior(tmp_path: Path) -> None:
    belief = _filter(tmp_path, {"plugin": "filters.gnn"}).initialise(
        Scene(_box_shape().cloud, _box_shape())
    )
    assert belief.names == StateLayout(1).names
    values = dict(zip(belief.names, belief.mean, strict=True))
    stds = dict(zip(belief.names, belief.std, strict=True))
    # the footprint's centroid: the box's centre
    assert values["x_0"] == pytest.approx(0.0, abs=1e-6)
    assert values["y_0"] == pytest.approx(0.45, abs=1e-6)
    assert values["m_0"] == pytest.approx(0.9) and stds["m_0"] == pytest.approx(0.4)
    assert values["f_0"] == pytest.approx(0.3) and stds["com_x_0"] == pytest.approx(0.028)
    in_shape = {"plugin": "filters.dual", "with": {"prior": {"com_in_shape": True}}}
    specs = {"model": {"plugin": "filters.gnn"}, "filter": in_shape}
    shaped = build_components(specs, tmp_path).component("filter").initialise(
        Scene(_box_shape().cloud, _box_shape())
    )
    values = dict(zip(shaped.names, shaped.mean, strict=True))
    stds = dict(zip(shaped.names, shaped.std, strict=True))
    # The CoM uniform over the fitted footprint: a near-rectangle of 90 x 112 mm.
    assert abs(values["com_x_0"]) < 1e-4 and abs(values["com_y_0"]) < 1e-4
    assert stds["com_x_0"] == pytest.approx(0.090 / 12**0.5, rel=0.03)
    assert stds["com_y_0"] == pytest.approx(0.112 / 12**0.5, rel=0.03)


def test_the_reported_com_adds_the_model_discrepancy_the_filter_keeps_its_own(
    tmp_path: Path,
) -> None:
    """com_discrepancy_m [a, b] adds (a + b |kappa1|)^2 to each reported CoM variance (kappa1
    the fitted taper), nothing to the other entries nor to the filter's own belief."""
    shape = _standing_link([0.045, 0.06, 0.02], [0.1, 0.1], [-0.8, 0.0], 0.3)
    plain = _filter(tmp_path, {"plugin": "filters.gnn"}).initialise(Scene(shape.cloud, shape))
    specs = {
        "model": {"plugin": "filters.gnn"},
        "filter": {"plugin": "filters.dual", "with": {"com_discrepancy_m": [0.01, 0.02]}},
    }
    component = build_components(specs, tmp_path).component("filter")
    reported = component.initialise(Scene(shape.cloud, shape))
    added = reported.cov - plain.cov
    rows = [reported.names.index(name) for name in ("com_x_0", "com_y_0")]
    want = np.zeros_like(added)
    want[rows, rows] = (0.01 + 0.02 * 0.8) ** 2
    np.testing.assert_allclose(added, want, atol=1e-15)
    np.testing.assert_allclose(component.belief.cov.numpy(), plain.cov, atol=1e-15)


def _standing_link(scale_m: list[float], exponents: list[float], taper: list[float],
                   theta_rad: float) -> ShapeEstimate:  # fmt: skip
    """One superquadric link at (0.1, 0.4) turned theta_rad, as a shape estimate."""
    pose = np.eye(4)
    pose[:2, :2] = [[np.cos(theta_rad), -np.sin(theta_rad)], [np.sin(theta_rad), np.cos(theta_rad)]]
    pose[:3, 3] = [0.1, 0.4, 0.02]
    link = Superquadric(np.array(scale_m), np.array(exponents), pose, np.array(taper))
    return ShapeEstimate((link,), np.array([[0.1, 0.4, theta_rad]]), np.zeros((1, 14)),
                         _box_shape().cloud)  # fmt: skip


def test_model_frames_of_a_fitted_link() -> None:
    """In the link's own frame, wherever it stands and however it is turned: an ellipse (a1,
    a2) sheared by x += s y keeps its centre, reaches sqrt(a1^2 + s^2 a2^2) along x and has
    covariance S diag(a1^2, a2^2) S' / 4, S = [[1, s], [0, 1]]; a near-rectangle tapered
    linearly (x scaled by 1 + k y / a2) is a trapezoid whose centroid lies k a2 / 3 towards
    its wide end. ``fitted`` frames are the fit's boxes, the footprint's centroid in them;
    ``trained`` frames stand at the centroid, their half extents measured from there as the
    training's are."""
    a1_m, a2_m, shear, taper = 0.03, 0.05, 0.4, 0.45
    ellipse = _standing_link([a1_m, a2_m, 0.02], [1.0, 1.0], [0.0, 0.0, shear], 2.0)
    stretch = np.array([[1.0, shear], [0.0, 1.0]])
    expected = stretch @ np.diag([a1_m**2, a2_m**2]) @ stretch.T / 4
    for convention in ("fitted", "trained"):
        frames = ModelFrames.of(ellipse, convention)
        np.testing.assert_allclose(frames.origin_m, np.zeros((1, 2)), atol=2e-5)
        np.testing.assert_allclose(frames.footprint_mean_m, np.zeros((1, 2)), atol=2e-5)
        np.testing.assert_allclose(frames.poses, ellipse.initial_poses, atol=2e-5)
        np.testing.assert_allclose(frames.footprint_cov_m2[0], expected, rtol=2e-3, atol=1e-8)
    reach_m = [[np.hypot(a1_m, shear * a2_m), a2_m]]
    np.testing.assert_allclose(frames.half_extents_m, reach_m, rtol=2e-3)
    np.testing.assert_allclose(ModelFrames.of(ellipse).half_extents_m, [[a1_m, a2_m]])
    theta = -0.7
    trapezoid = _standing_link([a1_m, a2_m, 0.02], [0.1, 0.1], [taper, 0.0], theta)
    shift_m = taper * a2_m / 3
    fitted = ModelFrames.of(trapezoid)
    np.testing.assert_array_equal(fitted.poses, trapezoid.initial_poses)
    np.testing.assert_allclose(fitted.footprint_mean_m, [[0.0, shift_m]], atol=5e-4)
    np.testing.assert_array_equal(fitted.box_poses(fitted.poses), fitted.poses)
    frames = ModelFrames.of(trapezoid, "trained")
    np.testing.assert_allclose(frames.origin_m, [[0.0, shift_m]], atol=5e-4)
    np.testing.assert_allclose(frames.poses[0, :2],
                               [0.1 - np.sin(theta) * shift_m, 0.4 + np.cos(theta) * shift_m],
                               atol=5e-4)  # fmt: skip
    # eps = 0.1 rounds the corners: the wide end's corners fall 1.5 mm short of a1 (1 + k)
    np.testing.assert_allclose(frames.half_extents_m, [[a1_m * (1 + taper), a2_m + shift_m]],
                               atol=2e-3)  # fmt: skip
    np.testing.assert_allclose(frames.box_poses(frames.poses), trapezoid.initial_poses, atol=1e-12)
    mean_m, cov_m2 = frames.footprint_mean_m, frames.footprint_cov_m2
    layout = StateLayout(1)
    belief = prior_belief(np.zeros((1, 6)), Prior(), layout, (mean_m, cov_m2))
    block = [layout.index("com_x_0"), layout.index("com_y_0")]
    np.testing.assert_allclose(belief.cov[block][:, block].numpy(), cov_m2[0])


def test_too_few_sigma_points_for_the_state_are_warned_of(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """A box's state has 10 entries: 10 points cannot be whitened (the parameters would
    drift), 11 can."""
    scene = Scene(_box_shape().cloud, _box_shape())
    for count, warned in ((10, True), (11, False)):
        caplog.clear()
        specs = {"model": {"plugin": "filters.gnn"},
                 "filter": {"plugin": "filters.dual", "with": {"sigma_points": count}}}  # fmt: skip
        build_components(specs, tmp_path).component("filter").initialise(scene)
        assert ("cannot be whitened" in caplog.text) is warned, count


@pytest.mark.parametrize(
    ("options", "where"),
    [
        ({"pose_std_floor": [-0.01, 0, 0, 0, 0, 0]}, "pose_std_floor.0"),
        ({"prior": {"mass_kg": [0.9, -0.4]}}, "prior.mass_kg.1"),
        ({"prior": {"com_m": [0.0, 0.0]}}, "prior.com_m.1"),
        ({"hinge_std_m": 0.0}, "hinge_std_m"),
    ],
)
def test_a_negative_std_is_refused_when_the_skill_is_read(options: dict, where: str) -> None:
    """Checked with the skill, before anything moves (the filter is built after a push)."""
    with pytest.raises(ValidationError, match=where.replace(".", r"\.")):
        DualFilterComponent.Config.model_validate(options)


def test_filter_needs_a_process_model(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="needs a process_model"):
        build_components({"filter": {"plugin": "filters.dual"}}, tmp_path).component("filter")


def test_fixed_link_model_rejects_another_link_count(tmp_path: Path) -> None:
    component = _filter(tmp_path, {"plugin": "filters.ff", "with": {"n_links": 2}})
    with pytest.raises(ConfigError, match="handles 2 link"):
        component.initialise(Scene(_box_shape().cloud, _box_shape()))


def _summary(out: Path) -> dict[str, object]:
    summary: dict[str, object] = json.loads((out / "summary.json").read_text(encoding="utf-8"))
    return summary


EXPLORE_SHORT = ("--set", "tree.sequence.1.repeat.max=1")


@pytest.mark.parametrize(
    "model",
    [
        "components.model.with.hidden=32",  # the shipped GNN checkpoint
        "components.model={plugin: filters.ff, with: {n_links: 1}}",
        "components.model={plugin: filters.analytical}",
    ],
    ids=["gnn", "ff", "analytical"],
)
def test_explore_push_runs_with_each_process_model(tmp_path: Path, model: str) -> None:
    out = tmp_path / "run"
    result = run_vistac(
        "-q", "run", str(SKILLS / "explore_push.yaml"), "--out", str(out), *EXPLORE_SHORT,
        "--set", model,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    summary = _summary(out)
    belief = summary["belief"]
    assert isinstance(belief, dict)
    assert {"m_0", "f_0", "com_x_0", "com_y_0"} <= set(belief)
    assert all(np.isfinite(entry["mean"]) for entry in belief.values())
    assert "parameter" in result.stdout and "truth" in result.stdout
    # the truth of the CoM is told in the belief's frame (the object rests at the end)
    truth, told = summary["ground_truth"], summary["belief_truth"]
    x, y, theta = (belief[f"{key}_0"]["mean"] for key in ("x", "y", "theta"))
    link_x, link_y, link_theta = truth["link_poses"][0]
    com = truth["parameters"]["com_x_0"], truth["parameters"]["com_y_0"]
    world = (link_x + np.cos(link_theta) * com[0] - np.sin(link_theta) * com[1],
             link_y + np.sin(link_theta) * com[0] + np.cos(link_theta) * com[1])  # fmt: skip
    dx, dy = world[0] - x, world[1] - y
    local = (np.cos(theta) * dx + np.sin(theta) * dy, -np.sin(theta) * dx + np.cos(theta) * dy)
    assert (told["com_x_0"], told["com_y_0"]) == pytest.approx(local)
    assert summary["errors"]["com_x_0"] == pytest.approx(abs(belief["com_x_0"]["mean"] - local[0]))


def test_trained_link_frames_stand_where_training_puts_them(tmp_path: Path) -> None:
    """``link_frames: trained`` on a welded rectangle and triangle, end to end: at the first
    filter step the belief's links stand at the true link frames (the footprint centroids),
    both turned as the object, or both a half turn off when the fit numbered the links the
    other way, so that each next link lies on the +x side as in training."""
    out = tmp_path / "run"
    result = run_vistac(
        "-q", "run", str(SKILLS / "explore_push.yaml"), "--out", str(out), *EXPLORE_SHORT,
        "--set", "components.world.with.object=objects/hetero_rect_tri.yaml",
        "--set", "components.filter.with.link_frames=trained",
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    summary = _summary(out)
    poses = first_poses(out, summary)
    assert poses is not None
    belief, truth = poses
    links = run_links(summary, poses)
    assert sorted(links.values()) == [0, 1]
    for b, t in links.items():
        assert np.hypot(*(belief[b, :2] - truth[t, :2])) < 0.006
    turn = np.angle(np.exp(1j * (belief[:, 2] - truth[0, 2])))
    flipped = links[0] == 1
    np.testing.assert_allclose(np.abs(turn), np.pi if flipped else 0.0, atol=np.radians(4))
    bad = run_vistac("validate", str(SKILLS / "explore_push.yaml"),
                     "--set", "components.filter.with.link_frames=training")  # fmt: skip
    assert bad.returncode != 0 and "link_frames" in bad.stdout + bad.stderr


def _joint_gaps_m(run: Path, summary: dict[str, Any]) -> np.ndarray:
    """[steps] how far apart the belief's two links put the true joint, found in both at the
    first filter step."""
    steps = cast(list[dict[str, Any]], summary["filter_steps"])
    spec = load_object(SKILLS / "objects" / "artic_rect_rect.yaml")
    _, hinge = attachment(spec)
    assert hinge is not None
    poses = belief_poses(steps, [0, 1])
    truth = episode_true_poses(run, int(steps[0]["episode"]))[0]
    joint = to_world_xy(hinge[None], truth[0])
    ends = [to_link_frame(joint, poses[0, k]) for k in (0, 1)]
    return np.array([np.linalg.norm(to_world_xy(ends[0], pose[0]) - to_world_xy(ends[1], pose[1]))
                     for pose in poses])  # fmt: skip


def test_held_joints_keep_a_hinged_pairs_tracked_links_together(tmp_path: Path) -> None:
    """``hinge_std_m`` on a hinged pair, end to end: the pushes filtered again (``vistac
    replay``) with the joint held keep the links' ends of the true joint together, which
    tracking each link on its own does not."""
    out, held = tmp_path / "run", tmp_path / "held"
    result = run_vistac(
        "-q", "run", str(SKILLS / "explore_push.yaml"), "--out", str(out),
        "--set", "tree.sequence.1.repeat.max=2",
        "--set", "components.world.with.object=objects/artic_rect_rect.yaml",
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    result = run_vistac("-q", "replay", str(out), "--out", str(held),
                        "--set", "components.filter.with.hinge_std_m=0.002")  # fmt: skip
    assert result.returncode == 0, result.stderr
    apart = _joint_gaps_m(out, _summary(out))  # measured 2.5 mm on average, at most 4.8
    together = _joint_gaps_m(out, _summary(held))  # 0.9 and 2.1 mm
    assert apart.mean() > 0.0015
    assert together.mean() < 0.0012 and together.max() < 0.003


def _pair_of_boxes(turn_rad: float) -> ShapeEstimate:
    """Two fitted 90 x 90 mm boxes side by side along x, 4 mm apart (the joint at (0.147,
    0.4)), the second one's frame turned by turn_rad (a box's symmetry)."""
    links = []
    for x_m, theta_rad in ((0.1, 0.0), (0.194, turn_rad)):
        pose = np.eye(4)
        c, s = np.cos(theta_rad), np.sin(theta_rad)
        pose[:2, :2] = [[c, -s], [s, c]]
        pose[:3, 3] = [x_m, 0.4, 0.025]
        links.append(Superquadric(np.array([0.045, 0.045, 0.025]), np.array([0.1, 0.1]), pose))
    poses = np.array([[0.1, 0.4, 0.0], [0.194, 0.4, turn_rad]])
    return ShapeEstimate(tuple(links), poses, np.zeros((2, 14)), _box_shape().cloud)


def test_models_get_the_joint_where_the_outlines_meet_with_joints_from_outlines(
    tmp_path: Path,
) -> None:
    """With the second box's frame a half turn round, the learned models' rule (link 0's +x
    side, link 1's -x side) puts the joint 45 mm off; ``joints_from: outlines`` gives the
    models the joint where the fitted outlines meet, within 2 mm."""
    shape = _pair_of_boxes(np.pi)
    true_joint = np.array([[0.147, 0.4]])
    specs = {"model": {"plugin": "filters.gnn"},
             "filter": {"plugin": "filters.dual", "with": {"joints_from": "outlines"}}}
    component = build_components(specs, tmp_path).component("filter")
    component.initialise(Scene(shape.cloud, shape))
    poses = component.frames.poses
    given = component._model_joints()["hinge_m"].numpy()
    assert np.linalg.norm(to_world_xy(given, poses[0]) - true_joint) < 0.002
    boxes = _filter(tmp_path / "boxes", {"plugin": "filters.gnn"})
    boxes.initialise(Scene(shape.cloud, shape))
    assert boxes._model_joints() == {}
    zero = torch.zeros((), dtype=DTYPE)
    fitted = ProcessInput(torch.zeros(6, dtype=DTYPE), zero, zero, torch.tensor(0),
                          torch.as_tensor(component.frames.half_extents_m, dtype=DTYPE),
                          torch.as_tensor(relative_poses(poses), dtype=DTYPE))  # fmt: skip
    rule = hinge_offsets(fitted)[0].numpy()
    assert np.linalg.norm(to_world_xy(rule, poses[0]) - true_joint) > 0.04


FF_BY_LINKS = (
    "components.model={plugin: filters.ff, with: {hidden: 32, checkpoints: "
    "{1: checkpoints/ff1/ff_push.pt, 2: checkpoints/ff2/ff_push.pt}}}"
)


@pytest.mark.parametrize(("name", "links"), [("rect2", 1), ("artic_rect_rect", 2)])
def test_one_ff_skill_filters_objects_of_each_shipped_link_count(
    tmp_path: Path, name: str, links: int
) -> None:
    """`filters.ff` with a checkpoint per link count: the same skill filters a one-link and
    a two-link object, each with the FF of its fitted link count."""
    out = tmp_path / "run"
    result = run_vistac(
        "-q", "run", str(SKILLS / "explore_push.yaml"), "--out", str(out), *EXPLORE_SHORT,
        "--set", FF_BY_LINKS, "--set", f"components.world.with.object=objects/{name}.yaml",
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    belief = _summary(out)["belief"]
    assert isinstance(belief, dict)
    assert {f"m_{link}" for link in range(links)} == {k for k in belief if k.startswith("m_")}
    assert all(np.isfinite(entry["mean"]) for entry in belief.values())


def test_a_push_blocked_on_its_way_down_is_not_carried_out_and_another_is_chosen(
    tmp_path: Path, cli: Callable[..., tuple[int, str, str]]
) -> None:
    """The first push's fingers come down on the object: the arm lifts off, no episode is
    recorded, the belief is not updated, and the next choice keeps ``avoid_blocked_m``
    away although the selector asks for the candidate nearest the blocked one."""
    out = tmp_path / "run"
    code, stdout, stderr = cli(
        "run", str(SKILLS / "explore_push.yaml"), "--out", str(out),
        "--set", "tree.sequence.1.repeat.max=2",
        "--set", "tree.sequence.1.repeat.do.0={choose_action: {avoid_blocked_m: 0.04}}",
        "--set", "components.planner={plugin: test.onto_object_first, with: {inward_m: 0.03}}",
    )  # fmt: skip
    assert code == 0, stderr
    summary = cast(dict[str, Any], _summary(out))
    (blocked,) = summary["blocked_actions"]
    assert blocked["blocked_at_m"][2] > 0.04, "stopped on the object's top (50 mm high)"
    (episode,) = summary["episodes"]
    assert episode["index"] == blocked["episode"] == 0
    gap_m = np.linalg.norm(np.subtract(episode["action"]["point_m"], blocked["point_m"]))
    assert gap_m > 0.04
    assert len(summary["belief_history"]) == 1
    assert len(list((out / "episodes").iterdir())) == 1
    assert "not carried out: push at" in stdout


def test_a_corrupt_checkpoint_is_a_clear_error(tmp_path: Path) -> None:
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"not a checkpoint")
    result = run_vistac(
        "run", str(SKILLS / "explore_push.yaml"), "--out", str(tmp_path / "run"),
        "--set", f"components.model.with.checkpoint={bad}",
    )  # fmt: skip
    assert result.returncode != 0
    assert "bad.pt" in result.stderr and "vistac train" in result.stderr
    assert "Traceback" not in result.stderr


def test_generated_objects_capped_per_split_keep_every_type(tmp_path: Path) -> None:
    files = object_files(TrainConfig(objects="generated", max_objects=4), SKILLS, tmp_path)
    for split in ("train", "val"):
        specs = [load_object(path) for path in files[split]]  # real files under tmp_path
        assert len(specs) == 4
        assert [spec.type for spec in specs[:3]] == ["homogeneous", "heterogeneous", "articulated"]
    everything = object_files(TrainConfig(objects="generated"), SKILLS, tmp_path)
    assert (len(everything["train"]), len(everything["val"])) == (96, 12)


def test_an_unknown_preset_is_a_clear_error(tmp_path: Path) -> None:
    result = run_vistac(
        "train", str(SKILLS / "collect_pushes.yaml"), "--out", str(tmp_path), "--preset", "huge"
    )
    assert result.returncode == 2
    assert "unknown preset 'huge'" in result.stderr


def test_training_data_without_validation_runs_is_refused_before_any_output(
    tmp_path: Path,
) -> None:
    (tmp_path / "data" / "train").mkdir(parents=True)
    out = tmp_path / "out"
    result = run_vistac("train", str(SKILLS / "collect_pushes.yaml"), "--out", str(out),
                        "--data", str(tmp_path / "data"))  # fmt: skip
    assert result.returncode == 2 and "no validation runs in" in result.stderr
    assert not out.exists()


def test_an_out_that_is_a_file_is_named_before_any_output(tmp_path: Path) -> None:
    out = tmp_path / "afile"
    out.write_text("not a folder")
    result = run_vistac("train", str(SKILLS / "collect_pushes.yaml"), "--out", str(out),
                        "--preset", "tiny")  # fmt: skip
    assert result.returncode == 2
    assert f"--out: {out} is a file; give a folder" in result.stderr
    assert out.read_text() == "not a folder"


def test_a_missing_data_folder_is_named_before_any_output(tmp_path: Path) -> None:
    (tmp_path / "data" / "train").mkdir(parents=True)
    (tmp_path / "data" / "val").mkdir()
    out = tmp_path / "out"
    result = run_vistac("train", str(SKILLS / "collect_pushes.yaml"), "--out", str(out),
                        "--data", str(tmp_path / "nowhere"), str(tmp_path / "data"))  # fmt: skip
    assert result.returncode == 2
    assert f"no such folder {tmp_path / 'nowhere'}; check the path" in result.stderr
    assert not out.exists()


def test_data_takes_several_folders_after_one_flag_or_one_per_flag() -> None:
    parser = build_parser()
    common = ["train", "skill.yaml", "--out", "out"]
    one_flag = parser.parse_args([*common, "--data", "a", "b"])
    two_flags = parser.parse_args([*common, "--data", "a", "--data", "b"])
    assert one_flag.data == two_flags.data == [Path("a"), Path("b")]


def test_tiny_training_gives_checkpoints_the_explore_skill_can_use(tmp_path: Path) -> None:
    out = tmp_path / "train"
    result = run_vistac("-q", "train", str(SKILLS / "collect_pushes.yaml"), "--out", str(out))
    assert result.returncode == 0, result.stderr
    report = json.loads((out / "train.json").read_text(encoding="utf-8"))
    history = report["push"]["gnn"]["history"]
    assert history[-1]["val"] < history[0]["val"], "training did not reduce the validation loss"
    assert report["push"]["windows"]["missed"] > 0  # missed-push copies were trained on
    # `--data` on this training's data/ folder keeps its train/val split.
    recorded = recorded_data([out / "data"])
    for split in ("train", "val"):
        assert len(recorded[split]) == report["data"][split]["trajectories"] > 0
    with pytest.raises(ConfigError, match="not both"):
        recorded_data([out / "data", next((out / "data" / "val").iterdir())])
    for name in ("gnn_push.pt", "ff_push.pt", "obs_noise_push.pt"):
        assert (out / name).stat().st_size < 2_000_000
        assert isinstance(torch.load(out / name, weights_only=True), dict)
    run = run_vistac(
        "-q", "run", str(SKILLS / "explore_push.yaml"), "--out", str(tmp_path / "run"),
        *EXPLORE_SHORT,
        "--set", f"components.model.with.checkpoint={out / 'gnn_push.pt'}",
        "--set", f"components.filter.with.noise_checkpoint={out / 'obs_noise_push.pt'}",
    )  # fmt: skip
    assert run.returncode == 0, run.stderr
    # The same data again with each training push also replayed with redrawn parameters.
    preset = tmp_path / "replayed.yaml"
    preset.write_text(json.dumps({
        "models": ["gnn"], "interactions": ["push"], "hidden": 8, "epochs": 1,
        "noise_epochs": 1, "filter_epochs": 0, "batch_size": 8, "replayed_pushes": 2,
    }), encoding="utf-8")  # fmt: skip
    again = run_vistac("-q", "train", str(SKILLS / "collect_pushes.yaml"), "--out",
                       str(tmp_path / "replayed"), "--preset", str(preset), "--data",
                       str(out / "data"))  # fmt: skip
    assert again.returncode == 0, again.stderr
    windows = json.loads((tmp_path / "replayed/train.json").read_text())["push"]["windows"]
    assert windows["replayed"] == 2 * windows["train"] > 0


def test_a_feed_forward_alone_trains_one_model_per_link_count(tmp_path: Path) -> None:
    """models: [ff] on one- and two-link objects: the noise net learns the first FF's force
    error on its own link count (it was handed every object and raised on the first two-link
    one)."""
    preset = tmp_path / "ff.yaml"
    preset.write_text(json.dumps({
        "shipped_train": ["rect1", "artic_rect_rect"], "shipped_val": ["rect3", "hetero_rect_tri"],
        "models": ["ff"], "interactions": ["push"], "hidden": 8, "epochs": 1, "noise_epochs": 1,
        "filter_epochs": 0, "batch_size": 4, "collect_overrides": [
            "tree.sequence.0.repeat.max=2", "components.affordances.with.interactions=[push]"],
    }), encoding="utf-8")  # fmt: skip
    out = tmp_path / "train"
    result = run_vistac("-q", "train", str(SKILLS / "collect_pushes.yaml"), "--out", str(out),
                        "--preset", str(preset))  # fmt: skip
    assert result.returncode == 0, result.stderr
    for name in ("ff1/ff_push.pt", "ff2/ff_push.pt", "obs_noise_push.pt"):
        assert (out / name).is_file()


def test_explore_pull_pulls_six_times_and_ends_with_a_belief(tmp_path: Path) -> None:
    """The shipped pull skill runs to its end: its pulls keep the object in reach (they used
    to walk it towards the robot until no pull was left, and the run failed)."""
    out = tmp_path / "pull"
    result = run_vistac("run", str(SKILLS / "explore_pull.yaml"), "--out", str(out))
    assert result.returncode == 0, result.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["status"] == "success"
    assert [e["action"]["kind"] for e in summary["episodes"]] == ["pull"] * 6
    assert {"m_0", "f_0", "com_x_0"} <= set(summary["belief"])


def _dense(polygon: np.ndarray, turn_rad: float, per_edge: int = 60) -> np.ndarray:
    """A CCW polygon [K, 2] turned by turn_rad about the origin, with per_edge points along
    each edge: [K per_edge, 2]."""
    ends = np.roll(polygon, -1, axis=0)
    fraction = np.arange(per_edge)[None, :, None] / per_edge
    points = (polygon[:, None] + fraction * (ends - polygon)[:, None]).reshape(-1, 2)
    c, s = np.cos(turn_rad), np.sin(turn_rad)
    return points @ np.array([[c, s], [-s, c]])


RECTANGLE = np.array([[-0.04, -0.03], [0.04, -0.03], [0.04, 0.03], [-0.04, 0.03]])
CIRCLE = 0.05 * np.column_stack([np.cos(np.arange(360) * np.pi / 180),
                                 np.sin(np.arange(360) * np.pi / 180)])  # fmt: skip


def test_outline_axes_follow_straight_sides() -> None:
    """A rectangle runs all along its axes; a right triangle with legs a, b along them
    (a + b) / (a + b + c) of its length; a circle along no direction."""
    yaw, clarity = outline_axes(_dense(RECTANGLE, 2.0))
    assert yaw == pytest.approx(2.0 - np.pi / 2, abs=1e-9) and clarity == pytest.approx(1.0)
    a_m, b_m = 0.06, 0.1
    triangle = np.array([[0.0, 0.0], [a_m, 0.0], [0.0, b_m]])
    yaw, clarity = outline_axes(_dense(triangle, 1.0))
    assert yaw == pytest.approx(1.0, abs=1e-9)
    assert clarity == pytest.approx((a_m + b_m) / (a_m + b_m + np.hypot(a_m, b_m)), abs=0.02)
    assert outline_axes(CIRCLE)[1] < AXES_CLEAR


def test_frame_yaws_give_a_chain_one_yaw_along_it() -> None:
    """Whatever axes the fit gave each link: a chain's links take the axes of the one that
    shows them, those nearest the direction from the first link to the last; the direction
    itself where no link shows its axes; a single link keeps the axes nearest its fit's."""
    turn, chain = 0.3, 0.5
    at = (0.1 * np.cos(chain), 0.1 * np.sin(chain))
    rectangle, circle = _dense(RECTANGLE, turn), CIRCLE + np.array(at)
    fitted = np.array([turn + np.pi / 2, 2.9])
    np.testing.assert_allclose(frame_yaws(fitted, [rectangle, circle]), [turn, turn])
    back = frame_yaws(fitted[::-1], [circle, rectangle])
    np.testing.assert_allclose(np.exp(1j * back), [np.exp(1j * (turn + np.pi))] * 2)
    np.testing.assert_allclose(frame_yaws(fitted, [CIRCLE, circle]), [chain, chain])
    single = frame_yaws(np.array([turn + np.pi / 2 + 0.05]), [rectangle])
    np.testing.assert_allclose(single, [turn + np.pi / 2])
