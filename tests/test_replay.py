"""``vistac replay``: a recorded run's belief updates again, offline, with the run's filter or
another one; and the pieces it reads back (actions, shapes, episodes)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from conftest import SKILLS, run_vistac
from vistac.behaviours.look import shape_from_links, shape_links
from vistac.cli import main
from vistac.errors import DataError
from vistac.protocols import Episode, StepObservation
from vistac.recording import RunRecorder
from vistac.replay import load_episode
from vistac.testing import two_box_scene
from vistac.types import (
    RGBD,
    ArmState,
    CameraIntrinsics,
    Pull,
    Push,
    TactileReading,
    action_from_dict,
    action_to_dict,
)


def test_actions_read_back_as_written() -> None:
    for action in (
        Push(np.array([0.1, 0.4]), 0.3, 0.02, 3.0, link=1),
        Pull(np.array([-0.1, 0.5]), -1.2, 0.015, 0.4, 2.0),
    ):
        back = action_from_dict(json.loads(json.dumps(action_to_dict(action))))
        assert type(back) is type(action) and action_to_dict(back) == action_to_dict(action)
    with pytest.raises(DataError, match="unknown action kind 'poke'"):
        action_from_dict({**action_to_dict(Push(np.zeros(2), 0.0, 0.02)), "kind": "poke"})


def test_shapes_read_back_as_written() -> None:
    shape = two_box_scene().shape
    assert shape is not None
    back = shape_from_links(json.loads(json.dumps(shape_links(shape))), shape.cloud)
    np.testing.assert_array_equal(back.initial_poses, shape.initial_poses)
    np.testing.assert_array_equal(back.uncertainty, shape.uncertainty)
    for link, original in zip(back.links, shape.links, strict=True):
        for name in ("scale_m", "exponents", "world_from_sq", "taper"):
            np.testing.assert_array_equal(getattr(link, name), getattr(original, name))


def test_episodes_read_back_as_recorded(tmp_path: Path) -> None:
    intrinsics = CameraIntrinsics(8, 6, 7.0, 7.5, 4.0, 3.0)
    rng = np.random.default_rng(2)
    steps = [
        StepObservation(
            0.1 * t,
            TactileReading(rng.normal(size=(2, 2)), 0.1 * t + 0.01),
            ArmState(rng.normal(size=4), rng.normal(size=4), 0.1 * t),
            RGBD(rng.uniform(0.4, 0.6, (6, 8)), intrinsics, np.eye(4), 0.1 * t),
            rng.normal(size=(2, 3)),
        )
        for t in range(3)
    ]
    episode = Episode(4, Push(np.array([0.0, 0.4]), 0.5, 0.02, 2.0, link=1), steps)
    back = load_episode(RunRecorder(tmp_path).save_episode(episode, None))
    assert back.index == 4 and back.outcome == "ok"
    assert action_to_dict(back.action) == action_to_dict(episode.action)
    for got, want in zip(back.steps, steps, strict=True):
        assert got.time_s == want.time_s and got.tactile.timestamp_s == want.tactile.timestamp_s
        np.testing.assert_array_equal(got.tactile.force_n, want.tactile.force_n)
        np.testing.assert_array_equal(got.arm.pose, want.arm.pose)
        np.testing.assert_array_equal(got.arm.twist, want.arm.twist)
        np.testing.assert_array_equal(got.ground_truth_poses, want.ground_truth_poses)
        assert got.depth is not None and want.depth is not None
        assert got.depth.intrinsics == intrinsics
        np.testing.assert_allclose(got.depth.depth_m, want.depth.depth_m, rtol=1e-7)  # float32


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One push of rect2 with the analytical model and the dual filter, recorded."""
    out = tmp_path_factory.mktemp("replay") / "run"
    result = run_vistac(
        "-q", "run", str(SKILLS / "explore_push.yaml"), "--out", str(out),
        "--set", "tree.sequence.1.repeat.max=1",
        "--set", "components.model={plugin: filters.analytical}",
        "--set", "components.filter.with.sigma_points=40",
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    return out


def _belief(folder: Path) -> dict[str, dict[str, float]]:
    summary = json.loads((folder / "summary.json").read_text())
    assert summary["status"] == "success"
    belief: dict[str, dict[str, float]] = summary["belief"]
    return belief


def test_replay_reproduces_the_runs_belief(recorded: Path, tmp_path: Path) -> None:
    """The run's own filter on the recorded stream ends exactly where the run ended (the
    filter reads depth at the float32 precision runs record it at)."""
    out = tmp_path / "again"
    result = run_vistac("-q", "replay", str(recorded), "--out", str(out))
    assert result.returncode == 0, result.stderr
    online, offline = _belief(recorded), _belief(out)
    assert online.keys() == offline.keys()
    assert offline == online
    summary = json.loads((out / "summary.json").read_text())
    assert len(summary["filter_steps"]) == summary["episodes"][0]["steps"]
    assert set(summary["errors"]) == {"m_0", "f_0", "com_x_0", "com_y_0"}
    info = json.loads((out / "run.json").read_text())
    assert info["replay_of"] == str(recorded) and info["status"] == "success"


def test_each_filter_step_predicts_with_the_tcp_at_its_start(
    recorded: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """As the models were trained: step k is predicted from k - 1 with the TCP of step k - 1
    (the first step with its own), and the push-level rollout likewise."""
    from vistac.pluginmanager import load_plugins
    from vistac.plugins.filters import component, dual
    from vistac.replay import replay

    seen: list[float] = []
    step = dual.DualFilter.step

    def spy(self: Any, belief: Any, inputs: Any, *args: Any, **kwargs: Any) -> Any:
        seen.append(float(inputs.tcp[0]))
        return step(self, belief, inputs, *args, **kwargs)

    rollouts: list[list[float]] = []
    end_poses = component.end_poses

    def rollout_spy(predict: Any, layout: Any, states: Any, inputs: Any, *args: Any) -> Any:
        rollouts.append([float(i.tcp[0]) for i in inputs])
        return end_poses(predict, layout, states, inputs, *args)

    monkeypatch.setattr(dual.DualFilter, "step", spy)
    monkeypatch.setattr(component, "end_poses", rollout_spy)
    replay(recorded, tmp_path / "out", load_plugins())
    episode = load_episode(recorded / "episodes" / "0000")
    tcp_x = [float(s.arm.pose[0]) for s in episode.steps if s.depth is not None]
    assert len(tcp_x) > 3 and len(set(tcp_x)) > 2  # the TCP moves
    assert seen == [tcp_x[0], *tcp_x[:-1]]
    assert rollouts == [tcp_x[:-1]]  # push_evidence is on in explore_push.yaml


def test_replay_with_another_filter_setting(recorded: Path, tmp_path: Path) -> None:
    """--set changes the replayed filter: the shipped GNN in place of the analytical model
    moves the estimates elsewhere, from the same prior."""
    out = tmp_path / "gnn"
    result = run_vistac(
        "-q", "replay", str(recorded), "--out", str(out), "--set",
        "components.model={plugin: filters.gnn, with: {checkpoint: checkpoints/gnn_push.pt, "
        "hidden: 32}}",
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    info = json.loads((out / "run.json").read_text())
    assert info["config"]["components"]["model"]["plugin"] == "filters.gnn"
    summary = json.loads((out / "summary.json").read_text())
    assert summary["prior"] == json.loads((recorded / "summary.json").read_text())["prior"]
    online, gnn = _belief(recorded), _belief(out)
    assert max(abs(gnn[n]["mean"] - online[n]["mean"]) for n in ("m_0", "f_0", "com_x_0")) > 1e-3


def test_replay_with_push_evidence(recorded: Path, tmp_path: Path) -> None:
    """The push-level update (on in explore_push.yaml) runs after the push: the CoM it scores
    ends surer than the step-by-step filter alone leaves it, and within 2 std of the truth
    (rect2's CoM is its centre; after one push both beliefs are a few mm off, so which is
    nearer is chance: the evaluations compare them over many runs); the pose stays where the
    filter tracked it."""
    folders = {}
    for enabled in ("false", "true"):
        folders[enabled] = tmp_path / enabled
        result = run_vistac(
            "-q", "replay", str(recorded), "--out", str(folders[enabled]),
            "--set", f"components.filter.with.push_evidence.enabled={enabled}",
        )  # fmt: skip
        assert result.returncode == 0, result.stderr
    steps, push = _belief(folders["false"]), _belief(folders["true"])
    assert push == _belief(recorded)
    errors = {
        enabled: json.loads((folder / "summary.json").read_text())["errors"]
        for enabled, folder in folders.items()
    }
    for name in ("com_x_0", "com_y_0"):
        assert push[name]["std"] < steps[name]["std"]
        assert errors["true"][name] < 2 * push[name]["std"]
    for name in ("x_0", "y_0"):
        assert abs(push[name]["mean"] - steps[name]["mean"]) < 1e-3


def test_replay_refuses_a_folder_it_cannot_use(recorded: Path, tmp_path: Path) -> None:
    missing = run_vistac("replay", str(tmp_path / "nothing"), "--out", str(tmp_path / "o"))
    assert missing.returncode == 2 and "run.json: not found" in missing.stderr
    old = tmp_path / "old"  # as recorded before runs kept the filter's start
    shutil.copytree(recorded, old)
    (old / "views/object_cloud.npz").unlink()
    result = run_vistac("replay", str(old), "--out", str(tmp_path / "o"))
    assert result.returncode == 2 and "no filter_start" in result.stderr
    assert not (tmp_path / "o").exists()  # nothing half-done left behind
    (old / "run.json").write_text("{}")
    bare = run_vistac("replay", str(old), "--out", str(tmp_path / "o"))
    assert bare.returncode == 2 and "no skill config" in bare.stderr


def test_replay_of_a_real_robot_run_builds_no_hardware(recorded: Path, tmp_path: Path) -> None:
    """A run of skills/real/explore_push.yaml replays on a machine without the robot: only
    the filter and its model are built (a UR5 at 192.168.1.10 would be dialled otherwise).
    The recorded stream is the simulated one, under the real skill's configuration."""
    run = tmp_path / "real_run"
    shutil.copytree(recorded, run)
    info = json.loads((run / "run.json").read_text())
    real = SKILLS / "real/explore_push.yaml"
    info.update(skill_path=str(real), config=yaml.safe_load(real.read_text()))
    (run / "run.json").write_text(json.dumps(info))
    out = tmp_path / "replayed"
    result = run_vistac("-q", "replay", str(run), "--out", str(out), timeout_s=120)
    assert result.returncode == 0, result.stderr
    replay = json.loads((out / "run.json").read_text())
    assert replay["config"]["components"]["arm"]["plugin"] == "ur_rtde.arm"
    prior = json.loads((out / "summary.json").read_text())["prior"]
    assert _belief(out)["m_0"]["std"] < prior["m_0"]["std"]  # the pushes informed it


@pytest.mark.parametrize("where", ["", "sub", ".."], ids=["same", "inside", "around"])
def test_replay_refuses_an_out_folder_overlapping_the_run(
    recorded: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], where: str
) -> None:
    """``--out RUN --overwrite`` deleted the recording it was about to replay."""
    run = tmp_path / "run"
    shutil.copytree(recorded, run)
    out = run / where if where != ".." else tmp_path
    assert main(["-q", "replay", str(run), "--out", str(out), "--overwrite"]) == 2
    assert "overlaps the replayed run" in capsys.readouterr().err
    assert sorted(p.name for p in run.iterdir()) == sorted(p.name for p in recorded.iterdir())
    assert not (run / "sub").exists()


def test_replay_with_a_checkpoint_that_is_not_there_writes_nothing(
    recorded: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "o"
    missing = tmp_path / "nonexistent.pt"
    args = ["--set", f"components.filter.with.noise_checkpoint={missing}"]
    assert main(["-q", "replay", str(recorded), "--out", str(out), *args]) == 2
    assert f"no such file {missing}" in capsys.readouterr().err
    assert not out.exists()


def test_replay_out_naming_a_file_is_exit_2(
    recorded: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "afile"
    out.write_text("not a folder")
    assert main(["-q", "replay", str(recorded), "--out", str(out)]) == 2
    assert f"--out: {out} is a file; give a folder" in capsys.readouterr().err
