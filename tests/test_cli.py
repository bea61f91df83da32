"""CLI commands other than run/validate."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest
from conftest import SKILLS
from vistac.cli import main

Cli = Callable[..., tuple[int, str, str]]


def test_schema_checks_each_plugins_with_block(cli: Cli) -> None:
    code, out, _ = cli("schema")
    assert code == 0
    schema = json.loads(out)
    component = schema["properties"]["components"]["additionalProperties"]
    assert "sim.depth_camera" in component["properties"]["plugin"]["enum"]
    camera = next(
        rule
        for rule in component["allOf"]
        if rule["if"]["properties"]["plugin"]["const"] == "sim.depth_camera"
    )
    ref = camera["then"]["properties"]["with"]["$ref"].split("/")[-1]
    assert "width" in schema["$defs"][ref]["properties"]
    assert "look" in schema["x-tree-nodes"]


def test_tree_prints_the_behaviour_tree(cli: Cli) -> None:
    code, out, _ = cli("tree", str(SKILLS / "collect_pushes.yaml"))
    assert code == 0
    for node in ("repeat (max 6)", "look", "choose_action", "execute_action", "stop"):
        assert node in out


def test_objects_generate(cli: Cli, tmp_path: Path) -> None:
    code, out, _ = cli("objects", "generate", "--seed", "4", "--out", str(tmp_path))
    assert code == 0 and "wrote 120" in out
    split = json.loads((tmp_path / "split.json").read_text())
    assert sum(len(v) for v in split.values()) == 120
    code, _, err = cli("validate", str(tmp_path / "nonexistent.yaml"))
    assert code == 2 and "file not found" in err
    code, _, err = cli("objects", "generate", "--out", str(tmp_path / "split.json" / "objects"))
    assert code == 2 and f"--out: {tmp_path / 'split.json'} is a file; give a folder" in err


def test_requested_plugin_that_is_missing_is_an_error(cli: Cli) -> None:
    code, _, err = cli("-p", "no_such_plugin_xyz", "plugins")
    assert code == 2
    assert "no_such_plugin_xyz" in err


@pytest.mark.parametrize(
    "command",
    [["run", str(SKILLS / "explore_push.yaml"), "--out", "x"],
     ["eval", str(SKILLS / "explore_push.yaml"), "--out", "x"],
     ["objects", "generate", "--out", "x"]],
    ids=["run", "eval", "objects"],
)  # fmt: skip
def test_a_negative_seed_is_exit_2_naming_it(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], command: list[str]
) -> None:
    with pytest.raises(SystemExit) as exited:
        main([*command[:-1], str(tmp_path / "out"), "--seed", "-1"])
    assert exited.value.code == 2
    assert "argument --seed: -1 is negative; give 0 or more" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()
    with pytest.raises(SystemExit) as exited:  # it overflowed the simulator's seed
        main([*command[:-1], str(tmp_path / "out"), "--seed", str(2**64)])
    assert exited.value.code == 2
    assert f"{2**64} is too large; give at most {2**32 - 1}" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_the_summary_names_the_files_the_run_wrote(tmp_path: Path) -> None:
    """A run stopped before its first push, or a replay, has no episodes/ (the line named
    every run file whether it was there or not)."""
    from vistac.cli import format_summary

    for name in ("run.json", "summary.json"):
        (tmp_path / name).write_text("{}")
    (tmp_path / "views").mkdir()
    text = format_summary({"skill": "s", "status": "success", "wall_time_s": 1.0}, tmp_path)
    assert text.splitlines()[-1] == f"  data: {tmp_path}/ (run.json, summary.json, views/)"


def test_output_into_a_closed_pipe_ends_without_a_traceback() -> None:
    """`vistac plugins | head -1`: the reader has gone when the output is written; exit 1,
    no traceback."""
    read_end, write_end = os.pipe()
    os.close(read_end)
    try:
        done = subprocess.run(
            [sys.executable, "-m", "vistac.cli", "plugins"],
            stdout=write_end, stderr=subprocess.PIPE, text=True, timeout=120,
        )  # fmt: skip
    finally:
        os.close(write_end)
    assert done.returncode == 1
    assert "Traceback" not in done.stderr and "BrokenPipe" not in done.stderr, done.stderr


def test_the_summary_tells_the_goal_and_each_change_report(tmp_path: Path) -> None:
    """goal_push.yaml and detect_change.yaml print their outcome, not only summary.json."""
    from vistac.cli import format_summary

    base = {"skill": "s", "status": "success", "wall_time_s": 1.0}
    goal = {"goal": [0.06, 0.5, 0.5], "planned_cost_m": [0.01, 0.004], "reached": True,
            "believed_error_m": 0.0032, "believed_turn_error_rad": 0.0524,
            "true_error_m": 0.0017, "true_turn_error_rad": 0.0873}  # fmt: skip
    lines = format_summary({**base, "goal_push": goal}, tmp_path).splitlines()
    assert lines[1] == (
        "  goal (0.060, 0.500) m, turn 29 deg: reached after 2 goal push(es); link 0 "
        "believed 3.2 mm, 3 deg from it, truly 1.7 mm, 5 deg"
    )
    real = {key: goal[key] for key in ("goal", "planned_cost_m", "believed_error_m",
                                       "believed_turn_error_rad")}  # fmt: skip
    lines = format_summary({**base, "goal_push": {**real, "reached": False}}, tmp_path)
    assert "not reached after 2 goal push(es); link 0 believed 3.2 mm, 3 deg from it\n" in lines
    unchecked = {"goal": goal["goal"], "planned_cost_m": [0.01]}
    lines = format_summary({**base, "goal_push": unchecked}, tmp_path)
    assert "turn 29 deg: not checked (1 goal push(es) planned)" in lines
    reports = [
        {"episode": 0, "score": -0.37, "flagged": False, "flagged_after_s": None},
        {"episode": 1, "score": -0.812, "flagged": True, "flagged_after_s": 1.43},
    ]
    lines = format_summary({**base, "change_detection": reports}, tmp_path).splitlines()
    assert lines[1:3] == [
        "  episode 0: likelihood score -0.37, no change",
        "  episode 1: likelihood score -0.81, change flagged 1.4 s after its start",
    ]
