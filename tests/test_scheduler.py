"""The scheduler: tree semantics, outputs, and the arm stopped on every way out."""

from __future__ import annotations

import json
from pathlib import Path

import fixtures_plugin
import numpy as np
import pytest
from conftest import SKILLS, write
from vistac.errors import ConfigError
from vistac.pluginmanager import Plugins
from vistac.scheduler import Scheduler, belief_truth
from vistac.skill import load_skill
from vistac.testing import build_components


def _run(
    tmp_path: Path,
    plugins: Plugins,
    tree: str,
    components: str = "arm: {plugin: test.arm}",
    **skill_keys: object,
) -> tuple[Scheduler, object]:
    extra = "".join(f"{k}: {v}\n" for k, v in skill_keys.items())
    path = write(
        tmp_path / "skill.yaml",
        f"version: 1\nname: t\n{extra}components:\n  {components}\ntree:\n{tree}\n",
    )
    scheduler = Scheduler(load_skill(path, plugins.registry), plugins, tmp_path / "out")
    fixtures_plugin.STOP_CALLS.clear()
    return scheduler, scheduler.run()


def test_repeat_until_condition(tmp_path: Path, plugins: Plugins) -> None:
    tree = "  repeat: {do: [{count: {ticks: 3}}], until: {count_at_least: {n: 4}}, max: 10}"
    scheduler, result = _run(tmp_path, plugins, tree)
    assert result.status == "success"
    assert scheduler.ctx.results == {}
    # 4 iterations of a 3-tick body: 12 ticks.
    assert scheduler.ticks == 12
    assert fixtures_plugin.STOP_CALLS, "the arm is stopped at the end of every run"


def test_repeat_stops_at_max_with_chosen_status(tmp_path: Path, plugins: Plugins) -> None:
    tree = "  repeat: {do: [count], until: {count_at_least: {n: 100}}, max: 5, on_max: failure}"
    scheduler, result = _run(tmp_path, plugins, tree)
    assert result.status == "failure" and result.exit_code == 1
    assert scheduler.ticks == 5


def test_failing_body_fails_the_repeat(tmp_path: Path, plugins: Plugins) -> None:
    _, result = _run(tmp_path, plugins, "  repeat: {do: [count, fail], max: 5}")
    assert result.status == "failure"


@pytest.mark.parametrize(
    ("error", "status", "code", "message"),
    [
        ("data", "error", 1, "boom: synthetic sensor failure"),
        ("config", "error", 2, "boom: synthetic invalid input"),
        ("bug", "error", 1, "RuntimeError: boom: synthetic bug"),
        ("interrupt", "interrupted", 130, "interrupted by Ctrl-C"),
    ],
)
def test_every_failure_stops_the_arm_and_is_recorded(
    tmp_path: Path, plugins: Plugins, error: str, status: str, code: int, message: str
) -> None:
    _, result = _run(tmp_path, plugins, f"  - count\n  - {{boom: {{error: {error}}}}}")
    assert (result.status, result.exit_code) == (status, code)
    assert result.error == message
    assert fixtures_plugin.STOP_CALLS == ["stop"]
    run = json.loads((tmp_path / "out/run.json").read_text())
    summary = json.loads((tmp_path / "out/summary.json").read_text())
    assert run["status"] == status and summary["error"] == message


BROKEN = "arm: {plugin: test.arm}\n  filter: {plugin: test.broken}"


def test_a_run_that_fails_while_it_sets_up_writes_nothing(
    tmp_path: Path, plugins: Plugins
) -> None:
    """Bad input found while the components are built: exit 2, the arm built before it
    stopped, and no folder, so that the same --out takes the run once the input is fixed."""
    _, result = _run(tmp_path, plugins, "  - count", components=BROKEN)
    assert (result.status, result.exit_code) == ("error", 2)
    assert result.error == "broken: synthetic checkpoint that is not there"
    assert result.summary == {}
    assert fixtures_plugin.STOP_CALLS == ["stop"]
    assert not (tmp_path / "out").exists()
    _, fixed = _run(tmp_path, plugins, "  - count")
    assert fixed.status == "success" and (tmp_path / "out/summary.json").is_file()


def test_a_run_that_fails_while_it_sets_up_keeps_the_run_it_would_overwrite(
    tmp_path: Path, plugins: Plugins
) -> None:
    _run(tmp_path, plugins, "  - count")
    before = {name: (tmp_path / "out" / name).read_text() for name in ("run.json", "summary.json")}
    path = write(
        tmp_path / "broken.yaml",
        f"version: 1\nname: t\ncomponents:\n  {BROKEN}\ntree:\n  - count\n",
    )
    skill = load_skill(path, plugins.registry)
    result = Scheduler(skill, plugins, tmp_path / "out", overwrite=True).run()
    assert result.exit_code == 2
    assert before == {name: (tmp_path / "out" / name).read_text() for name in before}


def test_the_set_up_is_not_a_control_period_overrun(tmp_path: Path, plugins: Plugins) -> None:
    """On the wall clock, building the components (here an arm that takes 0.3 s to connect,
    six 50 ms periods) is done before the first period starts."""
    arm = "arm: {plugin: test.arm, with: {build_s: 0.3}}"
    scheduler, result = _run(tmp_path, plugins, "  count: {ticks: 3}", arm, rate_hz=20)
    assert result.status == "success" and scheduler.ticks == 3
    assert result.summary["control_overruns"] == 0


def test_max_duration_is_a_safety_stop(tmp_path: Path, plugins: Plugins) -> None:
    _, result = _run(tmp_path, plugins, "  - forever", max_duration_s=0.2, rate_hz=100)
    assert result.status == "error"
    assert "exceeded max_duration_s = 0.2 s" in (result.error or "")
    assert fixtures_plugin.STOP_CALLS


def test_existing_run_is_not_overwritten(tmp_path: Path, plugins: Plugins) -> None:
    _run(tmp_path, plugins, "  - count")
    path = tmp_path / "skill.yaml"
    with pytest.raises(ConfigError, match="already holds a run"):
        Scheduler(load_skill(path, plugins.registry), plugins, tmp_path / "out")
    Scheduler(load_skill(path, plugins.registry), plugins, tmp_path / "out", overwrite=True)


def test_belief_nodes_with_a_known_filter(tmp_path: Path, plugins: Plugins) -> None:
    from vistac.behaviours.belief import BeliefConverged
    from vistac.testing import build_components

    ctx = build_components(
        {"filter": {"plugin": "test.kalman", "with": {"noise_var": 0.04}}},
        tmp_path,
        plugins=plugins,
    )
    kalman = ctx.component("filter")
    kalman.initialise(None)
    rng = np.random.default_rng(0)
    measurements = 0.7 + rng.normal(0, 0.2, 50)
    belief = kalman.update(fixtures_plugin.measurement_episode(0, measurements))
    # A constant observed with noise: the posterior is the precision-weighted mean.
    precision = 1 / 1.0 + 50 / 0.04
    assert belief.cov[0, 0] == pytest.approx(1 / precision)
    assert belief.mean[0] == pytest.approx((measurements.sum() / 0.04) / precision)
    node = BeliefConverged("c", BeliefConverged.Config(max_std={"m_*": 0.05}), None)
    assert node._limit("m_0") == 0.05 and node._limit("x_0") is None


FILTER = "arm: {plugin: test.arm}\n  filter: {plugin: test.kalman, with: {noise_var: 0.04%s}}"


def test_interact_until_converged(tmp_path: Path, plugins: Plugins) -> None:
    tree = (
        "  repeat: {do: [fake_interaction, update_belief], max: 20,"
        " until: {belief_converged: {max_std: {'m_*': 0.02}}}}"
    )
    scheduler, result = _run(tmp_path, plugins, tree, components=FILTER % "")
    assert result.status == "success"
    # std after k episodes of 15 measurements: 1/sqrt(1 + 15 k / 0.04) <= 0.02 from k = 7.
    assert scheduler.ctx.episode_count == 7
    assert scheduler.ctx.results["converged"] is True
    assert result.summary["belief"]["m_0"]["mean"] == pytest.approx(
        0.7, abs=0.06
    )  # 3 standard errors


def test_diverged_filter_stops_the_run(tmp_path: Path, plugins: Plugins) -> None:
    tree = "  - fake_interaction\n  - update_belief\n  - fake_interaction\n  - update_belief"
    _, result = _run(tmp_path, plugins, tree, components=FILTER % ", nan_after: 1")
    assert result.status == "error"
    assert "GaussianBelief.mean: contains NaN" in (result.error or "")
    assert fixtures_plugin.STOP_CALLS == ["stop"]


def test_the_truth_is_told_per_belief_link_in_its_frame() -> None:
    """The summary's truth for each belief entry: belief link 0 sits on true link 1, its
    frame turned by pi from the link's (a superquadric of a symmetric footprint), so the true
    CoM (0.02, -0.01) of link 1 reads (-0.02, 0.01) there; the joint friction goes by name."""
    belief = {
        f"{key}_{b}": {"mean": value, "std": 0.1}
        for b, pose in enumerate([(0.3, 0.1, np.pi), (0.0, 0.0, 0.0)])
        for key, value in zip(("x", "y", "theta", "m", "f", "com_x", "com_y"),
                              (*pose, 1.0, 0.3, 0.0, 0.0), strict=True)
    } | {"f_j_0": {"mean": 0.1, "std": 0.1}}  # fmt: skip
    truth = {
        "parameters": {"m_0": 0.4, "f_0": 0.2, "com_x_0": 0.0, "com_y_0": 0.0, "m_1": 0.9,
                       "f_1": 0.25, "com_x_1": 0.02, "com_y_1": -0.01, "f_j_0": 0.15},
        "link_poses": [[0.0, 0.0, 0.0], [0.3, 0.1, 0.0]],
    }  # fmt: skip
    told = belief_truth(belief, truth)
    assert told == pytest.approx({"m_0": 0.9, "f_0": 0.25, "com_x_0": -0.02, "com_y_0": 0.01,
                                  "m_1": 0.4, "f_1": 0.2, "com_x_1": 0.0, "com_y_1": 0.0,
                                  "f_j_0": 0.15})  # fmt: skip
    # without poses, entries compare by name
    assert belief_truth(belief, {"parameters": truth["parameters"]}) == truth["parameters"]


def test_the_run_end_does_not_close_the_gripper_fingers(tmp_path: Path) -> None:
    # a gripper's close() closes its fingers; close_all must leave them as they were
    world = {"plugin": "sim.mujoco", "with": {"object": str(SKILLS / "objects/rect1.yaml")}}
    ctx = build_components({"world": world, "gripper": {"plugin": "sim.gripper"}}, tmp_path)
    ctx.component("gripper").open()
    sim = ctx.component("world")
    ctx.close_all()
    fingers = sim.data.ctrl[sim.index.finger_actuators]
    assert sim.geometry.max_finger_travel_m > 0.0
    assert np.all(fingers == sim.geometry.max_finger_travel_m)
