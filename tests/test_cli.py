"""CLI commands other than run/validate."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

from conftest import SKILLS

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


def test_requested_plugin_that_is_missing_is_an_error(cli: Cli) -> None:
    code, _, err = cli("-p", "no_such_plugin_xyz", "plugins")
    assert code == 2 or code == 1
    assert "no_such_plugin_xyz" in err
