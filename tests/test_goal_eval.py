"""`vistac eval` on a goal-push skill: estimated vs default parameters over objects x trials."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from conftest import fake_run
from vistac.campaign import run_once
from vistac.cli import main
from vistac.errors import ConfigError
from vistac.plugins.actions.campaign import (
    GoalEvalOptions,
    aggregate,
    evaluate_goal,
    is_goal_skill,
    score_run,
    select_goal_objects,
    tables_markdown,
)

SKILLS = Path(__file__).resolve().parents[1] / "skills"
SKILL = SKILLS / "goal_push.yaml"
FAST = [
    "--set", "tree.sequence.1.repeat.max=1", "--set", "tree.sequence.2.repeat.max=1",
    "--set", "components.views.with.max_views=2",
    "--set", "components.camera.with.width=160", "--set", "components.camera.with.height=120",
    "--set", "components.controller.with.population=8",
    "--set", "components.controller.with.elites=2",
    "--set", "components.controller.with.iterations=1",
]  # fmt: skip


def _record(obj: str, trial: int, mode: str, error_m: float, **fields: object) -> dict[str, object]:
    base: dict[str, object] = {"object": obj, "trial": trial, "mode": mode, "status": "ok",
                               "position_error_m": error_m, "turn_error_rad": 0.1, "pushes": 2,
                               "goal_reached": True, "wall_s": 30.0}  # fmt: skip
    return base | fields


RECORDS = [
    _record("rect1", 0, "estimated", 0.010),
    _record("rect1", 0, "default", 0.020),
    _record("rect1", 1, "estimated", 0.030, pushes=4, goal_reached=False),
    _record("rect1", 1, "default", 0.010),
    _record("rect1", 2, "estimated", 0.020),
    {"object": "rect1", "trial": 2, "mode": "default", "status": "failed", "reason": "exit 1"},
    _record("tri1", 0, "estimated", 0.005, turn_error_rad=0.3),
    _record("tri1", 0, "default", 0.040),
]


def test_aggregate_pairs_the_modes_by_trial() -> None:
    row = aggregate([r for r in RECORDS if r["object"] == "rect1"])
    assert (row["runs"], row["failed"], row["paired_trials"]) == (6, 1, 2)
    assert row["estimated_minus_default"]["mean_m"] == pytest.approx(0.005)  # (-10 + 20) / 2 mm
    assert aggregate(RECORDS[5:6])["estimated_minus_default"] is None  # no paired trial
    assert row["estimated_lower"] == 1  # trial 2 has no default run to compare with
    estimated, default = row["estimated"], row["default"]
    assert estimated["runs"] == 3 and default["runs"] == 2
    assert estimated["position_error_mean_m"] == pytest.approx(0.020)
    assert estimated["position_error_median_m"] == pytest.approx(0.020)
    assert default["position_error_mean_m"] == pytest.approx(0.015)
    assert estimated["pushes_mean"] == pytest.approx(8 / 3)
    assert (estimated["reached"], default["reached"]) == (2, 2)


def test_aggregate_overall_and_the_table() -> None:
    overall = aggregate(RECORDS)
    assert (overall["paired_trials"], overall["estimated_lower"]) == (3, 2)
    assert overall["estimated"]["position_error_median_m"] == pytest.approx(0.015)
    assert overall["default"]["position_error_median_m"] == pytest.approx(0.020)
    rows = {"rect1": aggregate(RECORDS[:6]), "tri1": aggregate(RECORDS[6:]), "all": overall}
    table = tables_markdown(rows, RECORDS)
    assert "| rect1 | 2 (1 runs failed) | 20.0 / 15.0 | 20.0 / 15.0 |" in table
    tri1 = ("| tri1 | 1 | 5.0 / 40.0 | 5.0 / 40.0 | 17.2 / 5.7 | 2.0 / 2.0 | 1/1 / 1/1 | 1/1 "
            "| -35.0 [-35.0, -35.0] |")  # fmt: skip
    assert tri1 in table
    # the trials' differences are -10, +20 and -35 mm: mean -8.3, every resample within
    assert "| all | 3 (1 runs failed) |" in table and "| 2/3 | -8.3 [" in table
    difference = overall["estimated_minus_default"]
    assert difference["mean_m"] == pytest.approx(-0.025 / 3)
    assert -0.035 <= difference["low_m"] < difference["mean_m"] < difference["high_m"] <= 0.020
    assert "8 runs, 3.5 min of skill wall time" in table


def test_a_run_without_a_true_error_is_a_failure() -> None:
    record = score_run({"status": "failure", "error": "arm stopped", "goal_push": {}})
    assert record == {"status": "failed", "reason": "failure: arm stopped"}
    goal = {"true_error_m": 0.02, "true_turn_error_rad": 0.1, "planned_cost_m": [0.1, 0.05],
            "reached": True, "believed_error_m": 0.008}  # fmt: skip
    record = score_run({"status": "success", "wall_time_s": 40.0, "goal_push": goal})
    assert record["pushes"] == 2 and record["position_error_m"] == 0.02 and record["wall_s"] == 40


def test_objects_by_name_comma_separated_or_all() -> None:
    objects = SKILLS / "objects"
    assert [p.stem for p in select_goal_objects(["rect1,tri2", "rect1"], objects)] == [
        "rect1",
        "tri2",
    ]
    assert len(select_goal_objects(["all"], objects)) == len(list(objects.glob("*.yaml")))
    elsewhere = str(objects / "tri3.yaml")  # any object file, e.g. `vistac objects generate`
    assert select_goal_objects([elsewhere], SKILLS) == [Path(elsewhere)]
    with pytest.raises(ConfigError, match="did you mean hexagon"):
        select_goal_objects(["hexagn"], objects)
    with pytest.raises(ConfigError, match=r"no such file objects/gen/homog_03\.yaml; check"):
        select_goal_objects(["objects/gen/homog_03.yaml"], objects)


def test_only_goal_skills_take_the_goal_evaluation() -> None:
    assert is_goal_skill(SKILL)
    assert not is_goal_skill(SKILLS / "explore_push.yaml")
    options = GoalEvalOptions(SKILLS / "explore_push.yaml", Path("unused"), ("rect1",), 1)
    with pytest.raises(ConfigError, match="no plan_push in the tree") as error:
        evaluate_goal(options)
    assert error.value.exit_code == 2


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--objects", "rect1,spoon"], "no object 'spoon'"),
        (["--objects", "rect1", "--trials", "0"], "--trials must be at least 1"),
        (["--objects", "rect1", "--set", "components.filter.with.sigma=3"], "is not valid"),
        (["--objects", "rect1", "--paired", "--variants", "a-gnn"],
         "does not use --variants (only for parameter-estimation skills), --paired"),
    ],
    ids=["object", "trials", "override", "parameter-options"],
)
def test_bad_options_are_clear_errors(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], extra: list[str], message: str
) -> None:
    assert main(["eval", str(SKILL), "--out", str(tmp_path), *extra]) == 2
    assert message in capsys.readouterr().err


def test_eval_runs_both_modes_and_reuses_finished_runs(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    args = ["-q", "eval", str(SKILL), "--objects", "rect1", "--trials", "1",
            "--out", str(tmp_path), *FAST]  # fmt: skip
    assert main(args) == 0
    report = json.loads((tmp_path / "eval.json").read_text(encoding="utf-8"))
    records = {r["mode"]: r for r in report["records"]}
    assert set(records) == {"estimated", "default"}
    assert all(r["status"] == "ok" and r["object"] == "rect1" for r in records.values())
    assert all(r["pushes"] == 1 and r["position_error_m"] < 0.2 for r in records.values())
    run = json.loads((Path(records["default"]["run_dir"]) / "run.json").read_text())
    assert run["config"]["components"]["filter"]["with"]["estimate_parameters"] is False
    assert report["tables"]["all"]["paired_trials"] == 1
    assert "| rect1 | 1 |" in (tmp_path / "tables.md").read_text(encoding="utf-8")
    assert "evaluated 2 goal-push runs" in capsys.readouterr().out
    summary = Path(records["estimated"]["run_dir"]) / "summary.json"
    stamp = summary.stat().st_mtime_ns
    assert main(args) == 0  # finished runs with the same arguments are reused
    assert summary.stat().st_mtime_ns == stamp


def test_an_interrupted_run_stops_the_campaign_and_is_never_reused(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Exit 130 (Ctrl-C in the Scheduler) is a KeyboardInterrupt with no stamp written;
    before, the stamp said the interrupted run had finished, and it was reused."""
    run_dir = tmp_path / "run"
    first, second = (["-q", "run", "skill.yaml", "--out", str(run_dir), "--seed", seed]
                     for seed in ("0", "1"))  # fmt: skip
    fake_run(monkeypatch, 0)
    assert run_once(first, run_dir, "goal eval")[0] == 0
    fake_run(monkeypatch, 130)
    with pytest.raises(KeyboardInterrupt):
        run_once(second, run_dir, "goal eval")
    assert not (run_dir / "eval_args.json").exists()
    calls = fake_run(monkeypatch, 0)  # the folder holds the interrupted run, not the first
    assert run_once(first, run_dir, "goal eval")[0] == 0 and len(calls) == 1


def test_a_run_that_fails_before_it_starts_is_not_given_the_earlier_runs_summary(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Such a run writes nothing (a checkpoint that is not there, a robot that does not
    answer), so the folder still holds the run before it; that one is not this run's."""
    import vistac.cli

    run_dir = tmp_path / "run"
    first, second = (["-q", "run", "skill.yaml", "--out", str(run_dir), "--seed", seed]
                     for seed in ("0", "1"))  # fmt: skip
    fake_run(monkeypatch, 0)
    assert run_once(first, run_dir, "goal eval")[0] == 0
    monkeypatch.setattr(vistac.cli, "main", lambda args: 1)  # fails before it writes anything
    assert run_once(second, run_dir, "goal eval") == (1, None)
    assert not (run_dir / "eval_args.json").exists()


def test_a_run_made_by_other_code_is_not_reused(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The stamp holds the code's fingerprint: after a change to vistac's sources the same
    arguments run again (before, an evaluation mixed runs of old and new code)."""
    from vistac import campaign

    run_dir = tmp_path / "run"
    args = ["-q", "run", "skill.yaml", "--out", str(run_dir), "--seed", "0"]
    calls = fake_run(monkeypatch, 0)
    assert run_once(args, run_dir, "goal eval")[0] == 0
    assert run_once(args, run_dir, "goal eval")[0] == 0 and len(calls) == 1  # reused
    monkeypatch.setattr(campaign, "code_fingerprint", lambda: "other sources")
    assert run_once(args, run_dir, "goal eval")[0] == 0 and len(calls) == 2
    assert campaign.stamp_of(run_dir) == {
        "args": args, "inputs": campaign.args_digest(args), "exit_code": 0
    }
    (run_dir / campaign.STAMP).write_text("{not json")  # cut short, say: run again
    assert run_once(args, run_dir, "goal eval")[0] == 0 and len(calls) == 3


def test_a_run_whose_named_files_changed_is_not_reused(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The stamp holds a digest of the skill and of the files its values and the --set
    overrides name (and a checkpoint's architecture file beside it): a checkpoint retrained in
    place, or an edited skill or object, makes the same arguments run again (before, the
    earlier run was reused)."""
    skill = tmp_path / "skill.yaml"
    skill.write_text("components:\n  model: {plugin: m, with: {checkpoint: net.pt}}\n")
    (tmp_path / "net.pt").write_bytes(b"weights 1")
    (tmp_path / "net.pt.json").write_text('{"architecture": {"hidden": 32}}')
    (tmp_path / "object.yaml").write_text("mass: 1\n")
    run_dir = tmp_path / "run"
    args = ["-q", "run", str(skill), "--out", str(run_dir),
            "--set", f"components.world.with.object={tmp_path / 'object.yaml'}"]  # fmt: skip
    calls = fake_run(monkeypatch, 0)
    for change, runs in [(None, 1), (None, 1), ("net.pt", 2), ("net.pt.json", 3),
                         ("object.yaml", 4), ("skill.yaml", 5), (None, 5)]:  # fmt: skip
        if change is not None:
            path = tmp_path / change
            path.write_bytes(path.read_bytes() + b"\n# changed\n")
        assert run_once(args, run_dir, "goal eval")[0] == 0
        assert len(calls) == runs, change
