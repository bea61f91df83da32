"""Complete validation before anything moves: every error at once, with its YAML path."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import pytest
from conftest import SKILLS, write
from vistac.errors import ConfigError
from vistac.pluginmanager import Plugins
from vistac.skill import apply_overrides, load_skill

Cli = Callable[..., tuple[int, str, str]]

TWO_MISTAKES = """\
version: 1
name: two-mistakes
components:
  world:   {plugin: sim.mujoco, with: {object: objects/rect1.yaml}}
  arm:     {plugin: sim.armm}
  camera:  {plugin: sim.depth_camera, with: {width: -320}}
  views:   {plugin: shape.uniform_views}
tree: [look]
"""


def test_two_mistakes_are_both_reported_with_paths_and_exit_2(tmp_path: Path, cli: Cli) -> None:
    write(tmp_path / "objects/rect1.yaml", (SKILLS / "objects/rect1.yaml").read_text())
    skill = write(tmp_path / "skill.yaml", TWO_MISTAKES)
    code, _, err = cli("validate", str(skill))
    assert code == 2
    assert "components.arm.plugin: unknown plugin 'sim.armm' (did you mean 'sim.arm'" in err
    assert "components.camera.with.width: Input should be greater than 0" in err
    assert "Traceback" not in err


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("version: 1\nname: x\ntree: [look\n", "malformed YAML: line"),
        (
            "version: 1\nname: x\ncomponents: {}\ntree: [lok]\n",
            "unknown tree node 'lok' (did you mean 'look'?)",
        ),
        ("- just\n- a list\n", "a skill file must be a YAML mapping"),
        ("version: 2\nname: x\ntree: stop\n", "version: Input should be 1"),
        ("version: 1\nname: x\ntree: stop\nextra: 1\n", "extra: Extra inputs are not permitted"),
        (
            "version: 1\nname: x\ncomponents:\n"
            "  shape: {plugin: shape.ems, with: {shear_gain: 1}}\ntree: stop\n",
            "components.shape.with.shear_gain: Extra inputs are not permitted (did you mean "
            "'shear_gain_nats' or 'shear'?)",
        ),
        (  # a node left out for its arguments leaves the next one's reads unchecked
            "version: 1\nname: x\ncomponents: {}\n"
            "tree: [{count: {tickz: 2}}, count_at_least]\n",
            "tree[0].count.tickz: Extra inputs are not permitted (did you mean 'ticks'?)",
        ),
        (
            "version: 1\nname: x\ncomponents: {}\ntree: {repeat: {do: stop, maxx: 2}}\n",
            "tree.repeat.maxx: Extra inputs are not permitted (did you mean 'max' or 'on_max'?)",
        ),
        (  # safe_load would keep the last 'arm' silently
            "version: 1\nname: x\ncomponents:\n  arm: {plugin: sim.arm}\n"
            "  arm: {plugin: sim.gripper}\ntree: stop\n",
            "malformed YAML: line 5, column 3: duplicate key 'arm'",
        ),
        (
            "version: 1\nname: x\nseed: -1\ntree: stop\n",
            "seed: Input should be greater than or equal to 0",
        ),
    ],
)
def test_one_clear_line_per_problem(tmp_path: Path, cli: Cli, text: str, expected: str) -> None:
    code, _, err = cli("validate", str(write(tmp_path / "s.yaml", text)))
    assert code == 2
    assert expected in err
    assert len(err.strip().splitlines()) == 1, err
    assert "Traceback" not in err


def test_a_top_level_error_hides_no_other(tmp_path: Path, cli: Cli) -> None:
    text = (
        "version: 1\nname: x\nrate: 15\ncomponents:\n  arm: {plugin: sim.amr}\n"
        "  gripper: {plugn: sim.gripper}\ntree: [lok]\n"
    )
    code, _, err = cli("validate", str(write(tmp_path / "s.yaml", text)))
    assert code == 2
    assert sorted(line.split(": ")[2] for line in err.strip().splitlines()) == [
        "components.arm.plugin",  # unknown plugin 'sim.amr'
        "components.gripper.plugin",  # Field required
        "components.gripper.plugn",
        "rate",
        "tree[0]",  # unknown tree node 'lok'
    ]


@pytest.mark.parametrize(
    ("spec", "error"),
    [
        ("{plugin: filters.duall}", "components.filter.plugin: unknown plugin 'filters.duall'"),
        ("{plugn: filters.dual}", "components.filter.plugn: Extra inputs are not permitted"),
    ],
)
def test_a_component_in_error_is_not_also_a_missing_role(
    tmp_path: Path, cli: Cli, spec: str, error: str
) -> None:
    text = f"version: 1\nname: x\ncomponents:\n  filter: {spec}\ntree: goal_reached\n"
    code, _, err = cli("validate", str(write(tmp_path / "s.yaml", text)))
    assert code == 2
    assert error in err
    assert "reads 'belief', but no earlier node writes it" in err  # the tree is still checked
    assert "role" not in err, err


def test_missing_file(tmp_path: Path, cli: Cli) -> None:
    code, _, err = cli("run", str(tmp_path / "nope.yaml"), "--out", str(tmp_path / "out"))
    assert code == 2
    assert err.strip() == f"error: {tmp_path / 'nope.yaml'}: file not found"
    assert not (tmp_path / "out").exists(), "nothing is written for an invalid skill"


def test_data_flow_and_roles_are_checked(tmp_path: Path, plugins: Plugins) -> None:
    skill = write(
        tmp_path / "s.yaml",
        """\
version: 1
name: flow
components:
  arm: {plugin: test.arm}
tree:
  - needs_widget
  - {choose_action: {selector: arm}}
""",
    )
    with pytest.raises(ConfigError) as info:
        load_skill(skill, plugins.registry)
    text = str(info.value)
    assert "tree[0].needs_widget: reads 'widget', but no earlier node writes it" in text
    assert "tree[1].choose_action: needs a action_sampler component as role 'affordances'" in text
    assert "tree[1].choose_action: role 'arm' is an arm, this node needs an action_selector" in text
    assert "tree[1].choose_action: reads 'cloud', but no earlier node writes it" in text


def test_repeat_arguments_and_nested_errors(tmp_path: Path, plugins: Plugins) -> None:
    skill = write(
        tmp_path / "s.yaml",
        """\
version: 1
name: rep
tree:
  repeat: {do: [count, {count: {tickz: 2}}], until: {count_at_least: {n: x}}, max: 0}
""",
    )
    with pytest.raises(ConfigError) as info:
        load_skill(skill, plugins.registry)
    text = str(info.value)
    assert "tree.repeat.max: Input should be greater than 0" in text
    skill.write_text(skill.read_text().replace("max: 0", "max: 3"))
    with pytest.raises(ConfigError) as info:
        load_skill(skill, plugins.registry)
    text = str(info.value)
    assert "tree.repeat.do[1].count.tickz: Extra inputs are not permitted" in text
    assert "tree.repeat.until.count_at_least.n: Input should be a valid integer" in text


def test_overrides_and_relative_paths(tmp_path: Path, plugins: Plugins) -> None:
    write(tmp_path / "skills/objects/box.yaml", (SKILLS / "objects/rect1.yaml").read_text())
    skill_path = write(
        tmp_path / "skills/s.yaml",
        """\
version: 1
name: paths
components:
  world: {plugin: sim.mujoco, with: {object: objects/box.yaml}}
  arm: {plugin: sim.arm}
tree: stop
""",
    )
    skill = load_skill(
        skill_path, plugins.registry, ["components.arm.with.max_speed_mps=0.01", "seed=7"]
    )
    assert (
        skill.components["world"].config.object == (tmp_path / "skills/objects/box.yaml").resolve()
    )
    assert skill.components["arm"].config.max_speed_mps == 0.01
    assert skill.seed == 7
    with pytest.raises(ConfigError, match=r"components\.arm\.with\.max_speed_mps"):
        load_skill(skill_path, plugins.registry, ["components.arm.with.max_speed_mps=-1"])
    with pytest.raises(ConfigError, match=r"box2\.yaml: no such file \(a relative path is taken "):
        load_skill(skill_path, plugins.registry, ["components.world.with.object=objects/box2.yaml"])
    # a misspelt role makes a new component, which has no plugin
    with pytest.raises(ConfigError) as typo:
        load_skill(skill_path, plugins.registry, ["components.amr.with.max_speed_mps=0.01"])
    assert str(typo.value).endswith(
        "components.amr.plugin: missing: every component names its plugin (did you mean 'arm'?)"
    )
    with pytest.raises(ConfigError) as new:
        load_skill(skill_path, plugins.registry, ["components.probe.with.speed=0.01"])
    assert "components.probe.plugin: missing: every component names its plugin (the other " \
        "components: world, arm)" in str(new.value)


def test_apply_overrides_reports_bad_keys() -> None:
    assert apply_overrides({"a": {"b": 1}}, ["a.c=[1, 2]"]) == {"a": {"b": 1, "c": [1, 2]}}
    with pytest.raises(ConfigError, match="not of the form"):
        apply_overrides({}, ["nokey"])
    with pytest.raises(ConfigError, match=r"a\.b\.c: cannot set inside a int"):
        apply_overrides({"a": {"b": 1}}, ["a.b.c=2"])
    tree = {"tree": {"sequence": ["look", {"repeat": {"max": 4}}]}}
    assert (
        apply_overrides(tree, ["tree.sequence.1.repeat.max=1"])["tree"]["sequence"][1]["repeat"][
            "max"
        ]
        == 1
    )
    with pytest.raises(ConfigError, match="no list item '5'"):
        apply_overrides(tree, ["tree.sequence.5=stop"])
    with pytest.raises(ConfigError, match=r"--set: a: expected ',' or '}', but got '<stream end>'"):
        apply_overrides({}, ["a={plugin: x"])  # a mapping cut short
    assert apply_overrides({}, ["a=b: c: d"]) == {"a": "b: c: d"}  # a plain string YAML cannot read


def test_every_shipped_skill_validates(cli: Cli) -> None:
    skills = sorted(SKILLS.glob("*.yaml"))
    assert skills
    code, _out, err = cli("validate", *map(str, skills))
    assert code == 0, err
