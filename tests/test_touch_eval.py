"""`vistac eval` on a touch skill: objects x random poses x explorers, scored and tabulated."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from vistac.cli import main
from vistac.errors import ConfigError
from vistac.plugins.touch import campaign
from vistac.plugins.touch.campaign import (
    TouchEvalOptions,
    aggregate,
    evaluate_touch,
    is_touch_skill,
    run_trial,
)

SKILLS = Path(__file__).resolve().parents[1] / "skills"
SKILL = SKILLS / "touch_recognise.yaml"
FAST = ["--set", "rate_hz=500", "--set", "tree.sequence.0.explore_touch.max_touches=25"]


def _record(**fields: object) -> dict[str, object]:
    base: dict[str, object] = {"status": "ok", "is_known": True, "class_correct": True,
                               "steps_to_pose": None, "steps": 50, "stopped_by": "explorer",
                               "known": True, "max_particle_count": 100}  # fmt: skip
    return base | fields


def test_aggregate_counts_and_means() -> None:
    row = aggregate([
        _record(steps_to_pose=10, steps=40),
        _record(steps_to_pose=20, steps=60, stopped_by="max_touches", max_particle_count=900),
        _record(class_correct=False, known=False),
        _record(is_known=False, class_correct=False, known=False),
        {"status": "failed", "is_known": True, "reason": "exit code 1"},
    ])  # fmt: skip
    assert row["trials"] == 5 and row["failed"] == 1 and row["known_trials"] == 3
    assert row["class_right"] == 2 and row["pose_found"] == 2
    assert row["touches_to_pose"] == 15.0 and row["touches_to_stop"] == 50.0
    assert row["terminated"] == 3 and row["max_particles"] == 900
    assert (row["decision_right"], row["decided"]) == (3, 4)


def test_only_touch_skills_take_the_touch_evaluation() -> None:
    assert is_touch_skill(SKILL) and is_touch_skill(SKILLS / "touch_learn.yaml")
    assert not is_touch_skill(SKILLS / "explore_push.yaml")


def test_eval_runs_every_trial_and_writes_the_tables(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    args = ["-q", "eval", str(SKILL), "--objects", "mug", "mug_tall", "--trials", "1",
            "--explorers", "dhd", "--out", str(tmp_path), *FAST]  # fmt: skip
    assert main(args) == 0
    report = json.loads((tmp_path / "eval.json").read_text(encoding="utf-8"))
    records = {r["object"]: r for r in report["records"]}
    assert set(records) == {"mug", "mug_tall"}
    assert all(r["status"] == "ok" for r in records.values())
    assert records["mug"]["is_known"] and not records["mug_tall"]["is_known"]
    assert records["mug"]["steps"] <= 25
    mug = report["tables"]["dhd"]["mug"]
    assert mug["class_right"] == mug["known_trials"] == 1
    tables = (tmp_path / "tables.md").read_text(encoding="utf-8")
    assert "## touch.dhd" in tables and "| mug_tall | 1 | - | - |" in tables
    assert "evaluated 2 touch runs" in capsys.readouterr().out
    summary = Path(records["mug"]["run_dir"]) / "summary.json"
    stamp = summary.stat().st_mtime_ns
    assert main(args) == 0  # finished runs with the same arguments are reused
    assert summary.stat().st_mtime_ns == stamp


def _options(out: Path, *objects: str) -> TouchEvalOptions:
    return TouchEvalOptions(skill=SKILL, out=out, objects=objects, trials=1,
                            explorers=("dhd",), seed=0)  # fmt: skip


def test_a_mesh_path_object_runs_in_a_folder_named_after_its_stem(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """An absolute path no longer drops --out, nor does ../ leave it."""
    run_dirs: list[Path] = []

    def failing_run(args: list[str], run_dir: Path, who: str) -> tuple[int, None]:
        run_dirs.append(run_dir)
        return 1, None

    monkeypatch.setattr(campaign, "run_once", failing_run)
    out = tmp_path / "out"
    for obj in ("/abs/learned/cone_learned.ply", "../x.ply", "mug"):
        assert run_trial(_options(out, obj), obj, "dhd", 0)["status"] == "failed"
    assert run_dirs == [out / "runs" / "dhd" / name / "trial_00"
                        for name in ("cone_learned", "x", "mug")]  # fmt: skip


@pytest.mark.parametrize(
    "objects", [("run1/cone_learned.ply", "run2/cone_learned.ply"), ("mug", "shapes/mug.obj")]
)
def test_objects_sharing_a_runs_folder_are_a_config_error(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, objects: tuple[str, str]
) -> None:
    monkeypatch.setattr(campaign, "run_once", lambda *args: pytest.fail("a trial ran"))
    with pytest.raises(ConfigError, match=rf"{objects[0]} and {objects[1]} would share the "
                       r"runs folder .*rename one of the files"):  # fmt: skip
        evaluate_touch(_options(tmp_path, *objects))


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--explorers", "dhd,spiral"], "spiral is not one of dhd, rrt"),
        (["--trials", "0"], "--trials must be at least 1"),
        (["--set", "explore_touch.max_touches=3"], "is not valid"),
        (["--max-objects", "2"], "is a touch skill; its evaluation does not use --max-objects "
         "(only for parameter-estimation skills); leave it out"),
    ],
    ids=["explorer", "trials", "override", "parameter-options"],
)
def test_bad_options_are_clear_errors(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], extra: list[str], message: str
) -> None:
    code = main(["eval", str(SKILL), "--objects", "mug", "--trials", "1",
                 "--out", str(tmp_path), *extra])  # fmt: skip
    assert code == 2
    assert message in capsys.readouterr().err


def test_ctrl_c_stops_the_touch_evaluation(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """Ctrl-C in a trial's run (exit 130 from the Scheduler) ends the eval with 130, no other
    trial started; before, every trial ran and the eval exited 0."""
    from vistac.scheduler import Scheduler

    started: list[Path] = []

    def interrupted(self: Scheduler, tree: object) -> str:
        started.append(self.recorder.out_dir)
        raise KeyboardInterrupt

    monkeypatch.setattr(Scheduler, "_tick_until_done", interrupted)
    code = main(["-q", "eval", str(SKILL), "--objects", "mug", "--trials", "2",
                 "--explorers", "dhd", "--out", str(tmp_path), *FAST])  # fmt: skip
    assert code == 130
    assert "interrupted" in capsys.readouterr().err
    assert len(started) == 1
    assert not list(tmp_path.rglob("eval_args.json"))


@pytest.mark.parametrize("obj", ["mugg", "nothing/there.ply", "notes.txt"])
def test_an_object_that_is_not_there_is_exit_2_before_any_trial(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], obj: str
) -> None:
    monkeypatch.chdir(tmp_path)
    (tmp_path / "notes.txt").write_text("not a mesh")
    monkeypatch.setattr(campaign, "run_once", lambda *args: pytest.fail("a trial ran"))
    code = main(["eval", str(SKILL), "--objects", "mug", obj, "--out", str(tmp_path / "o")])
    assert code == 2
    assert f"--objects: {obj!r} is no library shape (mug, " in capsys.readouterr().err


def test_a_relative_mesh_path_is_the_working_folders(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The skill takes a relative path from its own folder: the trial gets it absolute."""
    monkeypatch.chdir(tmp_path)
    given: list[list[str]] = []
    monkeypatch.setattr(campaign, "run_once", lambda args, *_: (given.append(args), (1, None))[1])
    run_trial(_options(tmp_path / "o", "shapes/cone.ply"), "shapes/cone.ply", "dhd", 0)
    run_trial(_options(tmp_path / "o", "mug"), "mug", "dhd", 0)
    objects = [arg for args in given for arg in args if arg.startswith("components.probe")]
    assert objects == [f"components.probe.with.object={tmp_path / 'shapes/cone.ply'}",
                       "components.probe.with.object=mug"]  # fmt: skip


def test_a_failed_trial_makes_the_evaluation_exit_1(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(campaign, "run_once", lambda *args: (1, None))
    assert main(["-q", "eval", str(SKILL), "--objects", "mug", "--trials", "1",
                 "--explorers", "dhd", "--out", str(tmp_path)]) == 1  # fmt: skip


def test_out_naming_a_file_is_exit_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "afile"
    out.write_text("not a folder")
    code = main(["eval", str(SKILL), "--objects", "mug", "--out", str(out)])
    assert code == 2
    assert f"--out: {out} is a file; give a folder" in capsys.readouterr().err
