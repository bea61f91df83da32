"""``vistac information``: replays of recorded pushes, their Jacobians and the Bayes floor."""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from simctx import GRIPPER_Z_M, PUSH_RATE_HZ, PUSH_SPEED_MPS, box_object, sim_setup
from vistac.cli import main
from vistac.objects import MASS_RANGE_KG, ObjectSpec, link_frames, object_from_dict
from vistac.plugins.filters.data import central_twist, load_trajectories
from vistac.plugins.filters.information import (
    DEFAULT_ERROR,
    WINDOW_STEPS,
    ModelError,
    ModelReport,
    ObjectInformation,
    PushReplay,
    RecordedPush,
    measured_error,
    noise_covariance,
    parameter_names,
    posterior_covariance,
    prior_covariance,
    push_jacobian,
    repeated_share,
    replayed_pushes,
    sensitivity_agreement,
    squared_errors,
)

ROOT = Path(__file__).resolve().parents[1]


def straight_push(spec: ObjectSpec, seconds: float, start_x_m: float = -0.06) -> RecordedPush:
    """A push along +x through link 0's frame at 20 mm/s, the pads starting ``start_x_m``
    from it: a recording with the object where the spec puts it (a push planned, not run)."""
    steps = round(seconds * PUSH_RATE_HZ) + 1
    time_s = np.arange(steps) / PUSH_RATE_HZ
    x, y, _ = spec.pose
    arm = np.zeros((steps, 4))
    arm[:, 0] = x + start_x_m + PUSH_SPEED_MPS * time_s
    arm[:, 1], arm[:, 2] = y, GRIPPER_Z_M
    poses = np.repeat(link_frames(spec)[None], steps, axis=0)
    return RecordedPush(spec, time_s, arm, poses)


def box(**link: float) -> ObjectSpec:
    return object_from_dict(box_object(link=link))


def test_a_replay_retraces_a_push_the_world_recorded(tmp_path: Path) -> None:
    ctx = sim_setup(tmp_path, box_object(link={"com_m": [0.01, 0.02]}))
    world, arm, gripper = ctx.find("world"), ctx.find("arm"), ctx.find("gripper")
    gripper.close()
    world.step(1.0)
    planned = straight_push(world.spec, 4.0)
    index, model, data = world.index, world.model, world.data
    data.qpos[index.arm_qpos] = planned.arm_pose[0]
    data.act[model.actuator_actadr[index.arm_actuators]] = planned.arm_pose[0]
    data.qvel[index.arm_dof] = 0.0
    arm_pose, object_pose = [], []
    for _ in planned.time_s:
        arm_pose.append(arm.state().pose)
        object_pose.append(world.link_poses())
        arm.command_velocity(np.array([PUSH_SPEED_MPS, 0.0, 0.0, 0.0]))
        world.step(1.0 / PUSH_RATE_HZ)
    recorded = RecordedPush(world.spec, planned.time_s, np.array(arm_pose), np.array(object_pose))
    moved_m = np.linalg.norm(recorded.object_pose[-1, 0, :2] - recorded.object_pose[0, 0, :2])
    turned_rad = abs(recorded.object_pose[-1, 0, 2] - recorded.object_pose[0, 0, 2])
    assert moved_m > 0.03 and turned_rad > 0.05  # an off-centre CoM: the box turns

    replayed, _ = PushReplay(world.spec).run(recorded)
    assert np.abs(replayed[..., :2] - recorded.object_pose[..., :2]).max() < 1e-3
    assert np.abs(replayed[..., 2] - recorded.object_pose[..., 2]).max() < math.radians(0.5)


def test_parameters_set_on_the_model_equal_a_world_built_with_them() -> None:
    spec = box(mass_kg=0.5, friction=0.3)
    other = box(mass_kg=1.1, friction=0.45, com_m=(0.015, -0.01))
    push = straight_push(spec, 3.0)
    values = np.array([1.1, 0.45, 0.015, -0.01])
    set_on_model, _ = PushReplay(spec).run(push, values)
    built, _ = PushReplay(other).run(push)
    assert np.abs(set_on_model - built).max() < 1e-9
    assert np.abs(set_on_model[-1] - PushReplay(spec).run(push)[0][-1]).max() > 1e-3


def test_the_force_of_a_push_through_the_com_shows_the_friction_load() -> None:
    """Quasi-static: the pad balances the table's friction, m f g, so the mean force moves
    by about m g per unit of friction (8 % more over f 0.22-0.38). A heavier box of the same
    load needs a little more force in this simulator (measured: 4 % more than m f g at 0.8 kg,
    +0.15 N per kg at a fixed load), so m moves it by f g and somewhat more. Moving the CoM
    across the push line turns the box; moving it along the line does little."""
    mass_kg, friction = 0.8, 0.3
    spec = box(mass_kg=mass_kg, friction=friction)
    jacobian = push_jacobian(PushReplay(spec), straight_push(spec, 5.0))
    assert jacobian.shape == (3 * 5, 4)  # 75 steps: 3 windows of x, y, theta, force x, y
    sliding = jacobian[5:10]  # the middle window: the pads push from start to end
    g = 9.81
    assert -sliding[3, 1] == pytest.approx(mass_kg * g, rel=0.1)  # the pads feel -x
    assert friction * g < -sliding[3, 0] < 1.5 * friction * g
    assert abs(sliding[2, 3]) > 20 * abs(sliding[2, 2])  # theta: com_y against com_x
    assert sliding[0, 3] == pytest.approx(0.0, abs=0.02)  # x: not moved by the CoM
    assert sliding[3, 3] == pytest.approx(0.0, abs=0.1)  # nor the force along the push


def test_posterior_covariance_by_hand() -> None:
    prior = np.diag([4.0, 1.0])
    jacobian = np.array([[1.0, 0.0], [1.0, 0.0]])
    noise = np.sqrt([8.0, 8.0])
    # Two looks at the first parameter, each of variance 8: information 1/4 + 1/8 + 1/8.
    cov = posterior_covariance(jacobian, prior, noise)
    np.testing.assert_allclose(cov, np.diag([2.0, 1.0]), atol=1e-12)
    as_matrix = posterior_covariance(jacobian, prior, np.diag(noise**2))
    np.testing.assert_allclose(as_matrix, cov, atol=1e-12)
    far = posterior_covariance(jacobian, prior, np.array([1e9, 1e9]))
    np.testing.assert_allclose(far, prior, rtol=1e-9)


def test_rows_add_the_com_axes_and_keep_the_hinge() -> None:
    names = ("m_0", "f_0", "com_x_0", "com_y_0", "f_j_0")
    rows = squared_errors(names, np.diag([1.0, 2.0, 3.0, 4.0, 5.0]))
    assert rows == {"m_0": 1.0, "f_0": 2.0, "CoM_0": 7.0, "f_j_0": 5.0}


def test_the_prior_is_the_object_sets_sampling_spread() -> None:
    cov = prior_covariance(box())
    assert cov[0, 0] == pytest.approx((MASS_RANGE_KG[1] - MASS_RANGE_KG[0]) ** 2 / 12)
    half_m = 0.045 * 0.95  # rect1 is 90 mm square, its CoMs drawn in 95 % of it
    np.testing.assert_allclose(np.diag(cov)[2:], [half_m**2 / 3] * 2, rtol=1e-9)


def test_more_pushes_show_more() -> None:
    spec = box(mass_kg=0.8, friction=0.3, com_m=(0.0, 0.01))
    replay = PushReplay(spec)
    one = push_jacobian(replay, straight_push(spec, 2.0))
    assert len(one) == 5  # 30 steps: one window; the last 4 steps are too few for another
    info = ObjectInformation(spec, [Path("0000")], [one], [2.0])
    twice = ObjectInformation(spec, [Path("0000"), Path("0001")], [one, one], [2.0, 2.0])
    single, double = info.squared_errors(DEFAULT_ERROR), twice.squared_errors(DEFAULT_ERROR)
    prior = squared_errors(replay.names, prior_covariance(spec))
    for row in prior:
        assert double[row] < single[row] < prior[row]
    # An error that repeats whole is the same again in the same push: it shows nothing more
    repeating = replace(DEFAULT_ERROR, repeated=1.0)
    again = twice.squared_errors(repeating)
    for row, value in info.squared_errors(repeating).items():
        assert again[row] == pytest.approx(value, rel=1e-6)
    half = twice.squared_errors(replace(DEFAULT_ERROR, repeated=0.5))
    for row in prior:
        assert double[row] < half[row] < single[row]


def test_noise_covariance_of_repeating_errors() -> None:
    """Each window keeps its variance; a repeated share s correlates two windows by s, the
    positions and forces turned by the pushes' directions (a half turn: -s), the angles not."""
    error = ModelError(0.002, 0.05, 0.5, repeated=0.3)
    cov = noise_covariance(error, 1, [0.4, 0.4 + math.pi])
    var = error.per_window(1) ** 2
    np.testing.assert_allclose(np.diag(cov), np.tile(var, 2), rtol=1e-12)
    np.testing.assert_allclose(np.diag(cov[:5, 5:]), 0.3 * var * [-1, -1, 1, -1, -1], rtol=1e-9)
    np.testing.assert_allclose(cov, cov.T, atol=1e-15)
    independent = noise_covariance(replace(error, repeated=0.0), 1, [0.4, 1.0])
    np.testing.assert_allclose(independent, np.diag(np.tile(var, 2)), atol=1e-15)
    report = ModelReport({}, error, repeated_share=0.4, independent_share=0.2)
    assert report.repeating_error.repeated == pytest.approx(0.25)
    assert ModelReport({}, error, 0.1, 0.2).repeating_error.repeated == 0.0


def test_measured_error_pools_links_and_axes() -> None:
    one_link = np.array([[0.003, -0.004, 0.1, 1.0, -1.0]])  # x, y, theta, force x, y
    two_links = np.array([[0.0, 0.0, 0.0, 0.003, 0.004, -0.1, 2.0, 0.0]])
    error = measured_error([(one_link, 1), (two_links, 2)])
    # position: 3, -4, 0, 0, 3, 4 mm; angle: 0.1, 0, -0.1; force: 1, -1, 2, 0 N
    assert error.position_m == pytest.approx(math.sqrt(50e-6 / 6))
    assert error.angle_rad == pytest.approx(math.sqrt(0.02 / 3))
    assert error.force_n == pytest.approx(math.sqrt(6 / 4))



def test_repeated_share_of_window_errors() -> None:
    weights = DEFAULT_ERROR.per_window(1)
    along = np.array([0.004, 0.0, 0.0, 0.5, 0.0])  # 4 mm and 0.5 N against the push
    # The same error along each push, pushes in two directions: one error repeated.
    turned = np.array([0.0, 0.004, 0.0, 0.0, 0.5])  # along +y for a push along +y
    same = [(np.tile(along, (3, 1)), 0.0), (np.tile(turned, (2, 1)), math.pi / 2)]
    assert repeated_share(same, weights) == pytest.approx(1.0)
    # Errors that cancel from window to window repeat nothing.
    signs = np.array([[1.0], [-1.0], [1.0], [-1.0]])
    assert repeated_share([(signs * along, 0.3)], weights) == pytest.approx(0.0, abs=1e-12)
    # Independent errors: about 1 / W.
    rng = np.random.default_rng(0)
    noise = [(rng.normal(size=(10, 5)) * weights, rng.uniform(-3, 3)) for _ in range(100)]
    assert repeated_share(noise, weights) == pytest.approx(1 / 1000, abs=0.002)

def test_information_refuses_a_folder_without_runs(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["-q", "information", str(tmp_path)]) == 2
    error = capsys.readouterr().err
    assert "neither a run folder" in error and "--variant" in error
    with pytest.raises(SystemExit) as exit_info:
        main(["-q", "information", str(tmp_path), "--scale", "0"])
    assert exit_info.value.code == 2
    assert "not a finite number above 0" in capsys.readouterr().err
    assert main(["-q", "information", str(tmp_path), "--out", str(tmp_path)]) == 2
    assert "is a folder; give a file" in capsys.readouterr().err
    collect = str(ROOT / "skills/collect_pushes.yaml")  # a skill without a process model
    assert main(["-q", "information", str(tmp_path), "--skill", collect]) == 2
    assert "no components.model to compare" in capsys.readouterr().err
    assert sorted(tmp_path.iterdir()) == []  # nothing written


def test_window_steps_are_the_trainings_rollout() -> None:
    from vistac.plugins.filters.train import TrainConfig

    assert TrainConfig().rollout_steps == WINDOW_STEPS


def write_episode(folder: Path, push: RecordedPush) -> Path:
    """A recorded push as a run's episode folder (meta.json and data.npz), its poses and
    forces those of a replay at the true parameters."""
    poses, force_n = PushReplay(push.spec).run(push)
    folder.mkdir(parents=True)
    meta = {"action": {"kind": "push", "pd_rad": 0.0, "link": 0},
            "ground_truth": {"object": push.spec.model_dump(mode="json"),
                             "parameters": push.spec.parameters()}}  # fmt: skip
    (folder / "meta.json").write_text(json.dumps(meta), encoding="utf-8")
    np.savez(folder / "data.npz", time_s=push.time_s, object_pose=poses,
             arm_pose=push.arm_pose, arm_twist=np.gradient(push.arm_pose, axis=0) * PUSH_RATE_HZ,
             tactile_force_n=np.stack([force_n, np.zeros_like(force_n)], axis=1))  # fmt: skip
    return folder


def test_replayed_pushes_move_with_their_own_parameters(tmp_path: Path) -> None:
    spec = box(mass_kg=0.8, friction=0.3)
    folder = write_episode(tmp_path / "run/episodes/0000", straight_push(spec, 5.0))
    recorded = load_trajectories([tmp_path / "run"])
    replayed = replayed_pushes(recorded, 8, np.random.default_rng(0))
    again = replayed_pushes(recorded, 8, np.random.default_rng(0))
    assert len(replayed) == 8
    loads_n, forces_n = [], []
    for trajectory, same in zip(replayed, again, strict=True):
        assert trajectory.parameters == same.parameters != recorded[0].parameters
        np.testing.assert_array_equal(trajectory.poses, same.poses)
        np.testing.assert_array_equal(trajectory.tcp, recorded[0].tcp)
        assert trajectory.source == f"{folder} (replayed)" and trajectory.depth_m is None
        np.testing.assert_allclose(trajectory.twists,
                                   central_twist(trajectory.poses, 1 / PUSH_RATE_HZ), rtol=1e-9)
        truth = trajectory.parameters
        # Pushed along +x through the footprint's centre, the box turns towards its CoM's side.
        if abs(truth["com_y_0"]) > 0.005:
            assert np.sign(trajectory.poses[-1, 0, 2]) == np.sign(truth["com_y_0"])
        loads_n.append(truth["m_0"] * truth["f_0"] * 9.81)
        forces_n.append(-trajectory.force_n[30:60, 0].mean())  # the pads feel -x
    # The pad pushes at most the table's friction (less while the box turns).
    assert np.all(np.array(forces_n) < 1.1 * np.array(loads_n))
    assert np.corrcoef(loads_n, forces_n)[0, 1] > 0.7


def test_agreement_of_a_model_that_moves_twice_as_much_or_the_other_way() -> None:
    rng = np.random.default_rng(0)
    sim = rng.normal(size=(2 * 5, 4))  # two windows of a one-link object, four parameters
    model = 2.0 * sim
    model[:, 3] *= -1.0
    names = ("m_0", "f_0", "com_x_0", "com_y_0")
    agreement = sensitivity_agreement([(model, sim, 1)], names, DEFAULT_ERROR)
    for name in names[:3]:
        assert agreement[name] == pytest.approx({"cosine": 1.0, "length_ratio": 2.0})
    assert agreement["com_y_0"] == pytest.approx({"cosine": -1.0, "length_ratio": 2.0})


def test_information_of_a_recorded_run_with_the_skills_model(tmp_path: Path) -> None:
    """End to end on a run folder: the table, and the shipped push GNN's sensitivities,
    which follow the simulator's where a straight push shows them best (the force by the
    friction, the turn by the CoM across the push)."""
    spec = box(mass_kg=0.8, friction=0.3, com_m=(0.0, 0.01))
    write_episode(tmp_path / "run/episodes/0000", straight_push(spec, 5.0))
    out = tmp_path / "information.json"
    code = main(["-q", "information", str(tmp_path / "run"), "--scale", "1", "0.5",
                 "--skill", str(ROOT / "skills/explore_push.yaml"), "--out", str(out)])
    assert code == 0
    report = json.loads(out.read_text(encoding="utf-8"))
    table = report["tables"]["homogeneous"]
    assert list(table)[:3] == ["x 1", "x 0.5", "own"] and table["x 1"]["runs"] == 1
    prior = squared_errors(parameter_names(spec), prior_covariance(spec))
    for row in ("m_0", "f_0", "CoM_0"):
        assert table["x 0.5"][row] < table["x 1"][row]
    assert table["x 1"]["f_0"] < math.sqrt(prior["f_0"]) / 0.4
    model = report["model"]["homogeneous"]
    agreement = model["agreement"]
    assert agreement["f_0"]["cosine"] > 0.8 and agreement["com_y_0"]["cosine"] > 0.5
    # Its own error on this push, and what the push shows at that error.
    assert 0 < model["error"]["position_m"] < 0.01 and 0 < model["error"]["force_n"] < 1.0
    assert table["own"]["runs"] == 1 and 0 < table["own"]["overall"] < 0.3
    assert model["independent_share"] == pytest.approx(1 / 3)  # one push, three windows
    assert 0 < model["repeated_share"] <= 1
