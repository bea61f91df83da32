"""Active iterative training (paper 1, IV-B2): replay buffer, stop rule, validation error, and
one tiny end-to-end run of `vistac train --selection info_gain`."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
import yaml
from vistac.cli import main
from vistac.errors import ConfigError, DataError
from vistac.objects import link_frames, load_object
from vistac.plugins.filters import active
from vistac.plugins.filters.active import (
    ACTIVE_PRESETS,
    ReplayBuffer,
    active_settings,
    repeat_key,
    stop_reason,
    trajectories_to_threshold,
    trajectories_to_threshold_by_type,
    validation_error,
)
from vistac.plugins.filters.data import Trajectory, acted_link, load_trajectories
from vistac.plugins.filters.evaluate import read_skill
from vistac.plugins.filters.nets import RATE_SCALE_RADPS, SPEED_SCALE_MPS
from vistac.plugins.filters.state import DTYPE, Prediction, ProcessInput, StateLayout
from vistac.plugins.filters.train import (
    TrainConfig,
    disturb_twist,
    load_preset,
    one_step_force_loss,
    predicted_forces,
    rollout_errors,
    rollout_loss,
)

ROOT = Path(__file__).resolve().parents[1]
SKILLS = ROOT / "skills"


pytestmark = pytest.mark.usefixtures("single_thread")


def _trajectory(name: str, steps: int = 4) -> Trajectory:
    """A still rect1 (pose (0, 0.45, 0)) and a constant finger force of (1, 0) N."""
    zeros = np.zeros((steps, 1, 3))
    poses = zeros + np.array([0.0, 0.45, 0.0])
    return Trajectory(
        source=name, spec=load_object(SKILLS / "objects/rect1.yaml"), kind="push", pd_rad=0.0,
        link=0, dt_s=1 / 15, poses=poses, twists=zeros, tcp=np.zeros((steps, 6)),
        force_n=np.tile([1.0, 0.0], (steps, 1)), depth_m=None, camera_pose=None,
        intrinsics=None, parameters={"m_0": 0.8, "f_0": 0.3, "com_x_0": 0.0, "com_y_0": 0.0},
    )  # fmt: skip


def test_replay_buffer_keeps_the_newest_up_to_its_capacity() -> None:
    a, b, c, d = (_trajectory(name) for name in "abcd")
    buffer = ReplayBuffer(capacity=3)
    buffer.add([a, b])
    assert buffer.trajectories == [a, b] and buffer.added == 2
    buffer.add([c, d])
    assert buffer.trajectories == [b, c, d]  # the oldest (the seed) goes first
    assert (len(buffer), buffer.added) == (3, 4)
    unbounded = ReplayBuffer()
    unbounded.add([a, b])
    unbounded.add(iter([c]))
    assert unbounded.trajectories == [a, b, c] and unbounded.added == 3
    assert unbounded.added_by_type == {"homogeneous": 3}
    with pytest.raises(ValueError, match="capacity must be >= 1"):
        ReplayBuffer(capacity=0)


@pytest.mark.parametrize(
    ("val_error", "rounds_done", "expected"),
    [(0.5, 1, "threshold"), (0.49, 5, "threshold"), (0.51, 4, None), (0.51, 5, "max_rounds")],
)
def test_stop_rule(val_error: float, rounds_done: int, expected: str | None) -> None:
    assert stop_reason(val_error, threshold=0.5, rounds_done=rounds_done, max_rounds=5) == expected


def test_trajectories_to_threshold() -> None:
    rounds = [{"trajectories": 2, "val_error": 0.9}, {"trajectories": 4, "val_error": 0.45},
              {"trajectories": 6, "val_error": 0.3}]  # fmt: skip
    assert trajectories_to_threshold(rounds, 0.5) == 4
    assert trajectories_to_threshold(rounds, 0.3) == 6
    assert trajectories_to_threshold(rounds, 0.1) is None


def test_trajectories_to_threshold_by_type_counts_that_types_trajectories() -> None:
    rounds = [
        {"by_type": {"homogeneous": {"trajectories": 1, "val_error": 0.4},
                     "articulated": {"trajectories": 1, "val_error": 0.9}}},
        {"by_type": {"homogeneous": {"trajectories": 3, "val_error": 0.2},
                     "articulated": {"trajectories": 2, "val_error": 0.45}}},
        {"by_type": {"homogeneous": {"trajectories": 5, "val_error": 0.3}}},
    ]  # fmt: skip
    assert trajectories_to_threshold_by_type(rounds, 0.5) == {"articulated": 2, "homogeneous": 1}
    assert trajectories_to_threshold_by_type(rounds, 0.25) == {"articulated": None,
                                                                "homogeneous": 3}  # fmt: skip
    assert trajectories_to_threshold_by_type([{"val_error": 1.0}], 0.5) == {}


def test_summary_names_what_each_object_type_needed() -> None:
    rounds = [{"round": 0, "trajectories": 4, "val_error": 0.6,
               "by_type": {"homogeneous": {"trajectories": 2, "val_error": 0.4},
                           "articulated": {"trajectories": 2, "val_error": 0.8}}}]  # fmt: skip
    result = {"rounds": rounds, "threshold": 0.5, "trajectories_to_threshold": None,
              "trajectories_to_threshold_by_type": trajectories_to_threshold_by_type(rounds, 0.5)}
    lines = active.summary_lines({"selection": "uniform", "push": {"gnn": result}})
    assert lines == [
        "gnn push (uniform): validation error 0.6 > 0.5 after 1 rounds, 4 trajectories "
        "(not reached)",
        "  articulated: validation error 0.8 after 2 trajectories (not reached)",
        "  homogeneous: threshold reached after 2 trajectories",
    ]


def test_acted_link_is_the_true_link_nearest_the_tcp_at_contact() -> None:
    spec = load_object(SKILLS / "objects/artic_rect_rect.yaml")
    frames = link_frames(spec)  # link 0 at x = -0.047 m, link 1 at x = +0.047 m, y = 0.45 m
    assert frames[0, 0] < 0 < frames[1, 0]
    tcp = np.zeros((3, 6))
    tcp[:, :2] = [[-0.2, 0.45], [0.12, 0.45], [0.11, 0.45]]  # far left, then right of link 1
    pushed = dataclasses.replace(
        _trajectory("artic", steps=3), spec=spec, poses=np.stack([frames] * 3),
        twists=np.zeros((3, 2, 3)), tcp=tcp, link=0,
        force_n=np.array([[0.0, 0.0], [-1.0, 0.0], [-1.2, 0.0]]),
    )  # fmt: skip
    assert acted_link(pushed) == 1
    untouched = dataclasses.replace(pushed, force_n=np.array([[0.1, 0.0], [0.0, 0.0], [0.0, 0.0]]))
    assert acted_link(untouched) == 0  # no contact: the step of the largest force (far left)
    assert acted_link(_trajectory("one link")) == 0


def test_a_failed_run_leaves_its_object_out(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """In every collection, the seed and validation ones too: one object the arm could not
    push must not end a training of hours."""
    def collect(skill: Path, objects: list[Path], out: Path, config: object) -> list[Path]:
        if objects[0].stem == "tri2":
            raise DataError("collection failed on tri2 before any episode")
        return [out / objects[0].stem]

    monkeypatch.setattr(active, "collect", collect)
    monkeypatch.setattr(active, "load_trajectories", lambda runs: [_trajectory(runs[0].name)])
    collector = active.Collector(SKILLS / "explore_active.yaml", load_preset("tiny"),
                                 ACTIVE_PRESETS["tiny"])  # fmt: skip
    objects = [SKILLS / "objects" / f"{name}.yaml" for name in ("rect1", "tri2", "rect3")]
    kept = collector.run(objects, tmp_path, "random", 1, seed=0)
    assert [t.source for t in kept] == ["rect1", "rect3"]
    assert "left out tri2.yaml" in caplog.text


class _OffsetModel:
    """Predicts the current pose moved 1 cm along x and a force 0.5 N above the measured."""

    def predict(self, state: torch.Tensor, inputs: object, dt_s: float) -> Prediction:
        pose = state[..., :6].clone()
        pose[..., 0] += 0.01
        force = torch.tensor([[1.5, 0.0]], dtype=DTYPE).expand(state.shape[0], 1, 2)
        return Prediction(pose, force, torch.ones(state.shape[0], 6, dtype=DTYPE))


class _TcpForceModel:
    """A force of (10 x the TCP's x, the state's y) N: tells whether each step got its own
    input and its own true state."""

    def predict(self, state: torch.Tensor, inputs: ProcessInput, dt_s: float) -> Prediction:
        force = torch.stack([10.0 * inputs.tcp[..., 0], state[..., 0, 1]], -1)[..., None, :]
        return Prediction(state[..., :6], force, torch.ones(state.shape[0], 6, dtype=DTYPE))


def test_predicted_forces_are_one_step_ahead_of_each_true_state() -> None:
    window = _trajectory("a", steps=4)
    window.tcp[:, 0] = [0.1, 0.2, 0.3, 0.4]
    window.poses[:, 0, 1] = [0.5, 0.6, 0.7, 0.8]
    forces = predicted_forces(_TcpForceModel(), window)
    expected = [[1.0, 0.0], [1.0, 0.5], [2.0, 0.6], [3.0, 0.7]]  # step 0: the measured force
    torch.testing.assert_close(forces, torch.tensor(expected, dtype=DTYPE))


def test_the_force_one_step_ahead_of_the_truth_adds_its_squared_error() -> None:
    window = _trajectory("a", steps=4)
    window.tcp[:, 0] = [0.1, 0.2, 0.3, 0.4]
    window.poses[:, 0, 1] = [0.5, 0.6, 0.7, 0.8]
    # one step ahead: (1, 0.5), (2, 0.6), (3, 0.7) against the measured (1, 0)
    expected = (0.0 + 0.25 + 1.0 + 0.36 + 4.0 + 0.49) / 6
    model = _TcpForceModel()
    assert float(one_step_force_loss(model, [window])) == pytest.approx(expected)
    plain = float(rollout_loss(model, [window], rollout_steps=3))
    weighted = float(rollout_loss(model, [window], rollout_steps=3, truth_force_weight=2.0))
    assert weighted - plain == pytest.approx(2.0 * expected)
    still = _trajectory("b", steps=4)  # one step ahead (0, 0.45) against (1, 0), 3 times
    assert float(one_step_force_loss(model, [window, still])) == pytest.approx(
        (6 * expected + 3 * (1.0 + 0.45**2)) / 12
    )


def test_validation_error_by_hand() -> None:
    windows = [_trajectory("a"), _trajectory("b")]
    errors = validation_error(_OffsetModel(), windows, rollout_steps=1, batch_size=8)
    # scaled pose error (1, 0, 0, 0, 0, 0) -> MSE 1/6; force error (0.5, 0) -> MSE 0.125
    assert errors["val_error"] == pytest.approx(1 / 6 + 0.125)
    assert errors["position_rmse_mm"] == pytest.approx(10 * math.sqrt(0.5))
    assert errors["angle_rmse_deg"] == pytest.approx(0.0)
    assert errors["force_rmse_n"] == pytest.approx(math.sqrt(0.125))
    # open loop over 3 steps: the offset adds up (1, 2, 3 cm)
    errors = validation_error(_OffsetModel(), windows, rollout_steps=3, batch_size=8)
    assert errors["val_error"] == pytest.approx((1 + 4 + 9) / 3 / 6 + 0.125)


def test_rollout_variance_adds_up_along_each_rollout() -> None:
    """A 1 cm drift per step with unit process variance: at step k of a rollout the error is
    k cm and the variance k (x / 0.01 m scale, 1 / 0.01^2 in those units), restarting with
    every rollout."""
    window = _trajectory("a", steps=7)
    rows = list(rollout_errors(_OffsetModel(), [window], rollout_steps=3))
    assert len(rows) == 6
    drift = [float(error[0, 0, 0]) for error, _, _ in rows]
    variance = [float(var[0, 0, 0]) * 0.01**2 for _, var, _ in rows]
    assert drift == pytest.approx([1, 2, 3, 1, 2, 3])
    assert variance == pytest.approx([1, 2, 3, 1, 2, 3])


def test_twist_noise_disturbs_only_the_twist_a_rollout_starts_from() -> None:
    layout = StateLayout(2)
    states = torch.arange(layout.size, dtype=DTYPE).expand(4000, 1, -1)
    generator = torch.Generator().manual_seed(0)
    disturbed = disturb_twist(states, layout, 0.5, generator)
    change = (disturbed - states)[:, 0]
    twist = [layout.index(f"{name}_{link}") for link in (0, 1) for name in ("vx", "vy", "omega")]
    untouched = [i for i in range(layout.size) if i not in twist]
    assert torch.equal(change[:, untouched], torch.zeros_like(change[:, untouched]))
    expected = 0.5 * torch.tensor([SPEED_SCALE_MPS, SPEED_SCALE_MPS, RATE_SCALE_RADPS] * 2)
    torch.testing.assert_close(change[:, twist].std(0), expected.to(DTYPE), rtol=0.05, atol=0)
    assert disturb_twist(states, layout, 0.0, generator) is states


def test_active_settings_from_presets_files_and_options(tmp_path: Path) -> None:
    tiny = active_settings("tiny", selection="uniform", threshold=None, max_rounds=3)
    assert tiny.selection == "uniform" and tiny.max_rounds == 3
    assert tiny.threshold == ACTIVE_PRESETS["tiny"].threshold
    preset = tmp_path / "preset.yaml"
    preset.write_text(yaml.safe_dump({"models": ["gnn"], "active": {"per_round": 5}}))
    assert load_preset(str(preset)).models == ("gnn",)  # the active block is not TrainConfig's
    assert active_settings(str(preset), selection="random").per_round == 5
    with pytest.raises(ConfigError, match="max_rounds"):
        active_settings("tiny", max_rounds=0)


@pytest.mark.parametrize(
    ("text", "messages"),
    [
        ("epochs: -1\nepoch: 2\n", ["epochs: Input should be greater than 0",
                                     "epoch: Extra inputs are not permitted (did you mean "
                                     "'epochs'"]),
        ("models: [gnn\n", ["malformed YAML: line 2"]),
        ("- gnn\n", ["a preset file is a YAML mapping of training settings"]),
        ("active: {per_round: 0}\n", ["active.per_round: Input should be greater than 0"]),
    ],
    ids=["values", "malformed", "list", "active"],
)
def test_a_bad_preset_file_is_one_line_a_problem(
    tmp_path: Path, text: str, messages: list[str]
) -> None:
    preset = tmp_path / "preset.yaml"
    preset.write_text(text)
    with pytest.raises(ConfigError) as error:
        load_preset(str(preset))
        active_settings(str(preset))
    lines = str(error.value).splitlines()
    assert len(lines) == len(messages)
    for line, message in zip(lines, messages, strict=True):
        assert line.startswith(f"{preset}: ") and message in line


def test_the_loop_of_interactions_in_the_collection_skills() -> None:
    for name, key in (("explore_active", "tree.sequence.1.repeat"),
                      ("collect_pushes", "tree.sequence.0.repeat")):  # fmt: skip
        path = SKILLS / f"{name}.yaml"
        assert repeat_key(read_skill(path), path) == key
    with pytest.raises(ConfigError, match="a repeat of interactions"):
        repeat_key({"tree": {"sequence": ["look", "stop"]}}, Path("look.yaml"))


def _train(out: Path, preset: Path, *args: str) -> int:
    return main(["-q", "train", str(SKILLS / "explore_active.yaml"), "--out", str(out),
                 "--preset", str(preset), *args])  # fmt: skip


@pytest.mark.parametrize(
    ("skill", "args", "message"),
    [
        ("collect_pushes", ["--selection", "info_gain"], "use a collection skill with a filter"),
        ("explore_active", ["--rounds", "2"], "--rounds: only with --selection"),
        ("explore_active", ["--selection", "random", "--rounds", "0"], "max_rounds"),
        ("explore_active", ["--selection", "random", "--data", "x"], "--data: active training"),
    ],
    ids=["info-gain-needs-filter", "rounds-without-selection", "zero-rounds", "data"],
)
def test_bad_active_options_are_exit_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], skill: str, args: list[str], message: str
) -> None:
    out = tmp_path / "out"
    code = main(["-q", "train", str(SKILLS / f"{skill}.yaml"), "--out", str(out), *args])
    assert code == 2
    assert message in capsys.readouterr().err
    assert not out.exists()


@pytest.mark.parametrize(
    ("skill", "extra", "message"),
    [("collect_pushes", ["info_gain"], "use a collection skill with a filter"),
     ("explore_active", ["best"], "extra_val"),
     ("explore_active", ["random"], "the random validation set is always scored"),
     ("explore_active", ["uniform", "uniform"], "each selector is one set")],
    ids=["info-gain-needs-filter", "unknown-selector", "random", "twice"],
)  # fmt: skip
def test_bad_extra_validation_sets_are_exit_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], skill: str, extra: list[str], message: str
) -> None:
    preset = tmp_path / "preset.yaml"
    preset.write_text(yaml.safe_dump({"active": {"extra_val": extra}}))
    out = tmp_path / "out"
    code = main(["-q", "train", str(SKILLS / f"{skill}.yaml"), "--out", str(out),
                 "--preset", str(preset), "--selection", "random"])  # fmt: skip
    assert code == 2
    assert message in capsys.readouterr().err
    assert not out.exists()


FAST = [
    "components.views.with.max_views=1", "components.camera.with.width=160",
    "components.camera.with.height=120", "components.filter.with.sigma_points=16",
    "components.affordances.with.samples=16", "components.affordances.with.duration_s=2",
]  # fmt: skip


def test_active_training_end_to_end(tmp_path: Path) -> None:
    """One object, two rounds (the random seed interaction, then one chosen by information
    gain with the model of round 0), scored on random validation pushes and on pushes chosen
    by information gain with the skill's own model; then a reachable threshold stops after
    the seed round."""
    preset = tmp_path / "preset.yaml"
    preset.write_text(yaml.safe_dump({
        "shipped_train": ["rect1"], "shipped_val": ["rect3"], "models": ["gnn"],
        "interactions": ["push"], "hidden": 16, "noise_epochs": 1, "filter_epochs": 1,
        "filter_windows": 2, "filter_sigma_points": 8, "batch_size": 8,
        "active": {"seed_interactions": 1, "val_interactions": 2, "per_round": 1,
                   "max_rounds": 2, "threshold": 0.0, "epochs_per_round": 3,
                   "collect_overrides": FAST, "extra_val": ["info_gain"]},
    }))  # fmt: skip
    out = tmp_path / "out"
    assert _train(out, preset, "--selection", "info_gain") == 0
    report = json.loads((out / "train.json").read_text(encoding="utf-8"))
    assert report["mode"] == "active" and report["selection"] == "info_gain"
    result = report["push"]["gnn"]
    assert [(r["round"], r["trajectories"], r["buffer"]) for r in result["rounds"]] == [
        (0, 1, 1), (1, 2, 2)
    ]  # fmt: skip
    assert all(math.isfinite(r["val_error"]) and r["val_error"] > 0 for r in result["rounds"])
    assert result["stopped"] == "max_rounds" and result["trajectories_to_threshold"] is None
    for r in result["rounds"]:  # train and validation objects are all homogeneous
        assert r["by_type"]["homogeneous"]["val_error"] == pytest.approx(r["val_error"])
    assert [r["by_type"]["homogeneous"]["trajectories"] for r in result["rounds"]] == [1, 2]
    assert result["trajectories_to_threshold_by_type"] == {"homogeneous": None}
    assert report["data"]["val"]["trajectories"] == 2
    work = out / "active" / "info_gain" / "gnn_push"
    config = json.loads((work / "data/round_01/rect1_0/run.json").read_text())["config"]
    assert config["components"]["planner"]["plugin"] == "actions.info_gain"
    assert Path(config["components"]["model"]["with"]["checkpoint"]) == work / "gnn_push.pt"
    for name in ("gnn_push.pt", "gnn_push.pt.json", "obs_noise_push.pt", "active_training.png"):
        assert (out / name).stat().st_size > 0, name
    assert (out / "gnn_push.pt").read_bytes() == (work / "gnn_push.pt").read_bytes()
    _check_extra_validation(out, preset, result)

    seed_run = out / "active/data/seed/rect1_0/summary.json"
    stamp = seed_run.stat().st_mtime_ns
    assert _train(out, preset, "--selection", "info_gain", "--threshold", "1e6") == 0
    result = json.loads((out / "train.json").read_text(encoding="utf-8"))["push"]["gnn"]
    assert result["stopped"] == "threshold" and result["trajectories_to_threshold"] == 1
    assert result["trajectories_to_threshold_by_type"] == {"homogeneous": 1}
    assert result["trajectories_to_threshold_on"] == {"info_gain": 1}
    assert len(result["rounds"]) == 1
    assert seed_run.stat().st_mtime_ns == stamp  # the seed collection was reused

    assert _train(out, preset, "--selection", "random", "--threshold", "1e6") == 0
    assert [r["selection"] for r in active.selection_reports(out)] == ["info_gain", "random"]
    assert (work / "gnn_push.pt").is_file()  # another selection keeps its own weights
    assert (out / "active/random/gnn_push/gnn_push.pt").is_file()


def _check_extra_validation(out: Path, preset: Path, result: dict[str, Any]) -> None:
    """The extra validation set: pushes chosen by information gain with the skill's shipped
    model, scored with each round's weights as the random set is."""
    report = json.loads((out / "train.json").read_text(encoding="utf-8"))
    assert report["data"]["val_info_gain"]["trajectories"] == 2
    run = json.loads((out / "active/data/val_info_gain/rect3_0/run.json").read_text())["config"]
    assert run["components"]["planner"]["plugin"] == "actions.info_gain"
    shipped = read_skill(SKILLS / "explore_active.yaml")["components"]["model"]["with"]
    assert run["components"]["model"]["with"]["checkpoint"] == shipped["checkpoint"]
    chosen = load_trajectories([out / "active/data/val_info_gain/rect3_0"])
    work = out / "active/info_gain/gnn_push"
    last = result["rounds"][-1]["extra_val"]["info_gain"]
    assert last == active.model_error("gnn", "push", work, chosen, load_preset(str(preset)))
    assert all(r["extra_val"]["info_gain"]["val_error"] > 0 for r in result["rounds"])
    assert last["val_error"] != result["rounds"][-1]["val_error"]  # another set of pushes
    assert result["trajectories_to_threshold_on"] == {"info_gain": None}
    assert "on info_gain validation interactions: validation error" in "\n".join(
        active.summary_lines(report)
    )


def test_changed_data_settings_drop_every_selections_results(tmp_path: Path) -> None:
    kept = tmp_path / "active/uniform/gnn_push/gnn_push.pt"
    kept.parent.mkdir(parents=True)
    kept.write_bytes(b"weights")
    active._prepare(tmp_path, {"seed": 0})
    active._prepare(tmp_path, {"seed": 0})
    assert kept.is_file()
    active._prepare(tmp_path, {"seed": 1})
    assert not kept.exists()
    assert json.loads((tmp_path / "active/data/settings.json").read_text()) == {"seed": 1}


def test_fig10_curves_per_selection_and_object_type(tmp_path: Path) -> None:
    def report(selection: str, error: float) -> dict[str, object]:
        rounds = [{"trajectories": 6, "val_error": error,
                   "by_type": {"homogeneous": {"trajectories": 2, "val_error": error / 2}},
                   "extra_val": {"info_gain": {"val_error": error * 2}}}]
        return {"selection": selection, "active": {"threshold": 0.5},
                "push": {"gnn": {"rounds": rounds}}}  # fmt: skip

    reports = [report("info_gain", 1.0), report("random", 3.0)]
    assert active._curves(reports) == {
        ("all", "info_gain gnn push"): [(6, 1.0)],
        ("all, info_gain interactions", "info_gain gnn push"): [(6, 2.0)],
        ("homogeneous", "info_gain gnn push"): [(2, 0.5)],
        ("all", "random gnn push"): [(6, 3.0)],
        ("all, info_gain interactions", "random gnn push"): [(6, 6.0)],
        ("homogeneous", "random gnn push"): [(2, 1.5)],
    }
    active.plot_rounds(reports, tmp_path / "fig10.png")
    assert (tmp_path / "fig10.png").stat().st_size > 0


def test_data_without_one_of_the_interactions_is_refused_before_any_training(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Pushes only, and a preset that trains pushes and pulls: refused before the pushes are
    trained (which took minutes and left their checkpoints without a train.json)."""
    from vistac.plugins.filters import train as training

    data = {"train": [_trajectory(c) for c in "abcd"], "val": [_trajectory("e")]}
    monkeypatch.setattr(training, "recorded_data", lambda dirs: data)
    out = tmp_path / "out"
    config = TrainConfig(interactions=["push", "pull"], hidden=8, epochs=1)
    with pytest.raises(DataError, match=r"no pull trajectories .* interactions: \(without pull\)"):
        training.train(SKILLS / "collect_pushes.yaml", out, config, [tmp_path])
    assert not out.exists()


def test_a_feed_forward_without_validation_of_its_link_count_is_refused() -> None:
    """Training pushes of one- and two-link objects, validation of one-link objects only:
    the two-link FF could not be validated and was saved with its initial weights."""
    from test_training_mirror import _two_link_trajectory
    from vistac.plugins.filters.train import train_interaction

    data = {"train": [_trajectory(c) for c in "abcd"] + [_two_link_trajectory("articulated")],
            "val": [_trajectory("e")]}  # fmt: skip
    config = TrainConfig(models=["gnn", "ff"], hidden=8, epochs=1)
    with pytest.raises(DataError, match=r"no push trajectories of \[2\] links"):
        train_interaction("push", data, config, Path("unused"))


def test_an_ff_selects_with_the_net_of_the_fitted_link_count(tmp_path: Path) -> None:
    """Information gain with the FF predicts with every link count's FF in the work folder,
    picked by the fit (before, the FF of the object's true link count: a fit with another
    count failed the collection run)."""
    work = tmp_path / "work"
    for n in (1, 2):
        (work / f"ff{n}").mkdir(parents=True)
        (work / f"ff{n}/ff_push.pt").write_bytes(b"")
        (work / f"ff{n}/ff_push.pt.json").write_text(
            json.dumps({"model": "filters.ff", "architecture": {"hidden": 16, "n_links": n}})
        )
    model, noise = active.Collector._model_overrides("ff", "push", work)
    key, _, value = model.partition("=")
    assert key == "components.model" and noise.endswith("obs_noise_push.pt")
    assert json.loads(value) == {"plugin": "filters.ff", "with": {"hidden": 16, "checkpoints": {
        str(n): str((work / f"ff{n}/ff_push.pt").resolve()) for n in (1, 2)
    }}}  # fmt: skip
    with pytest.raises(DataError, match=r"cannot select with ff: no FF checkpoint in"):
        active.Collector._model_overrides("ff", "push", tmp_path)
